//! The workspace's one seeded random number generator (SplitMix64): training-sample draws, the
//! synthetic generator, evaluation and every test's random scenes use it, so they are
//! reproducible for a seed without pinning an external RNG crate whose streams may change
//! between versions.
//!
//! SplitMix64 passes BigCrush, needs 8 bytes of state and makes independent streams cheap:
//! [`Rng::fork`] derives a child generator from a key (a subject index, a frame index), so
//! parallel work gives the same numbers whatever the thread count or order.

/// SplitMix64's increment per draw (the golden ratio in 64 bits).
const GAMMA: u64 = 0x9e37_79b9_7f4a_7c15;

/// SplitMix64.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rng {
    state: u64,
}

impl Rng {
    /// A generator for `seed`.
    pub fn new(seed: u64) -> Self {
        Self {
            state: seed ^ 0x853c_49e6_748f_ea9b,
        }
    }

    /// An independent generator derived from this one's seed and `key` (does not advance self).
    pub fn fork(&self, key: u64) -> Self {
        let mut child = Self {
            state: self.state ^ key.wrapping_mul(GAMMA),
        };
        child.next_u64();
        Self::new(child.next_u64())
    }

    /// This generator as it will be after `n` more draws, in constant time. SplitMix64's state
    /// only advances by a constant per draw, so one long stream can be cut into chunks that
    /// threads draw independently, with exactly the numbers one thread would draw in order.
    pub fn skipped(&self, n: u64) -> Self {
        Self {
            state: self.state.wrapping_add(n.wrapping_mul(GAMMA)),
        }
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GAMMA);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1) with 24 random bits (every value exactly representable in `f32`).
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 * (1.0 / (1u32 << 24) as f32)
    }

    /// Uniform in [lo, hi), in `f32`.
    pub fn range_f32(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next_f32()
    }

    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[lo, hi)`.
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Uniform integer in `0..n` (`n > 0`; returns 0 for `n == 0`).
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            return 0;
        }
        // Multiply-shift: bias below 2^-64·n, irrelevant here.
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform(); // (0, 1]
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// `k` distinct values from `pool`, in random order (partial Fisher–Yates).
    pub fn sample_distinct(&mut self, pool: &[usize], k: usize) -> Vec<usize> {
        let mut v = pool.to_vec();
        let k = k.min(v.len());
        for i in 0..k {
            let j = i + self.below(v.len() - i);
            v.swap(i, j);
        }
        v.truncate(k);
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_forks_differ() {
        let (mut a, mut b) = (Rng::new(7), Rng::new(7));
        assert_eq!(a.next_u64(), b.next_u64());
        let r = Rng::new(7);
        assert_ne!(r.fork(1).next_u64(), r.fork(2).next_u64());
        assert_eq!(r.fork(1), r.fork(1));
    }

    /// Skipping `n` draws lands where `n` draws do, from any point of a stream.
    #[test]
    fn skipping_equals_drawing() {
        let mut walked = Rng::new(11).fork(3);
        let start = walked.clone();
        for n in 0..300u64 {
            assert_eq!(start.skipped(n), walked, "after {n} draws");
            walked.next_u64();
        }
        assert_eq!(start.skipped(100).skipped(200), start.skipped(300));
    }

    #[test]
    fn ranges_and_moments() {
        let mut r = Rng::new(1);
        let n = 20_000;
        let (mut s, mut s2) = (0.0, 0.0);
        for _ in 0..n {
            let x = r.normal();
            s += x;
            s2 += x * x;
            let u = r.uniform();
            assert!((0.0..1.0).contains(&u));
            assert!(r.below(5) < 5);
        }
        assert!((s / n as f64).abs() < 0.05);
        assert!((s2 / n as f64 - 1.0).abs() < 0.05);
        let d = r.sample_distinct(&[1, 2, 3, 4], 3);
        assert_eq!(d.len(), 3);
        assert!(d.iter().all(|x| (1..=4).contains(x)));
        assert!(d[0] != d[1] && d[1] != d[2] && d[0] != d[2]);
    }
}
