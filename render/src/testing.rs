//! Test support shared by the workspace's test suites (not part of the API).
//!
//! - [`Rng`]: a seeded generator, so scenes and weights are reproducible without a dependency.
//!   It is Knuth's MMIX linear congruential generator: no statistical quality is needed, only
//!   determinism across platforms.
//! - [`cpu_backend_tests!`](crate::cpu_backend_tests): one test body, run once per CPU backend
//!   (ndarray, which CI covers, and Flex).

/// A seeded linear congruential generator (MMIX constants).
#[derive(Debug, Clone)]
pub struct Rng(pub u64);

impl Rng {
    /// A generator with state `seed`.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    fn step(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0
    }

    /// Uniform in [0, 1), 24 bits.
    pub fn next_f32(&mut self) -> f32 {
        (self.step() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Uniform in [0, 1), 53 bits.
    pub fn next_f64(&mut self) -> f64 {
        (self.step() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next_f32()
    }

    /// Uniform in [lo, hi), in f64.
    pub fn range_f64(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }
}

/// Runs test bodies `fn(&burn::tensor::Device)` once per CPU backend.
///
/// - `cpu_backend_tests!(a, b)` makes `ndarray_backend::{a, b}` and `flex_backend::{a, b}`;
/// - `cpu_backend_tests!(name => body)` makes `name::{ndarray, flex}` calling `body`.
#[macro_export]
macro_rules! cpu_backend_tests {
    ($test:ident => $body:ident) => {
        mod $test {
            #[test]
            #[allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it.
            fn ndarray() {
                super::$body(&burn::tensor::Device::ndarray());
            }
            #[test]
            fn flex() {
                super::$body(&burn::tensor::Device::flex());
            }
        }
    };
    ($($name:ident),+ $(,)?) => {
        mod ndarray_backend {
            $(
                #[test]
                #[allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it.
                fn $name() {
                    super::$name(&burn::tensor::Device::ndarray());
                }
            )+
        }
        mod flex_backend {
            $(
                #[test]
                fn $name() {
                    super::$name(&burn::tensor::Device::flex());
                }
            )+
        }
    };
}
