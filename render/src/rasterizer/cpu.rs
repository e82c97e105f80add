//! The rasterizer's math as plain functions over `f32` slices: the CPU implementation of the op,
//! and the reference the GPU kernels are tested against.
//!
//! # Algorithm (forward)
//!
//! 1. **Project** every Gaussian (in parallel): view transform, frustum cull at `z ≤ 0.2`, EWA
//!    2D covariance `J W Σ Wᵀ Jᵀ + 0.3·I` with the reference's clamp of `x/z`, `y/z` to
//!    `±1.3·tan(fov/2)` inside `J`, conic, screen radius, and the rectangle of 16×16 tiles the
//!    Gaussian touches.
//! 2. **Sort** the survivors front to back by view depth; ties break by Gaussian index, so the
//!    output never depends on thread scheduling.
//! 3. **Bin**: per-tile lists of Gaussian ids (`gaussian_from_isect`), each already in depth
//!    order because Gaussians are appended in sorted order; `tile_offsets` delimits them.
//! 4. **Blend** each tile (rows of tiles in parallel), Gaussian-major: for each Gaussian of the
//!    tile list, visit only the pixels of the box outside which its alpha is provably below the
//!    cutoff (an exact shortcut, not an approximation: every skipped pixel would be skipped by
//!    the `alpha < 1/255` rule anyway). Per pixel: `α = min(0.99, o·exp(−½dᵀQd))`, skip if
//!    `α < 1/255`, stop when `T·(1−α) < 1e-4`, accumulate `Σ fᵢ αᵢ Tᵢ`.
//!
//! Pixel `(x, y)` is evaluated at the integer point `(x, y)` against the projected centre shifted
//! by −½, as in the reference (pixel `i` covers `[i, i+1)` in `K`-projected coordinates).
//!
//! # Algorithm (backward)
//!
//! The forward saves, per pixel, the final transmittance and the number of tile-list entries up
//! to the last one that blended. The backward replays each tile's list back to front, undoing
//! the blend (`Tᵢ = Tᵢ₊₁ / (1 − αᵢ)`, safe because `α ≤ 0.99`) and carrying the colour of
//! everything behind (`Sᵢ₋₁ = fᵢαᵢ + (1−αᵢ)Sᵢ`), so `∂C/∂αᵢ = Tᵢ (fᵢ − Sᵢ)`. Each (tile, Gaussian)
//! intersection accumulates its gradient in its own slot, so tiles run in parallel without
//! atomics and the reduction into per-Gaussian gradients is sequential and deterministic. A
//! per-Gaussian pass then chains the 2D gradients back through the conic, the EWA Jacobian and
//! the view transform to the 3D mean and covariance.
//!
//! Gradients are the exact derivatives of the forward as written, including the ones the
//! reference approximates: nothing flows through a clamped `α = 0.99` or a clamped `x/z`.
//!
//! # Channels
//!
//! Each Gaussian carries the feature `f = [r, g, b, 1, z]`: the output is premultiplied RGB, the
//! accumulated alpha `Σαᵢ Tᵢ = 1 − T_final` (the reference renders a constant 4th colour channel
//! of 1 to get its mask), and optionally the expected depth `Σ zᵢαᵢTᵢ` (not normalised).

use crate::camera::ViewParams;
use rayon::prelude::*;

/// Tile side, pixels.
pub const TILE: usize = 16;
/// Low-pass dilation added to the 2D covariance diagonal, px².
pub const DILATION: f32 = 0.3;
/// Upper clamp on a Gaussian's alpha.
pub const ALPHA_MAX: f32 = 0.99;
/// Hard cutoff: alphas below this are skipped.
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
/// Transmittance below which a pixel stops blending.
pub const T_MIN: f32 = 1e-4;
/// View-space depth at or below which a Gaussian is culled.
pub const NEAR_Z: f32 = 0.2;
/// The EWA Jacobian is evaluated with `x/z` clamped to `±FOV_CLAMP·tan(fovx/2)` (same for y).
pub const FOV_CLAMP: f32 = 1.3;
/// Smooth cutoff (tests only): alpha ramps with a C¹ smoothstep from 0 at `SMOOTH_LO` to itself
/// at `SMOOTH_HI`, so finite differences see a differentiable function.
pub const SMOOTH_LO: f32 = 0.5 / 255.0;
/// See [`SMOOTH_LO`].
pub const SMOOTH_HI: f32 = 1.5 / 255.0;
/// Floats per intersection gradient slot: xy 2, conic 3, opacity 1, rgb 3, depth 1.
const SLOT: usize = 10;

/// How alpha is cut off near zero.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum AlphaCutoff {
    /// The reference rule: skip `α < 1/255`. Tiles are bounded by the 3σ radius.
    #[default]
    Hard,
    /// A C¹ ramp (tests only, for exact finite differences); tiles are bounded by the radius
    /// where the ramp reaches zero, so nothing is truncated.
    Smooth,
}

/// Which channels the op writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Channels {
    /// `[r, g, b, alpha]`.
    #[default]
    RgbAlpha,
    /// `[r, g, b, alpha, depth]`.
    RgbAlphaDepth,
}

impl Channels {
    /// Number of output channels.
    pub const fn count(self) -> usize {
        match self {
            Channels::RgbAlpha => 4,
            Channels::RgbAlphaDepth => 5,
        }
    }

    /// The widths of the colour, alpha (and depth) blocks of the channels.
    pub const fn block_widths(self) -> &'static [usize] {
        match self {
            Channels::RgbAlpha => &[3, 1],
            Channels::RgbAlphaDepth => &[3, 1, 1],
        }
    }
}

/// Everything the op needs besides the Gaussians. Plain data, `Copy`, so it crosses Burn's
/// dispatch boundary unchanged.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RasterConfig {
    /// Camera and image size.
    pub view: ViewParams,
    /// Output channels.
    pub channels: Channels,
    /// Alpha cutoff rule.
    pub cutoff: AlphaCutoff,
}

impl RasterConfig {
    /// The output image's shape, `[H, W, C]`.
    pub fn image_shape(&self) -> burn::tensor::Shape {
        burn::tensor::Shape::new([
            self.view.height as usize,
            self.view.width as usize,
            self.channels.count(),
        ])
    }

    fn tiles(&self) -> (usize, usize) {
        let w = self.view.width as usize;
        let h = self.view.height as usize;
        (w.div_ceil(TILE), h.div_ceil(TILE))
    }
}

/// [`RasterConfig`] for several views of one image size, rendered in one call
/// ([`super::rasterize_views`]); the output is `[n, H, W, C]`. Not `Copy` (the views are a
/// list); it crosses Burn's dispatch boundary as a clone.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewsConfig {
    /// Camera and image size of each view, at least one; all of one size.
    pub views: Vec<ViewParams>,
    /// Output channels.
    pub channels: Channels,
    /// Alpha cutoff rule.
    pub cutoff: AlphaCutoff,
}

impl ViewsConfig {
    /// The output image's shape, `[n, H, W, C]`.
    pub fn image_shape(&self) -> burn::tensor::Shape {
        let one = self.view(0).image_shape();
        burn::tensor::Shape::new([self.views.len(), one[0], one[1], one[2]])
    }

    /// View `k`'s single-view configuration.
    ///
    /// # Panics
    ///
    /// If `k` is not below the number of views.
    pub fn view(&self, k: usize) -> RasterConfig {
        RasterConfig {
            view: self.views[k],
            channels: self.channels,
            cutoff: self.cutoff,
        }
    }
}

/// The Gaussians, as flat slices: means `[N,3]`, covariances `[N,6]` (xx, xy, xz, yy, yz, zz),
/// colours `[N,3]`, opacities `[N]`.
#[derive(Debug, Clone, Copy)]
pub struct GaussianSlices<'a> {
    /// `[N*3]`.
    pub means: &'a [f32],
    /// `[N*6]`.
    pub covariances: &'a [f32],
    /// `[N*3]`.
    pub colors: &'a [f32],
    /// `[N]`.
    pub opacities: &'a [f32],
}

impl GaussianSlices<'_> {
    /// Number of Gaussians; panics (a programming error, checked at the API) if lengths disagree.
    pub fn len(&self) -> usize {
        let n = self.opacities.len();
        assert!(
            self.means.len() == 3 * n
                && self.covariances.len() == 6 * n
                && self.colors.len() == 3 * n,
            "GaussianSlices: inconsistent lengths"
        );
        n
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A Gaussian after projection: what blending needs, and nothing more. Blending reads one of
/// these per tile intersection, in depth order, i.e. at random: keeping it at 32 bytes (two per
/// cache line) is worth more than caching derived values.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Splat2d {
    /// Centre in the reference pixel frame (projected `u − ½`, `v − ½`).
    pub xy: [f32; 2],
    /// Inverse 2D covariance `(A, B, C)`: `Q = [[A, B], [B, C]]`.
    pub conic: [f32; 3],
    /// Opacity.
    pub opacity: f32,
    /// View-space depth.
    pub depth: f32,
    /// `ln(cutoff / opacity)`: below this exponent alpha is under the cutoff, so `exp` can be
    /// skipped.
    pub log_cutoff: f32,
}

impl Splat2d {
    /// Half-extents, in pixels, of the box outside which alpha is below the cutoff: where
    /// `dᵀQd = k²` with `k² = −2·log_cutoff`, i.e. `k·√Σxx` and `k·√Σyy`. The 1e-3 relative
    /// margin keeps boundary pixels whose alpha equals the cutoff up to rounding.
    #[inline]
    pub fn extent(&self) -> [f32; 2] {
        let [qa, qb, qc] = self.conic;
        let inv_det = 1.0 / (qa * qc - qb * qb);
        let k2 = -2.0 * self.log_cutoff;
        [
            (k2 * qc * inv_det).sqrt() * 1.001 + 1e-3,
            (k2 * qa * inv_det).sqrt() * 1.001 + 1e-3,
        ]
    }
}

/// A projected Gaussian and the tiles it touches (`[x0, y0, x1, y1)`, in tiles).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Projected {
    /// What blending needs.
    pub splat: Splat2d,
    /// Tile rectangle, used only for binning.
    pub tiles: [u32; 4],
}

#[inline]
fn cutoff_threshold(cutoff: AlphaCutoff) -> f32 {
    match cutoff {
        AlphaCutoff::Hard => ALPHA_MIN,
        AlphaCutoff::Smooth => SMOOTH_LO,
    }
}

/// Projects one Gaussian; `None` when culled. Every guard is worded so that NaN fails it.
pub fn project_one(
    cfg: &RasterConfig,
    mean: [f32; 3],
    cov: [f32; 6],
    opacity: f32,
) -> Option<Projected> {
    let v = &cfg.view;
    let m = &v.view;
    let tx = m[0] * mean[0] + m[1] * mean[1] + m[2] * mean[2] + m[3];
    let ty = m[4] * mean[0] + m[5] * mean[1] + m[6] * mean[2] + m[7];
    let tz = m[8] * mean[0] + m[9] * mean[1] + m[10] * mean[2] + m[11];
    if !(tz > NEAR_Z && tz.is_finite() && tx.is_finite() && ty.is_finite()) {
        return None;
    }
    let thr = cutoff_threshold(cfg.cutoff);
    // A Gaussian that can never reach the cutoff contributes nothing anywhere.
    if !(opacity > thr && opacity.is_finite()) {
        return None;
    }
    let cov2 = ewa_cov2d(cfg, [tx, ty, tz], cov);
    let [a, b, c] = cov2;
    let det = a * c - b * b;
    if !(det > 0.0 && a > 0.0 && det.is_finite()) {
        return None;
    }
    let conic = [c / det, -b / det, a / det];
    let mid = 0.5 * (a + c);
    let lambda_max = mid + (mid * mid - det).max(0.1).sqrt();
    // Alpha reaches the cutoff where dᵀQd = k², k² = 2 ln(o/thr); the opacity is not capped here
    // because α ≥ thr ⇔ o·G ≥ thr whenever thr < 0.99.
    let k2 = 2.0 * (opacity / thr).ln();
    let radius = match cfg.cutoff {
        AlphaCutoff::Hard => (3.0 * lambda_max.sqrt()).ceil(),
        AlphaCutoff::Smooth => (k2 * lambda_max).sqrt().ceil(),
    };
    let xy = [v.fx * tx / tz + v.cx - 0.5, v.fy * ty / tz + v.cy - 0.5];
    let splat = Splat2d {
        xy,
        conic,
        opacity,
        depth: tz,
        log_cutoff: -0.5 * k2,
    };
    let extent = splat.extent();
    if !(xy[0].is_finite()
        && xy[1].is_finite()
        && radius.is_finite()
        && extent[0].is_finite()
        && extent[1].is_finite())
    {
        return None;
    }
    let (gx, gy) = cfg.tiles();
    let t = TILE as f32;
    let clamp_tile = |x: f32, g: usize| (x.floor().max(0.0) as u64).min(g as u64) as u32;
    let tile_min = [
        clamp_tile((xy[0] - radius) / t, gx),
        clamp_tile((xy[1] - radius) / t, gy),
    ];
    let tile_max = [
        clamp_tile((xy[0] + radius + t - 1.0) / t, gx),
        clamp_tile((xy[1] + radius + t - 1.0) / t, gy),
    ];
    if tile_max[0] <= tile_min[0] || tile_max[1] <= tile_min[1] {
        return None;
    }
    Some(Projected {
        splat,
        tiles: [tile_min[0], tile_min[1], tile_max[0], tile_max[1]],
    })
}

/// The EWA Jacobian rows (`J00`, `J02`, `J11`, `J12`) and whether x/y were clamped.
#[inline]
#[allow(clippy::neg_cmp_op_on_partial_ord)] // a NaN ratio counts as clamped
fn ewa_jacobian(cfg: &RasterConfig, t: [f32; 3]) -> ([f32; 4], [bool; 2]) {
    let v = &cfg.view;
    let limx = FOV_CLAMP * v.width as f32 / (2.0 * v.fx);
    let limy = FOV_CLAMP * v.height as f32 / (2.0 * v.fy);
    let z = t[2];
    let xz = t[0] / z;
    let yz = t[1] / z;
    let clamped = [!(xz.abs() <= limx), !(yz.abs() <= limy)];
    let txc = xz.clamp(-limx, limx) * z;
    let tyc = yz.clamp(-limy, limy) * z;
    let z2 = z * z;
    (
        [v.fx / z, -v.fx * txc / z2, v.fy / z, -v.fy * tyc / z2],
        clamped,
    )
}

/// `T = J·R` (2×3), rows.
#[inline]
fn jw(j: [f32; 4], r: &[f32; 12]) -> [[f32; 3]; 2] {
    [
        [
            j[0] * r[0] + j[1] * r[8],
            j[0] * r[1] + j[1] * r[9],
            j[0] * r[2] + j[1] * r[10],
        ],
        [
            j[2] * r[4] + j[3] * r[8],
            j[2] * r[5] + j[3] * r[9],
            j[2] * r[6] + j[3] * r[10],
        ],
    ]
}

#[inline]
fn sym3(c: [f32; 6]) -> [[f32; 3]; 3] {
    [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
}

#[inline]
fn mat3_vec(m: &[[f32; 3]; 3], v: [f32; 3]) -> [f32; 3] {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

#[inline]
fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Dilated 2D covariance `(a, b, c)` of a Gaussian at view-space position `t`.
#[inline]
fn ewa_cov2d(cfg: &RasterConfig, t: [f32; 3], cov: [f32; 6]) -> [f32; 3] {
    let (j, _) = ewa_jacobian(cfg, t);
    let tm = jw(j, &cfg.view.view);
    let s = sym3(cov);
    let s0 = mat3_vec(&s, tm[0]);
    let s1 = mat3_vec(&s, tm[1]);
    [
        dot3(tm[0], s0) + DILATION,
        dot3(tm[0], s1),
        dot3(tm[1], s1) + DILATION,
    ]
}

/// Alpha of a splat at offset `d` from its centre, with the derivative of the final alpha
/// w.r.t. the raw `o·G` product and `G` itself. `None` where the pixel skips the splat.
#[inline(always)]
fn eval_alpha(s: &Splat2d, dx: f32, dy: f32, cutoff: AlphaCutoff) -> Option<(f32, f32, f32)> {
    let [qa, qb, qc] = s.conic;
    let power = -0.5 * (qa * dx * dx + qc * dy * dy) - qb * dx * dy;
    // Outside [log_cutoff, 0] the pixel skips the splat (below the cutoff, or a non-PD conic).
    if power > 0.0 || power < s.log_cutoff {
        return None;
    }
    let g = power.exp();
    let raw = s.opacity * g;
    let (capped, dcap) = if raw > ALPHA_MAX {
        (ALPHA_MAX, 0.0)
    } else {
        (raw, 1.0)
    };
    match cutoff {
        AlphaCutoff::Hard => (capped >= ALPHA_MIN).then_some((capped, dcap, g)),
        AlphaCutoff::Smooth => {
            if capped <= SMOOTH_LO {
                return None;
            }
            let width = SMOOTH_HI - SMOOTH_LO;
            let u = ((capped - SMOOTH_LO) / width).min(1.0);
            let w = u * u * (3.0 - 2.0 * u);
            let dw = 6.0 * u * (1.0 - u) / width;
            Some((capped * w, dcap * (w + capped * dw), g))
        }
    }
}

/// The pixel range `[lo, hi)` along one axis where a splat can be above the cutoff, within
/// `[start, end)`.
#[inline]
fn axis_range(center: f32, extent: f32, start: usize, end: usize) -> (usize, usize) {
    let lo = (center - extent).ceil().max(start as f32) as usize;
    let hi = ((center + extent).floor() + 1.0).min(end as f32).max(0.0) as usize;
    (lo.max(start), hi.max(lo.max(start)))
}

/// Everything the backward needs from the forward, besides the inputs themselves.
#[derive(Debug, Clone)]
pub struct ForwardState {
    /// The config the forward ran with.
    pub cfg: RasterConfig,
    /// Number of Gaussians.
    pub num_gaussians: usize,
    /// Projected Gaussians (meaningless where `visible` is false).
    pub splats: Vec<Splat2d>,
    /// Whether each Gaussian survived culling.
    pub visible: Vec<bool>,
    /// `[num_tiles + 1]` offsets into `gaussian_from_isect`.
    pub tile_offsets: Vec<u32>,
    /// Per intersection, the Gaussian id; each tile's range is front to back.
    pub gaussian_from_isect: Vec<u32>,
    /// Per pixel, the number of tile-list entries up to the last that blended.
    pub last_contrib: Vec<u32>,
    /// Per pixel, the transmittance after the last blended Gaussian.
    pub final_t: Vec<f32>,
}

/// Projection, sort and binning: the part of the forward shared with the backward.
#[tracing::instrument(level = "trace", skip_all)]
fn project_and_bin(
    cfg: &RasterConfig,
    g: &GaussianSlices,
) -> (Vec<Splat2d>, Vec<bool>, Vec<u32>, Vec<u32>) {
    let n = g.len();
    let mut splats = vec![Splat2d::default(); n];
    let mut tiles = vec![[0u32; 4]; n];
    let mut visible = vec![false; n];
    {
        let _span = tracing::trace_span!("project").entered();
        splats
            .par_iter_mut()
            .zip(tiles.par_iter_mut())
            .zip(visible.par_iter_mut())
            .enumerate()
            .with_min_len(2048)
            .for_each(|(i, ((splat, rect), vis))| {
                // A non-finite colour would poison every pixel it touches: cull it like a NaN mean.
                if !g.colors[3 * i..3 * i + 3].iter().all(|v| v.is_finite()) {
                    return;
                }
                let m = [g.means[3 * i], g.means[3 * i + 1], g.means[3 * i + 2]];
                let c = &g.covariances[6 * i..6 * i + 6];
                if let Some(p) =
                    project_one(cfg, m, [c[0], c[1], c[2], c[3], c[4], c[5]], g.opacities[i])
                {
                    *splat = p.splat;
                    *rect = p.tiles;
                    *vis = true;
                }
            });
    }
    // Depth is > NEAR_Z > 0, so its bit pattern orders like the float; the index breaks ties.
    let order: Vec<u64> = {
        let _span = tracing::trace_span!("depth_sort").entered();
        let mut keys: Vec<u64> = (0..n)
            .filter(|&i| visible[i])
            .map(|i| ((splats[i].depth.to_bits() as u64) << 32) | i as u64)
            .collect();
        keys.par_sort_unstable();
        keys
    };
    let _span = tracing::trace_span!("bin").entered();
    // Gather the tile rectangles in depth order once (in parallel), so the two sequential passes
    // below stream through a compact array.
    let rects: Vec<(u32, [u32; 4])> = order
        .par_iter()
        .map(|key| {
            let gid = (*key & 0xffff_ffff) as u32;
            (gid, tiles[gid as usize])
        })
        .collect();
    drop(order);
    drop(tiles);
    let (gx, gy) = cfg.tiles();
    let mut tile_offsets = vec![0u32; gx * gy + 1];
    for (_, [x0, y0, x1, y1]) in &rects {
        for ty in *y0..*y1 {
            let row = ty as usize * gx;
            for tx in *x0..*x1 {
                tile_offsets[row + tx as usize + 1] += 1;
            }
        }
    }
    let mut total = 0u64;
    for offset in &mut tile_offsets {
        total += *offset as u64;
        assert!(total < u32::MAX as u64, "more than 2^32 tile intersections");
        *offset = total as u32;
    }
    let mut cursor = tile_offsets.clone();
    let mut gaussian_from_isect = vec![0u32; total as usize];
    for (gid, [x0, y0, x1, y1]) in &rects {
        for ty in *y0..*y1 {
            let row = ty as usize * gx;
            for tx in *x0..*x1 {
                let slot = &mut cursor[row + tx as usize];
                gaussian_from_isect[*slot as usize] = *gid;
                *slot += 1;
            }
        }
    }
    (splats, visible, tile_offsets, gaussian_from_isect)
}

#[inline]
fn feature(colors: &[f32], gid: usize, depth: f32) -> [f32; 5] {
    [
        colors[3 * gid],
        colors[3 * gid + 1],
        colors[3 * gid + 2],
        1.0,
        depth,
    ]
}

/// Renders the Gaussians. Returns the `[H, W, C]` image and the state for [`backward`].
#[tracing::instrument(level = "trace", skip_all, fields(n = g.opacities.len()))]
pub fn forward(cfg: &RasterConfig, g: &GaussianSlices) -> (Vec<f32>, ForwardState) {
    let (splats, visible, tile_offsets, gaussian_from_isect) = project_and_bin(cfg, g);
    let w = cfg.view.width as usize;
    let h = cfg.view.height as usize;
    let nc = cfg.channels.count();
    let (gx, _) = cfg.tiles();
    let mut image = vec![0.0f32; h * w * nc];
    let mut last_contrib = vec![0u32; h * w];
    let mut final_t = vec![1.0f32; h * w];
    {
        let _span = tracing::trace_span!("blend").entered();
        image
            .par_chunks_mut(TILE * w * nc)
            .zip(last_contrib.par_chunks_mut(TILE * w))
            .zip(final_t.par_chunks_mut(TILE * w))
            .enumerate()
            .for_each(|(ty, ((img, last), tt))| {
                let y0 = ty * TILE;
                let y1 = (y0 + TILE).min(h);
                for tx in 0..gx {
                    let x0 = tx * TILE;
                    let x1 = (x0 + TILE).min(w);
                    let t = ty * gx + tx;
                    let range = tile_offsets[t] as usize..tile_offsets[t + 1] as usize;
                    let mut live = (y1 - y0) * (x1 - x0);
                    let mut done = [false; TILE * TILE];
                    for (k, &gid) in gaussian_from_isect[range].iter().enumerate() {
                        let s = &splats[gid as usize];
                        let extent = s.extent();
                        let f = feature(g.colors, gid as usize, s.depth);
                        let (ylo, yhi) = axis_range(s.xy[1], extent[1], y0, y1);
                        let (xlo, xhi) = axis_range(s.xy[0], extent[0], x0, x1);
                        for py in ylo..yhi {
                            for px in xlo..xhi {
                                let local = (py - y0) * TILE + (px - x0);
                                if done[local] {
                                    continue;
                                }
                                let dx = s.xy[0] - px as f32;
                                let dy = s.xy[1] - py as f32;
                                let Some((alpha, _, _)) = eval_alpha(s, dx, dy, cfg.cutoff) else {
                                    continue;
                                };
                                let pix = (py - y0) * w + px;
                                let t_now = tt[pix];
                                let t_next = t_now * (1.0 - alpha);
                                if t_next < T_MIN {
                                    done[local] = true;
                                    live -= 1;
                                    continue;
                                }
                                let out = &mut img[pix * nc..pix * nc + nc];
                                for ch in 0..nc {
                                    out[ch] += f[ch] * alpha * t_now;
                                }
                                tt[pix] = t_next;
                                last[pix] = k as u32 + 1;
                            }
                        }
                        if live == 0 {
                            break;
                        }
                    }
                }
            });
    }
    let state = ForwardState {
        cfg: *cfg,
        num_gaussians: g.len(),
        splats,
        visible,
        tile_offsets,
        gaussian_from_isect,
        last_contrib,
        final_t,
    };
    (image, state)
}

/// Gradients of the four differentiable inputs.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GaussianGradients {
    /// `[N*3]`.
    pub means: Vec<f32>,
    /// `[N*6]`, per stored entry (off-diagonals count both symmetric positions).
    pub covariances: Vec<f32>,
    /// `[N*3]`.
    pub colors: Vec<f32>,
    /// `[N]`.
    pub opacities: Vec<f32>,
}

/// Backpropagates `d_image` (`[H, W, C]`, the gradient of the loss w.r.t. the forward's output)
/// through the forward that ran on `g` and produced `state`.
#[tracing::instrument(level = "trace", skip_all)]
pub fn backward(g: &GaussianSlices, state: &ForwardState, d_image: &[f32]) -> GaussianGradients {
    assert_eq!(
        g.len(),
        state.num_gaussians,
        "backward: inputs differ from the forward's"
    );
    let cfg = &state.cfg;
    let w = cfg.view.width as usize;
    let h = cfg.view.height as usize;
    let nc = cfg.channels.count();
    assert_eq!(
        d_image.len(),
        h * w * nc,
        "backward: gradient image has the wrong size"
    );
    let (gx, gy) = cfg.tiles();
    let num_isects = state.gaussian_from_isect.len();
    let mut slots = vec![0.0f32; num_isects * SLOT];

    // Each row of tiles owns a contiguous run of intersection slots.
    let mut band_slots: Vec<&mut [f32]> = Vec::with_capacity(gy);
    {
        let mut rest: &mut [f32] = &mut slots;
        for ty in 0..gy {
            let start = state.tile_offsets[ty * gx] as usize;
            let end = state.tile_offsets[(ty + 1) * gx] as usize;
            let (head, tail) = rest.split_at_mut((end - start) * SLOT);
            band_slots.push(head);
            rest = tail;
        }
    }
    {
        let _span = tracing::trace_span!("blend_backward").entered();
        band_slots
            .into_par_iter()
            .enumerate()
            .for_each(|(ty, band)| {
                let y0 = ty * TILE;
                let y1 = (y0 + TILE).min(h);
                let band_start = state.tile_offsets[ty * gx] as usize;
                for tx in 0..gx {
                    let x0 = tx * TILE;
                    let x1 = (x0 + TILE).min(w);
                    let t = ty * gx + tx;
                    let start = state.tile_offsets[t] as usize;
                    let mut trans = [0.0f32; TILE * TILE];
                    let mut behind = [[0.0f32; 5]; TILE * TILE];
                    let mut last = [0u32; TILE * TILE];
                    let mut max_last = 0u32;
                    for py in y0..y1 {
                        for px in x0..x1 {
                            let local = (py - y0) * TILE + (px - x0);
                            trans[local] = state.final_t[py * w + px];
                            last[local] = state.last_contrib[py * w + px];
                            max_last = max_last.max(last[local]);
                        }
                    }
                    for k in (0..max_last as usize).rev() {
                        let gid = state.gaussian_from_isect[start + k] as usize;
                        let s = &state.splats[gid];
                        let extent = s.extent();
                        let f = feature(g.colors, gid, s.depth);
                        let mut acc = [0.0f32; SLOT];
                        let (ylo, yhi) = axis_range(s.xy[1], extent[1], y0, y1);
                        let (xlo, xhi) = axis_range(s.xy[0], extent[0], x0, x1);
                        for py in ylo..yhi {
                            for px in xlo..xhi {
                                let local = (py - y0) * TILE + (px - x0);
                                if k as u32 >= last[local] {
                                    continue;
                                }
                                let dx = s.xy[0] - px as f32;
                                let dy = s.xy[1] - py as f32;
                                let Some((alpha, dalpha_draw, gval)) =
                                    eval_alpha(s, dx, dy, cfg.cutoff)
                                else {
                                    continue;
                                };
                                let pix = py * w + px;
                                let dpix = &d_image[pix * nc..pix * nc + nc];
                                let t_i = trans[local] / (1.0 - alpha);
                                let weight = alpha * t_i;
                                let mut d_alpha = 0.0f32;
                                for ch in 0..nc {
                                    d_alpha += dpix[ch] * (f[ch] - behind[local][ch]);
                                    behind[local][ch] =
                                        f[ch] * alpha + (1.0 - alpha) * behind[local][ch];
                                }
                                d_alpha *= t_i;
                                trans[local] = t_i;
                                for ch in 0..3 {
                                    acc[6 + ch] += weight * dpix[ch];
                                }
                                if nc == 5 {
                                    acc[9] += weight * dpix[4];
                                }
                                let d_raw = d_alpha * dalpha_draw;
                                acc[5] += d_raw * gval;
                                let d_power = d_raw * s.opacity * gval;
                                let [qa, qb, qc] = s.conic;
                                acc[0] += -d_power * (qa * dx + qb * dy);
                                acc[1] += -d_power * (qc * dy + qb * dx);
                                acc[2] += -0.5 * d_power * dx * dx;
                                acc[3] += -d_power * dx * dy;
                                acc[4] += -0.5 * d_power * dy * dy;
                            }
                        }
                        let at = (start + k - band_start) * SLOT;
                        band[at..at + SLOT].copy_from_slice(&acc);
                    }
                }
            });
    }

    let n = state.num_gaussians;
    let mut grad2d = vec![0.0f32; n * SLOT];
    for (isect, &gid) in state.gaussian_from_isect.iter().enumerate() {
        let src = &slots[isect * SLOT..isect * SLOT + SLOT];
        let dst = &mut grad2d[gid as usize * SLOT..gid as usize * SLOT + SLOT];
        for (d, s) in dst.iter_mut().zip(src) {
            *d += s;
        }
    }

    let _span = tracing::trace_span!("project_backward").entered();
    let mut grads = GaussianGradients {
        means: vec![0.0; n * 3],
        covariances: vec![0.0; n * 6],
        colors: vec![0.0; n * 3],
        opacities: vec![0.0; n],
    };
    grads
        .means
        .par_chunks_mut(3)
        .zip(grads.covariances.par_chunks_mut(6))
        .zip(grads.colors.par_chunks_mut(3))
        .zip(grads.opacities.par_iter_mut())
        .enumerate()
        .with_min_len(2048)
        .for_each(|(i, (((dm, dc), dcol), dop))| {
            if !state.visible[i] {
                return;
            }
            let s = &state.splats[i];
            let g2 = &grad2d[i * SLOT..i * SLOT + SLOT];
            dcol.copy_from_slice(&g2[6..9]);
            *dop = g2[5];
            let m = [g.means[3 * i], g.means[3 * i + 1], g.means[3 * i + 2]];
            let c = &g.covariances[6 * i..6 * i + 6];
            let (gm, gc) = project_backward(
                cfg,
                m,
                [c[0], c[1], c[2], c[3], c[4], c[5]],
                s,
                [g2[0], g2[1]],
                [g2[2], g2[3], g2[4]],
                g2[9],
            );
            dm.copy_from_slice(&gm);
            dc.copy_from_slice(&gc);
        });
    grads
}

/// Chains the gradients w.r.t. the projected centre, the conic and the depth back to the 3D mean
/// and the 6 stored covariance entries.
pub fn project_backward(
    cfg: &RasterConfig,
    mean: [f32; 3],
    cov: [f32; 6],
    splat: &Splat2d,
    d_xy: [f32; 2],
    d_conic: [f32; 3],
    d_depth: f32,
) -> ([f32; 3], [f32; 6]) {
    let v = &cfg.view;
    let r = &v.view;
    let t = [
        r[0] * mean[0] + r[1] * mean[1] + r[2] * mean[2] + r[3],
        r[4] * mean[0] + r[5] * mean[1] + r[6] * mean[2] + r[7],
        r[8] * mean[0] + r[9] * mean[1] + r[10] * mean[2] + r[11],
    ];
    let (j, clamped) = ewa_jacobian(cfg, t);
    let tm = jw(j, r);
    let sigma = sym3(cov);

    // Conic → 2D covariance: dL/dM = −Q·G·Q with G the symmetric-matrix gradient of Q, whose
    // off-diagonal entry B appears twice in Q.
    let [qa, qb, qc] = splat.conic;
    let gq = [
        [d_conic[0], 0.5 * d_conic[1]],
        [0.5 * d_conic[1], d_conic[2]],
    ];
    let q = [[qa, qb], [qb, qc]];
    let mut qg = [[0.0f32; 2]; 2];
    for a in 0..2 {
        for b in 0..2 {
            qg[a][b] = q[a][0] * gq[0][b] + q[a][1] * gq[1][b];
        }
    }
    let mut gm = [[0.0f32; 2]; 2];
    for a in 0..2 {
        for b in 0..2 {
            gm[a][b] = -(qg[a][0] * q[0][b] + qg[a][1] * q[1][b]);
        }
    }

    // M = T Σ Tᵀ + dilation: dL/dΣ = Tᵀ·dL/dM·T, dL/dT = 2·dL/dM·T·Σ.
    let mut d_sigma = [[0.0f32; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            let mut acc = 0.0;
            for p in 0..2 {
                for qi in 0..2 {
                    acc += tm[p][a] * gm[p][qi] * tm[qi][b];
                }
            }
            d_sigma[a][b] = acc;
        }
    }
    let d_cov = [
        d_sigma[0][0],
        d_sigma[0][1] + d_sigma[1][0],
        d_sigma[0][2] + d_sigma[2][0],
        d_sigma[1][1],
        d_sigma[1][2] + d_sigma[2][1],
        d_sigma[2][2],
    ];
    let ts = [mat3_vec(&sigma, tm[0]), mat3_vec(&sigma, tm[1])];
    let mut d_t = [[0.0f32; 3]; 2];
    for p in 0..2 {
        for a in 0..3 {
            d_t[p][a] = 2.0 * (gm[p][0] * ts[0][a] + gm[p][1] * ts[1][a]);
        }
    }
    // T rows: T0 = J00·R0 + J02·R2, T1 = J11·R1 + J12·R2.
    let row = |k: usize| [r[4 * k], r[4 * k + 1], r[4 * k + 2]];
    let d_j00 = dot3(d_t[0], row(0));
    let d_j02 = dot3(d_t[0], row(2));
    let d_j11 = dot3(d_t[1], row(1));
    let d_j12 = dot3(d_t[1], row(2));

    let (x, y, z) = (t[0], t[1], t[2]);
    let (z2, z3) = (z * z, z * z * z);
    let mut d_view = [0.0f32; 3];
    d_view[2] += -v.fx / z2 * d_j00 - v.fy / z2 * d_j11;
    if clamped[0] {
        // J02 = −fx·(±lim)/z: only z moves it.
        let lim = (x / z).signum() * FOV_CLAMP * v.width as f32 / (2.0 * v.fx);
        d_view[2] += v.fx * lim / z2 * d_j02;
    } else {
        d_view[0] += -v.fx / z2 * d_j02;
        d_view[2] += 2.0 * v.fx * x / z3 * d_j02;
    }
    if clamped[1] {
        let lim = (y / z).signum() * FOV_CLAMP * v.height as f32 / (2.0 * v.fy);
        d_view[2] += v.fy * lim / z2 * d_j12;
    } else {
        d_view[1] += -v.fy / z2 * d_j12;
        d_view[2] += 2.0 * v.fy * y / z3 * d_j12;
    }
    // Projected centre and depth.
    d_view[0] += v.fx / z * d_xy[0];
    d_view[1] += v.fy / z * d_xy[1];
    d_view[2] += -v.fx * x / z2 * d_xy[0] - v.fy * y / z2 * d_xy[1] + d_depth;
    // Back to world: dL/dm = Rᵀ·dL/dt.
    let d_mean = [
        r[0] * d_view[0] + r[4] * d_view[1] + r[8] * d_view[2],
        r[1] * d_view[0] + r[5] * d_view[1] + r[9] * d_view[2],
        r[2] * d_view[0] + r[6] * d_view[1] + r[10] * d_view[2],
    ];
    (d_mean, d_cov)
}
