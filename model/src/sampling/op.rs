//! Bilinear feature sampling as one custom Burn op on the CPU backends (design.md §7.2).
//!
//! [`BilinearSampleOps`] is a Burn backend extension like the renderer's: `#[backend_extension]`
//! generates its `Dispatch` implementation, so [`super::PreparedMaps::sample`] calls it on plain
//! tensors. It is implemented for NdArray and Flex (both run [`super::bilinear`]) and for
//! `Autodiff<B, C>` over them. It replaces about fifteen tensor ops per level and call (index
//! arithmetic, a four-corner row gather, weights, a weighted sum) whose intermediates and
//! autodiff nodes cost more than the sampling itself on a CPU: the profile in BENCHMARKS.md
//! ("Training step profile") put them at a third of a training step.
//!
//! There is no CubeCL implementation: on a GPU the same tensor-op composition
//! ([`super::Level::sample_reference`]) already runs as parallel kernels, and `sample` routes
//! CubeCL devices there (`lifegom_render::device::runs_on_host`).
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
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::{DType, Element};
use bytemuck::Pod;

use super::bilinear::{self, Maps, Real};
use lifegom_render::readback::{HostLend, cpu_float_from};

/// The layout of the maps of one call: `views × height × width` rows of `channels` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapLayout {
    /// Views N.
    pub views: usize,
    /// Map height H.
    pub height: usize,
    /// Map width W.
    pub width: usize,
    /// Channels C.
    pub channels: usize,
}

/// Bilinear sampling with zero padding, fused.
///
/// Inputs: `rows` `[N·H·W, C]` (the maps channel-last), `x`, `y` `[N, P]`: finite map-pixel
/// coordinates (pixel `i` has its centre at `x = i`). Output `[P, N, C]` in `rows`' float dtype.
/// Gradients flow to all three inputs. Callers check shapes (see [`super::PreparedMaps`]).
#[backend_extension(NdArray, Flex, Autodiff)]
pub trait BilinearSampleOps: Backend {
    /// Samples every view's maps at its points.
    fn bilinear_sample(
        rows: FloatTensor<Self>,
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        layout: MapLayout,
    ) -> FloatTensor<Self>;
}

/// The op's inputs on one backend: what the forward takes and the autodiff node keeps.
#[derive(Debug, Clone)]
pub struct SampleInputs<B: Backend> {
    /// `[N·H·W, C]`.
    pub rows: FloatTensor<B>,
    /// `[N, P]`.
    pub x: FloatTensor<B>,
    /// `[N, P]`.
    pub y: FloatTensor<B>,
    /// The maps' layout.
    pub layout: MapLayout,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait BilinearKernels: Backend {
    /// The forward, `[P, N, C]`.
    fn bilinear_forward(inputs: SampleInputs<Self>) -> FloatTensor<Self>;

    /// Gradients w.r.t. `rows` (only when `want_rows`), `x` and `y` given `dL/d(output)`, each
    /// in its input's dtype.
    fn bilinear_backward(
        inputs: SampleInputs<Self>,
        grad: FloatTensor<Self>,
        want_rows: bool,
    ) -> (
        Option<FloatTensor<Self>>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    );
}

fn cpu_forward<B: HostLend>(inputs: SampleInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.rows.dtype(), cpu_forward_in(inputs))
}

/// The op's inputs as host slices in precision `T`, lent in place where the backend allows it.
struct HostInputs<'a, T: Clone> {
    rows: Cow<'a, [T]>,
    x: Cow<'a, [T]>,
    y: Cow<'a, [T]>,
    layout: MapLayout,
}

impl<'a, T: Real + Element + Pod> HostInputs<'a, T> {
    fn lend<B: HostLend>(inputs: &'a SampleInputs<B>) -> Self {
        Self {
            rows: B::lend_float::<T>("maps", &inputs.rows),
            x: B::lend_float::<T>("x", &inputs.x),
            y: B::lend_float::<T>("y", &inputs.y),
            layout: inputs.layout,
        }
    }

    fn maps(&self) -> Maps<'_, T> {
        Maps {
            rows: &self.rows,
            views: self.layout.views,
            height: self.layout.height,
            width: self.layout.width,
            channels: self.layout.channels,
        }
    }

    /// Points per view P.
    fn points(&self) -> usize {
        self.x.len() / self.layout.views.max(1)
    }
}

fn cpu_forward_in<B: HostLend, T: Real + Element + Pod>(inputs: SampleInputs<B>) -> FloatTensor<B> {
    let device = inputs.rows.device();
    let dtype = inputs.rows.dtype();
    let host = HostInputs::<T>::lend(&inputs);
    let l = host.layout;
    let out = bilinear::forward(&host.maps(), &host.x, &host.y);
    cpu_float_from::<B, T>(out, [host.points(), l.views, l.channels], dtype, &device)
}

type SampleGrads<B> = (Option<FloatTensor<B>>, FloatTensor<B>, FloatTensor<B>);

fn cpu_backward<B: HostLend>(
    inputs: SampleInputs<B>,
    grad: FloatTensor<B>,
    want_rows: bool,
) -> SampleGrads<B> {
    in_precision!(
        inputs.rows.dtype(),
        cpu_backward_in(inputs, grad, want_rows)
    )
}

fn cpu_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: SampleInputs<B>,
    grad: FloatTensor<B>,
    want_rows: bool,
) -> SampleGrads<B> {
    let device = inputs.rows.device();
    let dtypes = [inputs.rows.dtype(), inputs.x.dtype(), inputs.y.dtype()];
    let grad = B::lend_float::<T>("sample gradient", &grad);
    let host = HostInputs::<T>::lend(&inputs);
    let (l, p) = (host.layout, host.points());
    let (grad_rows, grad_x, grad_y) =
        bilinear::backward(&host.maps(), &host.x, &host.y, &grad, want_rows);
    let tensor = |values: Vec<T>, shape: [usize; 2], dtype: DType| {
        cpu_float_from::<B, T>(values, shape, dtype, &device)
    };
    let rows_shape = [l.views * l.height * l.width, l.channels];
    (
        grad_rows.map(|g| tensor(g, rows_shape, dtypes[0])),
        tensor(grad_x, [l.views, p], dtypes[1]),
        tensor(grad_y, [l.views, p], dtypes[2]),
    )
}

/// Implements the op for a CPU backend through the shared slice functions.
macro_rules! cpu_sample_backend {
    ($backend:ty) => {
        impl BilinearSampleOps for $backend {
            fn bilinear_sample(
                rows: FloatTensor<Self>,
                x: FloatTensor<Self>,
                y: FloatTensor<Self>,
                layout: MapLayout,
            ) -> FloatTensor<Self> {
                cpu_forward::<Self>(SampleInputs { rows, x, y, layout })
            }
        }

        impl BilinearKernels for $backend {
            fn bilinear_forward(inputs: SampleInputs<Self>) -> FloatTensor<Self> {
                cpu_forward::<Self>(inputs)
            }

            fn bilinear_backward(
                inputs: SampleInputs<Self>,
                grad: FloatTensor<Self>,
                want_rows: bool,
            ) -> SampleGrads<Self> {
                cpu_backward::<Self>(inputs, grad, want_rows)
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
        let [rows_parent, x_parent, y_parent] = ops.parents;
        let (grad_rows, grad_x, grad_y) =
            B::bilinear_backward(ops.state, grad, rows_parent.is_some());
        if let (Some(parent), Some(g)) = (rows_parent, grad_rows) {
            grads.register::<B>(parent.id, g);
        }
        if let Some(parent) = x_parent {
            grads.register::<B>(parent.id, grad_x);
        }
        if let Some(parent) = y_parent {
            grads.register::<B>(parent.id, grad_y);
        }
    }
}

impl<B: BilinearSampleOps + BilinearKernels, C: CheckpointStrategy> BilinearSampleOps
    for Autodiff<B, C>
{
    fn bilinear_sample(
        rows: FloatTensor<Self>,
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        layout: MapLayout,
    ) -> FloatTensor<Self> {
        let (rows, rows_node) = rows.into_parts();
        let (x, x_node) = x.into_parts();
        let (y, y_node) = y.into_parts();
        let inputs = SampleInputs { rows, x, y, layout };
        match SampleBackward
            .prepare::<C>([rows_node, x_node, y_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::bilinear_forward(inputs.clone());
                prep.finish(inputs, out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::bilinear_sample(inputs.rows, inputs.x, inputs.y, layout))
            }
        }
    }
}
