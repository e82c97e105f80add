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

use std::sync::Mutex;

use burn::tensor::{Device, Tensor};

use crate::evaluate::SplitScores;
use crate::images::Image;
use crate::perceptual::{FeatureStats, InceptionPool3, Lpips, PerceptualModels, frechet_distance};
use crate::report::WEIGHTS_MISSING;

/// The perceptual networks that could be loaded, and why the others could not.
pub struct Models {
    models: Option<PerceptualModels>,
    problem: Option<String>,
    /// The last ground-truth set's Inception statistics, by a hash of its pixels: every method
    /// of an evaluation is scored against the same ground truth.
    gt_stats: Mutex<Option<(u64, FeatureStats)>>,
}

/// Loads what exists in `dir` (never fails: problems become the report note).
pub fn load_models(dir: &Path, device: &Device) -> Models {
    match PerceptualModels::discover(dir, device) {
        Ok(m) => {
            let problem = (!m.missing.is_empty()).then(|| m.missing.join(", "));
            Models {
                models: Some(m),
                problem,
                gt_stats: Mutex::new(None),
            }
        }
        Err(e) => Models {
            models: None,
            problem: Some(e.to_string()),
            gt_stats: Mutex::new(None),
        },
    }
}

impl Models {
    /// LPIPS-alex, when its weights were found.
    pub fn lpips_alex(&self) -> Option<&Lpips> {
        self.models.as_ref()?.lpips_alex.as_ref()
    }

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
    let fid = fid_of(models, pred, gt, device)?;
    Ok(SetScores {
        lpips_alex: mean(&m.lpips_alex)?,
        lpips_vgg: mean(&m.lpips_vgg)?,
        fid,
        fid_images: fid.map(|_| pred.len()),
    })
}

/// FID between two image sets (`None` without the Inception or with fewer than 2 images).
fn fid_of(
    models: &Models,
    pred: &[Image],
    gt: &[Image],
    device: &Device,
) -> Result<Option<f64>, EvalError> {
    let Some(net) = models.models.as_ref().and_then(|m| m.inception.as_ref()) else {
        return Ok(None);
    };
    if pred.len() < 2 {
        return Ok(None);
    }
    let stats = |imgs: &[Image]| -> Result<FeatureStats, EvalError> {
        Ok(FeatureStats::from_features(
            &pool3_features(net, imgs, device)?,
            2048,
        )?)
    };
    let key = pixels_hash(gt);
    let mut cache = models.gt_stats.lock().unwrap_or_else(|e| e.into_inner());
    let b = match cache.as_ref() {
        Some((k, b)) if *k == key => b.clone(),
        _ => {
            let b = stats(gt)?;
            *cache = Some((key, b.clone()));
            b
        }
    };
    Ok(Some(frechet_distance(&stats(pred)?, &b)?))
}

/// A hash of a set of images' sizes and pixels (the ground-truth cache's key).
fn pixels_hash(images: &[Image]) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for img in images {
        (img.width, img.height).hash(&mut h);
        for v in &img.data {
            v.to_bits().hash(&mut h);
        }
    }
    h.finish()
}

/// Images per network call: a batch fills the matrix products better than single images, and
/// bounds memory at large sizes.
const BATCH: usize = 8;

/// Consecutive runs of at most [`BATCH`] indices whose images share one size.
fn batches(images: &[&Image]) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let mut start = 0;
    while start < images.len() {
        let size = (images[start].width, images[start].height);
        let end = (start..images.len())
            .take(BATCH)
            .take_while(|&i| (images[i].width, images[i].height) == size)
            .last()
            .map_or(start + 1, |i| i + 1);
        out.push(start..end);
        start = end;
    }
    out
}

fn stack(images: &[&Image], device: &Device) -> Tensor<4> {
    Tensor::cat(images.iter().map(|i| i.to_batch(device)).collect(), 0)
}

/// Inception pool3 features of `images` (any sizes: each is resized to 299² inside),
/// row-major `images.len() × 2048`.
pub fn pool3_features(
    net: &InceptionPool3,
    images: &[Image],
    device: &Device,
) -> Result<Vec<f32>, EvalError> {
    let refs: Vec<&Image> = images.iter().collect();
    let mut rows = Vec::with_capacity(images.len() * 2048);
    for run in batches(&refs) {
        let f = net.try_features(stack(&refs[run], device))?;
        rows.extend(readback::read::<f32, 2, _>("Inception features", f)?);
    }
    Ok(rows)
}

/// LPIPS of every pair `pred[k]`, `gt[k]` (each pair of one size), in batches.
pub fn lpips_pairs(
    net: &Lpips,
    pred: &[Image],
    gt: &[Image],
    device: &Device,
) -> Result<Vec<f64>, EvalError> {
    let refs: Vec<&Image> = pred.iter().collect();
    let gt_refs: Vec<&Image> = gt.iter().collect();
    let mut out = Vec::with_capacity(pred.len());
    for run in batches(&refs) {
        let d = net.try_distance(
            stack(&refs[run.clone()], device),
            stack(&gt_refs[run], device),
        )?;
        out.extend(readback::read::<f64, 1, _>("LPIPS distance", d)?);
    }
    Ok(out)
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
    let d = lpips_pairs(net, pred, gt, device)?;
    Ok((!d.is_empty()).then(|| d.iter().sum::<f64>() / d.len() as f64))
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
    let (pred, gt) = (&scores.images.pred, &scores.images.gt);
    if let Some(net) = &m.lpips_alex {
        let d = lpips_pairs(net, pred, gt, device)?;
        for (view, d) in scores.views.iter_mut().zip(d) {
            view.lpips_alex = Some(d);
        }
    }
    if let Some(net) = &m.lpips_vgg {
        let d = lpips_pairs(net, pred, gt, device)?;
        for (view, d) in scores.views.iter_mut().zip(d) {
            view.lpips_vgg = Some(d);
        }
    }
    let fid = fid_of(models, &scores.images.pred, &scores.images.gt, device)?;
    Ok(PerceptualOutcome { fid })
}
