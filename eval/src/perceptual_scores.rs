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

use burn::tensor::Device;

use crate::evaluate::SplitScores;
use crate::images::Image;
use crate::perceptual::{FeatureStats, Lpips, PerceptualModels, frechet_distance};
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

/// LPIPS means and FID over image pairs that are not a [`SplitScores`] (a per-scene fit's
/// renders after K steps).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SetScores {
    /// Mean LPIPS-alex.
    pub lpips_alex: Option<f64>,
    /// Mean LPIPS-vgg.
    pub lpips_vgg: Option<f64>,
    /// FID between the predictions and the ground truths.
    pub fid: Option<f64>,
    /// Images per set that FID saw.
    pub fid_images: Option<usize>,
}

/// Scores `pred[k]` against `gt[k]` with whatever networks exist.
pub fn score_pairs(
    models: &Models,
    pred: &[Image],
    gt: &[Image],
    device: &Device,
) -> Result<SetScores, EvalError> {
    let Some(m) = &models.models else {
        return Ok(SetScores::default());
    };
    let mean = |net: &Option<Lpips>| match net {
        Some(net) => mean_lpips(net, pred, gt, device),
        None => Ok(None),
    };
    let fid = fid_of(m, pred, gt, device)?;
    Ok(SetScores {
        lpips_alex: mean(&m.lpips_alex)?,
        lpips_vgg: mean(&m.lpips_vgg)?,
        fid,
        fid_images: fid.map(|_| pred.len()),
    })
}

/// FID between two image sets (`None` without the Inception or with fewer than 2 images).
fn fid_of(
    m: &PerceptualModels,
    pred: &[Image],
    gt: &[Image],
    device: &Device,
) -> Result<Option<f64>, EvalError> {
    let Some(net) = &m.inception else {
        return Ok(None);
    };
    if pred.len() < 2 {
        return Ok(None);
    }
    let features = |imgs: &[Image]| -> Result<Vec<f32>, EvalError> {
        let mut rows = Vec::with_capacity(imgs.len() * 2048);
        for img in imgs {
            let f = net.try_features(img.to_batch(device))?;
            rows.extend(readback::read::<f32, 2, _>("Inception features", f)?);
        }
        Ok(rows)
    };
    let (fa, fb) = (features(pred)?, features(gt)?);
    let a = FeatureStats::from_features(&fa, 2048)?;
    let b = FeatureStats::from_features(&fb, 2048)?;
    Ok(Some(frechet_distance(&a, &b)?))
}

/// LPIPS of one pair of images.
pub fn lpips_of(net: &Lpips, pred: &Image, gt: &Image, device: &Device) -> Result<f64, EvalError> {
    let d = net.try_distance(pred.to_batch(device), gt.to_batch(device))?;
    Ok(readback::read::<f64, 1, _>("LPIPS distance", d)?
        .first()
        .copied()
        .unwrap_or(f64::NAN))
}

/// Mean LPIPS of `pred[k]` against `gt[k]` (`None` for no pairs).
pub fn mean_lpips(
    net: &Lpips,
    pred: &[Image],
    gt: &[Image],
    device: &Device,
) -> Result<Option<f64>, EvalError> {
    let mut sum = 0.0;
    for (p, g) in pred.iter().zip(gt) {
        sum += lpips_of(net, p, g, device)?;
    }
    Ok((!pred.is_empty()).then(|| sum / pred.len() as f64))
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
            view.lpips_alex = Some(lpips_of(net, p, g, device)?);
        }
        if let Some(net) = &m.lpips_vgg {
            view.lpips_vgg = Some(lpips_of(net, p, g, device)?);
        }
    }
    let fid = fid_of(m, &scores.images.pred, &scores.images.gt, device)?;
    Ok(PerceptualOutcome { fid })
}
