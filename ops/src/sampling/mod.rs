//! Projecting mesh vertices into the source views and sampling feature maps there (design.md §7.2,
//! §7.3).
//!
//! # Projection
//!
//! [`project_points`] maps the posed vertices of each view through that view's camera:
//! `(X, Y, Z) = E·x`, `(u, v) = (fx·X/Z + cx, fy·Y/Z + cy)`, in the pixel convention of
//! [`lifegom_render::camera`] (pixel `i` covers `[i, i+1)`). It is a chain of tensor ops, so the
//! gradient of anything sampled at `(u, v)` flows back to the vertices — the reconstructor's xyz
//! update depends on that path. Points at or behind the camera plane divide by
//! [`MIN_DEPTH`] instead of their depth: they land far outside the image and sample zeros,
//! where the reference would divide by a tiny or negative depth and could produce Inf/NaN or a
//! mirrored position (such points are marked invisible by the visibility raster anyway).
//!
//! # Sampling
//!
//! [`sample_maps`] is PyTorch's `grid_sample(mode="bilinear", padding_mode="zeros",
//! align_corners=False)` with the grid normalised by the **full image size**,
//! `x_n = 2u/W − 1`. For a feature map of width `W_l` that samples at map pixel
//! `x = u·W_l/W − ½` (map pixel `j` has its centre at `x = j`), so a coarse level is sampled at
//! the same image position as a fine one. Each of the four neighbouring texels contributes
//! its bilinear weight if it lies inside the map and zero otherwise (zero padding), so a sample
//! fades linearly to zero over the half pixel outside the border.
//!
//! [`PreparedMaps::sample`] computes this for a whole pyramid as one custom op ([`op`]): slice
//! code with a hand-written backward on the CPU backends ([`bilinear`]) and CubeCL kernels on
//! GPU devices (`cube`). Gradients reach the map values, the coordinates (through the bilinear
//! slopes) and the last level's tail. Its specification, and the reference it is tested
//! against, is plain Burn tensor ops ([`Level::sample_reference`]): one row-`select` per level
//! on a channel-last copy of the map (`[N·H·W, C]`, the four corners of all points fetched at
//! once) and a weighted sum. Burn's own `grid_sample_2d` is not used because its autodiff path
//! is a generic decomposition with four `[N, C, P]` gathers per call.
//!
//! Non-finite coordinates (NaN, ±Inf) sample zero with zero gradient.

use burn::tensor::{Bool, Int, Tensor, TensorData, s};
use lifegom_render::camera::Camera;
use lifegom_render::select::select_rows;

pub mod bilinear;
mod cube;
pub mod op;
mod projection_cube;
pub mod projection_op;

use bilinear::LevelShape;
use op::PyramidLayout;

/// Depth used in place of `Z` for points with `Z < MIN_DEPTH` (at or behind the camera).
pub const MIN_DEPTH: f64 = 1e-6;

/// An image coordinate outside every feature map by far: a point there samples exactly zero.
/// Coordinates are clamped to a map's border band before any index is formed (see
/// `Level::map_coordinates`), so this value never overflows an index.
pub const OUTSIDE_EVERY_MAP: f64 = -1e6;

/// Errors raised by the projection and sampling functions (shape contracts only).
#[derive(Debug, thiserror::Error)]
pub enum SamplingError {
    /// A tensor whose shape does not match the contract.
    #[error("sampling: shape mismatch for `{tensor}`: expected {expected}, got {got:?}")]
    Shape {
        /// Which input (`points`, `uv`, `maps[2]`, ...).
        tensor: String,
        /// The contract, in words.
        expected: String,
        /// The shape received.
        got: Vec<usize>,
    },
    /// An input that is well-shaped but unusable (no cameras, zero image size, no maps).
    #[error("sampling: invalid `{what}`: {reason}")]
    InvalidInput {
        /// Which input.
        what: &'static str,
        /// What is wrong with it.
        reason: String,
    },
}

fn shape_err(
    tensor: impl Into<String>,
    expected: impl Into<String>,
    got: &[usize],
) -> SamplingError {
    SamplingError::Shape {
        tensor: tensor.into(),
        expected: expected.into(),
        got: got.to_vec(),
    }
}

/// Pixel coordinates and depths of points projected into their views.
#[derive(Debug, Clone)]
pub struct Projection {
    /// `(u, v)` in pixels, `[N, V, 2]` (pixel `i` covers `[i, i+1)`).
    pub uv: Tensor<3>,
    /// Camera-space depth `Z` (not clamped), `[N, V]`.
    pub depth: Tensor<2>,
}

/// Projects the points of each view with that view's camera.
///
/// `points` is `[N, V, 3]`: row `n` holds the V points in the world frame of `cameras[n]` (the
/// body already posed for view `n`). Returns `uv` `[N, V, 2]` and `depth` `[N, V]` in the dtype
/// of `points`, differentiable in `points`. The image size of each camera is not used here:
/// [`sample_maps`] takes it separately.
pub fn project_points(points: Tensor<3>, cameras: &[Camera]) -> Result<Projection, SamplingError> {
    let [n, v, c] = points.dims();
    if c != 3 || n != cameras.len() {
        return Err(shape_err(
            "points",
            format!("[N = {} cameras, V, 3]", cameras.len()),
            &[n, v, c],
        ));
    }
    if n == 0 {
        return Err(SamplingError::InvalidInput {
            what: "cameras",
            reason: "no views".into(),
        });
    }
    let device = points.device();
    let dtype = points.dtype();
    if !lifegom_render::device::runs_on_host(&device) {
        return Ok(project_on_device(points, cameras));
    }
    // camᵀ = xᵀ·Rᵀ + tᵀ, with Rᵀ stored per view as [N, 3, 3] and t as [N, 1, 3].
    let mut rt = Vec::with_capacity(n * 9);
    let mut t = Vec::with_capacity(n * 3);
    let mut intr = Vec::with_capacity(n * 4);
    for cam in cameras {
        let (r, translation, k) = camera_parts(cam);
        rt.extend(r);
        t.extend(translation);
        intr.extend(k);
    }
    let rt = Tensor::<3>::from_data(TensorData::new(rt, [n, 3, 3]), (&device, dtype));
    let t = Tensor::<3>::from_data(TensorData::new(t, [n, 1, 3]), (&device, dtype));
    let intr = Tensor::<3>::from_data(TensorData::new(intr, [n, 1, 4]), (&device, dtype));

    let cam = points.matmul(rt) + t; // [N, V, 3]
    let x = cam.clone().slice(s![.., .., 0..1]);
    let y = cam.clone().slice(s![.., .., 1..2]);
    let z = cam.slice(s![.., .., 2..3]);
    let z_safe = z.clone().clamp_min(MIN_DEPTH);
    let f = intr.clone().slice(s![.., .., 0..2]); // [N, 1, 2]
    let pp = intr.slice(s![.., .., 2..4]);
    let uv = Tensor::cat(vec![x, y], 2) / z_safe * f + pp;
    Ok(Projection {
        uv,
        depth: z.reshape([n, v]),
    })
}

/// `camera`'s `Rᵀ` (row-major), `t` and `fx, fy, cx, cy`, as the projection reads them.
fn camera_parts(camera: &Camera) -> ([f32; 9], [f32; 3], [f32; 4]) {
    let m = camera.view_matrix(); // row-major [R | t]
    let rt = std::array::from_fn(|e| m[4 * (e % 3) + e / 3]);
    let k = camera.intrinsics;
    (rt, [m[3], m[7], m[11]], [k.fx, k.fy, k.cx, k.cy])
}

/// [`project_points`] on a CubeCL device: one op (`projection_op`) and one split of its
/// `(u, v, Z)` columns, where the tensor ops cost about twenty launches.
fn project_on_device(points: Tensor<3>, cameras: &[Camera]) -> Projection {
    let [n, v, _] = points.dims();
    let mut table = Vec::with_capacity(n * projection_op::CAMERA_FLOATS);
    for cam in cameras {
        let (r, translation, k) = camera_parts(cam);
        table.extend(r.into_iter().chain(translation).chain(k));
    }
    let device = points.device();
    let table = Tensor::<2>::from_data(
        TensorData::new(table, [n, projection_op::CAMERA_FLOATS]),
        (&device, points.dtype()),
    );
    let projected = Tensor::<3>::from_dispatch(
        <burn::backend::Dispatch as projection_op::ProjectionOps>::project(
            points.into_dispatch(),
            table.into_dispatch(),
        ),
    );
    let mut columns = lifegom_render::split::split_columns(projected, &[2, 1]).into_iter();
    let mut next = || columns.next().expect("two blocks");
    let uv = next();
    Projection {
        uv,
        depth: next().reshape([n, v]),
    }
}

/// `uv` `[N, V, 2]` with every point whose `visible` `[V, N]` entry is 0 moved outside every
/// map ([`OUTSIDE_EVERY_MAP`]); entries are 0 or 1.
///
/// Sampling the result gives exactly `sample(uv) · visible`, values and gradients alike: a
/// hidden point samples zero, its gradient to the maps is zero, and its coordinate gradient is
/// zero because the moved coordinate is a constant (the product's is `0 · ∂sample/∂uv`). The
/// product would be a `[V, N, C]` tensor op with its own backward; this is an `[N, V, 2]` mask.
pub fn hide_invisible(uv: Tensor<3>, visible: Tensor<2>) -> Tensor<3> {
    let [n, v, _] = uv.dims();
    let hidden = visible
        .transpose()
        .reshape([n, v, 1])
        .repeat_dim(2, 2)
        .lower_elem(0.5);
    uv.mask_fill(hidden, OUTSIDE_EVERY_MAP)
}

/// Feature maps stored channel-last, ready to be sampled at many point sets: the source-view
/// maps are sampled at new vertex positions every feedback iteration.
///
/// The last level may carry a per-texel linear map, its **tail** `[C_last, C_out]`, applied
/// after sampling (bilinear weights are linear, so this equals sampling the mapped level; the
/// encoder uses it for its rgb embedding, `lifegom_model::encoder::EncodedViews`).
#[derive(Debug, Clone)]
pub struct PreparedMaps {
    storage: Storage,
    shapes: Vec<LevelShape>,
    batch: usize,
    tail: Option<Tensor<2>>,
}

/// How [`PreparedMaps`] holds its levels, by [`SampleKernel`].
#[derive(Debug, Clone)]
enum Storage {
    /// Every level's `[N·H·W, C]` rows flattened, level after level: the custom op's input.
    Flat(Box<Tensor<1>>),
    /// One [`Level`] per level, for the tensor-op composition.
    Levels(Vec<Level>),
}

/// How [`PreparedMaps::sample`] is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleKernel {
    /// The fused custom op of [`op`]: slice code on the CPU backends, CubeCL kernels on GPU
    /// devices. What the model uses.
    FusedOp,
    /// Burn tensor ops per level: the specification the op is tested against.
    TensorOps,
}

/// One level of [`PreparedMaps`].
#[doc(hidden)]
#[derive(Debug, Clone)]
pub struct Level {
    /// `[N·H·W, C]`.
    rows: Tensor<2>,
    height: usize,
    width: usize,
    channels: usize,
}

impl PreparedMaps {
    /// Takes the maps `[N, C_l, H_l, W_l]` (one batch size `N` for all levels).
    pub fn new(maps: &[Tensor<4>]) -> Result<Self, SamplingError> {
        Self::with_kernel(maps, None, SampleKernel::FusedOp)
    }

    /// [`Self::new`] with the last level mapped by `tail` `[C_last, C_out]` after sampling.
    pub fn with_tail(maps: &[Tensor<4>], tail: Tensor<2>) -> Result<Self, SamplingError> {
        Self::with_kernel(maps, Some(tail), SampleKernel::FusedOp)
    }

    fn first(maps: &[Tensor<4>]) -> Result<&Tensor<4>, SamplingError> {
        maps.first().ok_or_else(|| SamplingError::InvalidInput {
            what: "maps",
            reason: "no feature maps given".into(),
        })
    }

    /// [`Self::with_tail`] computed by `kernel` (tests compare the two).
    pub fn with_kernel(
        maps: &[Tensor<4>],
        tail: Option<Tensor<2>>,
        kernel: SampleKernel,
    ) -> Result<Self, SamplingError> {
        let batch = Self::first(maps)?.dims()[0];
        let mut shapes = Vec::with_capacity(maps.len());
        for (l, map) in maps.iter().enumerate() {
            let [n, c, h, w] = map.dims();
            if n != batch || c == 0 || h == 0 || w == 0 {
                return Err(shape_err(
                    format!("maps[{l}]"),
                    format!("[N = {batch}, C > 0, H > 0, W > 0]"),
                    &[n, c, h, w],
                ));
            }
            shapes.push(LevelShape {
                height: h,
                width: w,
                channels: c,
            });
        }
        let c_last = shapes.last().map_or(0, |s| s.channels);
        if let Some(tail) = &tail {
            let dims = tail.dims();
            if dims[0] != c_last || dims[1] == 0 {
                return Err(shape_err(
                    "tail",
                    format!("[C_last = {c_last}, C_out > 0]"),
                    &dims,
                ));
            }
        }
        let channel_last = |map: &Tensor<4>| map.clone().permute([0, 2, 3, 1]);
        let storage = match kernel {
            SampleKernel::FusedOp => Storage::Flat(Box::new(Tensor::cat(
                maps.iter().map(|m| channel_last(m).reshape([-1])).collect(),
                0,
            ))),
            SampleKernel::TensorOps => Storage::Levels(
                maps.iter()
                    .zip(&shapes)
                    .map(|(m, s)| Level {
                        rows: channel_last(m).reshape([batch * s.height * s.width, s.channels]),
                        height: s.height,
                        width: s.width,
                        channels: s.channels,
                    })
                    .collect(),
            ),
        };
        Ok(Self {
            storage,
            shapes,
            batch,
            tail,
        })
    }

    /// The same maps detached from the autodiff graph.
    pub fn detach(self) -> Self {
        let storage = match self.storage {
            Storage::Flat(rows) => Storage::Flat(Box::new(rows.detach())),
            Storage::Levels(levels) => Storage::Levels(
                levels
                    .into_iter()
                    .map(|l| Level {
                        rows: l.rows.detach(),
                        ..l
                    })
                    .collect(),
            ),
        };
        Self {
            storage,
            tail: self.tail.map(Tensor::detach),
            ..self
        }
    }

    /// Channels of one sample: every level's, the last one's after the tail.
    pub fn out_channels(&self) -> usize {
        let (last, rest) = self.shapes.split_last().expect("at least one level");
        rest.iter().map(|s| s.channels).sum::<usize>()
            + self.tail.as_ref().map_or(last.channels, |t| t.dims()[1])
    }

    /// Samples every level at `uv` `[N, V, 2]` (pixels of a `width × height` image) and
    /// concatenates the channels (the last level's after the tail): `[V, N, C]`.
    pub fn sample(
        &self,
        uv: Tensor<3>,
        width: u32,
        height: u32,
    ) -> Result<Tensor<3>, SamplingError> {
        let [n, v, two] = uv.dims();
        if n != self.batch || two != 2 {
            return Err(shape_err(
                "uv",
                format!("[N = {}, V, 2]", self.batch),
                &[n, v, two],
            ));
        }
        if width == 0 || height == 0 {
            return Err(SamplingError::InvalidInput {
                what: "width/height",
                reason: format!("image size must be > 0, got {width}x{height}"),
            });
        }
        match &self.storage {
            Storage::Flat(rows) => {
                let tail = match &self.tail {
                    Some(tail) => tail.clone(),
                    None => identity(
                        self.shapes.last().expect("at least one level").channels,
                        rows,
                    ),
                };
                let rows: &Tensor<1> = rows;
                let layout = PyramidLayout {
                    views: n,
                    image: (width as usize, height as usize),
                    levels: self.shapes.clone(),
                };
                Ok(Tensor::from_dispatch(
                    <burn::backend::Dispatch as op::BilinearSampleOps>::bilinear_sample(
                        rows.clone().into_dispatch(),
                        uv.into_dispatch(),
                        tail.into_dispatch(),
                        layout,
                    ),
                ))
            }
            Storage::Levels(levels) => Ok(self.sample_reference(levels, uv, width, height)),
        }
    }

    /// [`Self::sample`] as tensor ops, level by level.
    fn sample_reference(
        &self,
        levels: &[Level],
        uv: Tensor<3>,
        width: u32,
        height: u32,
    ) -> Tensor<3> {
        let [n, v, _] = uv.dims();
        // NaN would survive clamping and turn into an arbitrary index: park it far outside.
        let uv = uv.clone().mask_fill(uv.is_nan(), OUTSIDE_EVERY_MAP);
        let u = uv.clone().slice(s![.., .., 0..1]).reshape([n, v]);
        let y = uv.slice(s![.., .., 1..2]).reshape([n, v]);
        let mut sampled: Vec<Tensor<3>> = levels
            .iter()
            .map(|level| {
                let (x, y) = level.map_coordinates(u.clone(), y.clone(), width, height);
                level.sample_reference(x, y).swap_dims(0, 1)
            })
            .collect();
        if let Some(tail) = &self.tail {
            let last = sampled.pop().expect("at least one level");
            let [v, n, c] = last.dims();
            let c_out = tail.dims()[1];
            sampled.push(
                last.reshape([v * n, c])
                    .matmul(tail.clone())
                    .reshape([v, n, c_out]),
            );
        }
        Tensor::cat(sampled, 2)
    }
}

/// The `size × size` identity in `like`'s dtype and device: the tail of maps that have none.
fn identity(size: usize, like: &Tensor<1>) -> Tensor<2> {
    let values: Vec<f64> = (0..size * size)
        .map(|i| if i / size == i % size { 1.0 } else { 0.0 })
        .collect();
    Tensor::from_data(
        TensorData::new(values, [size, size]),
        (&like.device(), like.dtype()),
    )
}

impl Level {
    /// `[N, V]` image-pixel coordinates → map-pixel coordinates of this level. Clamping to
    /// `[-2, W_l + 1]` changes no sample (both corners are outside the map beyond −1 and W_l)
    /// and removes ±Inf before any integer cast.
    fn map_coordinates(
        &self,
        u: Tensor<2>,
        v: Tensor<2>,
        width: u32,
        height: u32,
    ) -> (Tensor<2>, Tensor<2>) {
        let (w, h) = (self.width, self.height);
        (
            (u * (w as f64 / width as f64) - 0.5).clamp(-2.0, w as f64 + 1.0),
            (v * (h as f64 / height as f64) - 0.5).clamp(-2.0, h as f64 + 1.0),
        )
    }

    /// Map-pixel coordinates `[N, V]` → `[N, V, C]` as ordinary tensor ops: the specification
    /// the fused op is tested against.
    #[doc(hidden)]
    pub fn sample_reference(&self, x: Tensor<2>, y: Tensor<2>) -> Tensor<3> {
        let [n, p] = x.dims();
        let device = x.device();
        let (w, h) = (self.width, self.height);
        let x0 = x.clone().floor();
        let y0 = y.clone().floor();
        let fx = x - x0.clone(); // d fx / d x = 1: this is where the coordinate gradient flows
        let fy = y - y0.clone();
        let x0 = x0.int();
        let y0 = y0.int();
        let x1 = x0.clone() + 1;
        let y1 = y0.clone() + 1;
        let outside = |i: &Tensor<2, Int>, size: usize| -> Tensor<2, Bool> {
            i.clone()
                .lower_elem(0)
                .bool_or(i.clone().greater_equal_elem(size as i64))
        };
        let wx0 = (fx.ones_like() - fx.clone()).mask_fill(outside(&x0, w), 0.0);
        let wx1 = fx.mask_fill(outside(&x1, w), 0.0);
        let wy0 = (fy.ones_like() - fy.clone()).mask_fill(outside(&y0, h), 0.0);
        let wy1 = fy.mask_fill(outside(&y1, h), 0.0);
        // Corner order (x0,y0), (x1,y0), (x0,y1), (x1,y1).
        let weights = Tensor::stack::<3>(
            vec![
                wx0.clone() * wy0.clone(),
                wx1.clone() * wy0,
                wx0 * wy1.clone(),
                wx1 * wy1,
            ],
            2,
        ); // [N, P, 4]
        let clamp_x = |i: Tensor<2, Int>| i.clamp(0, w as i64 - 1);
        let clamp_y = |i: Tensor<2, Int>| i.clamp(0, h as i64 - 1);
        let (x0, x1, y0, y1) = (clamp_x(x0), clamp_x(x1), clamp_y(y0), clamp_y(y1));
        let base =
            (Tensor::<1, Int>::arange(0..n as i64, &device) * (h * w) as i64).reshape([n, 1]);
        let row = |y: Tensor<2, Int>| base.clone() + y * w as i64;
        let (r0, r1) = (row(y0), row(y1));
        let index = Tensor::stack::<3>(
            vec![
                r0.clone() + x0.clone(),
                r0 + x1.clone(),
                r1.clone() + x0,
                r1 + x1,
            ],
            2,
        )
        .reshape([n * p * 4]);
        let c = self.channels;
        let corners = select_rows(self.rows.clone(), 0, index).reshape([n, p, 4, c]);
        (corners * weights.unsqueeze_dim::<4>(3))
            .sum_dim(2)
            .reshape([n, p, c])
    }
}

/// Samples every map at `uv` and concatenates the channels.
///
/// `maps` are `[N, C_l, H_l, W_l]`, `uv` is `[N, V, 2]` in pixels of the full `width × height`
/// image. Returns `[V, N, ΣC_l]`, differentiable in the maps and in `uv`. See the module docs
/// for the exact convention (torch `grid_sample`, bilinear, zero padding, align_corners=False).
pub fn sample_maps(
    maps: &[Tensor<4>],
    uv: Tensor<3>,
    width: u32,
    height: u32,
) -> Result<Tensor<3>, SamplingError> {
    PreparedMaps::new(maps)?.sample(uv, width, height)
}

/// Samples a one-channel map (the rendered alpha of the feedback branch, design.md §7.3) at `uv`:
/// `[N, 1, H, W]`, `[N, V, 2]` → `[V, N]`.
pub fn sample_single(
    map: Tensor<4>,
    uv: Tensor<3>,
    width: u32,
    height: u32,
) -> Result<Tensor<2>, SamplingError> {
    let dims = map.dims();
    if dims[1] != 1 {
        return Err(shape_err("map", "[N, 1, H, W]", &dims));
    }
    let sampled = sample_maps(&[map], uv, width, height)?;
    let [v, n, _] = sampled.dims();
    Ok(sampled.reshape([v, n]))
}

#[cfg(test)]
mod tests {
    // `Device::ndarray()` is deprecated in Burn 0.22; ndarray is the CI backend the project
    // requires (design.md §1.4).
    #![allow(deprecated)]
    use super::*;
    use burn::tensor::ops::GridSampleOptions;
    use burn::tensor::{DType, Device};
    use glam::Vec3;
    use lifegom_render::camera::Intrinsics;
    use lifegom_render::rng::Rng;

    fn tensor<const D: usize>(v: Vec<f64>, shape: [usize; D], device: &Device) -> Tensor<D> {
        Tensor::from_data(TensorData::new(v, shape), (device, DType::F64))
    }

    fn read<const D: usize>(t: Tensor<D>) -> Vec<f64> {
        t.into_data().convert::<f64>().to_vec::<f64>().unwrap()
    }

    /// Scalar torch `grid_sample` (bilinear, zeros, align_corners=False) of `map` `[C,H,W]`
    /// at image pixel `(u, v)` of a `width × height` image.
    #[allow(clippy::too_many_arguments)] // a scalar reference reads best with plain arguments
    fn reference(
        map: &[f64],
        c: usize,
        h: usize,
        w: usize,
        u: f64,
        v: f64,
        width: f64,
        height: f64,
    ) -> Vec<f64> {
        let xn = 2.0 * u / width - 1.0;
        let yn = 2.0 * v / height - 1.0;
        let x = ((xn + 1.0) * w as f64 - 1.0) / 2.0;
        let y = ((yn + 1.0) * h as f64 - 1.0) / 2.0;
        let (x0, y0) = (x.floor(), y.floor());
        let mut out = vec![0.0; c];
        for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
            let (xi, yi) = (x0 + dx, y0 + dy);
            if !(xi >= 0.0 && xi < w as f64 && yi >= 0.0 && yi < h as f64) {
                continue;
            }
            let wgt = (1.0 - (x - xi).abs()) * (1.0 - (y - yi).abs());
            for (ch, o) in out.iter_mut().enumerate() {
                *o += wgt * map[ch * h * w + yi as usize * w + xi as usize];
            }
        }
        out
    }

    /// `map[j, i] = 1 + 2i + 3j` sampled inside returns 1 + 2x + 3y with x = u·W_l/W − ½.
    fn linear_ramp(device: &Device) {
        let (width, height) = (32u32, 16u32);
        for (w, h) in [(32usize, 16usize), (8, 4)] {
            let vals: Vec<f64> = (0..h)
                .flat_map(|j| (0..w).map(move |i| 1.0 + 2.0 * i as f64 + 3.0 * j as f64))
                .collect();
            let map = tensor(vals, [1, 1, h, w], device);
            let pts = [(5.3, 7.9), (16.0, 8.0), (10.01, 3.7), (27.2, 12.3)];
            let uv = tensor(
                pts.iter().flat_map(|&(u, v)| [u, v]).collect(),
                [1, pts.len(), 2],
                device,
            );
            let got = read(sample_single(map, uv, width, height).unwrap());
            for (k, &(u, v)) in pts.iter().enumerate() {
                let x = u * w as f64 / width as f64 - 0.5;
                let y = v * h as f64 / height as f64 - 0.5;
                let expect = 1.0 + 2.0 * x + 3.0 * y;
                assert!(
                    (got[k] - expect).abs() < 1e-9,
                    "{w}x{h} at ({u},{v}): {} vs {expect}",
                    got[k]
                );
            }
        }
    }
    lifegom_render::cpu_backend_tests!(linear_ramp_is_reproduced => linear_ramp);

    /// At a pixel centre of the full-resolution map the sample is that pixel, for every channel.
    fn pixel_centre(device: &Device) {
        let (c, h, w) = (3, 5, 7);
        let vals: Vec<f64> = (0..c * h * w).map(|i| (i as f64 * 0.37).sin()).collect();
        let map = tensor(vals.clone(), [1, c, h, w], device);
        let pix = [(0usize, 0usize), (6, 4), (3, 2), (6, 0)];
        let uv = tensor(
            pix.iter()
                .flat_map(|&(i, j)| [i as f64 + 0.5, j as f64 + 0.5])
                .collect(),
            [1, pix.len(), 2],
            device,
        );
        let got = read(sample_maps(&[map], uv, w as u32, h as u32).unwrap()); // [V, 1, C]
        for (k, &(i, j)) in pix.iter().enumerate() {
            for ch in 0..c {
                assert_eq!(
                    got[k * c + ch],
                    vals[ch * h * w + j * w + i],
                    "pixel ({i},{j}) ch {ch}"
                );
            }
        }
    }
    lifegom_render::cpu_backend_tests!(pixel_centre_returns_the_pixel => pixel_centre);

    /// Points half a pixel or more outside the image (every texel of the bilinear footprint is
    /// outside), NaN and ±Inf sample exactly zero; closer to the border the sample fades.
    fn outside(device: &Device) {
        let (h, w) = (4usize, 6usize);
        let map = tensor(vec![2.0; h * w], [1, 1, h, w], device);
        let pts = [
            (-0.5, 2.0),
            (6.6, 2.0),
            (3.0, -0.5),
            (3.0, 100.0),
            (f64::NAN, 2.0),
            (f64::INFINITY, 2.0),
            (3.0, f64::NEG_INFINITY),
            (-1e30, 1e30),
        ];
        let uv = tensor(
            pts.iter().flat_map(|&(u, v)| [u, v]).collect(),
            [1, pts.len(), 2],
            device,
        );
        let got = read(sample_single(map.clone(), uv, w as u32, h as u32).unwrap());
        assert!(got.iter().all(|&g| g == 0.0), "{got:?}");
        // u = 0.25: x = −0.25, only corner 0 is inside, with weight 0.75.
        let uv = tensor(vec![0.25, 2.0], [1, 1, 2], device);
        let got = read(sample_single(map, uv, w as u32, h as u32).unwrap());
        assert!((got[0] - 1.5).abs() < 1e-12, "{got:?}");
    }
    lifegom_render::cpu_backend_tests!(outside_samples_zero => outside);

    fn random_maps(
        rng: &mut Rng,
        n: usize,
        shapes: &[(usize, usize, usize)],
        device: &Device,
    ) -> (Vec<Vec<f64>>, Vec<Tensor<4>>) {
        let host: Vec<Vec<f64>> = shapes
            .iter()
            .map(|&(c, h, w)| (0..n * c * h * w).map(|_| rng.range(-1.0, 1.0)).collect())
            .collect();
        let maps = host
            .iter()
            .zip(shapes)
            .map(|(v, &(c, h, w))| tensor(v.clone(), [n, c, h, w], device))
            .collect();
        (host, maps)
    }

    /// Several levels and views at random points (some outside) against the scalar reference,
    /// and Burn's own `grid_sample_2d` on the normalised grid as a second opinion.
    fn random_reference(device: &Device) {
        let mut rng = Rng::new(7);
        let (width, height) = (40u32, 24u32);
        let (n, v) = (2, 37);
        let shapes = [(3, 24, 40), (2, 12, 20), (4, 3, 5), (1, 1, 1)];
        let (host, maps) = random_maps(&mut rng, n, &shapes, device);
        let uv_host: Vec<f64> = (0..n * v)
            .flat_map(|_| [rng.range(-3.0, 43.0), rng.range(-3.0, 27.0)])
            .collect();
        let uv = tensor(uv_host.clone(), [n, v, 2], device);
        let got = read(sample_maps(&maps, uv.clone(), width, height).unwrap());
        let total: usize = shapes.iter().map(|s| s.0).sum();
        for p in 0..v {
            for b in 0..n {
                let (u, y) = (uv_host[2 * (b * v + p)], uv_host[2 * (b * v + p) + 1]);
                let mut offset = 0;
                for (l, &(c, h, w)) in shapes.iter().enumerate() {
                    let map = &host[l][b * c * h * w..(b + 1) * c * h * w];
                    let expect = reference(map, c, h, w, u, y, width as f64, height as f64);
                    for ch in 0..c {
                        let g = got[(p * n + b) * total + offset + ch];
                        assert!(
                            (g - expect[ch]).abs() < 1e-9,
                            "level {l} view {b} point {p} ch {ch}: {g} vs {}",
                            expect[ch]
                        );
                    }
                    offset += c;
                }
            }
        }
        // Burn's grid_sample_2d on the normalised grid, the same convention written by others.
        let gx = uv.clone().slice(s![.., .., 0..1]) * (2.0 / width as f64) - 1.0;
        let gy = uv.clone().slice(s![.., .., 1..2]) * (2.0 / height as f64) - 1.0;
        let grid = Tensor::cat(vec![gx, gy], 2).reshape([n, v, 1, 2]);
        for (l, map) in maps.iter().enumerate() {
            let c = shapes[l].0;
            let burn_ref = map
                .clone()
                .grid_sample_2d(grid.clone(), GridSampleOptions::default())
                .reshape([n, c, v])
                .permute([2, 0, 1]);
            let ours = sample_maps(std::slice::from_ref(map), uv.clone(), width, height).unwrap();
            let diff = (burn_ref - ours).abs().max().into_scalar::<f64>();
            assert!(
                diff < 1e-9,
                "level {l}: Burn's grid_sample_2d differs by {diff}"
            );
        }
    }
    lifegom_render::cpu_backend_tests!(matches_reference_at_random_points => random_reference);

    /// `Σ W ⊙ sample_maps(maps, uv)` with the leaves it was built from.
    fn weighted_loss(
        maps: &[Vec<f64>],
        shapes: &[(usize, usize, usize)],
        uv: &[f64],
        weights: &[f64],
        n: usize,
        device: &Device,
    ) -> (Tensor<1>, Vec<Tensor<4>>, Tensor<3>) {
        let v = uv.len() / (2 * n);
        let maps: Vec<Tensor<4>> = maps
            .iter()
            .zip(shapes)
            .map(|(m, &(c, h, w))| tensor(m.clone(), [n, c, h, w], device).require_grad())
            .collect();
        let uv_t = tensor(uv.to_vec(), [n, v, 2], device).require_grad();
        let sampled = sample_maps(&maps, uv_t.clone(), 20, 12).unwrap();
        let w = tensor(weights.to_vec(), sampled.dims(), device);
        ((sampled * w).sum(), maps, uv_t)
    }

    fn scalar(t: Tensor<1>) -> f64 {
        read(t)[0]
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-6 * a.abs().max(b.abs()) + 1e-8
    }

    /// Central differences in f64 against `backward()` for every map value and coordinate.
    fn gradients(device: &Device) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(11);
        let n = 2;
        let shapes = [(2, 12, 20), (3, 3, 5), (1, 12, 20)];
        let maps: Vec<Vec<f64>> = shapes
            .iter()
            .map(|&(c, h, w)| (0..n * c * h * w).map(|_| rng.range(-1.0, 1.0)).collect())
            .collect();
        // 9 points per view, a few within a pixel of the border so zero padding is exercised.
        let uv: Vec<f64> = (0..n * 9)
            .flat_map(|_| [rng.range(-0.8, 20.8), rng.range(-0.8, 12.8)])
            .collect();
        let total: usize = shapes.iter().map(|s| s.0).sum();
        let weights: Vec<f64> = (0..9 * n * total).map(|_| rng.range(-1.0, 1.0)).collect();
        let (loss, map_leaves, uv_leaf) = weighted_loss(&maps, &shapes, &uv, &weights, n, &ad);
        let grads = loss.backward();
        let eps = 1e-6;
        let numeric = |maps: &[Vec<f64>], uv: &[f64]| {
            scalar(weighted_loss(maps, &shapes, uv, &weights, n, &ad).0)
        };
        let g_uv = read(uv_leaf.grad(&grads).expect("uv gradient"));
        for i in 0..uv.len() {
            let (mut plus, mut minus) = (uv.clone(), uv.clone());
            plus[i] += eps;
            minus[i] -= eps;
            let fd = (numeric(&maps, &plus) - numeric(&maps, &minus)) / (2.0 * eps);
            assert!(
                close(g_uv[i], fd),
                "uv[{i}]: analytic {} vs numeric {fd}",
                g_uv[i]
            );
        }
        assert!(
            g_uv.iter().any(|g| g.abs() > 1e-3),
            "coordinate gradients vanished"
        );
        for (l, leaf) in map_leaves.iter().enumerate() {
            let g = read(leaf.grad(&grads).expect("map gradient"));
            // The loss is linear in the map values: a step of 1 is exact.
            for i in (0..maps[l].len()).step_by(7) {
                let mut plus = maps.to_vec();
                plus[l][i] += 1.0;
                let fd = numeric(&plus, &uv) - numeric(&maps, &uv);
                assert!(
                    close(g[i], fd),
                    "maps[{l}][{i}]: analytic {} vs numeric {fd}",
                    g[i]
                );
            }
        }
    }
    lifegom_render::cpu_backend_tests!(gradients_match_finite_differences => gradients);

    fn cameras() -> Vec<Camera> {
        let intr = Intrinsics {
            fx: 30.0,
            fy: 28.0,
            cx: 10.0,
            cy: 6.5,
        };
        vec![
            Camera::look_at(Vec3::new(0.0, 0.1, 2.5), Vec3::ZERO, Vec3::Y, intr, 20, 12).unwrap(),
            Camera::look_at(
                Vec3::new(2.0, 0.4, 1.0),
                Vec3::new(0.1, 0.0, 0.0),
                Vec3::Y,
                intr,
                20,
                12,
            )
            .unwrap(),
        ]
    }

    /// `project_points` agrees with `Camera::project`, and depth is the camera-space Z.
    fn projection(device: &Device) {
        let cams = cameras();
        let mut rng = Rng::new(3);
        let v = 10;
        let pts: Vec<f64> = (0..cams.len() * v * 3)
            .map(|_| rng.range(-0.4, 0.4))
            .collect();
        let proj = project_points(tensor(pts.clone(), [2, v, 3], device), &cams).unwrap();
        let (uv, depth) = (read(proj.uv), read(proj.depth));
        for (b, cam) in cams.iter().enumerate() {
            for p in 0..v {
                let k = b * v + p;
                let x = Vec3::new(
                    pts[3 * k] as f32,
                    pts[3 * k + 1] as f32,
                    pts[3 * k + 2] as f32,
                );
                let (e, z) = cam.project(x).unwrap();
                assert!((uv[2 * k] - e.x as f64).abs() < 1e-3, "view {b} point {p}");
                assert!(
                    (uv[2 * k + 1] - e.y as f64).abs() < 1e-3,
                    "view {b} point {p}"
                );
                assert!((depth[k] - z as f64).abs() < 1e-5);
            }
        }
        // A point behind the camera lands far outside the image instead of mirroring into it.
        let behind = tensor(vec![0.1, 0.1, 3.0, 0.0, 0.0, 0.0], [1, 2, 3], device);
        let proj = project_points(behind, &cams[..1]).unwrap();
        let uv = read(proj.uv);
        assert!(
            uv[0].abs() > 1e4 && uv.iter().all(|x| x.is_finite()),
            "{uv:?}"
        );
        assert!(read(proj.depth)[0] < 0.0);
    }
    lifegom_render::cpu_backend_tests!(projection_matches_camera => projection);

    /// Gradients from sampled features reach the 3D points (the xyz update path).
    fn projection_gradients(device: &Device) {
        let ad = device.clone().autodiff();
        let cams = cameras();
        let mut rng = Rng::new(5);
        let (n, v, c) = (2, 6, 2);
        let map: Vec<f64> = (0..n * c * 12 * 20).map(|_| rng.range(-1.0, 1.0)).collect();
        let pts: Vec<f64> = (0..n * v * 3).map(|_| rng.range(-0.3, 0.3)).collect();
        let w: Vec<f64> = (0..v * n * c).map(|_| rng.range(-1.0, 1.0)).collect();
        let loss = |pts: &[f64], device: &Device| {
            let p = tensor(pts.to_vec(), [n, v, 3], device).require_grad();
            let proj = project_points(p.clone(), &cams).unwrap();
            let m = tensor(map.clone(), [n, c, 12, 20], device);
            let s = sample_maps(&[m], proj.uv, 20, 12).unwrap();
            ((s * tensor(w.clone(), [v, n, c], device)).sum(), p)
        };
        let (l, leaf) = loss(&pts, &ad);
        let g = read(leaf.grad(&l.backward()).expect("points gradient"));
        let eps = 1e-6;
        for i in 0..pts.len() {
            let (mut plus, mut minus) = (pts.clone(), pts.clone());
            plus[i] += eps;
            minus[i] -= eps;
            let fd = (scalar(loss(&plus, &ad).0) - scalar(loss(&minus, &ad).0)) / (2.0 * eps);
            assert!(
                (g[i] - fd).abs() <= 1e-5 * g[i].abs().max(fd.abs()) + 1e-7,
                "points[{i}]: analytic {} vs numeric {fd}",
                g[i]
            );
        }
        assert!(
            g.iter().any(|x| x.abs() > 1e-2),
            "point gradients vanished: {g:?}"
        );
    }
    lifegom_render::cpu_backend_tests!(projection_gradients_reach_points => projection_gradients);

    /// On wgpu the projection op and its split equal the tensor ops on Flex: `uv`, depth and the
    /// points' gradient of a loss weighing both, in f32, for points in front of the cameras,
    /// behind them and in the plane of their centres (where the clamp stops the depth's share).
    #[test]
    fn projection_op_matches_tensor_ops_wgpu() {
        let Some(device) = lifegom_render::testing::wgpu_test_device() else {
            return;
        };
        let cams = cameras();
        let mut rng = Rng::new(17);
        let (n, v) = (cams.len(), 40);
        let mut pts: Vec<f32> = (0..n * v * 3)
            .map(|_| rng.range(-0.5, 0.5) as f32)
            .collect();
        // Behind the first camera (at z = 2.5 looking at the origin), and in its centre's plane.
        pts[..3].copy_from_slice(&[0.1, 0.2, 3.0]);
        pts[3..6].copy_from_slice(&[0.3, -0.1, 2.5]);
        let wu: Vec<f32> = (0..n * v * 2)
            .map(|_| rng.range(-1.0, 1.0) as f32)
            .collect();
        let wd: Vec<f32> = (0..n * v).map(|_| rng.range(-1.0, 1.0) as f32).collect();
        let run = |device: &Device| {
            let ad = device.clone().autodiff();
            let p =
                Tensor::<3>::from_data(TensorData::new(pts.clone(), [n, v, 3]), &ad).require_grad();
            let proj = project_points(p.clone(), &cams).unwrap();
            let weights_uv = Tensor::<3>::from_data(TensorData::new(wu.clone(), [n, v, 2]), &ad);
            let weights_depth = Tensor::<2>::from_data(TensorData::new(wd.clone(), [n, v]), &ad);
            let loss =
                (proj.uv.clone() * weights_uv).sum() + (proj.depth.clone() * weights_depth).sum();
            let grad = p.grad(&loss.backward()).expect("points gradient");
            [read(proj.uv), read(proj.depth), read(grad)]
        };
        let want = run(&Device::flex());
        let got = run(&device);
        for (what, (g, w)) in ["uv", "depth", "points' gradient"]
            .iter()
            .zip(got.iter().zip(&want))
        {
            let scale = w.iter().fold(0f64, |m, x| m.max(x.abs()));
            for (i, (a, b)) in g.iter().zip(w).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-5 * scale.max(1.0),
                    "{what}[{i}]: {a} on wgpu, {b} from the tensor ops"
                );
            }
        }
    }

    /// The fused op equals the tensor-op composition it replaces (per level
    /// [`Level::sample_reference`], then the tail's product and the concatenation), values and
    /// gradients (every level's maps, the coordinates and the tail), in f32, at points inside,
    /// on the border and outside the maps, and at NaN and Inf: the CPU slice code and, on wgpu,
    /// the CubeCL kernels (whose rows' gradient adds atomically, native or emulated).
    fn fused_matches_reference(device: &Device) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(13);
        let (n, p, size) = (3usize, 700usize, (40u32, 24u32));
        let shapes = [(8usize, 12usize, 20usize), (5, 3, 5), (4, 24, 40)];
        let maps: Vec<Vec<f32>> = shapes
            .iter()
            .map(|&(c, h, w)| {
                (0..n * c * h * w)
                    .map(|_| rng.range_f32(-1.0, 1.0))
                    .collect()
            })
            .collect();
        let mut uv: Vec<f32> = (0..n * p)
            .flat_map(|_| [rng.range_f32(-3.0, 43.0), rng.range_f32(-3.0, 27.0)])
            .collect();
        uv[10] = f32::NAN;
        uv[13] = f32::INFINITY;
        let tail: Vec<f32> = (0..4 * 6).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let c_out = 8 + 5 + 6;
        let weight: Vec<f32> = (0..p * n * c_out)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let run = |kernel: SampleKernel| {
            let map_t: Vec<Tensor<4>> = maps
                .iter()
                .zip(&shapes)
                .map(|(m, &(c, h, w))| {
                    Tensor::<4>::from_data(TensorData::new(m.clone(), [n, c, h, w]), &ad)
                        .require_grad()
                })
                .collect();
            let uv_t =
                Tensor::<3>::from_data(TensorData::new(uv.clone(), [n, p, 2]), &ad).require_grad();
            let tail_t =
                Tensor::<2>::from_data(TensorData::new(tail.clone(), [4, 6]), &ad).require_grad();
            let prepared = PreparedMaps::with_kernel(&map_t, Some(tail_t.clone()), kernel).unwrap();
            assert_eq!(prepared.out_channels(), c_out);
            let out = prepared.sample(uv_t.clone(), size.0, size.1).unwrap();
            assert_eq!(out.dims(), [p, n, c_out]);
            let wt = Tensor::<1>::from_data(TensorData::new(weight.clone(), [p * n * c_out]), &ad)
                .reshape([p, n, c_out]);
            let grads = (out.clone() * wt).sum().backward();
            let mut parts = vec![
                out.reshape([-1]),
                uv_t.grad(&grads).expect("uv gradient").reshape([-1]),
                tail_t.grad(&grads).expect("tail gradient").reshape([-1]),
            ];
            parts.extend(
                map_t
                    .iter()
                    .map(|m| m.grad(&grads).expect("map gradient").reshape([-1])),
            );
            parts.into_iter().map(read).collect::<Vec<_>>()
        };
        let (fused, reference) = (run(SampleKernel::FusedOp), run(SampleKernel::TensorOps));
        let names = [
            "values",
            "uv gradient",
            "tail gradient",
            "map 0",
            "map 1",
            "map 2",
        ];
        for (k, name) in names.iter().enumerate() {
            assert_eq!(fused[k].len(), reference[k].len(), "{name}");
            let scale = reference[k].iter().fold(1.0f64, |m, v| m.max(v.abs()));
            let diff = fused[k]
                .iter()
                .zip(&reference[k])
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                diff <= 1e-5 * scale,
                "{name}: max diff {diff:.2e} (scale {scale:.2e})"
            );
        }
        assert!(
            fused[1].iter().any(|g| g.abs() > 1e-3),
            "uv gradients vanished"
        );
        assert_eq!(
            &fused[1][10..14],
            &[0.0; 4],
            "NaN and Inf points have no gradient"
        );
    }
    lifegom_render::cpu_backend_tests!(fused_op_matches_reference => fused_matches_reference);

    #[test]
    fn fused_op_matches_reference_wgpu() {
        let Some(device) = lifegom_render::testing::wgpu_test_device() else {
            return;
        };
        fused_matches_reference(&device);
        lifegom_render::rasterizer::force_emulated_float_atomics(true);
        let result = std::panic::catch_unwind(|| fused_matches_reference(&device));
        lifegom_render::rasterizer::force_emulated_float_atomics(false);
        if let Err(panic) = result {
            std::panic::resume_unwind(panic);
        }
    }

    /// Sampling at [`hide_invisible`] coordinates equals sampling and then multiplying by the
    /// visibility: values, map gradients and coordinate gradients, on several levels, with
    /// hidden and visible points inside, on the border of and outside the maps.
    fn hidden_points_sample_like_a_visibility_product(device: &Device) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(29);
        let (n, p, size) = (3usize, 400usize, 24u32);
        let shapes = [(4usize, 12usize, 12usize), (6, 6, 6), (3, 3, 3)];
        let (host, _) = random_maps(&mut rng, n, &shapes, device);
        let uv: Vec<f64> = (0..n * p * 2)
            .map(|_| rng.range(-3.0, f64::from(size) + 3.0))
            .collect();
        let visible: Vec<f64> = (0..p * n)
            .map(|_| if rng.uniform() < 0.6 { 1.0 } else { 0.0 })
            .collect();
        let c: usize = shapes.iter().map(|s| s.0).sum();
        let weight: Vec<f64> = (0..p * n * c).map(|_| rng.range(-1.0, 1.0)).collect();
        let run = |masked_coordinates: bool| {
            let maps: Vec<Tensor<4>> = host
                .iter()
                .zip(&shapes)
                .map(|(v, &(c, h, w))| tensor(v.clone(), [n, c, h, w], &ad).require_grad())
                .collect();
            let uv_t = tensor(uv.clone(), [n, p, 2], &ad).require_grad();
            let vis = tensor(visible.clone(), [p, n], &ad);
            let out = if masked_coordinates {
                sample_maps(&maps, hide_invisible(uv_t.clone(), vis), size, size).unwrap()
            } else {
                sample_maps(&maps, uv_t.clone(), size, size).unwrap() * vis.reshape([p, n, 1])
            };
            let grads = (out.clone() * tensor(weight.clone(), [p, n, c], &ad))
                .sum()
                .backward();
            let mut parts = vec![read(out), read(uv_t.grad(&grads).expect("uv gradient"))];
            parts.extend(
                maps.iter()
                    .map(|m| read(m.grad(&grads).expect("map gradient"))),
            );
            parts
        };
        let (masked, product) = (run(true), run(false));
        for (k, (a, b)) in masked.iter().zip(&product).enumerate() {
            assert_eq!(a.len(), b.len());
            let diff = a
                .iter()
                .zip(b)
                .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
            assert!(diff <= 1e-12, "part {k}: max diff {diff:.2e}");
        }
        assert!(
            masked[1].iter().any(|g| g.abs() > 1e-3),
            "visible points keep their coordinate gradient"
        );
    }
    lifegom_render::cpu_backend_tests!(
        hidden_points_sample_like_a_visibility_product => hidden_points_sample_like_a_visibility_product
    );

    /// Shape contracts are checked and the offending input is named.
    #[test]
    fn shape_errors_name_the_input() {
        let device = Device::flex();
        let cams = cameras();
        let err = project_points(Tensor::zeros([3, 4, 3], &device), &cams).unwrap_err();
        assert!(err.to_string().contains("`points`"), "{err}");
        let maps = [
            Tensor::<4>::zeros([2, 3, 4, 4], &device),
            Tensor::zeros([1, 3, 2, 2], &device),
        ];
        let err = sample_maps(&maps, Tensor::zeros([2, 5, 2], &device), 8, 8).unwrap_err();
        assert!(err.to_string().contains("`maps[1]`"), "{err}");
        let err = sample_maps(&maps[..1], Tensor::zeros([1, 5, 2], &device), 8, 8).unwrap_err();
        assert!(err.to_string().contains("`uv`"), "{err}");
        let err =
            sample_single(maps[0].clone(), Tensor::zeros([2, 5, 2], &device), 8, 8).unwrap_err();
        assert!(err.to_string().contains("`map`"), "{err}");
        let err = sample_maps(&[], Tensor::zeros([2, 5, 2], &device), 8, 8).unwrap_err();
        assert!(err.to_string().contains("`maps`"), "{err}");
    }
}
