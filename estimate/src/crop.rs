//! Rotated crops of a photo, resampled to a graph's square input, and the way back.
//!
//! A crop is a rectangle of the photo (centre, size, rotation; pixels) mapped onto an
//! `n × n` grid: output pixel `(i, j)` samples the photo at
//! `centre + (i / n − ½)·width·u + (j / n − ½)·height·v`, with `u = (cos r, sin r)` and
//! `v = (−sin r, cos r)`: the rectangle's corners land on the grid's outer corners, pixel
//! indices taken as positions (OpenCV's perspective warp between a rotated box's corners and
//! the output's, which MediaPipe's graphs were trained behind). Landmarks come back the same
//! way: a position `(x, y)` in the grid's units is `centre + (x / n − ½)·width·u + …`.
//!
//! Sampling is bilinear on 8-bit pixels with OpenCV's fixed-point arithmetic (positions
//! rounded to 1/32 pixel, weights to 1/32768, the sum rounded to the nearest integer), so that
//! the graphs see the pixels they see under MediaPipe.

use glam::Vec2;

/// A rotated rectangle of a photo, in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Roi {
    /// Its centre.
    pub center: Vec2,
    /// Width and height.
    pub size: Vec2,
    /// Rotation in radians (positive turns the width axis from +x towards +y, clockwise on
    /// screen).
    pub rotation: f32,
}

/// What a sample outside the photo reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Border {
    /// Zero (black).
    Zero,
    /// The nearest edge pixel.
    Replicate,
}

impl Roi {
    /// The whole `width × height` photo padded to a square about its centre (what a graph
    /// with a square input sees of a photo: MediaPipe's letterbox), and the padding as a
    /// fraction of the square's side: `[horizontal, vertical]`, each side.
    pub fn letterbox(width: u32, height: u32) -> (Self, [f32; 2]) {
        let (w, h) = (width as f32, height as f32);
        let side = w.max(h);
        let roi = Roi {
            center: Vec2::new(w / 2.0, h / 2.0),
            size: Vec2::splat(side),
            rotation: 0.0,
        };
        (roi, [(1.0 - w / side) / 2.0, (1.0 - h / side) / 2.0])
    }

    /// The photo position of grid position `p` (grid units: `0..n` across) on an `n × n` grid.
    pub fn to_photo(&self, p: Vec2, n: f32) -> Vec2 {
        let (s, c) = self.rotation.sin_cos();
        let u = Vec2::new(c, s);
        let v = Vec2::new(-s, c);
        let t = p / n - Vec2::splat(0.5);
        self.center + t.x * self.size.x * u + t.y * self.size.y * v
    }

    /// The grid position (`0..n` across) of photo position `q`: the inverse of
    /// [`Roi::to_photo`].
    pub fn to_grid(&self, q: Vec2, n: f32) -> Vec2 {
        let (s, c) = self.rotation.sin_cos();
        let d = q - self.center;
        let t = Vec2::new(d.x * c + d.y * s, -d.x * s + d.y * c) / self.size;
        (t + Vec2::splat(0.5)) * n
    }
}

/// The `n × n` RGB crop of `rgb` (`width × height`, 8-bit, row-major) under `roi`.
pub fn crop(
    rgb: &[u8],
    width: usize,
    height: usize,
    roi: &Roi,
    n: usize,
    border: Border,
) -> Vec<u8> {
    let mut out = vec![0u8; n * n * 3];
    // Positions in f64, as OpenCV computes them, then fixed point.
    let (s, c) = (f64::from(roi.rotation)).sin_cos();
    let (cx, cy) = (f64::from(roi.center.x), f64::from(roi.center.y));
    let (sw, sh) = (f64::from(roi.size.x), f64::from(roi.size.y));
    for j in 0..n {
        for i in 0..n {
            let tx = i as f64 / n as f64 - 0.5;
            let ty = j as f64 / n as f64 - 0.5;
            let x = cx + tx * sw * c - ty * sh * s;
            let y = cy + tx * sw * s + ty * sh * c;
            let px = sample(rgb, width, height, x, y, border);
            out[(j * n + i) * 3..(j * n + i) * 3 + 3].copy_from_slice(&px);
        }
    }
    out
}

/// OpenCV's bilinear sample of 8-bit RGB at `(x, y)`.
fn sample(rgb: &[u8], width: usize, height: usize, x: f64, y: f64, border: Border) -> [u8; 3] {
    const BITS: i64 = 5;
    const TAB: i64 = 1 << BITS;
    let xi = (x * TAB as f64).round() as i64;
    let yi = (y * TAB as f64).round() as i64;
    let (x0, y0) = (xi >> BITS, yi >> BITS);
    let (fx, fy) = ((xi & (TAB - 1)) as usize, (yi & (TAB - 1)) as usize);
    let w = weights(fx, fy);
    let pixel = |px: i64, py: i64| -> [i32; 3] {
        let (px, py) = match border {
            Border::Replicate => (
                px.clamp(0, width as i64 - 1),
                py.clamp(0, height as i64 - 1),
            ),
            Border::Zero => {
                if px < 0 || py < 0 || px >= width as i64 || py >= height as i64 {
                    return [0; 3];
                }
                (px, py)
            }
        };
        let k = (py as usize * width + px as usize) * 3;
        [
            i32::from(rgb[k]),
            i32::from(rgb[k + 1]),
            i32::from(rgb[k + 2]),
        ]
    };
    let p = [
        pixel(x0, y0),
        pixel(x0 + 1, y0),
        pixel(x0, y0 + 1),
        pixel(x0 + 1, y0 + 1),
    ];
    let mut out = [0u8; 3];
    for (ch, o) in out.iter_mut().enumerate() {
        let sum: i32 = (0..4).map(|k| w[k] * p[k][ch]).sum();
        *o = ((sum + (1 << 14)) >> 15).clamp(0, 255) as u8;
    }
    out
}

/// OpenCV's fixed-point bilinear weights for sub-pixel position `(fx, fy)` / 32:
/// `[top-left, top-right, bottom-left, bottom-right]`, in 1/32768 (exact: each product of two
/// 1/32 steps is a whole number of 1/1024).
fn weights(fx: usize, fy: usize) -> [i32; 4] {
    let (fx, fy) = (fx as i32, fy as i32);
    [
        (32 - fy) * (32 - fx),
        (32 - fy) * fx,
        fy * (32 - fx),
        fy * fx,
    ]
    .map(|w| w * 32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_and_photo_positions_invert() {
        let roi = Roi {
            center: Vec2::new(120.0, 200.0),
            size: Vec2::new(300.0, 300.0),
            rotation: 0.7,
        };
        for p in [Vec2::ZERO, Vec2::new(256.0, 0.0), Vec2::new(31.5, 200.25)] {
            let back = roi.to_grid(roi.to_photo(p, 256.0), 256.0);
            assert!((back - p).length() < 1e-3, "{p} → {back}");
        }
        // The grid's corner (0, 0) is the rectangle's top-left corner.
        let axis = Roi {
            rotation: 0.0,
            ..roi
        };
        assert_eq!(axis.to_photo(Vec2::ZERO, 256.0), Vec2::new(-30.0, 50.0));
    }

    #[test]
    fn an_unrotated_crop_of_the_whole_photo_is_a_resize() {
        // A 4 × 4 photo onto a 2 × 2 grid: samples at photo pixels 0 and 2.
        let rgb: Vec<u8> = (0..16).flat_map(|v| [v * 10, v * 10, v * 10]).collect();
        let (roi, pad) = Roi::letterbox(4, 4);
        assert_eq!(pad, [0.0, 0.0]);
        let out = crop(&rgb, 4, 4, &roi, 2, Border::Zero);
        let grey: Vec<u8> = out.chunks(3).map(|p| p[0]).collect();
        assert_eq!(grey, [0, 20, 80, 100]);
        // Half-way positions average their neighbours.
        let roi = Roi {
            center: Vec2::new(2.0, 2.0),
            size: Vec2::splat(4.0),
            rotation: 0.0,
        };
        let out = crop(&rgb, 4, 4, &roi, 8, Border::Replicate);
        assert_eq!(out[3], 5, "x = 0.5 between 0 and 10");
    }
}
