//! What each feedback step does on people the model never saw (design.md §10.7).
//!
//! One reconstruction per validation subject runs all T feedback steps; the state after every
//! step `t = 1…T` is rendered in each target view and scored exactly as the evaluation scores
//! the final one (protocol region, PSNR, skimage SSIM). Training runs this every
//! `[train] validate_every` steps, so the curves show, over training, whether later steps help
//! and how the model compares with the baselines that need no learning. Given the LPIPS-alex
//! network (cheap: a few ms a view), each step's LPIPS is scored on the same regions; each
//! step's error is also split by the silhouette ([`ErrorByRegion`]), so the curves tell outline
//! from appearance.

use std::collections::HashMap;

use burn::tensor::Device;
use lifegom_data::dataset::{Dataset, Protocol};
use lifegom_model::inputs::SubjectRig;
use lifegom_model::reconstructor::{Reconstructor, render_views};
use lifegom_render::gom::GomMesh;
use serde::{Deserialize, Serialize};

use crate::error::EvalError;
use crate::evaluate::{
    ValidationSample, score_region, target_mask, thuman_crop_size, validation_samples,
};
use crate::images::Image;
use crate::metrics::ErrorByRegion;
use crate::perceptual::Lpips;
use crate::perceptual_scores::lpips_of;

/// Mean scores of the state after one feedback step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepScore {
    /// The feedback step (1-based).
    pub t: usize,
    /// Mean PSNR over the target views (dB).
    pub psnr: f64,
    /// Mean SSIM over the target views.
    pub ssim: f64,
    /// Mean LPIPS-alex over the target views, when the network was given.
    #[serde(default)]
    pub lpips_alex: Option<f64>,
    /// Mean MSE split by the silhouette over the target views.
    #[serde(default)]
    pub regions: Option<ErrorByRegion>,
}

/// Scores every feedback step of `model` (an inference model: no autodiff) on the targets of
/// `dataset` (a validation split), at `subdivide` subdivisions, on at most `max_subjects`.
pub fn score_feedback_steps(
    model: &Reconstructor,
    dataset: &Dataset,
    subdivide: u32,
    max_subjects: Option<usize>,
    lpips: Option<&Lpips>,
    device: &Device,
) -> Result<Vec<StepScore>, EvalError> {
    let _span = tracing::info_span!("score_feedback_steps").entered();
    let rigs = SubjectRig::for_split(dataset)?;
    let mesh = GomMesh::new(&rigs[0].topology, subdivide, device)?;
    let (w, h) = (dataset.img_size.0, dataset.img_size.1);
    let crop_size = thuman_crop_size(h as usize, w as usize);
    let crop_protocol = dataset.rule.protocol != Protocol::Aistpp;
    let t_max = model.iterations();
    let mut psnr = vec![0.0; t_max];
    let mut ssim = vec![0.0; t_max];
    let mut lpips_sum = vec![0.0; t_max];
    let mut regions: Vec<Vec<ErrorByRegion>> = vec![Vec::new(); t_max];
    let mut views = 0usize;
    let mut cache = HashMap::new();
    for item in validation_samples(dataset, &rigs, max_subjects, device) {
        let ValidationSample {
            index,
            sample,
            inputs,
        } = item?;
        let key = (index.subject, index.inputs.clone());
        if !cache.contains_key(&key) {
            let rec = model
                .forward(&inputs.subject, &mesh, &inputs.sources)
                .map_err(|e| EvalError::Frame {
                    frame: sample.frame_name.clone(),
                    source: Box::new(e.into()),
                })?;
            cache.clear();
            cache.insert(key.clone(), rec.states);
        }
        let gt = Image::from_chw(inputs.target_rgb.clone())?;
        let mask = target_mask(&inputs)?;
        for (t, state) in cache[&key].iter().enumerate() {
            let rendered = render_views(
                &mesh,
                &state.xyz,
                &state.faces,
                &inputs.subject,
                std::slice::from_ref(&inputs.target_camera),
                std::slice::from_ref(&inputs.target_skinning),
                inputs.sources.background,
            )?;
            let pred = Image::from_chw(rendered.rgb.squeeze_dim::<3>(0))?;
            let (m, region_errors, pred, gt) = score_region(
                &pred,
                &gt,
                Some(&mask),
                crop_protocol,
                crop_size,
                &sample.frame_name,
            )?;
            psnr[t] += m.psnr;
            ssim[t] += m.ssim;
            regions[t].extend(region_errors);
            if let Some(net) = lpips {
                lpips_sum[t] += lpips_of(net, &pred, &gt, device)?;
            }
        }
        views += 1;
    }
    let n = views.max(1) as f64;
    Ok((0..t_max)
        .map(|t| StepScore {
            t: t + 1,
            psnr: psnr[t] / n,
            ssim: ssim[t] / n,
            lpips_alex: lpips.map(|_| lpips_sum[t] / n),
            regions: (!regions[t].is_empty()).then(|| ErrorByRegion::mean(&regions[t])),
        })
        .collect())
}
