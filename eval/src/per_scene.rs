//! The per-scene optimisation baseline scored after K = 10, 30, 100, … gradient steps
//! (design.md §10.8): quality against time on the same axes as the learned model's T = 1…5.
//!
//! For each validation subject the template in its mean colour
//! ([`crate::baselines::template_one_colour`]) is fitted to the N source views
//! ([`lifegom_train::fit`]); after each requested K the fitted avatar renders every target view
//! of the subject, scored as the evaluation scores the model (protocol region, PSNR, SSIM). The
//! time of a point is the fit's own wall time up to K, per subject (scoring excluded). With
//! the perceptual weights, each K's renders also get LPIPS and FID, on the same regions.

use burn::tensor::Device;
use lifegom_data::dataset::{Dataset, Protocol};
use lifegom_model::inputs::{ModelInputs, SubjectRig};
use lifegom_render::gom::GomMesh;
use lifegom_train::fit::{FitConfig, fit};
use lifegom_train::losses::{LossWeights, UniformLaplacian};
use serde::{Deserialize, Serialize};

use crate::baselines::template_one_colour;
use crate::error::EvalError;
use crate::evaluate::{
    ValidationSample, render_timed, score_region, target_mask, thuman_crop_size, validation_samples,
};
use crate::images::Image;
use crate::metrics::ErrorByRegion;

/// Scores of the fit after `steps` gradient steps, averaged over subjects and target views.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FitPoint {
    /// Gradient steps K.
    pub steps: usize,
    /// Mean PSNR over the target views (dB).
    pub psnr: f64,
    /// Mean SSIM over the target views.
    pub ssim: f64,
    /// Mean fit wall time per subject up to K (ms).
    pub ms: f64,
    /// Subjects fitted (the means are over their target views).
    pub subjects: usize,
    /// Mean LPIPS-alex over the target views, when its weights exist.
    #[serde(default)]
    pub lpips_alex: Option<f64>,
    /// Mean LPIPS-vgg over the target views, when its weights exist.
    #[serde(default)]
    pub lpips_vgg: Option<f64>,
    /// FID between the renders and the targets, when the Inception weights exist.
    #[serde(default)]
    pub fid: Option<f64>,
    /// Images per set that FID saw.
    #[serde(default)]
    pub fid_images: Option<usize>,
    /// Mean MSE split by the silhouette over the target views.
    #[serde(default)]
    pub regions: Option<ErrorByRegion>,
}

/// The validation samples of each subject, in split order (the first sample's inputs are the
/// subject's inputs; every target shares them).
fn samples_by_subject(
    dataset: &Dataset,
    rigs: &[SubjectRig],
    max_subjects: Option<usize>,
    device: &Device,
) -> Result<Vec<Vec<ModelInputs>>, EvalError> {
    let mut groups: Vec<Vec<ModelInputs>> = Vec::new();
    for item in validation_samples(dataset, rigs, max_subjects, device) {
        let ValidationSample { index, inputs, .. } = item?;
        if groups.len() <= index.subject {
            groups.resize_with(index.subject + 1, Vec::new);
        }
        groups[index.subject].push(inputs);
    }
    groups.retain(|g| !g.is_empty());
    Ok(groups)
}

/// What the per-scene optimisation baseline fits and where it is scored.
#[derive(Debug, Clone)]
pub struct PerSceneFit {
    /// Score after each of these gradient step counts K.
    pub ks: Vec<usize>,
    /// The Gaussians' subdivision level.
    pub subdivide: u32,
    /// The optimiser's settings.
    pub cfg: FitConfig,
    /// The loss it minimises on the source views.
    pub weights: LossWeights,
    /// Subjects fitted (default: all).
    pub max_subjects: Option<usize>,
}

/// Fits every subject (at most `fit.max_subjects`) for `max(ks)` steps and scores it after
/// each `K ∈ ks` (module docs), with LPIPS and FID when `perceptual` has the networks.
pub fn score_per_scene_fit(
    dataset: &Dataset,
    fit_settings: &PerSceneFit,
    perceptual: &crate::perceptual_scores::Models,
    device: &Device,
) -> Result<Vec<FitPoint>, EvalError> {
    let PerSceneFit {
        ks,
        subdivide,
        cfg,
        weights,
        max_subjects,
    } = fit_settings;
    let (subdivide, max_subjects) = (*subdivide, *max_subjects);
    let _span = tracing::info_span!("score_per_scene_fit").entered();
    let rigs = SubjectRig::for_split(dataset)?;
    let topology = &rigs[0].topology;
    let mesh = GomMesh::new(topology, subdivide, device)?;
    let laplacian = UniformLaplacian::new(&topology.faces, rigs[0].num_vertices())
        .map_err(|e| EvalError::Fit(e.into()))?;
    let (w, h) = (dataset.img_size.0 as usize, dataset.img_size.1 as usize);
    let crop_size = thuman_crop_size(h, w);
    let crop_protocol = dataset.rule.protocol != Protocol::Aistpp;
    let k_max = ks.iter().copied().max().unwrap_or(0);
    let mut sums: Vec<FitPoint> = ks
        .iter()
        .map(|&steps| FitPoint {
            steps,
            psnr: 0.0,
            ssim: 0.0,
            ms: 0.0,
            subjects: 0,
            lpips_alex: None,
            lpips_vgg: None,
            fid: None,
            fid_images: None,
            regions: None,
        })
        .collect();
    // Each K's per-view error by region, averaged at the end.
    let mut errors: Vec<Vec<ErrorByRegion>> = vec![Vec::new(); ks.len()];
    // Each K's metric regions (prediction, ground truth), for LPIPS and FID at the end.
    let mut regions: Vec<(Vec<Image>, Vec<Image>)> = vec![(Vec::new(), Vec::new()); ks.len()];
    let mut views = 0usize;
    let groups = samples_by_subject(dataset, &rigs, max_subjects, device)?;
    for targets in &groups {
        let start = template_one_colour(&mesh, &targets[0], device)?.avatar;
        let mut failure = None;
        fit(
            &start,
            &targets[0],
            &laplacian,
            weights,
            cfg,
            k_max,
            |k, seconds, avatar| {
                let Some(at) = sums.iter().position(|p| p.steps == k) else {
                    return Ok(true);
                };
                let point = &mut sums[at];
                point.ms += seconds * 1e3;
                for inputs in targets {
                    let scored = render_timed(
                        avatar,
                        inputs,
                        &inputs.target_camera,
                        &inputs.target_skinning,
                    )
                    .and_then(|(pred, _)| {
                        let gt = Image::from_chw(inputs.target_rgb.clone())?;
                        score_region(
                            &pred,
                            &gt,
                            Some(&target_mask(inputs)?),
                            crop_protocol,
                            crop_size,
                            "per-scene fit",
                        )
                    });
                    match scored {
                        Ok((m, region_errors, pred, gt)) => {
                            point.psnr += m.psnr;
                            point.ssim += m.ssim;
                            errors[at].extend(region_errors);
                            regions[at].0.push(pred);
                            regions[at].1.push(gt);
                        }
                        Err(e) => {
                            failure = Some(e);
                            return Ok(false);
                        }
                    }
                }
                Ok(true)
            },
        )?;
        if let Some(e) = failure {
            return Err(e);
        }
        views += targets.len();
    }
    let (views, subjects) = (views.max(1) as f64, groups.len().max(1) as f64);
    sums.into_iter()
        .zip(&regions)
        .zip(&errors)
        .map(|((p, (pred, gt)), errors)| {
            let perceptual = crate::perceptual_scores::score_pairs(perceptual, pred, gt, device)?;
            Ok(FitPoint {
                psnr: p.psnr / views,
                ssim: p.ssim / views,
                ms: p.ms / subjects,
                subjects: groups.len(),
                lpips_alex: perceptual.lpips_alex,
                lpips_vgg: perceptual.lpips_vgg,
                fid: perceptual.fid,
                fid_images: perceptual.fid_images,
                regions: (!errors.is_empty()).then(|| ErrorByRegion::mean(errors)),
                ..p
            })
        })
        .collect()
}
