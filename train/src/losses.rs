//! Training losses (design.md §9.2), as differentiable Burn tensor ops.
//!
//! Every feedback iteration is supervised: the caller stacks the T iterations' renders of the N
//! source views and the target view into one image batch and the T low-res canonical meshes into
//! one vertex batch, so each mean below is "over every iteration, view and pixel" as in the
//! reference.
//!
//! - **RGB** ([`l1`]) and **mask** ([`mask_l1`]): mean absolute error over everything.
//! - **SSIM** ([`ssim_gaussian`]): the training SSIM LIFe-GoM inherits from Generalizable Human
//!   Gaussians (design.md §9.2). Local means, variances and covariance come from an 11×11 Gaussian
//!   window (σ = 1.5, normalised to sum 1) applied per channel with **zero padding 5**, so the map
//!   has the input's size and the border pixels see a window partly filled with zeros (their
//!   statistics are biased towards 0; this is the reference's behaviour and we keep it). The map
//!   `((2μxμy + C1)(2σxy + C2)) / ((μx² + μy² + C1)(σx² + σy² + C2))` with `C1 = 0.01²`, `C2 =
//!   0.03²` (data range 1) is averaged over all images, channels and pixels; the loss is `1 − SSIM`
//!   ([`ssim_loss`]).
//!   The Gaussian window is the outer product of a 1-D Gaussian, so we filter with two 1-D
//!   depthwise convolutions (11 taps each instead of 121). With zero padding this is exactly
//!   the 2-D filter: the horizontal pass over the padded rows yields zeros, which is what the
//!   2-D filter sees there. The five filtered quantities (x, y, x², y², xy) go through one
//!   grouped convolution call. On the CPU backends [`SsimConfig::ssim`] is one custom op with a
//!   hand-written backward instead ([`crate::ssim_op`]); the tensor ops stay for CubeCL devices
//!   and as its test reference.
//! - **Laplacian** ([`laplacian_uniform`], [`UniformLaplacian`]): the uniform Laplacian of
//!   pytorch3d's `laplacian_packed`, `(L v)_i = Σ_{j∈N(i)} v_j / deg(i) − v_i`, with N(i) from
//!   the mesh's unique undirected edges. The loss is the mean over vertices of `‖(L v)_i‖²`
//!   (squared norm, as LIFe-GoM's `mesh_laplacian_smoothing`, not pytorch3d's plain norm). The
//!   neighbour structure is a constant: gradients flow only through the vertex positions.
//!   **Deviation:** a vertex that no face references has deg 0; pytorch3d's matrix still has −1
//!   on its diagonal (it would contribute `‖v_i‖²`), here it contributes 0 (it has no
//!   neighbourhood to be smooth with). Body-model meshes have no such vertices, so the losses
//!   agree on them; isolated vertices still count in the mean's denominator.
//!   Rather than a sparse V×V matrix, neighbours are stored in a padded `[V, K]` index table
//!   (K = maximum degree) with weights `1/deg` (0 on padding): one gather, one weighted sum.
//! - **Weights** ([`LossWeights`]): THuman defaults rgb 1, mask 5, ssim 1, lpips 0,
//!   laplacian 100; [`LossWeights::total`] sums the weighted terms and returns them for logging.
//!
//! LPIPS (AIST++ only) is not implemented here; [`LossTerms::lpips`] takes a value computed
//! elsewhere.

use burn::config::Config;
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Int, Tensor, TensorData};
use lifegom_render::device::runs_on_host;
use lifegom_render::readback::{self, ReadbackError};
use lifegom_render::select::select_rows;

use crate::ssim_op::{SsimOps, SsimWindow};

/// Errors of the loss helpers.
#[derive(Debug, thiserror::Error)]
pub enum LossError {
    /// A face refers to a vertex index `>= num_vertices`.
    #[error("face {face} refers to vertex {index}, but the mesh has {num_vertices} vertices")]
    FaceIndexOutOfRange {
        /// Face number.
        face: usize,
        /// Offending vertex index.
        index: u32,
        /// Vertex count of the mesh.
        num_vertices: usize,
    },
    /// A term has a non-zero weight but was not supplied.
    #[error("loss term `{0}` has a non-zero weight but no value was given")]
    MissingTerm(&'static str),
}

/// Mean absolute error over every element: the RGB loss.
pub fn l1<const D: usize>(pred: Tensor<D>, gt: Tensor<D>) -> Tensor<1> {
    (pred - gt).abs().mean()
}

/// Mean absolute error between the rendered alpha and the GT mask: the mask loss. Same maths as
/// [`l1`]; a separate name so the training loop reads like design.md §9.2.
pub fn mask_l1<const D: usize>(pred_alpha: Tensor<D>, gt_mask: Tensor<D>) -> Tensor<1> {
    l1(pred_alpha, gt_mask)
}

/// Parameters of the Gaussian-window SSIM. The defaults are the training SSIM of design.md §9.2.
#[derive(Config, Debug)]
pub struct SsimConfig {
    /// Window side (odd); the zero padding is `window_size / 2`.
    #[config(default = 11)]
    pub window_size: usize,
    /// Standard deviation of the Gaussian window, in pixels.
    #[config(default = 1.5)]
    pub sigma: f64,
    /// Luminance stabiliser, `(0.01 · data_range)²`.
    #[config(default = 1e-4)]
    pub c1: f64,
    /// Contrast stabiliser, `(0.03 · data_range)²`.
    #[config(default = 9e-4)]
    pub c2: f64,
}

impl SsimConfig {
    /// The normalised 1-D Gaussian taps `exp(−(i − w/2)² / 2σ²) / Σ`.
    pub fn gaussian_1d(&self) -> Vec<f64> {
        let half = (self.window_size / 2) as f64;
        let g: Vec<f64> = (0..self.window_size)
            .map(|i| (-((i as f64 - half).powi(2)) / (2.0 * self.sigma * self.sigma)).exp())
            .collect();
        let s: f64 = g.iter().sum();
        g.into_iter().map(|v| v / s).collect()
    }

    /// The SSIM map `[B, C, H, W]` of two image batches `[B, C, H, W]` (data range 1).
    pub fn ssim_map(&self, pred: Tensor<4>, gt: Tensor<4>) -> Tensor<4> {
        assert_eq!(
            pred.dims(),
            gt.dims(),
            "ssim: image batches differ in shape"
        );
        assert!(self.window_size % 2 == 1, "ssim: window size must be odd");
        let [b, c, h, w] = pred.dims();
        let device = pred.device();
        let dtype = pred.dtype();
        // All five local moments in one grouped convolution: channel blocks x, y, x², y², xy.
        let stacked = Tensor::cat(
            vec![
                pred.clone(),
                gt.clone(),
                pred.clone() * pred.clone(),
                gt.clone() * gt.clone(),
                pred * gt,
            ],
            1,
        );
        let groups = 5 * c;
        let k = self.window_size;
        let pad = k / 2;
        let taps = self.gaussian_1d();
        let kernel = |shape: [usize; 4]| {
            let data: Vec<f64> = (0..groups).flat_map(|_| taps.iter().copied()).collect();
            Tensor::<4>::from_data(TensorData::new(data, shape), (&device, dtype))
        };
        let horizontal = conv2d(
            stacked,
            kernel([groups, 1, 1, k]),
            None,
            ConvOptions::new([1, 1], [0, pad], [1, 1], groups),
        );
        let filtered = conv2d(
            horizontal,
            kernel([groups, 1, k, 1]),
            None,
            ConvOptions::new([1, 1], [pad, 0], [1, 1], groups),
        );
        let mut moments = filtered.chunk(5, 1).into_iter();
        let mut next = || moments.next().expect("five moment blocks");
        let (mu_x, mu_y, xx, yy, xy) = (next(), next(), next(), next(), next());
        let mu_xx = mu_x.clone() * mu_x.clone();
        let mu_yy = mu_y.clone() * mu_y.clone();
        let mu_xy = mu_x * mu_y;
        let var_x = xx - mu_xx.clone();
        let var_y = yy - mu_yy.clone();
        let cov = xy - mu_xy.clone();
        let num = (mu_xy * 2.0 + self.c1) * (cov * 2.0 + self.c2);
        let den = (mu_xx + mu_yy + self.c1) * (var_x + var_y + self.c2);
        let map = num / den;
        debug_assert_eq!(map.dims(), [b, c, h, w]);
        map
    }

    /// Mean of [`Self::ssim_map`] over all images, channels and pixels: on the CPU backends one
    /// custom op ([`crate::ssim_op`]), on CubeCL devices the map's tensor ops.
    pub fn ssim(&self, pred: Tensor<4>, gt: Tensor<4>) -> Tensor<1> {
        if !runs_on_host(&pred.device()) {
            return self.ssim_map(pred, gt).mean();
        }
        assert_eq!(
            pred.dims(),
            gt.dims(),
            "ssim: image batches differ in shape"
        );
        assert!(self.window_size % 2 == 1, "ssim: window size must be odd");
        let window = SsimWindow {
            taps: self.gaussian_1d(),
            c1: self.c1,
            c2: self.c2,
        };
        Tensor::from_dispatch(<burn::backend::Dispatch as SsimOps>::ssim_mean(
            pred.into_dispatch(),
            gt.into_dispatch(),
            window,
        ))
    }
}

/// The training SSIM of design.md §9.2 (window 11, σ 1.5, C1 0.01², C2 0.03², zero padding 5) on
/// `[B, C, H, W]` images in [0, 1], averaged over every image, channel and pixel. Renders are
/// channel-last (`[…, H, W, 3]`): permute them to channel-first before calling.
pub fn ssim_gaussian(pred: Tensor<4>, gt: Tensor<4>) -> Tensor<1> {
    SsimConfig::new().ssim(pred, gt)
}

/// The SSIM loss `1 − SSIM` with [`ssim_gaussian`].
pub fn ssim_loss(pred: Tensor<4>, gt: Tensor<4>) -> Tensor<1> {
    ssim_gaussian(pred, gt).neg() + 1.0
}

/// The uniform-Laplacian neighbour structure of a triangle mesh, built once from its faces and
/// reused on every batch of vertex positions (the faces never change during training).
#[derive(Debug, Clone)]
pub struct UniformLaplacian {
    num_vertices: usize,
    /// Maximum vertex degree K (width of the padded tables).
    max_degree: usize,
    /// `[V·K]` neighbour indices, row-major; padding slots point at the vertex itself.
    neighbours: Vec<i64>,
    /// `[V·K]` weights `1/deg(i)` on real neighbours, 0 on padding.
    weights: Vec<f64>,
    /// `[V]` 1 where the vertex has a neighbour, 0 for isolated vertices.
    connected: Vec<f64>,
}

impl UniformLaplacian {
    /// Builds the structure from the unique undirected edges of `faces`.
    pub fn new(faces: &[[u32; 3]], num_vertices: usize) -> Result<Self, LossError> {
        let mut edges = Vec::with_capacity(faces.len() * 3);
        for (f, face) in faces.iter().enumerate() {
            for &index in face {
                if index as usize >= num_vertices {
                    return Err(LossError::FaceIndexOutOfRange {
                        face: f,
                        index,
                        num_vertices,
                    });
                }
            }
            for (a, b) in [(face[0], face[1]), (face[1], face[2]), (face[2], face[0])] {
                // Degenerate faces can repeat a vertex; a self-loop is not a neighbour.
                if a != b {
                    edges.push((a.min(b), a.max(b)));
                }
            }
        }
        // An interior edge is shared by two faces; pytorch3d counts each edge once.
        edges.sort_unstable();
        edges.dedup();
        let mut adjacency = vec![Vec::new(); num_vertices];
        for &(a, b) in &edges {
            adjacency[a as usize].push(b as i64);
            adjacency[b as usize].push(a as i64);
        }
        let max_degree = adjacency.iter().map(Vec::len).max().unwrap_or(0).max(1);
        let mut neighbours = Vec::with_capacity(num_vertices * max_degree);
        let mut weights = Vec::with_capacity(num_vertices * max_degree);
        let mut connected = Vec::with_capacity(num_vertices);
        for (i, nbrs) in adjacency.iter().enumerate() {
            let w = if nbrs.is_empty() {
                0.0
            } else {
                1.0 / nbrs.len() as f64
            };
            for k in 0..max_degree {
                match nbrs.get(k) {
                    Some(&j) => {
                        neighbours.push(j);
                        weights.push(w);
                    }
                    None => {
                        neighbours.push(i as i64);
                        weights.push(0.0);
                    }
                }
            }
            connected.push(if nbrs.is_empty() { 0.0 } else { 1.0 });
        }
        Ok(Self {
            num_vertices,
            max_degree,
            neighbours,
            weights,
            connected,
        })
    }

    /// Number of vertices the structure was built for.
    pub fn num_vertices(&self) -> usize {
        self.num_vertices
    }

    /// `(L v)_i = Σ_{j∈N(i)} v_j / deg(i) − v_i` (0 for isolated vertices) for a batch of meshes
    /// `[M, V, 3]` sharing these faces; returns `[M, V, 3]`.
    pub fn apply(&self, vertices: Tensor<3>) -> Tensor<3> {
        let [m, v, d] = vertices.dims();
        assert_eq!(
            v, self.num_vertices,
            "laplacian: the vertex batch has {v} vertices, the faces were built for {}",
            self.num_vertices
        );
        let device = vertices.device();
        let dtype = vertices.dtype();
        let k = self.max_degree;
        let index =
            Tensor::<1, Int>::from_data(TensorData::new(self.neighbours.clone(), [v * k]), &device);
        let weights = Tensor::<4>::from_data(
            TensorData::new(self.weights.clone(), [1, v, k, 1]),
            (&device, dtype),
        );
        let connected = Tensor::<3>::from_data(
            TensorData::new(self.connected.clone(), [1, v, 1]),
            (&device, dtype),
        );
        let gathered = select_rows(vertices.clone(), 1, index).reshape([m, v, k, d]);
        let centroid: Tensor<3> = (gathered * weights).sum_dim(2).reshape([m, v, d]);
        centroid - vertices * connected
    }

    /// Mean over all `M·V` vertices of `‖(L v)_i‖²`, for `[M, V, 3]` vertex batches.
    pub fn loss(&self, vertices: Tensor<3>) -> Tensor<1> {
        let lv = self.apply(vertices);
        lv.clone().mul(lv).sum_dim(2).mean()
    }
}

/// The Laplacian smoothing loss of design.md §9.2 for one mesh: mean over the `V` vertices
/// (`vertices` is `[V, 3]`) of `‖Σ_{j∈N(i)} v_j/deg(i) − v_i‖²`. Builds the neighbour structure
/// on every call; a training loop should build a [`UniformLaplacian`] once instead.
///
/// # Panics
/// If a face refers to a vertex index `>= V`.
pub fn laplacian_uniform(vertices: Tensor<2>, faces: &[[u32; 3]]) -> Tensor<1> {
    let [v, _] = vertices.dims();
    let lap = UniformLaplacian::new(faces, v).unwrap_or_else(|e| panic!("laplacian_uniform: {e}"));
    lap.loss(vertices.unsqueeze_dim(0))
}

/// Loss coefficients (design.md §9.3). Defaults are THuman's; AIST++ uses mask 0 and lpips 1.
#[derive(Config, Debug)]
pub struct LossWeights {
    /// Weight of the RGB L1 loss.
    #[config(default = 1.0)]
    pub rgb: f64,
    /// Weight of the mask L1 loss.
    #[config(default = 5.0)]
    pub mask: f64,
    /// Weight of `1 − SSIM`.
    #[config(default = 1.0)]
    pub ssim: f64,
    /// Weight of LPIPS (0 on THuman).
    #[config(default = 0.0)]
    pub lpips: f64,
    /// Weight of the Laplacian smoothing loss.
    #[config(default = 100.0)]
    pub laplacian: f64,
}

/// The unweighted loss terms of one training step, each a one-element tensor.
#[derive(Debug, Clone)]
pub struct LossTerms {
    /// [`l1`] of the composited renders.
    pub rgb: Tensor<1>,
    /// [`mask_l1`] of the rendered alpha.
    pub mask: Tensor<1>,
    /// [`ssim_loss`], i.e. `1 − SSIM`.
    pub ssim: Tensor<1>,
    /// LPIPS, where the caller computes it; needed only if its weight is non-zero.
    pub lpips: Option<Tensor<1>>,
    /// [`UniformLaplacian::loss`] of the canonical meshes.
    pub laplacian: Tensor<1>,
}

/// The weighted total and its parts.
#[derive(Debug, Clone)]
pub struct WeightedLoss {
    /// Sum of the weighted terms; call `backward` on this.
    pub total: Tensor<1>,
    /// `(name, weight · term)` for every term with a non-zero weight, detached from the graph
    /// so logging them keeps no autodiff state alive.
    pub parts: Vec<(&'static str, Tensor<1>)>,
}

impl WeightedLoss {
    /// Reads the total and the parts to the host (a device sync; do it at the logging interval).
    pub fn scalars(&self) -> Result<Vec<(&'static str, f64)>, ReadbackError> {
        let (names, values) = self.scalars_with(&[])?;
        Ok(names.into_iter().zip(values).collect())
    }

    /// The names of the total and the parts, and their values followed by those of `more`
    /// (1-D tensors, flattened in order): one read-back for all of them, where one per tensor
    /// would wait on the device once each (`readback::take_device_reads`).
    pub fn scalars_with(
        &self,
        more: &[Tensor<1>],
    ) -> Result<(Vec<&'static str>, Vec<f64>), ReadbackError> {
        let names: Vec<&'static str> = std::iter::once("total")
            .chain(self.parts.iter().map(|(name, _)| *name))
            .collect();
        let tensors: Vec<Tensor<1>> = std::iter::once(&self.total)
            .chain(self.parts.iter().map(|(_, t)| t))
            .chain(more)
            .map(|t| t.clone().detach())
            .collect();
        let values = readback::read::<f64, 1, _>("loss statistics", Tensor::cat(tensors, 0))?;
        Ok((names, values))
    }
}

impl LossWeights {
    /// Sums the weighted terms. Terms with weight 0 are left out of the graph entirely (so a
    /// missing LPIPS is fine at weight 0); a non-zero LPIPS weight without a value is an error.
    pub fn total(&self, terms: LossTerms) -> Result<WeightedLoss, LossError> {
        // Every weight 0 leaves nothing to sum: fall back to a zero on the terms' device.
        let zero = terms.rgb.clone().detach().zeros_like();
        let lpips = match (terms.lpips, self.lpips != 0.0) {
            (Some(t), true) => Some(t),
            (None, true) => return Err(LossError::MissingTerm("lpips")),
            (_, false) => None,
        };
        let candidates = [
            ("rgb", self.rgb, Some(terms.rgb)),
            ("mask", self.mask, Some(terms.mask)),
            ("ssim", self.ssim, Some(terms.ssim)),
            ("lpips", self.lpips, lpips),
            ("laplacian", self.laplacian, Some(terms.laplacian)),
        ];
        let mut total: Option<Tensor<1>> = None;
        let mut parts = Vec::new();
        for (name, weight, term) in candidates {
            let Some(term) = term else { continue };
            if weight == 0.0 {
                continue;
            }
            let weighted = term * weight;
            parts.push((name, weighted.clone().detach()));
            total = Some(match total {
                Some(t) => t + weighted,
                None => weighted,
            });
        }
        Ok(WeightedLoss {
            total: total.unwrap_or(zero),
            parts,
        })
    }
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;
    use burn::tensor::{DType, Device};

    fn read<const D: usize>(t: Tensor<D>) -> Vec<f64> {
        t.into_data().try_into_vec_as::<f64>().unwrap()
    }

    fn scalar(t: Tensor<1>) -> f64 {
        read(t)[0]
    }

    /// f64 tensors so finite differences and hand computations compare tightly.
    fn tensor<const D: usize>(values: Vec<f64>, shape: [usize; D], device: &Device) -> Tensor<D> {
        Tensor::from_data(TensorData::new(values, shape), (device, DType::F64))
    }

    /// Deterministic values in [0, 1) from the workspace's seeded generator.
    fn pseudo_random(n: usize, seed: u64) -> Vec<f64> {
        let mut rng = lifegom_render::rng::Rng::new(seed);
        (0..n).map(|_| rng.uniform()).collect()
    }

    /// Straightforward 2-D SSIM with the full 11×11 window and explicit zero padding, written
    /// independently of the separable, batched implementation under test.
    fn slow_ssim(x: &[f64], y: &[f64], [b, c, h, w]: [usize; 4]) -> f64 {
        let g = SsimConfig::new().gaussian_1d();
        let (c1, c2) = (1e-4, 9e-4);
        let at = |img: &[f64], plane: usize, i: isize, j: isize| -> f64 {
            if i < 0 || j < 0 || i >= h as isize || j >= w as isize {
                0.0
            } else {
                img[plane * h * w + i as usize * w + j as usize]
            }
        };
        let mut total = 0.0;
        for plane in 0..b * c {
            for i in 0..h as isize {
                for j in 0..w as isize {
                    let (mut mx, mut my, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for (di, gi) in g.iter().enumerate() {
                        for (dj, gj) in g.iter().enumerate() {
                            let wgt = gi * gj;
                            let (ii, jj) = (i + di as isize - 5, j + dj as isize - 5);
                            let (a, bb) = (at(x, plane, ii, jj), at(y, plane, ii, jj));
                            mx += wgt * a;
                            my += wgt * bb;
                            xx += wgt * a * a;
                            yy += wgt * bb * bb;
                            xy += wgt * a * bb;
                        }
                    }
                    let (vx, vy, cxy) = (xx - mx * mx, yy - my * my, xy - mx * my);
                    total += ((2.0 * mx * my + c1) * (2.0 * cxy + c2))
                        / ((mx * mx + my * my + c1) * (vx + vy + c2));
                }
            }
        }
        total / (b * c * h * w) as f64
    }

    fn identical_images(device: &Device) {
        let shape = [2, 3, 16, 13];
        let x = tensor(pseudo_random(2 * 3 * 16 * 13, 1), shape, device);
        assert_eq!(scalar(l1(x.clone(), x.clone())), 0.0);
        assert_eq!(scalar(mask_l1(x.clone(), x.clone())), 0.0);
        let s = scalar(ssim_gaussian(x.clone(), x.clone()));
        assert!((s - 1.0).abs() < 1e-12, "SSIM(x, x) = {s}");
        assert!(scalar(ssim_loss(x.clone(), x)).abs() < 1e-12);
        // L1 on a known difference: |0.25| everywhere.
        let a = tensor(vec![0.5; 6], [2, 3], device);
        let b = tensor(vec![0.25; 6], [2, 3], device);
        assert!((scalar(l1(a, b)) - 0.25).abs() < 1e-15);
    }

    /// Constant images `a` and `b = a + 0.2`: with zero padding, the in-image window mass at a
    /// pixel is `s = s_row · s_col` (partial sums of the 1-D taps), and then `μx = a·s`,
    /// `σx² = a²·s(1−s)`, `σxy = ab·s(1−s)`, so the map has a closed form per pixel.
    fn constant_shift_matches_hand_computation(device: &Device) {
        let (h, w) = (17, 12);
        let (a, b) = (0.3, 0.5);
        let (c1, c2) = (1e-4, 9e-4);
        let g = SsimConfig::new().gaussian_1d();
        let inside = |i: usize, n: usize| -> f64 {
            (0..11)
                .filter(|&k| {
                    let p = i as isize + k as isize - 5;
                    p >= 0 && p < n as isize
                })
                .map(|k| g[k])
                .sum()
        };
        let mut expect = 0.0;
        for i in 0..h {
            for j in 0..w {
                let s = inside(i, h) * inside(j, w);
                let v = s * (1.0 - s);
                expect += ((2.0 * a * b * s * s + c1) * (2.0 * a * b * v + c2))
                    / (((a * a + b * b) * s * s + c1) * ((a * a + b * b) * v + c2));
            }
        }
        expect /= (h * w) as f64;
        let x = tensor(vec![a; h * w], [1, 1, h, w], device);
        let y = tensor(vec![b; h * w], [1, 1, h, w], device);
        let got = scalar(ssim_gaussian(x.clone(), y.clone()));
        assert!((got - expect).abs() < 1e-12, "{got} vs {expect}");
        // Far from the border s = 1: the luminance term alone, (2ab + C1)/(a² + b² + C1).
        let map = read(SsimConfig::new().ssim_map(x, y));
        let centre = map[8 * w + 6];
        let interior = (2.0 * a * b + c1) / (a * a + b * b + c1);
        assert!((centre - interior).abs() < 1e-12);

        // A textured image and its copy shifted by d: in the interior σy = σx = σxy, so the
        // contrast-structure term is 1 and only luminance remains, with μy = μx + d.
        let (h, w, d) = (16, 16, 0.1);
        let xs = pseudo_random(h * w, 7);
        let ys: Vec<f64> = xs.iter().map(|v| v + d).collect();
        let map = read(SsimConfig::new().ssim_map(
            tensor(xs.clone(), [1, 1, h, w], device),
            tensor(ys, [1, 1, h, w], device),
        ));
        for i in 5..h - 5 {
            for j in 5..w - 5 {
                let mut mu = 0.0;
                for (di, gi) in g.iter().enumerate() {
                    for (dj, gj) in g.iter().enumerate() {
                        mu += gi * gj * xs[(i + di - 5) * w + j + dj - 5];
                    }
                }
                let hand = (2.0 * mu * (mu + d) + c1) / (mu * mu + (mu + d) * (mu + d) + c1);
                let got = map[i * w + j];
                assert!((got - hand).abs() < 1e-10, "({i},{j}): {got} vs {hand}");
            }
        }
    }

    fn ssim_matches_slow_reference_symmetric_and_bounded(device: &Device) {
        let shape = [2, 3, 9, 14];
        let n = shape.iter().product();
        let xs = pseudo_random(n, 3);
        let ys: Vec<f64> = pseudo_random(n, 4)
            .iter()
            .zip(&xs)
            .map(|(r, x)| 0.7 * x + 0.3 * r)
            .collect();
        let x = tensor(xs.clone(), shape, device);
        let y = tensor(ys.clone(), shape, device);
        let xy = scalar(ssim_gaussian(x.clone(), y.clone()));
        let yx = scalar(ssim_gaussian(y.clone(), x.clone()));
        let slow = slow_ssim(&xs, &ys, shape);
        assert!((xy - slow).abs() < 1e-10, "{xy} vs slow {slow}");
        assert!((xy - yx).abs() < 1e-12, "not symmetric: {xy} vs {yx}");
        assert!(xy < 1.0 && xy > 0.0, "{xy}");
        assert!(
            read(SsimConfig::new().ssim_map(x, y))
                .iter()
                .all(|&v| v <= 1.0 + 1e-12)
        );
        // Unrelated noise scores far lower than the correlated pair.
        let z = tensor(pseudo_random(n, 99), shape, device);
        let xz = scalar(ssim_gaussian(tensor(xs, shape, device), z));
        assert!(xz < xy, "{xz} vs {xy}");
    }

    /// Central differences of `f` w.r.t. each listed entry of `values`, against autodiff.
    fn check_gradient<const D: usize>(
        device: &Device,
        values: &[f64],
        shape: [usize; D],
        entries: &[usize],
        f: impl Fn(Tensor<D>) -> Tensor<1>,
    ) {
        let ad = device.clone().autodiff();
        let input = tensor(values.to_vec(), shape, &ad).require_grad();
        let grads = f(input.clone()).backward();
        let analytic = read(input.grad(&grads).expect("input gets a gradient"));
        let eps = 1e-6;
        for &e in entries {
            let eval = |delta: f64| {
                let mut v = values.to_vec();
                v[e] += delta;
                scalar(f(tensor(v, shape, device)))
            };
            let numeric = (eval(eps) - eval(-eps)) / (2.0 * eps);
            let err = (numeric - analytic[e]).abs();
            assert!(
                err < 1e-7 + 1e-5 * numeric.abs(),
                "entry {e}: autodiff {} vs finite difference {numeric}",
                analytic[e]
            );
        }
    }

    fn ssim_gradient_matches_finite_differences(device: &Device) {
        let shape = [1, 2, 7, 9];
        let n = shape.iter().product();
        let xs = pseudo_random(n, 11);
        let ys = pseudo_random(n, 12);
        let gt = tensor(ys, shape, device);
        // Corners, edges and interior pixels of both channels.
        let entries = [0, 4, 8, 31, 40, 62, 63, 70, 95, 125];
        check_gradient(device, &xs, shape, &entries, |x| {
            let gt = gt.clone().to_device(&x.device());
            ssim_loss(x, gt)
        });
    }

    /// `n × n` grid in the z = 0 plane, each quad split along the same diagonal.
    fn flat_grid(n: usize) -> (Vec<f64>, Vec<[u32; 3]>) {
        let mut verts = Vec::new();
        for i in 0..n {
            for j in 0..n {
                verts.extend([j as f64 * 0.1, i as f64 * 0.2, 0.0]);
            }
        }
        let id = |i: usize, j: usize| (i * n + j) as u32;
        let mut faces = Vec::new();
        for i in 0..n - 1 {
            for j in 0..n - 1 {
                faces.push([id(i, j), id(i, j + 1), id(i + 1, j + 1)]);
                faces.push([id(i, j), id(i + 1, j + 1), id(i + 1, j)]);
            }
        }
        (verts, faces)
    }

    fn laplacian_flat_and_known_mesh(device: &Device) {
        // Interior vertices of a regular flat grid have 6 neighbours symmetric about them.
        let n = 5;
        let (verts, faces) = flat_grid(n);
        let lap = UniformLaplacian::new(&faces, n * n).unwrap();
        let lv = read(lap.apply(tensor(verts.clone(), [1, n * n, 3], device)));
        for i in 0..n {
            for j in 0..n {
                let norm: f64 = lv[(i * n + j) * 3..][..3].iter().map(|v| v * v).sum();
                let interior = i > 0 && j > 0 && i < n - 1 && j < n - 1;
                if interior {
                    assert!(norm < 1e-24, "interior ({i},{j}) has |Lv|² = {norm}");
                } else {
                    assert!(
                        norm > 1e-6,
                        "boundary ({i},{j}) should not be at its centroid"
                    );
                }
            }
        }

        // Two triangles (0,1,2), (1,3,2) plus an isolated vertex 4, with a duplicated face that
        // must not double-count edges. By hand: |Lv|² = 0.5, 1, 1, 1.5, 0 → mean 4/5.
        let verts = vec![
            0.0, 0.0, 0.0, //
            1.0, 0.0, 0.0, //
            0.0, 1.0, 0.0, //
            1.0, 1.0, 1.0, //
            5.0, 5.0, 5.0,
        ];
        let faces = [[0, 1, 2], [1, 3, 2], [2, 1, 0]];
        let loss = scalar(laplacian_uniform(
            tensor(verts.clone(), [5, 3], device),
            &faces,
        ));
        assert!((loss - 0.8).abs() < 1e-12, "{loss}");
        let lap = UniformLaplacian::new(&faces, 5).unwrap();
        let lv = read(lap.apply(tensor(verts.clone(), [1, 5, 3], device)));
        let expect = [
            0.5,
            0.5,
            0.0, //
            -2.0 / 3.0,
            2.0 / 3.0,
            1.0 / 3.0, //
            2.0 / 3.0,
            -2.0 / 3.0,
            1.0 / 3.0, //
            -0.5,
            -0.5,
            -1.0, //
            0.0,
            0.0,
            0.0,
        ];
        for (g, e) in lv.iter().zip(expect) {
            assert!((g - e).abs() < 1e-12, "{lv:?}");
        }
        // A batch of meshes averages over all their vertices; doubling positions quadruples it.
        let doubled: Vec<f64> = verts.iter().map(|v| 2.0 * v).collect();
        let both = [verts, doubled].concat();
        let batch = scalar(lap.loss(tensor(both, [2, 5, 3], device)));
        assert!((batch - (0.8 + 3.2) / 2.0).abs() < 1e-12, "{batch}");
        // Out-of-range faces are reported, not indexed.
        assert!(matches!(
            UniformLaplacian::new(&[[0, 1, 7]], 5),
            Err(LossError::FaceIndexOutOfRange { index: 7, .. })
        ));
    }

    fn laplacian_gradient_matches_finite_differences(device: &Device) {
        let n = 4;
        let (_, faces) = flat_grid(n);
        let verts = pseudo_random(n * n * 3, 21);
        let entries: Vec<usize> = (0..verts.len()).collect();
        check_gradient(device, &verts, [n * n, 3], &entries, |v| {
            laplacian_uniform(v, &faces)
        });
    }

    fn weights_combine_terms(device: &Device) {
        let w = LossWeights::new();
        assert_eq!(
            (w.rgb, w.mask, w.ssim, w.lpips, w.laplacian),
            (1.0, 5.0, 1.0, 0.0, 100.0)
        );
        let t = |v: f64| tensor(vec![v], [1], device);
        let terms = LossTerms {
            rgb: t(0.1),
            mask: t(0.2),
            ssim: t(0.3),
            lpips: None,
            laplacian: t(0.01),
        };
        let out = w.total(terms.clone()).unwrap();
        let scalars = out.scalars().unwrap();
        let names: Vec<_> = scalars.iter().map(|(n, _)| *n).collect();
        assert_eq!(names, ["total", "rgb", "mask", "ssim", "laplacian"]);
        let expect = [2.4, 0.1, 1.0, 0.3, 1.0];
        for ((_, got), e) in scalars.iter().zip(expect) {
            assert!((got - e).abs() < 1e-12, "{scalars:?}");
        }
        // More tensors ride on the same read-back, after the parts and in order.
        let more = [t(0.5), tensor(vec![0.25, 0.125], [2], device)];
        let (with_names, values) = out.scalars_with(&more).unwrap();
        assert_eq!(with_names, names);
        assert_eq!(values.len(), expect.len() + 3);
        for (got, e) in values.iter().zip(expect.iter().chain(&[0.5, 0.25, 0.125])) {
            assert!((got - e).abs() < 1e-12, "{values:?}");
        }
        // A non-zero LPIPS weight needs the term; with it, the term is added.
        let aist = LossWeights::new().with_mask(0.0).with_lpips(1.0);
        assert!(matches!(
            aist.total(terms.clone()),
            Err(LossError::MissingTerm("lpips"))
        ));
        let with_lpips = LossTerms {
            lpips: Some(t(0.05)),
            ..terms
        };
        let out = aist.total(with_lpips).unwrap();
        assert!((scalar(out.total) - (0.1 + 0.3 + 0.05 + 1.0)).abs() < 1e-12);
        assert!(out.parts.iter().all(|(n, _)| *n != "mask"));

        // The total is differentiable end to end: d total / d pred of the RGB term.
        let ad = device.clone().autodiff();
        let pred = tensor(vec![0.2, 0.8], [2], &ad).require_grad();
        let gt = tensor(vec![0.5, 0.5], [2], &ad);
        let zero = tensor(vec![0.0], [1], &ad);
        let terms = LossTerms {
            rgb: l1(pred.clone(), gt),
            mask: zero.clone(),
            ssim: zero.clone(),
            lpips: None,
            laplacian: zero,
        };
        let grads = w.total(terms).unwrap().total.backward();
        let g = read(pred.grad(&grads).unwrap());
        assert!(
            (g[0] + 0.5).abs() < 1e-12 && (g[1] - 0.5).abs() < 1e-12,
            "{g:?}"
        );
    }

    /// The CPU op ([`crate::ssim_op`]) equals the mean of the tensor-op map it replaces (the
    /// CubeCL path), values and the gradients of both images, in f32 and f64, on a batch with
    /// several images and channels whose planes are smaller and larger than the window.
    fn ssim_op_matches_tensor_ops(device: &Device) {
        let ad = device.clone().autodiff();
        let cfg = SsimConfig::new();
        for (shape, dtype, tol) in [
            ([3usize, 2usize, 13usize, 17usize], DType::F64, 1e-12),
            ([2, 3, 6, 9], DType::F32, 2e-5),
        ] {
            let n: usize = shape.iter().product();
            let make = |seed: u64| {
                Tensor::<4>::from_data(TensorData::new(pseudo_random(n, seed), shape), (&ad, dtype))
                    .require_grad()
            };
            let (x, y) = (make(21), make(22));
            let weights =
                Tensor::<4>::from_data(TensorData::new(pseudo_random(n, 23), shape), (&ad, dtype));
            let run = |fused: bool| {
                let s = if fused {
                    cfg.ssim(x.clone(), y.clone())
                } else {
                    cfg.ssim_map(x.clone(), y.clone()).mean()
                };
                // A loss that is not the SSIM alone, so the upstream gradient is not 1.
                let loss = s.clone() * 3.0 + (x.clone() * weights.clone()).sum() * 0.0;
                let grads = loss.backward();
                [
                    read(s),
                    read(x.grad(&grads).expect("prediction gradient")),
                    read(y.grad(&grads).expect("target gradient")),
                ]
            };
            let (fused, reference) = (run(true), run(false));
            for (k, name) in ["mean", "prediction gradient", "target gradient"]
                .iter()
                .enumerate()
            {
                let scale = reference[k].iter().fold(1e-3f64, |m, v| m.max(v.abs()));
                for (a, b) in fused[k].iter().zip(&reference[k]) {
                    assert!(
                        (a - b).abs() <= tol * scale,
                        "{shape:?} {dtype:?} {name}: op {a} vs tensor ops {b}"
                    );
                }
            }
            assert!(
                fused[1].iter().any(|g| g.abs() > 1e-6),
                "gradients vanished"
            );
        }
    }

    fn run_all(device: &Device) {
        ssim_op_matches_tensor_ops(device);
        identical_images(device);
        constant_shift_matches_hand_computation(device);
        ssim_matches_slow_reference_symmetric_and_bounded(device);
        ssim_gradient_matches_finite_differences(device);
        laplacian_flat_and_known_mesh(device);
        laplacian_gradient_matches_finite_differences(device);
        weights_combine_terms(device);
    }

    #[test]
    fn losses_ndarray() {
        run_all(&Device::ndarray());
    }

    #[test]
    fn losses_flex() {
        run_all(&Device::flex());
    }
}
