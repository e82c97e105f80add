//! The rasterizer as one custom Burn op.
//!
//! [`GaussianRasterOps`] is a Burn backend extension: `#[backend_extension]` generates its
//! `Dispatch` implementation, so model code calls it on a plain `Tensor` and the backend is the
//! one the tensors live on. Implemented for NdArray and Flex (both run [`super::cpu`]), for
//! Burn's CubeCL backend (wgpu; the `cube` module) and for `Autodiff<B, C>` over any backend
//! that also implements [`RasterKernels`].
//!
//! Only the forward is public through dispatch. The autodiff implementation calls the hidden
//! [`RasterKernels`] trait: a forward that also hands back its intermediates (tile lists, final
//! transmittance, last contributors), kept in the autodiff node's state so the backward never
//! recomputes projection, sorting or binning (the op is marked compute-bound: no checkpointing
//! recomputation either).

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use std::any::Any;
use std::fmt;
use std::sync::{Arc, OnceLock};

use crate::cube::deferred::{Input, Output, Value, array, deferred};
use crate::op_backward::gradient_per_input;
use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::{DType, TensorData};

use super::cpu::{self, GaussianSlices, RasterConfig, ViewsConfig};
use crate::readback::{self, HostLend};

/// The differentiable Gaussian rasterizer, as a Burn backend extension.
///
/// Inputs: means `[N,3]`, covariances `[N,6]` (xx, xy, xz, yy, yz, zz), colours `[N,3]`,
/// opacities `[N]`. Output: `[H, W, C]`, premultiplied RGB, alpha, and depth when
/// `config.channels` asks for it. Callers validate shapes and finiteness first (see
/// [`super::rasterize`]); the kernels themselves cull anything non-finite rather than panic.
#[backend_extension(NdArray, Flex, Cube, Fusion, Autodiff)]
pub trait GaussianRasterOps: Backend {
    /// Renders the Gaussians.
    #[fusion(meta = |_means, _covariances, _colors, _opacities, config| {
        TensorSpec::new(config.image_shape(), DType::F32)
    })]
    fn rasterize_gaussians(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: RasterConfig,
    ) -> FloatTensor<Self>;

    /// Renders the Gaussians in every view of `config`: `[n, H, W, C]`, view `k` at `[k]` equal
    /// to [`Self::rasterize_gaussians`] with `config.view(k)`; the gradients are the views'
    /// summed in view order.
    #[fusion(meta = |_means, _covariances, _colors, _opacities, config| {
        TensorSpec::new(config.image_shape(), DType::F32)
    })]
    fn rasterize_gaussian_views(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: ViewsConfig,
    ) -> FloatTensor<Self>;
}

/// A backend's saved forward intermediates, opaque to autodiff.
#[derive(Clone)]
pub struct SavedRaster(pub Arc<dyn Any + Send + Sync>);

impl fmt::Debug for SavedRaster {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("SavedRaster(..)")
    }
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait RasterKernels: Backend {
    /// The forward, also returning what the backward needs.
    fn rasterize_saving(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: RasterConfig,
    ) -> (FloatTensor<Self>, SavedRaster);

    /// [`GaussianRasterOps::rasterize_gaussian_views`], also returning what the backward needs.
    fn rasterize_views_saving(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: ViewsConfig,
    ) -> (FloatTensor<Self>, SavedRaster);

    /// Gradients w.r.t. `[means, covariances, colors, opacities]` given `dL/dimage`.
    fn rasterize_backward(
        saved: &SavedRaster,
        grad_image: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 4];
}

/// What a CPU backend saves for the backward: the inputs (moved, not copied) and the
/// forward's intermediates.
struct CpuSaved {
    means: Vec<f32>,
    covariances: Vec<f32>,
    colors: Vec<f32>,
    opacities: Vec<f32>,
    /// One per view, in order.
    states: Vec<cpu::ForwardState>,
}

impl CpuSaved {
    fn slices(&self) -> GaussianSlices<'_> {
        GaussianSlices {
            means: &self.means,
            covariances: &self.covariances,
            colors: &self.colors,
            opacities: &self.opacities,
        }
    }
}

/// The Gaussians rendered by [`cpu::forward`] in each of `views` in turn, the images one after
/// the other in an output of `shape` (`[H, W, C]` for one view, `[n, H, W, C]` for several).
fn cpu_render<B: Backend>(
    gaussians: [FloatTensor<B>; 4],
    views: &[RasterConfig],
    shape: burn::tensor::Shape,
) -> (FloatTensor<B>, CpuSaved) {
    let device = gaussians[0].device();
    let [means, covariances, colors, opacities] = gaussians;
    let means = readback::cpu_float::<B>("means", means);
    let covariances = readback::cpu_float::<B>("covariances", covariances);
    let colors = readback::cpu_float::<B>("colors", colors);
    let opacities = readback::cpu_float::<B>("opacities", opacities);
    let slices = GaussianSlices {
        means: &means,
        covariances: &covariances,
        colors: &colors,
        opacities: &opacities,
    };
    let mut images = Vec::new();
    let mut states = Vec::with_capacity(views.len());
    for view in views {
        let (image, state) = cpu::forward(view, &slices);
        images.extend(image);
        states.push(state);
    }
    let saved = CpuSaved {
        means,
        covariances,
        colors,
        opacities,
        states,
    };
    (
        B::float_from_data(TensorData::new(images, shape), &device),
        saved,
    )
}

/// Every view of `config` rendered in turn: `[n, H, W, C]`.
fn cpu_views_forward<B: Backend>(
    gaussians: [FloatTensor<B>; 4],
    config: &ViewsConfig,
) -> (FloatTensor<B>, CpuSaved) {
    let views: Vec<RasterConfig> = (0..config.views.len()).map(|k| config.view(k)).collect();
    cpu_render::<B>(gaussians, &views, config.image_shape())
}

fn cpu_forward<B: Backend>(
    gaussians: [FloatTensor<B>; 4],
    config: RasterConfig,
) -> (FloatTensor<B>, CpuSaved) {
    cpu_render::<B>(gaussians, &[config], config.image_shape())
}

fn cpu_backward<B: HostLend>(
    saved: &SavedRaster,
    grad_image: FloatTensor<B>,
) -> [FloatTensor<B>; 4] {
    let saved = saved
        .0
        .downcast_ref::<CpuSaved>()
        .expect("CPU backward given a CPU forward state");
    let device = grad_image.device();
    let grad_image = B::lend_float::<f32>("grad_image", &grad_image);
    // View `k`'s gradient is the `k`-th of equal blocks of `dL/dimage`; the views' Gaussian
    // gradients are summed in view order (one view: its own, unchanged).
    let per_view = grad_image.len() / saved.states.len().max(1);
    let mut views = saved.states.iter().enumerate().map(|(k, state)| {
        cpu::backward(
            &saved.slices(),
            state,
            &grad_image[k * per_view..][..per_view],
        )
    });
    let mut grads = views.next().expect("a forward renders at least one view");
    for more in views {
        let add = |total: &mut Vec<f32>, more: Vec<f32>| {
            total.iter_mut().zip(more).for_each(|(t, m)| *t += m);
        };
        add(&mut grads.means, more.means);
        add(&mut grads.covariances, more.covariances);
        add(&mut grads.colors, more.colors);
        add(&mut grads.opacities, more.opacities);
    }
    let n = saved.opacities.len();
    [
        B::float_from_data(TensorData::new(grads.means, [n, 3]), &device),
        B::float_from_data(TensorData::new(grads.covariances, [n, 6]), &device),
        B::float_from_data(TensorData::new(grads.colors, [n, 3]), &device),
        B::float_from_data(TensorData::new(grads.opacities, [n]), &device),
    ]
}

/// Implements the op for a CPU backend through the shared slice functions.
macro_rules! cpu_raster_backend {
    ($backend:ty) => {
        impl GaussianRasterOps for $backend {
            fn rasterize_gaussians(
                means: FloatTensor<Self>,
                covariances: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                opacities: FloatTensor<Self>,
                config: RasterConfig,
            ) -> FloatTensor<Self> {
                cpu_forward::<Self>([means, covariances, colors, opacities], config).0
            }

            fn rasterize_gaussian_views(
                means: FloatTensor<Self>,
                covariances: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                opacities: FloatTensor<Self>,
                config: ViewsConfig,
            ) -> FloatTensor<Self> {
                cpu_views_forward::<Self>([means, covariances, colors, opacities], &config).0
            }
        }

        impl RasterKernels for $backend {
            fn rasterize_saving(
                means: FloatTensor<Self>,
                covariances: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                opacities: FloatTensor<Self>,
                config: RasterConfig,
            ) -> (FloatTensor<Self>, SavedRaster) {
                let (image, state) =
                    cpu_forward::<Self>([means, covariances, colors, opacities], config);
                (image, SavedRaster(Arc::new(state)))
            }

            fn rasterize_views_saving(
                means: FloatTensor<Self>,
                covariances: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                opacities: FloatTensor<Self>,
                config: ViewsConfig,
            ) -> (FloatTensor<Self>, SavedRaster) {
                let (image, state) =
                    cpu_views_forward::<Self>([means, covariances, colors, opacities], &config);
                (image, SavedRaster(Arc::new(state)))
            }

            fn rasterize_backward(
                saved: &SavedRaster,
                grad_image: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 4] {
                cpu_backward::<Self>(saved, grad_image)
            }
        }
    };
}

cpu_raster_backend!(NdArray);
cpu_raster_backend!(Flex);

#[derive(Debug)]
struct RasterBackward;

impl<B: RasterKernels> Backward<B, 4> for RasterBackward {
    type State = SavedRaster;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 4>(ops, grads, |state, grad_image| {
            B::rasterize_backward(&state, grad_image)
        });
    }
}

/// The rasterizer on `Autodiff<B, C>`, one view or several: the node keeps what
/// `saving` returns when an input is tracked (for [`RasterKernels::rasterize_backward`]), else
/// `plain` renders without saving anything.
fn record_raster<B: RasterKernels, C: CheckpointStrategy>(
    gaussians: [FloatTensor<Autodiff<B, C>>; 4],
    saving: impl FnOnce([FloatTensor<B>; 4]) -> (FloatTensor<B>, SavedRaster),
    plain: impl FnOnce([FloatTensor<B>; 4]) -> FloatTensor<B>,
) -> FloatTensor<Autodiff<B, C>> {
    let [(means, m), (covariances, c), (colors, col), (opacities, o)] =
        gaussians.map(|t| t.into_parts());
    let inputs = [means, covariances, colors, opacities];
    match RasterBackward
        .prepare::<C>([m, c, col, o])
        .compute_bound()
        .stateful()
    {
        OpsKind::Tracked(prep) => {
            let (image, saved) = saving(inputs);
            prep.finish(saved, image)
        }
        OpsKind::UnTracked(prep) => prep.finish(plain(inputs)),
    }
}

impl<B: GaussianRasterOps + RasterKernels, C: CheckpointStrategy> GaussianRasterOps
    for Autodiff<B, C>
{
    fn rasterize_gaussians(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: RasterConfig,
    ) -> FloatTensor<Self> {
        record_raster::<B, C>(
            [means, covariances, colors, opacities],
            |[m, c, col, o]| B::rasterize_saving(m, c, col, o, config),
            |[m, c, col, o]| B::rasterize_gaussians(m, c, col, o, config),
        )
    }

    fn rasterize_gaussian_views(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: ViewsConfig,
    ) -> FloatTensor<Self> {
        let plain = config.clone();
        record_raster::<B, C>(
            [means, covariances, colors, opacities],
            |[m, c, col, o]| B::rasterize_views_saving(m, c, col, o, config),
            |[m, c, col, o]| B::rasterize_gaussian_views(m, c, col, o, plain),
        )
    }
}

/// A saving forward recorded on the fusion stream: `run` renders the four inputs into an image
/// of `shape` on the inner backend when the stream runs it, and its state fills the returned
/// [`DeferredSaved`].
fn deferred_saving<B: FusionBackend + RasterKernels>(
    gaussians: [FloatTensor<Fusion<B>>; 4],
    shape: burn::tensor::Shape,
    run: impl Fn([FloatTensor<B>; 4]) -> (FloatTensor<B>, SavedRaster) + Send + Sync + 'static,
) -> (FloatTensor<Fusion<B>>, SavedRaster) {
    let count = gaussians[3].shape().num_elements();
    let spec = Output::Float(TensorSpec::new(shape, DType::F32));
    let inputs = gaussians.into_iter().map(Input::Float).collect();
    let inner = Arc::new(OnceLock::new());
    let filled = inner.clone();
    let [image] = array(deferred::<B, _>(
        "rasterize_saving",
        inputs,
        vec![spec],
        move |v| {
            let (image, saved) = run(array::<_, 4>(v).map(Value::float));
            // The stream runs a recorded op once; a second run would find the cell full and
            // keep the first state, which is the same.
            let _ = filled.set(saved);
            vec![Value::Float(image)]
        },
    ));
    let saved = DeferredSaved::<B> {
        inner,
        image: image.clone(),
        gaussians: count,
    };
    (image, SavedRaster(Arc::new(saved)))
}

/// The fusion backend's forward state. The forward is recorded, not run, so the inner backend's
/// state exists only once the stream has run it: the cell is filled then. The backward reads it
/// when the stream runs the backward, which records the forward's image as an input so that it
/// runs after the forward even when autodiff runs on another thread's stream.
struct DeferredSaved<B: FusionBackend> {
    inner: Arc<OnceLock<SavedRaster>>,
    image: FloatTensor<Fusion<B>>,
    gaussians: usize,
}

impl<B: FusionBackend + RasterKernels> RasterKernels for Fusion<B> {
    fn rasterize_saving(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: RasterConfig,
    ) -> (FloatTensor<Self>, SavedRaster) {
        let shape = config.image_shape();
        deferred_saving::<B>(
            [means, covariances, colors, opacities],
            shape,
            move |[m, c, col, o]| B::rasterize_saving(m, c, col, o, config),
        )
    }

    fn rasterize_views_saving(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: ViewsConfig,
    ) -> (FloatTensor<Self>, SavedRaster) {
        let shape = config.image_shape();
        deferred_saving::<B>(
            [means, covariances, colors, opacities],
            shape,
            move |[m, c, col, o]| B::rasterize_views_saving(m, c, col, o, config.clone()),
        )
    }

    fn rasterize_backward(
        saved: &SavedRaster,
        grad_image: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 4] {
        let saved = saved
            .0
            .downcast_ref::<DeferredSaved<B>>()
            .expect("fusion backward given a fusion forward state");
        let n = saved.gaussians;
        let specs = [vec![n, 3], vec![n, 6], vec![n, 3], vec![n]]
            .map(|shape| Output::Float(TensorSpec::new(shape.into(), DType::F32)))
            .into();
        let inputs = vec![Input::Float(grad_image), Input::Float(saved.image.clone())];
        let inner = saved.inner.clone();
        array(deferred::<B, _>(
            "rasterize_backward",
            inputs,
            specs,
            move |v| {
                let [grad_image, _forward_image] = array(v);
                let state = inner
                    .get()
                    .expect("the stream ran the forward before its backward");
                B::rasterize_backward(state, grad_image.float())
                    .into_iter()
                    .map(Value::Float)
                    .collect()
            },
        ))
    }
}
