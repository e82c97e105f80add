//! Per-scene optimisation: one avatar fitted to its own N source views by gradient descent
//! through the differentiable renderer (design.md §10.8).
//!
//! This is the rival LIFe-GoM's thesis is about: instead of learned feedback steps, plain
//! gradient steps on the same representation (GoMAvatar-style optimisation, the paper's gray
//! rows). The parameters are the low-res canonical vertices and every Gaussian's `so3`, `scale`,
//! `offset` and colour; the loss is the training loss restricted to the source views (RGB L1,
//! 1 − SSIM, mask L1, the Laplacian of the canonical mesh; the same weights); Adam with one
//! learning rate per parameter kind. It starts from any avatar: the template in its mean
//! colour (the per-scene baseline) or a reconstructor's output (test-time refinement).
//!
//! ```text
//! for k in 1..=K:
//!     R, M = render(avatar, source cameras and poses)
//!     loss = w_rgb·|R − I| + w_ssim·(1 − SSIM(R, I)) + w_mask·|M − mask| + w_lap·Lap(xyz)
//!     avatar ← Adam step on loss
//! ```

use std::time::Instant;

use burn::config::Config;
use burn::module::{Module, Param, ParamGroup};
use burn::optim::lr_scheduler::LrSchedulerConfig;
use burn::optim::lr_scheduler::module_lr_scheduler::ModuleLrSchedulerConfig;
use burn::optim::{GradientsParams, ModuleOptimizer};

use crate::adam::FusedAdamConfig;
use burn::tensor::Tensor;
use lifegom_model::avatar::Avatar;
use lifegom_model::inputs::ModelInputs;
use lifegom_model::reconstructor::render_views;
use lifegom_render::gom::GomParams;

use crate::losses::{LossTerms, LossWeights, UniformLaplacian, l1, mask_l1, ssim_loss};
use crate::trainer::TrainError;

/// Learning rates of the fit, one per parameter kind.
#[derive(Config, Debug)]
pub struct FitConfig {
    /// Canonical low-res vertices (metres per step, roughly: Adam's steps are ≈ lr).
    #[config(default = 1e-3)]
    pub lr_xyz: f64,
    /// Gaussian rotations (axis-angle in the face's frame).
    #[config(default = 1e-2)]
    pub lr_so3: f64,
    /// Gaussian scales (relative to the face's Steiner ellipse).
    #[config(default = 1e-2)]
    pub lr_scales: f64,
    /// Gaussian offsets (in the face's frame).
    #[config(default = 1e-3)]
    pub lr_offsets: f64,
    /// Gaussian colours.
    #[config(default = 3e-2)]
    pub lr_colors: f64,
}

/// What the fit optimises (module docs).
#[derive(Module, Debug)]
struct FitParams {
    xyz: Param<Tensor<2>>,
    so3: Param<Tensor<2>>,
    scales: Param<Tensor<2>>,
    offsets: Param<Tensor<2>>,
    colors: Param<Tensor<2>>,
}

impl FitParams {
    fn faces(&self, opacities: Tensor<1>) -> GomParams {
        GomParams {
            so3: self.so3.val(),
            scales: self.scales.val(),
            offsets: self.offsets.val(),
            colors: self.colors.val(),
            opacities,
        }
    }
}

/// The avatar `start` with its geometry and colours replaced by the fitted ones (detached, on
/// the avatar's own device).
fn snapshot(start: &Avatar, params: &FitParams) -> Avatar {
    let inner = |t: Tensor<2>| t.detach().inner();
    Avatar::new(
        inner(params.xyz.val()),
        GomParams {
            so3: inner(params.so3.val()),
            scales: inner(params.scales.val()),
            offsets: inner(params.offsets.val()),
            colors: inner(params.colors.val()),
            opacities: start.faces.opacities.clone(),
        },
        start.lbs_weights.clone(),
        start.skeleton.clone(),
        start.mesh.clone(),
    )
}

/// Fits `start` to the source views of `inputs` for `steps` Adam steps (module docs). After
/// every step `k` (1-based) `observe(k, seconds, avatar)` sees the fitted avatar and the fit's
/// own wall time so far (time spent inside `observe` is not counted); it may stop early by
/// returning `false`. Returns the last avatar.
///
/// `start` and `inputs` live on an inference device (not autodiff); the fit runs on its
/// autodiff twin. `laplacian` is over the template's low-res faces.
pub fn fit(
    start: &Avatar,
    inputs: &ModelInputs,
    laplacian: &UniformLaplacian,
    weights: &LossWeights,
    cfg: &FitConfig,
    steps: usize,
    mut observe: impl FnMut(usize, f64, &Avatar) -> Result<bool, TrainError>,
) -> Result<Avatar, TrainError> {
    let _span = tracing::info_span!("fit", steps).entered();
    let device = start.xyz.device().autodiff();
    let ad = |t: &Tensor<2>| Param::from_tensor(t.clone().autodiff());
    let mut params = FitParams {
        xyz: ad(&start.xyz),
        so3: ad(&start.faces.so3),
        scales: ad(&start.faces.scales),
        offsets: ad(&start.faces.offsets),
        colors: ad(&start.faces.colors),
    };
    let mut optim = ModuleOptimizer::from(FusedAdamConfig::default().init());
    let group = |m: Param<Tensor<2>>, lr: f64| (ParamGroup::ids_from_module(m), lr);
    let mut scheduler = [
        group(params.xyz.clone(), cfg.lr_xyz),
        group(params.so3.clone(), cfg.lr_so3),
        group(params.scales.clone(), cfg.lr_scales),
        group(params.offsets.clone(), cfg.lr_offsets),
        group(params.colors.clone(), cfg.lr_colors),
    ]
    .into_iter()
    .fold(
        ModuleLrSchedulerConfig::new(LrSchedulerConfig::Constant(cfg.lr_colors)),
        |c, (g, lr)| c.with_group(g, LrSchedulerConfig::Constant(lr)),
    )
    .init()
    .map_err(TrainError::LearningRates)?;
    let lr = scheduler.step();

    let subject = lifegom_model::reconstructor::CanonicalSubject {
        canonical_vertices: inputs.subject.canonical_vertices.clone().autodiff(),
        lbs_weights: start.lbs_weights.clone().autodiff(),
        skeleton: start.skeleton.clone(),
    };
    let sub = &start.mesh.subdivision;
    let mesh = lifegom_render::gom::GomMesh::new(&sub.lowres, sub.levels, &device)
        .map_err(lifegom_model::error::ModelError::from)?;
    let opacities = start.faces.opacities.clone().autodiff();
    let gt_rgb = inputs.sources.images.clone().autodiff();
    let gt_mask = inputs.source_masks.clone().autodiff();
    let mut seconds = 0.0;
    for k in 1..=steps {
        let clock = Instant::now();
        let renders = render_views(
            &mesh,
            &params.xyz.val(),
            &params.faces(opacities.clone()),
            &subject,
            &inputs.sources.cameras,
            &inputs.sources.skinning,
            inputs.sources.background,
        )?;
        let terms = LossTerms {
            rgb: l1(renders.rgb.clone(), gt_rgb.clone()),
            mask: mask_l1(renders.alpha, gt_mask.clone()),
            ssim: ssim_loss(renders.rgb, gt_rgb.clone()),
            lpips: None,
            laplacian: laplacian.loss(params.xyz.val().unsqueeze_dim(0)),
        };
        let loss = weights.total(terms)?;
        let grads = GradientsParams::from_grads(loss.total.backward(), &params);
        params = optim.step(lr.clone(), params, grads);
        seconds += clock.elapsed().as_secs_f64();
        if !observe(k, seconds, &snapshot(start, &params))? {
            break;
        }
    }
    Ok(snapshot(start, &params))
}
