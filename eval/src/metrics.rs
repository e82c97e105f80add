//! Image metrics of the evaluation protocol (design.md §10.2–§10.4), computed on the host in f64.
//!
//! Images are row-major `H × W × C` slices of `f32` in [0, 1] (what a PNG divided by 255 gives),
//! wrapped in [`ImageRef`] so the shape travels with the data and mismatches are errors rather
//! than panics.
//!
//! - **PSNR** ([`psnr`]): `10·log10(max² / MSE)` with the MSE over every pixel and channel. With
//!   `max = 1` this is both the THuman script's `10·log10(1/MSE)` and AIST++'s
//!   `−10·log10(MSE)`. Identical images have MSE 0: we return `f64::INFINITY` (NumPy would give
//!   `inf` with a divide-by-zero warning).
//! - **SSIM** ([`ssim_skimage`]): scikit-image's `structural_similarity(pred, gt,
//!   channel_axis=2, data_range=1)` with its defaults: a 7×7 **uniform** window,
//!   `use_sample_covariance=True` (variances and covariance scaled by `N/(N−1)` with `N = 49`),
//!   `C1 = (0.01·L)²`, `C2 = (0.03·L)²`, `L = 1`. skimage filters the whole image (scipy's
//!   `uniform_filter`, mode "reflect") and then averages the SSIM map after cropping
//!   `(7−1)/2 = 3` pixels from every side; in that cropped region every window lies fully inside
//!   the image, so the reflect padding never matters and we compute only those valid windows
//!   (with summed-area tables, O(1) per pixel). The per-channel means are averaged over
//!   channels, as `channel_axis` does. Images smaller than 7 in height or width are an error, as
//!   in skimage.
//!   **Precision:** skimage keeps float32 inputs in float32 for the filtering (it promotes only
//!   the final mean to float64), while we accumulate in f64; expect differences around 1e-6.
//! - **THuman crop** ([`thuman_crop_box`], [`thuman_metrics`]): the script crops both images to
//!   a fixed **1000 × 500** (H × W) box around the GT foreground before PSNR and SSIM. The
//!   foreground is every GT pixel that is not exactly black in all channels (the stored GT has a
//!   black background; the mask file is read but unused). Per axis, with the foreground spanning
//!   `[lo, hi]` (inclusive, extent `n = hi − lo + 1`) and the crop size `S`, the box starts
//!   `⌊(S − n)/2⌋` before `lo` (floor division, so a foreground larger than `S` gives a box
//!   inside it) and is `S` long; if it would start before 0 it becomes `[0, S)`, else if it
//!   would end past the image it becomes `[len − S, len)`. A GT with no foreground is skipped
//!   by the script ("target is empty"): we return `None`. An image smaller than the crop is an
//!   error (the script would fail its assertion).
//!   The script resizes predictions that are not 1024² to the GT size with OpenCV before
//!   cropping; resizing is the caller's job here ([`thuman_metrics`] requires equal shapes).
//! - **AIST++** ([`full_image_metrics`]): the same PSNR and SSIM on the full uncropped images.
//! - **Where the error sits** ([`error_by_region`]): not a protocol metric but a diagnosis: the
//!   MSE split into the pixels near the ground-truth silhouette, those inside it and those
//!   outside, so two methods' PSNR gap can be traced to geometry (the band) or appearance (the
//!   inside).

use std::fmt;

/// Crop size of the THuman2.0 / XHuman protocol, `[height, width]`.
pub const THUMAN_CROP: [usize; 2] = [1000, 500];

/// Side of skimage's default uniform window.
pub const SKIMAGE_WIN_SIZE: usize = 7;

/// Errors of the metric functions.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MetricsError {
    /// The slice length is not `H·W·C`.
    #[error("image data has {len} values but its shape {shape:?} needs {}", shape[0] * shape[1] * shape[2])]
    DataLength {
        /// Length of the slice.
        len: usize,
        /// Declared `[H, W, C]`.
        shape: [usize; 3],
    },
    /// The two images differ in shape.
    #[error("prediction has shape {pred:?} (HWC) but ground truth has {gt:?}")]
    ShapeMismatch {
        /// Prediction `[H, W, C]`.
        pred: [usize; 3],
        /// Ground truth `[H, W, C]`.
        gt: [usize; 3],
    },
    /// An image has zero pixels or channels.
    #[error("image of shape {0:?} is empty")]
    Empty([usize; 3]),
    /// The image is smaller than the SSIM window (skimage raises the same).
    #[error("SSIM window {win}x{win} exceeds image extent {height}x{width}")]
    WindowTooLarge {
        /// Window side.
        win: usize,
        /// Image height.
        height: usize,
        /// Image width.
        width: usize,
    },
    /// skimage requires an odd window side.
    #[error("SSIM window side {0} must be odd")]
    EvenWindow(usize),
    /// The image is smaller than the evaluation crop.
    #[error("crop {crop:?} does not fit in an image of {height}x{width}")]
    CropTooLarge {
        /// Crop `[height, width]`.
        crop: [usize; 2],
        /// Image height.
        height: usize,
        /// Image width.
        width: usize,
    },
    /// A mask whose shape is not the image's `[H, W, 1]`.
    #[error("mask has shape {mask:?} (HWC) but the images are {image:?}")]
    MaskShape {
        /// Mask `[H, W, C]`.
        mask: [usize; 3],
        /// Image `[H, W, C]`.
        image: [usize; 3],
    },
}

/// A borrowed `H × W × C` row-major image.
#[derive(Clone, Copy)]
pub struct ImageRef<'a> {
    data: &'a [f32],
    shape: [usize; 3],
}

impl fmt::Debug for ImageRef<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ImageRef{:?}", self.shape)
    }
}

impl<'a> ImageRef<'a> {
    /// Wraps `data` as an image of shape `[H, W, C]`; the length must match and be non-zero.
    pub fn new(data: &'a [f32], shape: [usize; 3]) -> Result<Self, MetricsError> {
        if shape.contains(&0) {
            return Err(MetricsError::Empty(shape));
        }
        if data.len() != shape[0] * shape[1] * shape[2] {
            return Err(MetricsError::DataLength {
                len: data.len(),
                shape,
            });
        }
        Ok(Self { data, shape })
    }

    /// `[H, W, C]`.
    pub fn shape(&self) -> [usize; 3] {
        self.shape
    }

    /// The raw values.
    pub fn data(&self) -> &'a [f32] {
        self.data
    }

    fn at(&self, row: usize, col: usize, ch: usize) -> f64 {
        let [_, w, c] = self.shape;
        self.data[(row * w + col) * c + ch] as f64
    }
}

fn same_shape(pred: &ImageRef, gt: &ImageRef) -> Result<(), MetricsError> {
    if pred.shape != gt.shape {
        return Err(MetricsError::ShapeMismatch {
            pred: pred.shape,
            gt: gt.shape,
        });
    }
    Ok(())
}

/// Mean squared error over every pixel and channel, accumulated in f64.
pub fn mse(pred: ImageRef, gt: ImageRef) -> Result<f64, MetricsError> {
    same_shape(&pred, &gt)?;
    let sum: f64 = pred
        .data
        .iter()
        .zip(gt.data)
        .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
        .sum();
    Ok(sum / pred.data.len() as f64)
}

/// `10·log10(max² / MSE)`; `f64::INFINITY` for identical images.
pub fn psnr(pred: ImageRef, gt: ImageRef, max: f64) -> Result<f64, MetricsError> {
    let m = mse(pred, gt)?;
    if m == 0.0 {
        return Ok(f64::INFINITY);
    }
    Ok(10.0 * (max * max / m).log10())
}

/// Summed-area table of one channel (or of a product of two channels), `(H+1) × (W+1)`, so a
/// window sum is four lookups.
struct Integral {
    w1: usize,
    table: Vec<f64>,
}

impl Integral {
    fn new(h: usize, w: usize, value: impl Fn(usize, usize) -> f64) -> Self {
        let w1 = w + 1;
        let mut table = vec![0.0; (h + 1) * w1];
        for r in 0..h {
            let mut row_sum = 0.0;
            for c in 0..w {
                row_sum += value(r, c);
                table[(r + 1) * w1 + c + 1] = table[r * w1 + c + 1] + row_sum;
            }
        }
        Self { w1, table }
    }

    /// Sum over rows `[r0, r0+k)` and columns `[c0, c0+k)`.
    fn window(&self, r0: usize, c0: usize, k: usize) -> f64 {
        let t = &self.table;
        let (r1, c1) = (r0 + k, c0 + k);
        t[r1 * self.w1 + c1] - t[r0 * self.w1 + c1] - t[r1 * self.w1 + c0] + t[r0 * self.w1 + c0]
    }
}

/// skimage's `structural_similarity(pred, gt, channel_axis=2, data_range=1)` (7×7 uniform
/// window, sample covariance, border-cropped mean, averaged over channels).
pub fn ssim_skimage(pred: ImageRef, gt: ImageRef) -> Result<f64, MetricsError> {
    ssim_uniform(pred, gt, SKIMAGE_WIN_SIZE, 1.0)
}

/// [`ssim_skimage`] with an explicit odd window side and data range.
pub fn ssim_uniform(
    pred: ImageRef,
    gt: ImageRef,
    win: usize,
    data_range: f64,
) -> Result<f64, MetricsError> {
    same_shape(&pred, &gt)?;
    if win.is_multiple_of(2) {
        return Err(MetricsError::EvenWindow(win));
    }
    let [h, w, channels] = pred.shape;
    if h < win || w < win || win == 0 {
        return Err(MetricsError::WindowTooLarge {
            win,
            height: h,
            width: w,
        });
    }
    let np = (win * win) as f64;
    let cov_norm = np / (np - 1.0);
    let c1 = (0.01 * data_range).powi(2);
    let c2 = (0.03 * data_range).powi(2);
    let mut total = 0.0;
    for ch in 0..channels {
        let x = |r: usize, c: usize| pred.at(r, c, ch);
        let y = |r: usize, c: usize| gt.at(r, c, ch);
        let sx = Integral::new(h, w, x);
        let sy = Integral::new(h, w, y);
        let sxx = Integral::new(h, w, |r, c| x(r, c) * x(r, c));
        let syy = Integral::new(h, w, |r, c| y(r, c) * y(r, c));
        let sxy = Integral::new(h, w, |r, c| x(r, c) * y(r, c));
        // Window top-left corners whose window lies inside the image = skimage's cropped map.
        let mut sum = 0.0;
        for r0 in 0..=h - win {
            for c0 in 0..=w - win {
                let ux = sx.window(r0, c0, win) / np;
                let uy = sy.window(r0, c0, win) / np;
                let uxx = sxx.window(r0, c0, win) / np;
                let uyy = syy.window(r0, c0, win) / np;
                let uxy = sxy.window(r0, c0, win) / np;
                let vx = cov_norm * (uxx - ux * ux);
                let vy = cov_norm * (uyy - uy * uy);
                let vxy = cov_norm * (uxy - ux * uy);
                sum += ((2.0 * ux * uy + c1) * (2.0 * vxy + c2))
                    / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
            }
        }
        total += sum / ((h - win + 1) * (w - win + 1)) as f64;
    }
    Ok(total / channels as f64)
}

/// A crop window: rows `[top, top + height)`, columns `[left, left + width)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CropBox {
    /// First row.
    pub top: usize,
    /// First column.
    pub left: usize,
    /// Rows.
    pub height: usize,
    /// Columns.
    pub width: usize,
}

/// Places a window of `size` along an axis of length `len` around the foreground `[lo, hi]`
/// (see the module docs). Requires `size <= len`.
fn place_axis(lo: usize, hi: usize, size: usize, len: usize) -> usize {
    let extent = (hi + 1 - lo) as i64;
    let before = (size as i64 - extent).div_euclid(2);
    let start = lo as i64 - before;
    if start < 0 {
        0
    } else if start + size as i64 > len as i64 {
        len - size
    } else {
        start as usize
    }
}

/// The THuman evaluation crop of size `crop` (`[height, width]`, normally [`THUMAN_CROP`])
/// around the non-black pixels of `gt`; `None` when `gt` is black everywhere.
pub fn thuman_crop_box(gt: ImageRef, crop: [usize; 2]) -> Result<Option<CropBox>, MetricsError> {
    let [h, w, c] = gt.shape;
    if crop[0] > h || crop[1] > w {
        return Err(MetricsError::CropTooLarge {
            crop,
            height: h,
            width: w,
        });
    }
    let (mut rmin, mut rmax, mut cmin, mut cmax) = (usize::MAX, 0, usize::MAX, 0);
    for r in 0..h {
        for col in 0..w {
            let px = &gt.data[(r * w + col) * c..][..c];
            if px.iter().any(|&v| v != 0.0) {
                rmin = rmin.min(r);
                rmax = rmax.max(r);
                cmin = cmin.min(col);
                cmax = cmax.max(col);
            }
        }
    }
    if rmin == usize::MAX {
        return Ok(None);
    }
    Ok(Some(CropBox {
        top: place_axis(rmin, rmax, crop[0], h),
        left: place_axis(cmin, cmax, crop[1], w),
        height: crop[0],
        width: crop[1],
    }))
}

/// Copies the `bbox` region of `img`; returns the pixels and their `[H, W, C]` shape.
pub fn crop(img: ImageRef, bbox: CropBox) -> Result<(Vec<f32>, [usize; 3]), MetricsError> {
    let [h, w, c] = img.shape;
    if bbox.top + bbox.height > h || bbox.left + bbox.width > w {
        return Err(MetricsError::CropTooLarge {
            crop: [bbox.height, bbox.width],
            height: h,
            width: w,
        });
    }
    let mut out = Vec::with_capacity(bbox.height * bbox.width * c);
    for r in bbox.top..bbox.top + bbox.height {
        let start = (r * w + bbox.left) * c;
        out.extend_from_slice(&img.data[start..start + bbox.width * c]);
    }
    Ok((out, [bbox.height, bbox.width, c]))
}

/// PSNR and SSIM of one image pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageMetrics {
    /// [`psnr`] with `max = 1`.
    pub psnr: f64,
    /// [`ssim_skimage`].
    pub ssim: f64,
}

/// The AIST++ protocol (design.md §10.3): PSNR and SSIM on the full images.
pub fn full_image_metrics(pred: ImageRef, gt: ImageRef) -> Result<ImageMetrics, MetricsError> {
    Ok(ImageMetrics {
        psnr: psnr(pred, gt, 1.0)?,
        ssim: ssim_skimage(pred, gt)?,
    })
}

/// The THuman2.0 / XHuman protocol (design.md §10.2): crop both images to `crop` (normally
/// [`THUMAN_CROP`]) around the GT foreground, then PSNR and SSIM. `None` when the GT is
/// entirely black (the script skips such views).
pub fn thuman_metrics(
    pred: ImageRef,
    gt: ImageRef,
    crop_size: [usize; 2],
) -> Result<Option<ImageMetrics>, MetricsError> {
    same_shape(&pred, &gt)?;
    let Some(bbox) = thuman_crop_box(gt, crop_size)? else {
        return Ok(None);
    };
    let (p, shape) = crop(pred, bbox)?;
    let (g, _) = crop(gt, bbox)?;
    full_image_metrics(ImageRef::new(&p, shape)?, ImageRef::new(&g, shape)?).map(Some)
}

/// Half-width of the silhouette band of [`error_by_region`], in pixels. Two pixels hold the
/// loader's anti-aliased edge (one pixel each side) and a pixel of misplaced outline; at the
/// 128 px the demo models work at, a body is about 60 px tall, so the band is narrow against it.
pub const SILHOUETTE_BAND_PX: usize = 2;

/// A prediction's MSE split by where its pixels lie against the ground-truth silhouette: each
/// field is the region's squared error summed and divided by **all** the values of the image,
/// so the three add up to [`mse`] and `10·log10(1/(mse − silhouette))` is the PSNR the image
/// would have with a perfect band.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ErrorByRegion {
    /// Pixels within [`SILHOUETTE_BAND_PX`] (Chebyshev distance) of a pixel on the other side
    /// of the silhouette, either side.
    pub silhouette: f64,
    /// The part of `silhouette` on the ground truth's foreground side: edge colours and a
    /// prediction too small to cover the person land here, a prediction spilling over on the
    /// other side. Older logs lack it (zero).
    #[serde(default)]
    pub silhouette_foreground: f64,
    /// Foreground pixels farther in.
    pub inside: f64,
    /// Background pixels farther out.
    pub outside: f64,
}

impl ErrorByRegion {
    /// Field-wise mean (zero for none).
    pub fn mean<'a>(all: impl IntoIterator<Item = &'a ErrorByRegion>) -> ErrorByRegion {
        let (mut sum, mut n) = (ErrorByRegion::default(), 0usize);
        for e in all {
            sum.silhouette += e.silhouette;
            sum.silhouette_foreground += e.silhouette_foreground;
            sum.inside += e.inside;
            sum.outside += e.outside;
            n += 1;
        }
        let k = 1.0 / n.max(1) as f64;
        ErrorByRegion {
            silhouette: sum.silhouette * k,
            silhouette_foreground: sum.silhouette_foreground * k,
            inside: sum.inside * k,
            outside: sum.outside * k,
        }
    }

    /// The three fields' sum: the image's MSE.
    pub fn total(&self) -> f64 {
        self.silhouette + self.inside + self.outside
    }
}

/// Max (`keep_max`) or min of `v` over a `(2r+1)²` square around every pixel of an `h × w`
/// grid, the square clipped to the grid (separable: rows, then columns).
fn square_extreme(v: &[bool], h: usize, w: usize, r: usize, keep_max: bool) -> Vec<bool> {
    let pick = |acc: bool, x: bool| if keep_max { acc | x } else { acc & x };
    let mut rows = vec![false; v.len()];
    for y in 0..h {
        for x in 0..w {
            let (lo, hi) = (x.saturating_sub(r), (x + r).min(w - 1));
            rows[y * w + x] = (lo..=hi).map(|i| v[y * w + i]).fold(!keep_max, pick);
        }
    }
    let mut out = vec![false; v.len()];
    for y in 0..h {
        let (lo, hi) = (y.saturating_sub(r), (y + r).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (lo..=hi).map(|j| rows[j * w + x]).fold(!keep_max, pick);
        }
    }
    out
}

/// [`ErrorByRegion`] of `pred` against `gt`, the silhouette from `mask` (`[H, W, 1]`, the
/// foreground where it is at least ½), its band `band` pixels wide on each side.
pub fn error_by_region(
    pred: ImageRef,
    gt: ImageRef,
    mask: ImageRef,
    band: usize,
) -> Result<ErrorByRegion, MetricsError> {
    same_shape(&pred, &gt)?;
    let [h, w, c] = gt.shape;
    if mask.shape != [h, w, 1] {
        return Err(MetricsError::MaskShape {
            mask: mask.shape,
            image: gt.shape,
        });
    }
    let fg: Vec<bool> = mask.data.iter().map(|&m| m >= 0.5).collect();
    // A pixel is in the band when its square holds both sides: the dilation and the erosion
    // of the foreground disagree there.
    let grown = square_extreme(&fg, h, w, band, true);
    let shrunk = square_extreme(&fg, h, w, band, false);
    let mut out = ErrorByRegion::default();
    let norm = 1.0 / pred.data.len() as f64;
    for (i, ((p, g), (&big, &small))) in pred
        .data
        .chunks_exact(c)
        .zip(gt.data.chunks_exact(c))
        .zip(grown.iter().zip(&shrunk))
        .enumerate()
    {
        let sq: f64 = p
            .iter()
            .zip(g)
            .map(|(&a, &b)| (a as f64 - b as f64).powi(2))
            .sum::<f64>()
            * norm;
        let region = if big != small {
            if fg[i] {
                out.silhouette_foreground += sq;
            }
            &mut out.silhouette
        } else if fg[i] {
            &mut out.inside
        } else {
            &mut out.outside
        };
        *region += sq;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in [0, 1) from the workspace's seeded generator.
    fn pseudo_random(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = lifegom_render::rng::Rng::new(seed);
        (0..n).map(|_| rng.next_f32()).collect()
    }

    fn img(data: &[f32], shape: [usize; 3]) -> ImageRef<'_> {
        ImageRef::new(data, shape).unwrap()
    }

    /// skimage's SSIM written the slow way: gather each full 7×7 window, two-pass mean, sample
    /// (co)variance with N − 1, average over the valid windows, then over channels.
    fn slow_ssim(x: &[f32], y: &[f32], [h, w, c]: [usize; 3]) -> f64 {
        let (c1, c2) = (1e-4, 9e-4);
        let mut per_channel = Vec::new();
        for ch in 0..c {
            let mut values = Vec::new();
            for i in 3..h - 3 {
                for j in 3..w - 3 {
                    let mut xs = Vec::new();
                    let mut ys = Vec::new();
                    for di in 0..7 {
                        for dj in 0..7 {
                            let k = ((i + di - 3) * w + (j + dj - 3)) * c + ch;
                            xs.push(x[k] as f64);
                            ys.push(y[k] as f64);
                        }
                    }
                    let n = xs.len() as f64;
                    let mx = xs.iter().sum::<f64>() / n;
                    let my = ys.iter().sum::<f64>() / n;
                    let vx = xs.iter().map(|v| (v - mx).powi(2)).sum::<f64>() / (n - 1.0);
                    let vy = ys.iter().map(|v| (v - my).powi(2)).sum::<f64>() / (n - 1.0);
                    let cxy = xs
                        .iter()
                        .zip(&ys)
                        .map(|(a, b)| (a - mx) * (b - my))
                        .sum::<f64>()
                        / (n - 1.0);
                    values.push(
                        ((2.0 * mx * my + c1) * (2.0 * cxy + c2))
                            / ((mx * mx + my * my + c1) * (vx + vy + c2)),
                    );
                }
            }
            per_channel.push(values.iter().sum::<f64>() / values.len() as f64);
        }
        per_channel.iter().sum::<f64>() / c as f64
    }

    #[test]
    fn identical_images_are_perfect() {
        let shape = [12, 10, 3];
        let x = pseudo_random(360, 1);
        assert_eq!(psnr(img(&x, shape), img(&x, shape), 1.0), Ok(f64::INFINITY));
        let s = ssim_skimage(img(&x, shape), img(&x, shape)).unwrap();
        assert!((s - 1.0).abs() < 1e-12, "{s}");
    }

    #[test]
    fn psnr_of_known_noise() {
        // ±1/8 around 0.5 (exact in f32): MSE = 1/64, PSNR = 10·log10(64) ≈ 18.06 dB.
        let shape = [4, 6, 3];
        let gt = vec![0.5f32; 72];
        let pred: Vec<f32> = (0..72)
            .map(|i| if i % 2 == 0 { 0.625 } else { 0.375 })
            .collect();
        assert_eq!(mse(img(&pred, shape), img(&gt, shape)), Ok(1.0 / 64.0));
        let p = psnr(img(&pred, shape), img(&gt, shape), 1.0).unwrap();
        assert!((p - 10.0 * 64f64.log10()).abs() < 1e-12, "{p}");
        // The same images on a 0..255 scale give the same PSNR with max 255.
        let scale = |v: &[f32]| v.iter().map(|x| x * 255.0).collect::<Vec<_>>();
        let (pred255, gt255) = (scale(&pred), scale(&gt));
        let p255 = psnr(img(&pred255, shape), img(&gt255, shape), 255.0).unwrap();
        assert!((p255 - p).abs() < 1e-9);
        // Doubling the error costs 20·log10(2) ≈ 6.02 dB.
        let pred2: Vec<f32> = (0..72)
            .map(|i| if i % 2 == 0 { 0.75 } else { 0.25 })
            .collect();
        let p2 = psnr(img(&pred2, shape), img(&gt, shape), 1.0).unwrap();
        assert!((p - p2 - 20.0 * 2f64.log10()).abs() < 1e-12);
    }

    #[test]
    fn ssim_matches_slow_reference() {
        for (shape, seed) in [([9, 11, 3], 5), ([7, 7, 1], 6), ([15, 8, 2], 7)] {
            let n = shape.iter().product();
            let x = pseudo_random(n, seed);
            let y: Vec<f32> = pseudo_random(n, seed + 100)
                .iter()
                .zip(&x)
                .map(|(r, v)| 0.6 * v + 0.4 * r)
                .collect();
            let fast = ssim_skimage(img(&x, shape), img(&y, shape)).unwrap();
            let slow = slow_ssim(&x, &y, shape);
            assert!((fast - slow).abs() < 1e-12, "{shape:?}: {fast} vs {slow}");
            let back = ssim_skimage(img(&y, shape), img(&x, shape)).unwrap();
            assert!((fast - back).abs() < 1e-12, "not symmetric");
            assert!(fast < 1.0 && fast > 0.0);
        }
    }

    #[test]
    fn ssim_of_constant_images_by_hand() {
        // Zero variances: the contrast term is C2/C2 = 1, leaving (2ab + C1)/(a² + b² + C1).
        let shape = [8, 9, 3];
        let (a, b) = (0.25f32, 0.75f32);
        let x = vec![a; 216];
        let y = vec![b; 216];
        let s = ssim_skimage(img(&x, shape), img(&y, shape)).unwrap();
        let (a, b) = (a as f64, b as f64);
        let hand = (2.0 * a * b + 1e-4) / (a * a + b * b + 1e-4);
        assert!((s - hand).abs() < 1e-12, "{s} vs {hand}");
        // Only the 7×7 windows fully inside the image count: on 8×9 that is 2×3 windows.
        let mut x2 = x.clone();
        x2[0] = 0.9; // lies in the single window at the top-left corner
        let fast = ssim_skimage(img(&x2, shape), img(&y, shape)).unwrap();
        assert!((fast - slow_ssim(&x2, &y, shape)).abs() < 1e-12);
        assert!(fast != s);
    }

    #[test]
    fn errors_instead_of_panics() {
        let a = vec![0.0f32; 8 * 8 * 3];
        let b = vec![0.0f32; 8 * 9 * 3];
        let (ia, ib) = (img(&a, [8, 8, 3]), img(&b, [8, 9, 3]));
        let mismatch = MetricsError::ShapeMismatch {
            pred: [8, 8, 3],
            gt: [8, 9, 3],
        };
        assert_eq!(psnr(ia, ib, 1.0), Err(mismatch.clone()));
        assert_eq!(ssim_skimage(ia, ib), Err(mismatch.clone()));
        assert_eq!(thuman_metrics(ia, ib, [4, 4]), Err(mismatch.clone()));
        assert!(mismatch.to_string().contains("[8, 8, 3]"));
        assert!(matches!(
            ImageRef::new(&a, [8, 8, 4]),
            Err(MetricsError::DataLength { len: 192, .. })
        ));
        assert_eq!(
            ImageRef::new(&[], [0, 4, 3]).unwrap_err(),
            MetricsError::Empty([0, 4, 3])
        );
        assert_eq!(
            ssim_uniform(ia, ia, 4, 1.0),
            Err(MetricsError::EvenWindow(4))
        );
        let small = vec![0.0f32; 6 * 9];
        assert!(matches!(
            ssim_skimage(img(&small, [6, 9, 1]), img(&small, [6, 9, 1])),
            Err(MetricsError::WindowTooLarge { win: 7, .. })
        ));
        assert!(matches!(
            thuman_crop_box(ia, [9, 4]),
            Err(MetricsError::CropTooLarge { .. })
        ));
    }

    /// A black `h × w` image with the given pixels lit (channel 2 only, to check "not black in
    /// all channels" means any non-zero channel).
    fn lit(h: usize, w: usize, pixels: &[(usize, usize)]) -> Vec<f32> {
        let mut v = vec![0.0f32; h * w * 3];
        for &(r, c) in pixels {
            v[(r * w + c) * 3 + 2] = 0.5;
        }
        v
    }

    #[test]
    fn thuman_crop_box_placement() {
        let (h, w) = (20, 16);
        let bbox = |pixels: &[(usize, usize)], crop: [usize; 2]| {
            let gt = lit(h, w, pixels);
            thuman_crop_box(img(&gt, [h, w, 3]), crop).unwrap()
        };
        let at = |top, left, height, width| {
            Some(CropBox {
                top,
                left,
                height,
                width,
            })
        };
        // Foreground rows 8..=10 (3 tall), cols 5..=6 (2 wide): centred with the odd pixel
        // after, i.e. ⌊(6−3)/2⌋ = 1 row before and ⌊(4−2)/2⌋ = 1 column before.
        assert_eq!(bbox(&[(8, 5), (10, 6)], [6, 4]), at(7, 4, 6, 4));
        // Near the top-left: clamped to start at 0.
        assert_eq!(bbox(&[(0, 0), (1, 1)], [6, 4]), at(0, 0, 6, 4));
        // Near the bottom-right: shifted to end at the image edge.
        assert_eq!(bbox(&[(18, 14), (19, 15)], [6, 4]), at(14, 12, 6, 4));
        // Foreground taller than the crop: floor division gives a window inside it.
        assert_eq!(bbox(&[(2, 7), (15, 7)], [6, 4]), at(6, 6, 6, 4));
        // All black: skipped.
        assert_eq!(bbox(&[], [6, 4]), None);
        // The real protocol size on a 1024² canvas: a 600×200 figure at rows 300..=899 would
        // be centred at rows [100, 1100), past the bottom, so it is shifted to [24, 1024);
        // columns 400..=599 centre exactly at [250, 750).
        let (h, w) = (1024, 1024);
        let gt = lit(h, w, &[(300, 400), (899, 599)]);
        assert_eq!(
            thuman_crop_box(img(&gt, [h, w, 3]), THUMAN_CROP).unwrap(),
            at(24, 250, 1000, 500)
        );
        let gt = lit(h, w, &[(20, 400), (519, 599)]);
        assert_eq!(
            thuman_crop_box(img(&gt, [h, w, 3]), THUMAN_CROP).unwrap(),
            at(0, 250, 1000, 500)
        );
    }

    #[test]
    fn thuman_metrics_use_only_the_crop() {
        let (h, w) = (24, 20);
        let shape = [h, w, 3];
        let mut gt = lit(h, w, &[(10, 9), (13, 11)]);
        // Texture inside the eventual crop so SSIM is not trivial.
        for (k, v) in pseudo_random(h * w * 3, 3).iter().enumerate() {
            let (r, c) = (k / 3 / w, k / 3 % w);
            if (9..15).contains(&r) && (8..13).contains(&c) {
                gt[k] = *v;
            }
        }
        let mut pred: Vec<f32> = gt.iter().map(|v| (v * 0.9 + 0.05).min(1.0)).collect();
        let crop_size = [10, 8];
        let bbox = thuman_crop_box(img(&gt, shape), crop_size)
            .unwrap()
            .unwrap();
        let got = thuman_metrics(img(&pred, shape), img(&gt, shape), crop_size)
            .unwrap()
            .unwrap();
        let (pc, cshape) = crop(img(&pred, shape), bbox).unwrap();
        let (gc, _) = crop(img(&gt, shape), bbox).unwrap();
        assert_eq!(cshape, [10, 8, 3]);
        let expect = full_image_metrics(img(&pc, cshape), img(&gc, cshape)).unwrap();
        assert_eq!(got, expect);
        assert!((expect.ssim - slow_ssim(&pc, &gc, cshape)).abs() < 1e-12);
        // Errors outside the crop change nothing.
        pred[0] = 1.0;
        pred[h * w * 3 - 1] = 1.0;
        let again = thuman_metrics(img(&pred, shape), img(&gt, shape), crop_size).unwrap();
        assert_eq!(again, Some(expect));
    }

    /// A square body on black: an error confined to its outline lands in the band, one on its
    /// middle inside, one in a far corner outside, and the three always sum to the MSE.
    #[test]
    fn error_by_region_sorts_pixels_by_the_silhouette() {
        let (h, w) = (20, 20);
        let mut mask = vec![0.0f32; h * w];
        for y in 5..15 {
            for x in 5..15 {
                mask[y * w + x] = 1.0;
            }
        }
        let gt = vec![0.25f32; h * w * 3];
        let with_error_at = |pixels: &[(usize, usize)]| {
            let mut p = gt.clone();
            for &(y, x) in pixels {
                p[(y * w + x) * 3] += 0.5;
            }
            p
        };
        let shape = [h, w, 3];
        let m = img(&mask, [h, w, 1]);
        let score = |p: &[f32]| error_by_region(img(p, shape), img(&gt, shape), m, 2).unwrap();
        let one = 0.25 / (h * w * 3) as f64;
        // The outline's corner (5, 5), just outside it (4, 9) and two in (6, 6): the band.
        let band = score(&with_error_at(&[(5, 5), (4, 9), (6, 6)]));
        assert!((band.silhouette - 3.0 * one).abs() < 1e-12, "{band:?}");
        // Two of them on the body's side.
        assert!(
            (band.silhouette_foreground - 2.0 * one).abs() < 1e-12,
            "{band:?}"
        );
        assert_eq!((band.inside, band.outside), (0.0, 0.0));
        // Three in from the edge is inside; three out is outside.
        let inside = score(&with_error_at(&[(8, 8), (10, 11)]));
        assert!((inside.inside - 2.0 * one).abs() < 1e-12, "{inside:?}");
        assert_eq!((inside.silhouette, inside.outside), (0.0, 0.0));
        let outside = score(&with_error_at(&[(0, 0), (2, 10)]));
        assert!((outside.outside - 2.0 * one).abs() < 1e-12, "{outside:?}");
        // Any error: the regions add up to the MSE.
        let noise: Vec<f32> = pseudo_random(h * w * 3, 7);
        let e = score(&noise);
        let total = mse(img(&noise, shape), img(&gt, shape)).unwrap();
        assert!((e.total() - total).abs() < 1e-12 * total.max(1.0));
        assert!(e.silhouette > 0.0 && e.inside > 0.0 && e.outside > 0.0);
        assert!(0.0 < e.silhouette_foreground && e.silhouette_foreground < e.silhouette);
        // A mask of another size is an error naming both shapes, not a panic.
        let small = vec![0.0f32; 10];
        assert_eq!(
            error_by_region(
                img(&noise, shape),
                img(&gt, shape),
                img(&small, [2, 5, 1]),
                2
            ),
            Err(MetricsError::MaskShape {
                mask: [2, 5, 1],
                image: shape
            })
        );
    }
}
