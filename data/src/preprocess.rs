//! Image preprocessing exactly in the reference's order (design.md §8.3):
//!
//! 1. read the RGB image and the mask (mask channel 0 / 255 = alpha, a soft mask);
//! 2. undistort both with `(K, D)` at the original resolution, if `D` is stored;
//! 3. composite over the background *before* resizing: `img = α·img + (1−α)·bg` (0..255);
//! 4. resize to the target size ([`ResizeMode`]): by default an axis that shrinks averages the
//!    source pixels each output pixel covers (an area filter, `cv2.INTER_AREA`), so detail
//!    above the new Nyquist frequency does not alias; an axis that grows, and every axis under
//!    [`ResizeMode::Reference`], resamples as the reference's `cv2.resize` does: the image with
//!    a Lanczos-4 kernel, alpha bilinearly, OpenCV's grid (`src = (dst + ½)·scale − ½`) and a
//!    fixed kernel support (no widening when shrinking, so a photo shrunk several times is
//!    point-sampled);
//! 5. divide by 255 and scale `K`: row 0 by `W_new/W_orig`, row 1 by `H_new/H_orig`.
//!
//! Images are `f32` planes, interleaved `H×W×C`, row-major.

use std::path::Path;

use crate::error::{DataError, Location, Result};

/// An interleaved float image.
#[derive(Debug, Clone, PartialEq)]
pub struct FloatImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Channels per pixel.
    pub channels: usize,
    /// `H×W×C` values, row-major.
    pub data: Vec<f32>,
}

impl FloatImage {
    /// An RGB8 buffer (`H×W×3`) as a float image in the 0..255 domain.
    pub fn from_rgb8(width: u32, height: u32, rgb: &[u8]) -> Self {
        Self {
            width,
            height,
            channels: 3,
            data: rgb.iter().map(|&v| f32::from(v)).collect(),
        }
    }

    /// An 8-bit mask buffer (`H×W`) as alpha in `[0, 1]`.
    pub fn mask_from_l8(width: u32, height: u32, mask: &[u8]) -> Self {
        Self {
            width,
            height,
            channels: 1,
            data: mask.iter().map(|&v| f32::from(v) / 255.0).collect(),
        }
    }

    fn at(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[(y * self.width as usize + x) * self.channels + c]
    }
}

/// How [`resize`] shrinks (`[data] resize` in a config).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ResizeMode {
    /// Shrinking averages the covered source pixels (area filter); enlarging as
    /// [`ResizeMode::Reference`]. For photos of any size.
    #[default]
    AntiAliased,
    /// `cv2.resize` exactly, shrinking too: for comparisons with the official pipeline on data
    /// stored at the size it is used (THuman's), where both modes agree anyway.
    Reference,
}

/// The size a view is brought to, and how it is shrunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Resampling {
    /// `(W, H)`.
    pub size: (u32, u32),
    /// How larger images are shrunk.
    pub mode: ResizeMode,
}

/// Resampling kernel of [`resize`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kernel {
    /// `cv2.INTER_LINEAR`: 2 taps.
    Linear,
    /// `cv2.INTER_LANCZOS4`: 8 taps, `sinc(x)·sinc(x/4)`.
    Lanczos4,
}

impl Kernel {
    fn radius(self) -> i64 {
        match self {
            Self::Linear => 1,
            Self::Lanczos4 => 4,
        }
    }

    fn weight(self, x: f64) -> f64 {
        match self {
            Self::Linear => (1.0 - x.abs()).max(0.0),
            Self::Lanczos4 => {
                if x.abs() < 1e-9 {
                    1.0
                } else if x.abs() >= 4.0 {
                    0.0
                } else {
                    let px = std::f64::consts::PI * x;
                    4.0 * px.sin() * (px / 4.0).sin() / (px * px)
                }
            }
        }
    }
}

/// Reads a PNG as RGB8 (grey and RGBA are converted, as PIL's `.convert('RGB')`).
pub fn read_rgb(path: &Path, loc: &Location) -> Result<FloatImage> {
    let bytes = std::fs::read(path).map_err(|e| DataError::io(loc.clone(), e))?;
    let img = image::load_from_memory(&bytes).map_err(|e| DataError::Image {
        location: Box::new(loc.clone()),
        reason: format!("unreadable PNG: {e}"),
    })?;
    let rgb = img.to_rgb8();
    Ok(FloatImage::from_rgb8(
        rgb.width(),
        rgb.height(),
        rgb.as_raw(),
    ))
}

/// Reads a mask PNG as alpha in `[0, 1]`: channel 0 of its RGB conversion, divided by 255.
pub fn read_mask(path: &Path, loc: &Location) -> Result<FloatImage> {
    let rgb = read_rgb(path, loc)?;
    Ok(FloatImage {
        width: rgb.width,
        height: rgb.height,
        channels: 1,
        data: rgb.data.chunks_exact(3).map(|p| p[0] / 255.0).collect(),
    })
}

/// `img = α·img + (1−α)·bg` in the 0..255 domain (step 3).
pub fn composite(rgb: &mut FloatImage, alpha: &FloatImage, bg: [f32; 3]) {
    for (px, &a) in rgb.data.chunks_exact_mut(3).zip(&alpha.data) {
        for (v, b) in px.iter_mut().zip(bg) {
            *v = a * *v + (1.0 - a) * b;
        }
    }
}

/// Resizes with OpenCV's sampling grid and a fixed-support kernel (module docs). Weights are
/// normalised per output pixel, and taps outside the image clamp to the border (OpenCV's
/// `BORDER_REPLICATE` for resize).
pub fn resize(
    src: &FloatImage,
    width: u32,
    height: u32,
    kernel: Kernel,
    mode: ResizeMode,
) -> FloatImage {
    if (src.width, src.height) == (width, height) {
        return src.clone();
    }
    let taps = |n_src: u32, n_dst: u32| -> Vec<Vec<(usize, f32)>> {
        if mode == ResizeMode::AntiAliased && n_dst < n_src {
            return area_taps(n_src, n_dst);
        }
        let scale = n_src as f64 / n_dst as f64;
        (0..n_dst)
            .map(|d| {
                let s = (d as f64 + 0.5) * scale - 0.5;
                let base = s.floor() as i64;
                let mut w: Vec<(usize, f64)> = (base - kernel.radius() + 1
                    ..=base + kernel.radius())
                    .map(|i| {
                        let wt = kernel.weight(s - i as f64);
                        (i.clamp(0, n_src as i64 - 1) as usize, wt)
                    })
                    .filter(|&(_, wt)| wt != 0.0)
                    .collect();
                let sum: f64 = w.iter().map(|t| t.1).sum();
                if sum.abs() > 1e-12 {
                    w.iter_mut().for_each(|t| t.1 /= sum);
                }
                w.into_iter().map(|(i, wt)| (i, wt as f32)).collect()
            })
            .collect()
    };
    let (tx, ty) = (taps(src.width, width), taps(src.height, height));
    let c = src.channels;
    // Horizontal pass, then vertical.
    let mut mid = vec![0f32; src.height as usize * width as usize * c];
    for y in 0..src.height as usize {
        for (x, t) in tx.iter().enumerate() {
            for ch in 0..c {
                mid[(y * width as usize + x) * c + ch] =
                    t.iter().map(|&(i, w)| w * src.at(i, y, ch)).sum();
            }
        }
    }
    let mut data = vec![0f32; height as usize * width as usize * c];
    for (y, t) in ty.iter().enumerate() {
        for x in 0..width as usize {
            for ch in 0..c {
                data[(y * width as usize + x) * c + ch] = t
                    .iter()
                    .map(|&(i, w)| w * mid[(i * width as usize + x) * c + ch])
                    .sum();
            }
        }
    }
    FloatImage {
        width,
        height,
        channels: c,
        data,
    }
}

/// The area filter's taps when shrinking `n_src` pixels to `n_dst`: output pixel `d` covers the
/// source interval `[d·s, (d+1)·s)` with `s = n_src / n_dst`, and each source pixel weighs the
/// length of its overlap with it (weights sum to 1).
fn area_taps(n_src: u32, n_dst: u32) -> Vec<Vec<(usize, f32)>> {
    let scale = n_src as f64 / n_dst as f64;
    (0..n_dst)
        .map(|d| {
            let (lo, hi) = (d as f64 * scale, (d as f64 + 1.0) * scale);
            let first = lo.floor() as usize;
            let last = (hi.ceil() as usize).min(n_src as usize);
            (first..last)
                .filter_map(|i| {
                    let overlap = (hi.min(i as f64 + 1.0) - lo.max(i as f64)) / scale;
                    (overlap > 1e-12).then_some((i, overlap as f32))
                })
                .collect()
        })
        .collect()
}

/// `K` for an image resized from `from` to `to` (both `(W, H)`): row 0 × `W'/W`, row 1 × `H'/H`.
pub fn scale_intrinsics(k: [[f64; 3]; 3], from: (u32, u32), to: (u32, u32)) -> [[f64; 3]; 3] {
    let (sx, sy) = (to.0 as f64 / from.0 as f64, to.1 as f64 / from.1 as f64);
    let mut out = k;
    out[0].iter_mut().for_each(|v| *v *= sx);
    out[1].iter_mut().for_each(|v| *v *= sy);
    out
}

/// `cv2.undistort(img, K, D)` with the same `K` as the new camera: for every output pixel, its
/// normalised ray is distorted with the OpenCV model (`k1, k2, p1, p2[, k3]`) and the source is
/// sampled bilinearly; rays landing outside the source give 0, as OpenCV's constant border.
pub fn undistort(src: &FloatImage, k: &[[f64; 3]; 3], d: &[f64]) -> FloatImage {
    let (fx, fy, cx, cy) = (k[0][0], k[1][1], k[0][2], k[1][2]);
    let coeff = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let (k1, k2, p1, p2, k3) = (coeff(0), coeff(1), coeff(2), coeff(3), coeff(4));
    let (w, h, c) = (src.width as usize, src.height as usize, src.channels);
    let mut data = vec![0f32; w * h * c];
    for y in 0..h {
        for x in 0..w {
            // OpenCV samples at integer pixel coordinates here (remap convention).
            let xn = (x as f64 - cx) / fx;
            let yn = (y as f64 - cy) / fy;
            let r2 = xn * xn + yn * yn;
            let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            let xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn);
            let yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
            let (u, v) = (fx * xd + cx, fy * yd + cy);
            if !(u >= 0.0 && v >= 0.0 && u <= (w - 1) as f64 && v <= (h - 1) as f64) {
                continue;
            }
            let (u0, v0) = (u.floor() as usize, v.floor() as usize);
            let (u1, v1) = ((u0 + 1).min(w - 1), (v0 + 1).min(h - 1));
            let (a, b) = ((u - u0 as f64) as f32, (v - v0 as f64) as f32);
            for ch in 0..c {
                let top = src.at(u0, v0, ch) * (1.0 - a) + src.at(u1, v0, ch) * a;
                let bot = src.at(u0, v1, ch) * (1.0 - a) + src.at(u1, v1, ch) * a;
                data[(y * w + x) * c + ch] = top * (1.0 - b) + bot * b;
            }
        }
    }
    FloatImage {
        width: src.width,
        height: src.height,
        channels: c,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: u32, h: u32) -> FloatImage {
        FloatImage {
            width: w,
            height: h,
            channels: 1,
            data: (0..w * h).map(|i| (i % w) as f32).collect(),
        }
    }

    #[test]
    fn resize_preserves_constants_and_linear_ramps() {
        let flat = FloatImage {
            width: 16,
            height: 8,
            channels: 3,
            data: vec![7.0; 16 * 8 * 3],
        };
        for kernel in [Kernel::Linear, Kernel::Lanczos4] {
            for mode in [ResizeMode::AntiAliased, ResizeMode::Reference] {
                let r = resize(&flat, 5, 11, kernel, mode);
                assert!(r.data.iter().all(|v| (v - 7.0).abs() < 1e-4));
            }
        }
        // 2× down a ramp: both modes average neighbours, (2x + 2x+1)/2.
        for mode in [ResizeMode::AntiAliased, ResizeMode::Reference] {
            let r = resize(&ramp(8, 2), 4, 1, Kernel::Linear, mode);
            assert_eq!(r.data, vec![0.5, 2.5, 4.5, 6.5]);
        }
        // Shrunk by whole factors a ramp stays a ramp: each output pixel is its footprint's
        // centre value. By a fractional factor the footprint cuts pixels, which are constant
        // over their area, so the value is within a fraction of a step of the centre's.
        for (w, n, tolerance) in [(16u32, 4u32, 1e-4), (12, 4, 1e-4), (10, 3, 0.05)] {
            let r = resize(&ramp(w, 1), n, 1, Kernel::Lanczos4, ResizeMode::AntiAliased);
            let s = w as f32 / n as f32;
            for (d, v) in r.data.iter().enumerate() {
                let centre = (d as f32 + 0.5) * s - 0.5;
                assert!((v - centre).abs() < tolerance, "{w}→{n}: {:?}", r.data);
            }
        }
    }

    /// Stripes of a 3 px period (above the Nyquist frequency of a 4× smaller image) shrunk 4×:
    /// the anti-aliased resize equals the 4×4 box average (the supersampled training renders'
    /// filter: a quarter or half bright, by phase), the reference resize point-samples them
    /// into full-contrast aliases.
    #[test]
    fn shrinking_fine_stripes_leaves_no_aliasing() {
        let (w, h) = (64u32, 64u32);
        let stripes = FloatImage {
            width: w,
            height: h,
            channels: 1,
            // A period of 3 px: beats against the 4 px footprint in the reference resize.
            data: (0..w * h)
                .map(|i| if (i % w) % 3 == 0 { 255.0 } else { 0.0 })
                .collect(),
        };
        let box_average = |img: &FloatImage, f: u32| -> Vec<f32> {
            let (bw, bh) = (img.width / f, img.height / f);
            (0..bw * bh)
                .map(|o| {
                    let (x, y) = (o % bw, o / bw);
                    let mut sum = 0.0;
                    for dy in 0..f {
                        for dx in 0..f {
                            sum += img.data[((y * f + dy) * img.width + x * f + dx) as usize];
                        }
                    }
                    sum / (f * f) as f32
                })
                .collect()
        };
        let reference = box_average(&stripes, 4);
        let aa = resize(
            &stripes,
            w / 4,
            h / 4,
            Kernel::Lanczos4,
            ResizeMode::AntiAliased,
        );
        let worst = aa
            .data
            .iter()
            .zip(&reference)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(
            worst < 1e-3,
            "anti-aliased differs from the box average by {worst}"
        );
        // The aliasing energy: variance around the box average (0 for a perfect filter).
        let energy = |img: &[f32]| {
            img.iter()
                .zip(&reference)
                .map(|(a, b)| (a - b).powi(2))
                .sum::<f32>()
                / img.len() as f32
        };
        let cv = resize(
            &stripes,
            w / 4,
            h / 4,
            Kernel::Lanczos4,
            ResizeMode::Reference,
        );
        assert!(energy(&aa.data) < 1e-6);
        assert!(
            energy(&cv.data) > 100.0,
            "the reference resize aliases: {}",
            energy(&cv.data)
        );
    }

    #[test]
    fn k_scales_by_rows() {
        let k = [[800.0, 0.0, 512.0], [0.0, 810.0, 537.0], [0.0, 0.0, 1.0]];
        let s = scale_intrinsics(k, (1024, 1024), (512, 256));
        assert_eq!(s[0], [400.0, 0.0, 256.0]);
        assert_eq!(s[1], [0.0, 202.5, 134.25]);
        assert_eq!(s[2], [0.0, 0.0, 1.0]);
    }

    #[test]
    fn zero_distortion_is_identity_and_composite_mixes() {
        let img = ramp(6, 4);
        let k = [[5.0, 0.0, 3.0], [0.0, 5.0, 2.0], [0.0, 0.0, 1.0]];
        assert_eq!(undistort(&img, &k, &[0.0; 5]).data, img.data);
        let bent = undistort(&img, &k, &[0.3, 0.0, 0.0, 0.0]);
        assert_ne!(bent.data, img.data);
        let mut rgb = FloatImage {
            width: 1,
            height: 1,
            channels: 3,
            data: vec![200.0, 100.0, 0.0],
        };
        let alpha = FloatImage {
            width: 1,
            height: 1,
            channels: 1,
            data: vec![0.25],
        };
        composite(&mut rgb, &alpha, [0.0, 0.0, 255.0]);
        assert_eq!(rgb.data, vec![50.0, 25.0, 191.25]);
    }
}
