//! Bilinear sampling of a whole feature pyramid as one custom Burn op (design.md §7.2).
//!
//! [`BilinearSampleOps`] is a Burn backend extension like the renderer's: `#[backend_extension]`
//! generates its `Dispatch` implementation, so [`super::PreparedMaps::sample`] calls it on plain
//! tensors. It is implemented for NdArray and Flex (both run the slice code of
//! [`super::bilinear`]), for Burn's CubeCL backend (the kernels of `super::cube`) and for
//! `Autodiff<B, C>` over them. One call samples every level at the same image positions and
//! writes all of them into one output, the last level through its per-texel linear tail (the
//! encoder's rgb embedding). It replaces, per level and call, the map coordinates (a scale, a
//! shift and a clamp per axis), about fifteen ops of index arithmetic, gather and weighted sum,
//! and then a concatenation of the levels and the tail's product: on a CPU their intermediates
//! and autodiff nodes cost more than the sampling, and the concatenation's backward handed each
//! level a strided slice of the gradient to copy (BENCHMARKS.md, 2026-11-24: "After the fused
//! feature sampling", and 2026-11-25: "five more cuts of the serial part"); on a GPU each of
//! those ops, forward and backward, was a kernel launch of its own (about 2,800 of a quickstart
//! step's launches went to sampling's forward alone).
//!
//! The autodiff node keeps the op's inputs (handles, no copies); the backward recomputes each
//! point's footprint, which costs about what storing it would.

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use std::borrow::Cow;

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::{Element, Shape};
use bytemuck::Pod;
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};

use super::bilinear::{self, LevelShape, Pyramid, Real};
use lifegom_render::in_precision;
use lifegom_render::op_backward::record;
use lifegom_render::readback::{HostLend, cpu_float_from};

/// The layout of one call: the views, the image the coordinates are in, and the levels.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PyramidLayout {
    /// Views N.
    pub views: usize,
    /// `(width, height)` of the image, in pixels.
    pub image: (usize, usize),
    /// The levels in output order; the last one passes through the tail.
    pub levels: Vec<LevelShape>,
}

impl PyramidLayout {
    /// The output's shape for `uv` of shape `[N, P, 2]` and a tail of shape `[C_last, C_out]`:
    /// `[P, N, Σ_{l<L−1} C_l + C_out]`.
    pub fn output_shape(&self, uv: &Shape, tail: &Shape) -> Shape {
        let channels: usize = self.levels.iter().map(|l| l.channels).sum();
        let c_last = self.levels.last().map_or(1, |l| l.channels);
        let width = channels.saturating_sub(c_last) + tail.num_elements() / c_last.max(1);
        Shape::new([uv[1], self.views, width])
    }
}

/// Bilinear sampling of a whole feature pyramid with zero padding, fused.
///
/// Inputs: `rows` `[Σ_l N·H_l·W_l·C_l]` (each level's maps channel-last, level after level),
/// `uv` `[N, P, 2]` image-pixel coordinates, `tail` `[C_last, C_out]`. Output
/// `[P, N, Σ_{l<L−1} C_l + C_out]` in `rows`' float dtype; see [`Pyramid`] for the exact map.
/// Gradients flow to all three inputs. Callers check shapes (see [`super::PreparedMaps`]).
#[backend_extension(NdArray, Flex, Cube, Fusion, Autodiff)]
pub trait BilinearSampleOps: Backend {
    /// Samples every level of every view at its points.
    #[fusion(dtype = rows, shape = layout.output_shape(uv, tail))]
    fn bilinear_sample(
        rows: FloatTensor<Self>,
        uv: FloatTensor<Self>,
        tail: FloatTensor<Self>,
        layout: PyramidLayout,
    ) -> FloatTensor<Self>;
}

/// The op's inputs on one backend: what the forward takes and the autodiff node keeps.
#[derive(Debug, Clone)]
pub struct SampleInputs<B: Backend> {
    /// `[Σ_l N·H_l·W_l·C_l]`.
    pub rows: FloatTensor<B>,
    /// `[N, P, 2]`.
    pub uv: FloatTensor<B>,
    /// `[C_last, C_out]`.
    pub tail: FloatTensor<B>,
    /// The pyramid's layout.
    pub layout: PyramidLayout,
}

/// Which gradients a backward call computes (the coordinates' always).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Wanted {
    /// The maps'.
    pub rows: bool,
    /// The tail's.
    pub tail: bool,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait BilinearKernels: Backend {
    /// The forward, `[P, N, C_out]`.
    fn bilinear_forward(inputs: SampleInputs<Self>) -> FloatTensor<Self>;

    /// Gradients w.r.t. `rows` and `tail` (each only when wanted) and `uv` given
    /// `dL/d(output)`, each in its input's dtype.
    fn bilinear_backward(
        inputs: SampleInputs<Self>,
        grad: FloatTensor<Self>,
        wanted: Wanted,
    ) -> SampleGrads<Self>;
}

/// `(∂rows, ∂uv, ∂tail)`.
pub type SampleGrads<B> = (
    Option<FloatTensor<B>>,
    FloatTensor<B>,
    Option<FloatTensor<B>>,
);

fn cpu_forward<B: HostLend>(inputs: SampleInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.rows.dtype(), cpu_forward_in(inputs))
}

/// The op's inputs as host slices in precision `T`, lent in place where the backend allows it.
struct HostInputs<'a, T: Clone> {
    rows: Cow<'a, [T]>,
    uv: Cow<'a, [T]>,
    tail: Cow<'a, [T]>,
    layout: &'a PyramidLayout,
}

impl<'a, T: Real + Element + Pod> HostInputs<'a, T> {
    fn lend<B: HostLend>(inputs: &'a SampleInputs<B>) -> Self {
        Self {
            rows: B::lend_float::<T>("maps", &inputs.rows),
            uv: B::lend_float::<T>("uv", &inputs.uv),
            tail: B::lend_float::<T>("tail", &inputs.tail),
            layout: &inputs.layout,
        }
    }

    fn pyramid(&self) -> Pyramid<'_, T> {
        Pyramid {
            rows: &self.rows,
            views: self.layout.views,
            levels: &self.layout.levels,
            image: self.layout.image,
            tail: &self.tail,
        }
    }

    /// Points per view P.
    fn points(&self) -> usize {
        self.uv.len() / (2 * self.layout.views).max(1)
    }
}

fn cpu_forward_in<B: HostLend, T: Real + Element + Pod>(inputs: SampleInputs<B>) -> FloatTensor<B> {
    let device = inputs.rows.device();
    let dtype = inputs.rows.dtype();
    let host = HostInputs::<T>::lend(&inputs);
    let pyramid = host.pyramid();
    let out = bilinear::forward(&pyramid, &host.uv);
    let shape = [host.points(), host.layout.views, pyramid.out_channels()];
    cpu_float_from::<B, T>(out, shape, dtype, &device)
}

fn cpu_backward<B: HostLend>(
    inputs: SampleInputs<B>,
    grad: FloatTensor<B>,
    wanted: Wanted,
) -> SampleGrads<B> {
    in_precision!(inputs.rows.dtype(), cpu_backward_in(inputs, grad, wanted))
}

fn cpu_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: SampleInputs<B>,
    grad: FloatTensor<B>,
    wanted: Wanted,
) -> SampleGrads<B> {
    let device = inputs.rows.device();
    let shapes = [inputs.rows.shape(), inputs.uv.shape(), inputs.tail.shape()];
    let dtypes = [inputs.rows.dtype(), inputs.uv.dtype(), inputs.tail.dtype()];
    let grad = B::lend_float::<T>("sample gradient", &grad);
    let host = HostInputs::<T>::lend(&inputs);
    let grads = bilinear::backward(&host.pyramid(), &host.uv, &grad, wanted.rows, wanted.tail);
    let tensor = |values: Vec<T>, i: usize| {
        cpu_float_from::<B, T>(values, shapes[i].clone(), dtypes[i], &device)
    };
    (
        grads.rows.map(|g| tensor(g, 0)),
        tensor(grads.uv, 1),
        grads.tail.map(|g| tensor(g, 2)),
    )
}

/// Implements the op for a CPU backend through the shared slice functions.
macro_rules! cpu_sample_backend {
    ($backend:ty) => {
        impl BilinearSampleOps for $backend {
            fn bilinear_sample(
                rows: FloatTensor<Self>,
                uv: FloatTensor<Self>,
                tail: FloatTensor<Self>,
                layout: PyramidLayout,
            ) -> FloatTensor<Self> {
                cpu_forward::<Self>(SampleInputs {
                    rows,
                    uv,
                    tail,
                    layout,
                })
            }
        }

        impl BilinearKernels for $backend {
            fn bilinear_forward(inputs: SampleInputs<Self>) -> FloatTensor<Self> {
                cpu_forward::<Self>(inputs)
            }

            fn bilinear_backward(
                inputs: SampleInputs<Self>,
                grad: FloatTensor<Self>,
                wanted: Wanted,
            ) -> SampleGrads<Self> {
                cpu_backward::<Self>(inputs, grad, wanted)
            }
        }
    };
}

cpu_sample_backend!(NdArray);
cpu_sample_backend!(Flex);

#[derive(Debug)]
struct SampleBackward;

impl<B: BilinearKernels> Backward<B, 3> for SampleBackward {
    type State = SampleInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [rows_parent, uv_parent, tail_parent] = ops.parents;
        let wanted = Wanted {
            rows: rows_parent.is_some(),
            tail: tail_parent.is_some(),
        };
        let (grad_rows, grad_uv, grad_tail) = B::bilinear_backward(ops.state, grad, wanted);
        if let (Some(parent), Some(g)) = (rows_parent, grad_rows) {
            grads.register::<B>(parent.id, g);
        }
        if let Some(parent) = uv_parent {
            grads.register::<B>(parent.id, grad_uv);
        }
        if let (Some(parent), Some(g)) = (tail_parent, grad_tail) {
            grads.register::<B>(parent.id, g);
        }
    }
}

impl<B: BilinearSampleOps + BilinearKernels, C: CheckpointStrategy> BilinearSampleOps
    for Autodiff<B, C>
{
    fn bilinear_sample(
        rows: FloatTensor<Self>,
        uv: FloatTensor<Self>,
        tail: FloatTensor<Self>,
        layout: PyramidLayout,
    ) -> FloatTensor<Self> {
        let (rows, rows_node) = rows.into_parts();
        let (uv, uv_node) = uv.into_parts();
        let (tail, tail_node) = tail.into_parts();
        let inputs = SampleInputs {
            rows,
            uv,
            tail,
            layout,
        };
        record::<B, C, _, _, 3>(
            SampleBackward,
            [rows_node, uv_node, tail_node],
            inputs,
            B::bilinear_forward,
        )
    }
}

impl<B: FusionBackend + BilinearKernels> BilinearKernels for Fusion<B> {
    fn bilinear_forward(inputs: SampleInputs<Self>) -> FloatTensor<Self> {
        let shape = inputs
            .layout
            .output_shape(&inputs.uv.shape(), &inputs.tail.shape());
        let spec = float_like::<B>(&inputs.rows, shape);
        let (recorded, layout) = sample_inputs(inputs);
        let [out] = array(deferred::<B, _>(
            "bilinear_forward",
            recorded,
            vec![spec],
            move |v| vec![Value::Float(B::bilinear_forward(sample_values(v, &layout)))],
        ));
        out
    }

    fn bilinear_backward(
        inputs: SampleInputs<Self>,
        grad: FloatTensor<Self>,
        wanted: Wanted,
    ) -> SampleGrads<Self> {
        // Only the wanted gradients are outputs: rows (if wanted), uv, tail (if wanted).
        let mut specs = Vec::new();
        if wanted.rows {
            specs.push(float_like::<B>(&inputs.rows, inputs.rows.shape()));
        }
        specs.push(float_like::<B>(&inputs.uv, inputs.uv.shape()));
        if wanted.tail {
            specs.push(float_like::<B>(&inputs.tail, inputs.tail.shape()));
        }
        let (mut recorded, layout) = sample_inputs(inputs);
        recorded.push(Input::Float(grad));
        let outputs = deferred::<B, _>("bilinear_backward", recorded, specs, move |mut v| {
            let grad = v.pop().expect("the gradient was recorded last").float();
            let (rows, uv, tail) = B::bilinear_backward(sample_values(v, &layout), grad, wanted);
            let wanted_or_absent = |g: Option<_>, want: bool| {
                // A backend returns a gradient exactly when it is wanted.
                debug_assert_eq!(g.is_some(), want);
                g.map(Value::Float)
            };
            let mut out = Vec::new();
            out.extend(wanted_or_absent(rows, wanted.rows));
            out.push(Value::Float(uv));
            out.extend(wanted_or_absent(tail, wanted.tail));
            out
        });
        let mut outputs = outputs.into_iter();
        let rows = wanted.rows.then(|| outputs.next().expect("recorded"));
        let uv = outputs.next().expect("recorded");
        let tail = wanted.tail.then(|| outputs.next().expect("recorded"));
        (rows, uv, tail)
    }
}

/// The sampling op's three tensors, in the order [`sample_values`] reads them back, and its
/// layout.
fn sample_inputs<B: FusionBackend>(
    inputs: SampleInputs<Fusion<B>>,
) -> (Vec<Input<B>>, PyramidLayout) {
    let tensors = [inputs.rows, inputs.uv, inputs.tail]
        .into_iter()
        .map(Input::Float)
        .collect();
    (tensors, inputs.layout)
}

fn sample_values<B: FusionBackend>(
    values: Vec<Value<B>>,
    layout: &PyramidLayout,
) -> SampleInputs<B> {
    let [rows, uv, tail] = array(values);
    SampleInputs {
        rows: rows.float(),
        uv: uv.float(),
        tail: tail.float(),
        layout: layout.clone(),
    }
}
