//! Differentiable EWA splatting of 3D Gaussians, the renderer of LIFe-GoM (design.md §6).
//!
//! The official code uses the graphdeco 3DGS rasterizer with precomputed covariances and colours;
//! this module reproduces its forward exactly (constants in [`cpu`]) and differentiates it
//! exactly. [`rasterize`] is the entry point: it checks shapes and values at the boundary, then
//! calls the custom Burn op [`op::GaussianRasterOps`], which runs on whichever backend the
//! tensors live on and records a backward node when they require gradients. [`rasterize_views`]
//! renders several views of the same Gaussians in one call (`[n, H, W, C]`), every GPU stage one
//! launch for all of them.
//!
//! ```no_run
//! # use lifegom_render::rasterizer::{Gaussians, RasterSettings, rasterize};
//! # fn f(gaussians: Gaussians, settings: RasterSettings) -> lifegom_render::Result<()> {
//! let rendered = rasterize(&gaussians, &settings)?;
//! let (rgb, alpha) = (rendered.rgb(), rendered.alpha()); // [H,W,3] premultiplied, [H,W]
//! # Ok(()) }
//! ```

pub mod cpu;
pub(crate) mod cube;
pub mod op;

use std::sync::OnceLock;

use burn::tensor::Tensor;

pub use crate::camera::ViewParams;
pub use cpu::{AlphaCutoff, Channels, RasterConfig, ViewsConfig};

use crate::camera::Camera;
use crate::error::{RenderError, Result, check_finite};
use crate::readback;
use crate::split::{join_columns, split_columns};

/// A set of 3D Gaussians in world space, ready to render.
#[derive(Debug, Clone)]
pub struct Gaussians {
    /// Centres, `[N, 3]`.
    pub means: Tensor<2>,
    /// Covariances as their 6 upper-triangular entries (xx, xy, xz, yy, yz, zz), `[N, 6]`.
    pub covariances: Tensor<2>,
    /// Colours, `[N, 3]` (any real values; LIFe-GoM passes raw, unclamped RGB).
    pub colors: Tensor<2>,
    /// Opacities in `[0, 1]`, `[N]`.
    pub opacities: Tensor<1>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacities.dims()[0]
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Checks the shape contract: `[N,3]`, `[N,6]`, `[N,3]`, `[N]` with one `N`.
    pub fn check_shapes(&self) -> Result<usize> {
        let n = self.len();
        let expect = |tensor: &'static str, got: [usize; 2], cols: usize| {
            if got == [n, cols] {
                Ok(())
            } else {
                Err(RenderError::Shape {
                    tensor,
                    expected: format!("[{n}, {cols}]"),
                    got: got.to_vec(),
                })
            }
        };
        expect("means", self.means.dims(), 3)?;
        expect("covariances", self.covariances.dims(), 6)?;
        expect("colors", self.colors.dims(), 3)?;
        Ok(n)
    }

    /// Checks every value is finite. Opacities must also be in [0, 1]. A tensor that cannot be
    /// read back is a [`RenderError::Readback`], never "no values".
    ///
    /// On a CubeCL device one scalar is read back first ([`Gaussians::any_bad_value`]): a sync,
    /// but of 4 bytes, where reading the four tensors was four syncs and 13 floats per Gaussian
    /// (23 MB per render at the paper's setting, the model's renders being validated every
    /// feedback step). Only when it says a value is bad are the tensors read, to name it. The
    /// CPU backends read the tensors directly: that is no sync there.
    pub fn check_values(&self) -> Result<()> {
        if !crate::device::runs_on_host(&self.means.device()) && !self.any_bad_value()? {
            return Ok(());
        }
        self.check_values_on_host()
    }

    /// Whether some value is not finite or some opacity lies outside [0, 1], computed on the
    /// tensors' device and read back as one scalar.
    pub fn any_bad_value(&self) -> Result<bool> {
        let n = self.len();
        let device = self.means.device();
        // The four tensors side by side, `[N, 13]`, in one launch on a CubeCL device; then one
        // sum of `x · 0 + w · |x − clamp(x, 0, 1)|`, where `w` is 1 in the opacity column only
        // (arithmetic, not comparisons: Burn's fusion joins it to the sum). `x · 0` is 0 for
        // every finite `x` and NaN for ±∞ and NaN, so the sum is NaN exactly when a value is not
        // finite, positive when an opacity is outside [0, 1] and 0 otherwise.
        let values = join_columns(vec![
            self.means.clone().detach(),
            self.covariances.clone().detach(),
            self.colors.clone().detach(),
            self.opacities.clone().detach().reshape([n, 1]),
        ]);
        let mut opacity_column = [0.0f32; 13];
        opacity_column[12] = 1.0;
        let w = Tensor::<1>::from_floats(opacity_column, &device).reshape([1, 13]);
        let outside = (values.clone() - values.clone().clamp(0.0, 1.0)).abs();
        let flag = (values * 0.0 + outside * w).sum();
        let flag: Vec<f32> = readback::read("Gaussian value check", flag)?;
        Ok(flag.first().is_none_or(|&f| f != 0.0))
    }

    /// [`Gaussians::check_values`] by reading the four tensors back: names the first bad value.
    fn check_values_on_host(&self) -> Result<()> {
        let means: Vec<f32> = readback::read("means", self.means.clone())?;
        check_finite("means", &means)?;
        let covariances: Vec<f32> = readback::read("covariances", self.covariances.clone())?;
        check_finite("covariances", &covariances)?;
        let colors: Vec<f32> = readback::read("colors", self.colors.clone())?;
        check_finite("colors", &colors)?;
        let opacities: Vec<f32> = readback::read("opacities", self.opacities.clone())?;
        check_finite("opacities", &opacities)?;
        if let Some(index) = opacities.iter().position(|o| !(0.0..=1.0).contains(o)) {
            return Err(RenderError::InvalidInput {
                what: "opacities",
                reason: format!(
                    "value {} at index {index} is outside [0, 1]",
                    opacities[index]
                ),
            });
        }
        Ok(())
    }
}

/// Whether [`rasterize`] reads the inputs back to check they are finite.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Validation {
    /// Check shapes and values; a NaN or Inf gives [`RenderError::NonFinite`]. (Default.)
    #[default]
    Full,
    /// Check shapes only. The kernels still cull non-finite Gaussians instead of panicking.
    ShapesOnly,
}

/// Per-call settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RasterSettings {
    /// The camera (and image size).
    pub camera: Camera,
    /// Output channels.
    pub channels: Channels,
    /// Alpha cutoff rule; [`AlphaCutoff::Smooth`] is for gradient tests.
    pub cutoff: AlphaCutoff,
    /// Input validation.
    pub validation: Validation,
}

impl RasterSettings {
    /// RGB + alpha, the reference cutoff, full validation.
    pub fn new(camera: Camera) -> Self {
        Self {
            camera,
            channels: Channels::RgbAlpha,
            cutoff: AlphaCutoff::Hard,
            validation: Validation::Full,
        }
    }

    /// Also output expected depth.
    pub fn with_depth(mut self) -> Self {
        self.channels = Channels::RgbAlphaDepth;
        self
    }

    /// Sets the cutoff rule.
    pub fn with_cutoff(mut self, cutoff: AlphaCutoff) -> Self {
        self.cutoff = cutoff;
        self
    }

    /// Sets the validation level.
    pub fn with_validation(mut self, validation: Validation) -> Self {
        self.validation = validation;
        self
    }

    /// The flattened form the kernels take.
    pub fn config(&self) -> RasterConfig {
        RasterConfig {
            view: self.camera.view_params(),
            channels: self.channels,
            cutoff: self.cutoff,
        }
    }
}

/// A rendered image: `[H, W, C]` with premultiplied RGB, alpha, and depth if asked for.
#[derive(Debug, Clone)]
pub struct Rendered {
    /// The raw op output.
    pub image: Tensor<3>,
    /// Which channels `image` holds.
    pub channels: Channels,
    /// `image`'s colour, alpha (and depth) as tensors of their own, made on first use by one
    /// split ([`crate::split`]): every reader of a channel then shares one node, and on a GPU
    /// the split and its backward are one launch each instead of a slice per read.
    blocks: OnceLock<Vec<Tensor<3>>>,
}

impl Rendered {
    fn blocks(&self) -> &[Tensor<3>] {
        self.blocks
            .get_or_init(|| split_columns(self.image.clone(), self.channels.block_widths()))
    }

    /// Premultiplied RGB (over black), `[H, W, 3]`.
    pub fn rgb(&self) -> Tensor<3> {
        self.blocks()[0].clone()
    }

    /// Accumulated alpha `1 − T`, `[H, W]`.
    pub fn alpha(&self) -> Tensor<2> {
        self.blocks()[1].clone().squeeze_dim(2)
    }

    /// Expected depth `Σ zᵢαᵢTᵢ` (not divided by alpha), `[H, W]`, if rendered.
    pub fn depth(&self) -> Option<Tensor<2>> {
        (self.channels == Channels::RgbAlphaDepth).then(|| self.blocks()[2].clone().squeeze_dim(2))
    }

    /// Standard "over" compositing onto a constant background: `rgb + bg·(1 − α)`.
    pub fn over(&self, background: [f32; 3]) -> Tensor<3> {
        let device = self.image.device();
        let bg = Tensor::<1>::from_floats(background, &device).reshape([1, 1, 3]);
        let alpha = self.alpha().unsqueeze_dim::<3>(2);
        self.rgb() + bg * (alpha.ones_like() - alpha)
    }

    /// The official code's compositing, `rgb·α + bg·(1 − α)` (design.md §6.5): the premultiplied
    /// colour is multiplied by alpha a second time, darkening soft edges by `α²`.
    pub fn composite_reference(&self, background: [f32; 3]) -> Tensor<3> {
        composite_reference(self.rgb(), self.alpha().unsqueeze_dim::<3>(2), background)
    }
}

/// Renders `gaussians` with `settings`, differentiably.
///
/// Errors on a bad shape, a degenerate camera, or (with [`Validation::Full`]) a non-finite value,
/// naming the input. Gradients reach all four inputs through `backward()` when they require them.
pub fn rasterize(gaussians: &Gaussians, settings: &RasterSettings) -> Result<Rendered> {
    let _span = tracing::debug_span!("rasterize", n = gaussians.len()).entered();
    settings.camera.validate()?;
    gaussians.check_shapes()?;
    if settings.validation == Validation::Full {
        gaussians.check_values()?;
    }
    let image = Tensor::from_dispatch(
        <burn::backend::Dispatch as op::GaussianRasterOps>::rasterize_gaussians(
            gaussians.means.clone().into_dispatch(),
            gaussians.covariances.clone().into_dispatch(),
            gaussians.colors.clone().into_dispatch(),
            gaussians.opacities.clone().into_dispatch(),
            settings.config(),
        ),
    );
    Ok(Rendered {
        image,
        channels: settings.channels,
        blocks: OnceLock::new(),
    })
}

/// Several views of one set of Gaussians: `[n, H, W, C]`, premultiplied RGB, alpha, and depth
/// if asked for ([`rasterize_views`]).
#[derive(Debug, Clone)]
pub struct RenderedViews {
    /// The raw op output.
    pub image: Tensor<4>,
    /// Which channels `image` holds.
    pub channels: Channels,
}

impl RenderedViews {
    /// [`Rendered::composite_reference`] of every view, `[n, H, W, 3]`, and the alpha,
    /// `[n, H, W, 1]`.
    pub fn composite_reference(&self, background: [f32; 3]) -> (Tensor<4>, Tensor<4>) {
        let mut blocks =
            split_columns(self.image.clone(), self.channels.block_widths()).into_iter();
        let rgb = blocks.next().expect("colour block");
        let alpha = blocks.next().expect("alpha block");
        (composite_reference(rgb, alpha.clone(), background), alpha)
    }
}

/// The official code's compositing `rgb·α + bg·(1 − α)` (design.md §6.5) of `rgb` `[.., 3]`
/// and `alpha` `[.., 1]`.
fn composite_reference<const D: usize>(
    rgb: Tensor<D>,
    alpha: Tensor<D>,
    background: [f32; 3],
) -> Tensor<D> {
    let mut shape = [1usize; D];
    shape[D - 1] = 3;
    let bg = Tensor::<1>::from_floats(background, &rgb.device()).reshape(shape);
    rgb * alpha.clone() + bg * (alpha.ones_like() - alpha)
}

/// Renders `gaussians` in every view of `settings`, differentiably, in one call: on a CubeCL
/// device every stage is one launch for all the views (design.md §6.3), where a view at a time
/// takes about ten launches forward and three backward per view. View `k` of the result equals
/// [`rasterize`] with `settings[k]`; the Gaussians' gradients are the views' summed.
///
/// The views share one image size, channel set and cutoff; errors name a bad camera, views
/// that differ in those, or (as [`rasterize`]) a bad Gaussian input.
pub fn rasterize_views(
    gaussians: &Gaussians,
    settings: &[RasterSettings],
) -> Result<RenderedViews> {
    let _span = tracing::debug_span!(
        "rasterize_views",
        n = gaussians.len(),
        views = settings.len()
    )
    .entered();
    let Some(first) = settings.first() else {
        return Err(RenderError::InvalidInput {
            what: "cameras",
            reason: "no view".into(),
        });
    };
    for view in settings {
        view.camera.validate()?;
        let size = |s: &RasterSettings| (s.camera.width, s.camera.height);
        if size(view) != size(first)
            || view.channels != first.channels
            || view.cutoff != first.cutoff
        {
            return Err(RenderError::InvalidInput {
                what: "cameras",
                reason: format!(
                    "the views of one call share an image size, channels and cutoff: {:?} and {:?}",
                    (size(first), first.channels, first.cutoff),
                    (size(view), view.channels, view.cutoff)
                ),
            });
        }
    }
    gaussians.check_shapes()?;
    if settings.iter().any(|s| s.validation == Validation::Full) {
        gaussians.check_values()?;
    }
    let config = ViewsConfig {
        views: settings.iter().map(|s| s.camera.view_params()).collect(),
        channels: first.channels,
        cutoff: first.cutoff,
    };
    let image = Tensor::from_dispatch(
        <burn::backend::Dispatch as op::GaussianRasterOps>::rasterize_gaussian_views(
            gaussians.means.clone().into_dispatch(),
            gaussians.covariances.clone().into_dispatch(),
            gaussians.colors.clone().into_dispatch(),
            gaussians.opacities.clone().into_dispatch(),
            config,
        ),
    );
    Ok(RenderedViews {
        image,
        channels: first.channels,
    })
}

/// Renders `gaussians` in every view of `settings` and composites each onto `background` as
/// the official code does ([`Rendered::composite_reference`]): the colour `[n, H, W, 3]` and
/// the alpha `[n, H, W, 1]`, differentiably.
///
/// Several views on a CubeCL device are one [`rasterize_views`] call (every stage one launch
/// for all of them). The CPU backends, and a single view, take a [`rasterize`] call per view:
/// the same values, and the Gaussians' gradients summed view by view, in the order a caller
/// rendering one view at a time sums them (training's gradients to the bit).
///
/// Errors as [`rasterize_views`].
pub fn composite_views(
    gaussians: &Gaussians,
    settings: &[RasterSettings],
    background: [f32; 3],
) -> Result<(Tensor<4>, Tensor<4>)> {
    if settings.is_empty() {
        return Err(RenderError::InvalidInput {
            what: "cameras",
            reason: "no view".into(),
        });
    }
    if settings.len() > 1 && !crate::device::runs_on_host(&gaussians.means.device()) {
        return Ok(rasterize_views(gaussians, settings)?.composite_reference(background));
    }
    let mut rgb = Vec::with_capacity(settings.len());
    let mut alpha = Vec::with_capacity(settings.len());
    for view in settings {
        let rendered = rasterize(gaussians, view)?;
        rgb.push(rendered.composite_reference(background));
        alpha.push(rendered.alpha().unsqueeze_dim::<3>(2));
    }
    Ok((Tensor::stack(rgb, 0), Tensor::stack(alpha, 0)))
}

/// Makes the GPU backward use its emulated (atomic-exchange) float adds even where the device has
/// native ones (process-wide; both paths compute the same sums). For tests and benchmarks.
#[doc(hidden)]
pub fn force_emulated_float_atomics(force: bool) {
    crate::cube::atomic::FORCE_EMULATED.store(force, std::sync::atomic::Ordering::Relaxed);
}

/// Makes the GPU backward split every tile into `groups` pixel groups (1, 2, 4 or 8; 1 is one
/// cube per tile), or, with `None`, into the default eight (process-wide; every count computes
/// the same sums up to the order of float additions). For tests and benchmarks; any other
/// count is an [`RenderError::InvalidInput`] and changes nothing.
#[doc(hidden)]
pub fn force_backward_pixel_groups(groups: Option<u32>) -> Result<()> {
    cube::force_backward_pixel_groups(groups)
}

/// Whether the GPU backward on `device` would use native float atomic adds (`false` on CPU
/// devices, and where [`force_emulated_float_atomics`] is set).
#[doc(hidden)]
pub fn native_float_atomics(device: &burn::tensor::Device) -> bool {
    cube::native_float_atomics(device)
}

#[cfg(test)]
mod tests;
