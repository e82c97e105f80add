//! Procedural albedo: solid textures evaluated at the *canonical* (unposed, clothed) surface
//! point, so a pattern sticks to the body when it moves and needs no UV map (the low-res
//! template has none).
//!
//! Patterns: solid, horizontal stripes, 3D checks, value noise, and "prints" (a dot lattice) for
//! the training stream; camouflage, patchwork and ring motifs for the share of it that
//! `[synthetic.stream_variety] prints = "more"` varies ([`Material::more_cloth`]); plaid,
//! diagonal stripes and colour ramps only for the held-out family
//! ([`Material::held_out_cloth`], design.md §8.11), which no training subject wears.
//! Colours are linear `[0, 1]` RGB, written to PNG as they are (albedo is the default look).

use glam::Vec3;
use serde::{Deserialize, Serialize};

use lifegom_render::rng::Rng;

/// A procedural pattern over canonical space (metres).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Pattern {
    /// One colour.
    Solid,
    /// Bands along the vertical axis, `period` metres apart.
    Stripes {
        /// Band period, metres.
        period: f32,
    },
    /// A 3D checkerboard of `size`-metre cells.
    Checks {
        /// Cell size, metres.
        size: f32,
    },
    /// Smooth value noise mixing the two colours.
    Noise {
        /// Feature size, metres.
        scale: f32,
        /// Lattice hash seed.
        seed: u32,
    },
    /// Dots of `radius` on a `period` lattice (a simple print).
    Dots {
        /// Lattice period, metres.
        period: f32,
        /// Dot radius, metres.
        radius: f32,
    },
    /// Value noise cut at its median: irregular blots with sharp edges (stream variety).
    Camo {
        /// Feature size, metres.
        scale: f32,
        /// Lattice hash seed.
        seed: u32,
    },
    /// Cubic patches, each a hashed one of three tones (base, half-way, accent; stream variety).
    Patchwork {
        /// Patch size, metres.
        size: f32,
        /// Lattice hash seed.
        seed: u32,
    },
    /// A disc inside a ring on a sparse `period` lattice: large printed motifs (stream variety).
    Motifs {
        /// Lattice period, metres.
        period: f32,
        /// Outer radius of the ring, metres.
        radius: f32,
    },
    /// Two crossed sets of bands (vertical and around the body): three tones (held out).
    Plaid {
        /// Band period, metres.
        period: f32,
    },
    /// Bands running diagonally across the body, `period` metres apart (held out).
    Diagonal {
        /// Band period, metres.
        period: f32,
    },
    /// A smooth ramp from one colour to the other and back over `length` metres of height
    /// (held out).
    Ramp {
        /// Half period, metres.
        length: f32,
    },
}

/// A surface material: two colours and the pattern that mixes them.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Material {
    /// Main colour.
    pub base: [f32; 3],
    /// Second colour (stripes, checks, dots, noise).
    pub accent: [f32; 3],
    /// The pattern.
    pub pattern: Pattern,
}

impl Material {
    /// A solid material.
    pub fn solid(c: [f32; 3]) -> Self {
        Self {
            base: c,
            accent: c,
            pattern: Pattern::Solid,
        }
    }

    /// Albedo at canonical point `p`.
    pub fn albedo(&self, p: Vec3) -> [f32; 3] {
        let t = match self.pattern {
            Pattern::Solid => 0.0,
            Pattern::Stripes { period } => {
                if (p.y / period).rem_euclid(1.0) < 0.5 {
                    0.0
                } else {
                    1.0
                }
            }
            Pattern::Checks { size } => {
                let c = (p / size).floor();
                if (c.x + c.y + c.z).rem_euclid(2.0) < 0.5 {
                    0.0
                } else {
                    1.0
                }
            }
            Pattern::Noise { scale, seed } => value_noise(p / scale, seed),
            Pattern::Dots { period, radius } => {
                let cell = (p / period).round() * period;
                if (p - cell).length() < radius {
                    1.0
                } else {
                    0.0
                }
            }
            Pattern::Camo { scale, seed } => {
                f32::from(u8::from(value_noise(p / scale, seed) > 0.5))
            }
            Pattern::Patchwork { size, seed } => {
                let c = (p / size).floor();
                let h = lattice(c.x as i32, c.y as i32, c.z as i32, seed);
                (h * 3.0).floor().min(2.0) * 0.5
            }
            Pattern::Motifs { period, radius } => {
                let d = (p - (p / period).round() * period).length();
                f32::from(u8::from(
                    d < 0.5 * radius || (0.75 * radius..radius).contains(&d),
                ))
            }
            Pattern::Plaid { period } => {
                let band = |x: f32| f32::from(u8::from((x / period).rem_euclid(1.0) < 0.35));
                0.5 * (band(p.y) + band(p.x + p.z))
            }
            Pattern::Diagonal { period } => {
                if ((p.y + p.x) / period).rem_euclid(1.0) < 0.5 {
                    0.0
                } else {
                    1.0
                }
            }
            Pattern::Ramp { length } => {
                // A triangle wave: 0 → 1 over `length`, back to 0 over the next.
                let u = (p.y / length).rem_euclid(2.0);
                if u < 1.0 { u } else { 2.0 - u }
            }
        };
        std::array::from_fn(|i| self.base[i] * (1.0 - t) + self.accent[i] * t)
    }

    /// A garment of two random colours (drawn first) and the pattern `draw` picks.
    fn cloth(rng: &mut Rng, draw: impl FnOnce(&mut Rng) -> Pattern) -> Self {
        let (base, accent) = two_colours(rng);
        Self {
            base,
            accent,
            pattern: draw(rng),
        }
    }

    /// A random garment material: one of the five patterns with random colours.
    pub fn random_cloth(rng: &mut Rng) -> Self {
        Self::cloth(rng, |rng| match rng.below(5) {
            0 => Pattern::Solid,
            1 => Pattern::Stripes {
                period: rng.range(0.04, 0.12) as f32,
            },
            2 => Pattern::Checks {
                size: rng.range(0.03, 0.08) as f32,
            },
            3 => Pattern::Noise {
                scale: rng.range(0.03, 0.1) as f32,
                seed: rng.next_u64() as u32,
            },
            _ => {
                let period = rng.range(0.04, 0.09) as f32;
                Pattern::Dots {
                    period,
                    radius: period * rng.range(0.15, 0.35) as f32,
                }
            }
        })
    }

    /// A garment material of the stream's extra prints (`[synthetic.stream_variety] prints =
    /// "more"`, design.md §8.11): camouflage, patchwork or ring motifs, sharper-edged and more
    /// varied in scale than [`Material::random_cloth`]'s, and none of the held-out family's.
    pub fn more_cloth(rng: &mut Rng) -> Self {
        Self::cloth(rng, |rng| match rng.below(3) {
            0 => Pattern::Camo {
                scale: rng.range(0.04, 0.12) as f32,
                seed: rng.next_u64() as u32,
            },
            1 => Pattern::Patchwork {
                size: rng.range(0.04, 0.1) as f32,
                seed: rng.next_u64() as u32,
            },
            _ => {
                let period = rng.range(0.15, 0.3) as f32;
                Pattern::Motifs {
                    period,
                    radius: period * rng.range(0.25, 0.4) as f32,
                }
            }
        })
    }

    /// A held-out garment material (design.md §8.11): plaid, diagonal stripes or a colour ramp,
    /// patterns the stream's [`Material::random_cloth`] never draws.
    pub fn held_out_cloth(rng: &mut Rng) -> Self {
        Self::cloth(rng, |rng| match rng.below(3) {
            0 => Pattern::Plaid {
                period: rng.range(0.05, 0.12) as f32,
            },
            1 => Pattern::Diagonal {
                period: rng.range(0.04, 0.1) as f32,
            },
            _ => Pattern::Ramp {
                length: rng.range(0.15, 0.4) as f32,
            },
        })
    }

    /// Held-out hair: dyed colours (blue, pink, green, platinum, violet) the stream's
    /// [`Material::random_hair`] never draws, with coarser strands.
    pub fn held_out_hair(rng: &mut Rng) -> Self {
        const DYED: [[f32; 3]; 5] = [
            [0.15, 0.25, 0.7],
            [0.85, 0.4, 0.6],
            [0.2, 0.55, 0.3],
            [0.9, 0.88, 0.8],
            [0.45, 0.2, 0.6],
        ];
        let base = DYED[rng.below(DYED.len())];
        Self {
            base,
            accent: base.map(|c| c * 0.6),
            pattern: Pattern::Noise {
                scale: 0.02,
                seed: rng.next_u64() as u32,
            },
        }
    }

    /// A skin tone from a light-to-dark range, with a faint noise.
    pub fn random_skin(rng: &mut Rng) -> Self {
        let t = rng.uniform() as f32;
        let light = [0.96, 0.80, 0.69];
        let dark = [0.36, 0.23, 0.15];
        let base: [f32; 3] = std::array::from_fn(|i| light[i] * (1.0 - t) + dark[i] * t);
        Self {
            base,
            accent: base.map(|c| c * 0.92),
            pattern: Pattern::Noise {
                scale: 0.05,
                seed: rng.next_u64() as u32,
            },
        }
    }

    /// A hair colour (black, brown, blond, red, grey), with strand-like noise.
    pub fn random_hair(rng: &mut Rng) -> Self {
        const HAIR: [[f32; 3]; 5] = [
            [0.05, 0.04, 0.04],
            [0.25, 0.14, 0.07],
            [0.75, 0.6, 0.35],
            [0.5, 0.2, 0.08],
            [0.6, 0.6, 0.6],
        ];
        let base = HAIR[rng.below(HAIR.len())];
        Self {
            base,
            accent: base.map(|c| c * 0.7),
            pattern: Pattern::Noise {
                scale: 0.01,
                seed: rng.next_u64() as u32,
            },
        }
    }
}

/// A garment's base and accent colours, the accent kept visibly different from the base.
fn two_colours(rng: &mut Rng) -> ([f32; 3], [f32; 3]) {
    let base = random_colour(rng);
    let mut accent = random_colour(rng);
    if (0..3).map(|i| (base[i] - accent[i]).abs()).sum::<f32>() < 0.4 {
        accent = base.map(|c| 1.0 - c);
    }
    (base, accent)
}

/// A saturated-enough random colour.
fn random_colour(rng: &mut Rng) -> [f32; 3] {
    // HSV with s, v away from the extremes, so garments read clearly against skin and black.
    let h = rng.uniform() as f32 * 6.0;
    let s = rng.range(0.2, 0.9) as f32;
    let v = rng.range(0.25, 0.95) as f32;
    let c = v * s;
    let x = c * (1.0 - ((h % 2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// Smooth (trilinear, smoothstep-weighted) value noise in `[0, 1]`.
fn value_noise(p: Vec3, seed: u32) -> f32 {
    let cell = p.floor();
    let f = p - cell;
    let s = f * f * (Vec3::splat(3.0) - 2.0 * f);
    let (x0, y0, z0) = (cell.x as i32, cell.y as i32, cell.z as i32);
    let mut acc = 0.0;
    for dz in 0..2 {
        for dy in 0..2 {
            for dx in 0..2 {
                let wx = if dx == 0 { 1.0 - s.x } else { s.x };
                let wy = if dy == 0 { 1.0 - s.y } else { s.y };
                let wz = if dz == 0 { 1.0 - s.z } else { s.z };
                acc += wx * wy * wz * lattice(x0 + dx, y0 + dy, z0 + dz, seed);
            }
        }
    }
    acc
}

/// A hash of a lattice point to `[0, 1]`.
fn lattice(x: i32, y: i32, z: i32, seed: u32) -> f32 {
    let mut h = (x as u32).wrapping_mul(0x8da6_b343)
        ^ (y as u32).wrapping_mul(0xd816_3841)
        ^ (z as u32).wrapping_mul(0xcb1a_b31f)
        ^ seed.wrapping_mul(0x1656_67b1);
    h ^= h >> 13;
    h = h.wrapping_mul(0x5bd1_e995);
    h ^= h >> 15;
    (h & 0xffff) as f32 / 65535.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_mix_only_their_two_colours_and_vary() {
        let mut rng = Rng::new(5);
        let (mut patterned, mut varied) = (0, 0);
        for _ in 0..50 {
            let m = Material::random_cloth(&mut rng);
            let mut seen = Vec::new();
            for k in 0..200 {
                let p = Vec3::new(k as f32 * 0.013, k as f32 * 0.007, -(k as f32) * 0.011);
                let a = m.albedo(p);
                assert!(a.iter().all(|c| (0.0..=1.0).contains(c)), "{a:?}");
                seen.push(a);
            }
            let distinct = seen.iter().any(|a| a != &seen[0]);
            if m.pattern == Pattern::Solid {
                assert!(!distinct, "{m:?}");
            } else {
                patterned += 1;
                varied += usize::from(distinct);
            }
        }
        assert!(
            patterned > 20 && varied * 10 >= patterned * 8,
            "{varied}/{patterned}"
        );
    }

    #[test]
    fn held_out_patterns_are_never_drawn_by_the_stream_and_vary() {
        let held_out = |m: &Material| {
            matches!(
                m.pattern,
                Pattern::Plaid { .. } | Pattern::Diagonal { .. } | Pattern::Ramp { .. }
            )
        };
        let mut rng = Rng::new(9);
        for _ in 0..300 {
            assert!(!held_out(&Material::random_cloth(&mut rng)));
            let more = Material::more_cloth(&mut rng);
            assert!(!held_out(&more), "{more:?}");
            let m = Material::held_out_cloth(&mut rng);
            assert!(held_out(&m), "{m:?}");
            for m in [m, more] {
                let values: Vec<[f32; 3]> = (0..400)
                    .map(|k| m.albedo(Vec3::new(k as f32 * 0.011, k as f32 * 0.009, 0.02)))
                    .collect();
                assert!(values.iter().flatten().all(|c| (0.0..=1.0).contains(c)));
                assert!(values.iter().any(|a| a != &values[0]), "{m:?}");
            }
        }
    }

    #[test]
    fn more_prints_are_new_to_the_stream_and_mix_their_colours() {
        let mut rng = Rng::new(11);
        let mut kinds = [0usize; 3];
        for _ in 0..300 {
            let m = Material::more_cloth(&mut rng);
            kinds[match m.pattern {
                Pattern::Camo { .. } => 0,
                Pattern::Patchwork { .. } => 1,
                Pattern::Motifs { .. } => 2,
                other => panic!("{other:?} is not one of the extra prints"),
            }] += 1;
            // Camouflage and motifs take only the two colours; patchwork also their midpoint.
            let mid: [f32; 3] = std::array::from_fn(|i| 0.5 * (m.base[i] + m.accent[i]));
            for k in 0..100 {
                let a = m.albedo(Vec3::new(k as f32 * 0.017, 0.4 - k as f32 * 0.013, 0.05));
                let near = |c: [f32; 3]| (0..3).all(|i| (a[i] - c[i]).abs() < 1e-5);
                assert!(near(m.base) || near(m.accent) || near(mid), "{a:?} {m:?}");
            }
        }
        assert!(kinds.iter().all(|&k| k > 70), "{kinds:?}");
    }

    #[test]
    fn noise_is_smooth_and_in_range() {
        let mut prev = value_noise(Vec3::new(0.0, 0.3, 0.7), 1);
        for k in 1..1000 {
            let v = value_noise(Vec3::new(k as f32 * 0.01, 0.3, 0.7), 1);
            assert!((0.0..=1.0).contains(&v));
            assert!((v - prev).abs() < 0.1);
            prev = v;
        }
    }
}
