//! LPIPS and FID over an evaluation's metric regions, when the weights exist.
//!
//! The networks come from [`crate::perceptual::PerceptualModels::discover`] (converted files in
//! `weights/` or `$LIFEGOM_WEIGHTS`). Whatever is missing stays `None` in the scores and the
//! report carries [`crate::report::WEIGHTS_MISSING`] naming the missing files — no number is
//! ever substituted.
//!
//! LPIPS is computed per view on the same uint8-quantised crop PSNR uses (inputs in \[0, 1\], the
//! 2x−1 mapping happens inside the network, as the pip `lpips` package with `normalize=True`).
//! FID compares the Inception pool3 statistics of all prediction crops with those of all
//! ground-truth crops (pytorch-fid on the two PNG folders). With fewer images than the 2048
//! feature dimensions the covariances are rank-deficient; the value is still what pytorch-fid
//! reports on such folders, but it is biased high and only comparable at equal image counts.

use crate::error::EvalError;
use lifegom_render::readback;
use std::path::Path;

use burn::tensor::{Device, Tensor, TensorData};

use crate::evaluate::SplitScores;
use crate::images::Image;
use crate::perceptual::{FeatureStats, PerceptualModels, frechet_distance};
use crate::report::WEIGHTS_MISSING;

/// The perceptual networks that could be loaded, and why the others could not.
pub struct Models {
    models: Option<PerceptualModels>,
    problem: Option<String>,
}

/// Loads what exists in `dir` (never fails: problems become the report note).
pub fn load_models(dir: &Path, device: &Device) -> Models {
    match PerceptualModels::discover(dir, device) {
        Ok(m) => {
            let problem = (!m.missing.is_empty()).then(|| m.missing.join(", "));
            Models {
                models: Some(m),
                problem,
            }
        }
        Err(e) => Models {
            models: None,
            problem: Some(e.to_string()),
        },
    }
}

impl Models {
    /// The note for the report when something is missing.
    pub fn note(&self) -> Option<String> {
        self.problem
            .as_ref()
            .map(|p| format!("{WEIGHTS_MISSING}. Missing or unreadable: {p}"))
    }
}

/// What [`score_perceptual`] computed beyond the per-view LPIPS.
#[derive(Debug, Clone, Copy, Default)]
pub struct PerceptualOutcome {
    /// FID between prediction and ground-truth regions.
    pub fid: Option<f64>,
}

fn batch(img: &Image, device: &Device) -> Tensor<4> {
    Tensor::<3>::from_data(
        TensorData::new(img.data.clone(), [img.height, img.width, 3]),
        device,
    )
    .permute([2, 0, 1])
    .unsqueeze_dim(0)
}

fn first(t: Tensor<1>) -> Result<Option<f64>, EvalError> {
    Ok(readback::read::<f64, 1, _>("LPIPS distance", t)?
        .first()
        .copied())
}

/// Fills `lpips_alex` / `lpips_vgg` of every view and computes FID, with whatever weights exist.
pub fn score_perceptual(
    models: &Models,
    scores: &mut SplitScores,
    device: &Device,
) -> Result<PerceptualOutcome, EvalError> {
    let Some(m) = &models.models else {
        return Ok(PerceptualOutcome::default());
    };
    let _span = tracing::info_span!("perceptual", views = scores.views.len()).entered();
    for (k, view) in scores.views.iter_mut().enumerate() {
        let (p, g) = (&scores.images.pred[k], &scores.images.gt[k]);
        if let Some(net) = &m.lpips_alex {
            view.lpips_alex = first(net.try_distance(batch(p, device), batch(g, device))?)?;
        }
        if let Some(net) = &m.lpips_vgg {
            view.lpips_vgg = first(net.try_distance(batch(p, device), batch(g, device))?)?;
        }
    }
    let fid = match &m.inception {
        Some(net) if scores.images.pred.len() >= 2 => {
            let features = |imgs: &[Image]| -> Result<Vec<f32>, EvalError> {
                let mut rows = Vec::with_capacity(imgs.len() * 2048);
                for img in imgs {
                    let f = net.try_features(batch(img, device))?;
                    rows.extend(readback::read::<f32, 2, _>("Inception features", f)?);
                }
                Ok(rows)
            };
            let a = FeatureStats::from_features(&features(&scores.images.pred)?, 2048)?;
            let b = FeatureStats::from_features(&features(&scores.images.gt)?, 2048)?;
            Some(frechet_distance(&a, &b)?)
        }
        _ => None,
    };
    Ok(PerceptualOutcome { fid })
}
