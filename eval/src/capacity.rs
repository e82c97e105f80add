//! The capacity check (design.md §10.10): can the representation reproduce one person at all?
//!
//! Before a reconstructor is trained longer, the avatar it predicts must be able to show the
//! subject: otherwise no amount of training closes the gap. This fits one subject's avatar
//! (template geometry, Gaussians of the subdivided mesh) directly to many of its views by
//! gradient descent ([`lifegom_train::fit`], the per-scene optimisation of §10.8) and scores
//! views it never fitted:
//!
//! ```text
//! sources  = the subject's ring views (16 for THuman-style subjects), or an even subset
//! held out = every other view (the 48 in-between targets)
//! start    = projective texturing of the sources (§10.7)
//! for K in ks: fit K steps in all; score the held-out views (protocol region, PSNR/SSIM)
//! ```
//!
//! The held-out PSNR after many steps is the ceiling a reconstructor of the same avatar can
//! reach on this subject; the source PSNR beside it tells over- from under-fitting.

use burn::tensor::Device;
use lifegom_data::dataset::{Dataset, Protocol, Sample};
use lifegom_model::inputs::{ModelInputs, SubjectRig, model_inputs};
use lifegom_render::gom::GomMesh;
use lifegom_train::fit::{FitConfig, fit};
use lifegom_train::losses::{LossWeights, UniformLaplacian};
use serde::{Deserialize, Serialize};

use crate::baselines::projective_texturing;
use crate::error::EvalError;
use crate::evaluate::{render_timed, score_region, thuman_crop_size};
use crate::images::{Image, error_map, grid};

/// Which of a subject's frames are fitted and which are held out.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ViewSplit {
    /// Frames the avatar is fitted to.
    pub sources: Vec<usize>,
    /// Frames only scored.
    pub held_out: Vec<usize>,
}

impl ViewSplit {
    /// `n` sources spread evenly over the first `ring` frames (the camera ring), every frame
    /// from `ring` on held out.
    pub fn ring(ring: usize, n: usize, frames: usize) -> Self {
        let n = n.clamp(1, ring.max(1));
        Self {
            sources: (0..n).map(|k| k * ring / n).collect(),
            held_out: (ring..frames).collect(),
        }
    }
}

/// Scores after `steps` gradient steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CapacityPoint {
    /// Gradient steps so far.
    pub steps: usize,
    /// Mean PSNR over the held-out views (dB, protocol region).
    pub psnr_held_out: f64,
    /// Mean SSIM over the held-out views.
    pub ssim_held_out: f64,
    /// Mean PSNR over the fitted source views (dB, protocol region).
    pub psnr_sources: f64,
    /// Fit wall time so far (s).
    pub seconds: f64,
}

/// The result of [`fit_one_subject`].
pub struct Capacity {
    /// One point per requested step count, in order.
    pub points: Vec<CapacityPoint>,
    /// GT | prediction | error (×4) of up to four held-out views, after the last step.
    pub sheet: Option<Image>,
}

/// The inputs of `frames[..]` as sources with `target` as the target view.
fn inputs_for(
    dataset: &Dataset,
    subject: usize,
    rig: &SubjectRig,
    sources: &[usize],
    target: usize,
    device: &Device,
) -> Result<ModelInputs, EvalError> {
    let s = &dataset.subjects[subject];
    let bg = dataset
        .background
        .draw(&mut lifegom_render::rng::Rng::new(0));
    let views = sources
        .iter()
        .chain(std::iter::once(&target))
        .map(|&f| lifegom_data::dataset::load_view(s, f, bg, dataset.img_size, dataset.resize))
        .collect::<Result<Vec<_>, _>>()?;
    let sample = Sample {
        subject: s.name.clone(),
        frame_name: format!("scene_{}_{}", s.name, s.frames[target]),
        views,
        bgcolor: bg.map(|c| c / 255.0),
        canonical_vertices: s.canonical.vertices.iter().map(|v| v.to_array()).collect(),
    };
    Ok(model_inputs(
        rig,
        &sample,
        dataset.img_size.0,
        dataset.img_size.1,
        device,
    )?)
}

/// Fits subject `subject` of `dataset` to the `split.sources` views and scores the held-out
/// views after each `K ∈ ks` (module docs); `subdivide` is the Gaussians' level.
#[allow(clippy::too_many_arguments)]
pub fn fit_one_subject(
    dataset: &Dataset,
    subject: usize,
    split: &ViewSplit,
    ks: &[usize],
    subdivide: u32,
    cfg: &FitConfig,
    weights: &LossWeights,
    device: &Device,
) -> Result<Capacity, EvalError> {
    let _span = tracing::info_span!("capacity", subject).entered();
    let s = dataset.subjects.get(subject).ok_or_else(|| {
        EvalError::Invalid(format!(
            "subject {subject} out of range ({} subjects)",
            dataset.subjects.len()
        ))
    })?;
    let frames = s.frames.len();
    if let Some(&f) = split
        .sources
        .iter()
        .chain(&split.held_out)
        .find(|&&f| f >= frames)
    {
        return Err(EvalError::Invalid(format!(
            "{}: frame {f} out of range ({frames} frames)",
            s.dir.display()
        )));
    }
    if split.held_out.is_empty() {
        return Err(EvalError::Invalid(format!(
            "{}: no held-out views ({frames} frames)",
            s.dir.display()
        )));
    }
    let rig = SubjectRig::new(&s.name, &s.canonical)?;
    let mesh = GomMesh::new(&rig.topology, subdivide, device)?;
    let laplacian = UniformLaplacian::new(&rig.topology.faces, rig.num_vertices())
        .map_err(|e| EvalError::Fit(e.into()))?;
    let (w, h) = (dataset.img_size.0 as usize, dataset.img_size.1 as usize);
    let crop_size = thuman_crop_size(h, w);
    let crop_protocol = dataset.rule.protocol != Protocol::Aistpp;
    let held_out = split
        .held_out
        .iter()
        .map(|&t| inputs_for(dataset, subject, &rig, &split.sources, t, device))
        .collect::<Result<Vec<_>, _>>()?;
    let fitted = &held_out[0];
    let start = projective_texturing(&mesh, fitted, device)?.avatar;

    let score = |avatar: &lifegom_model::avatar::Avatar,
                 camera: &lifegom_render::camera::Camera,
                 skinning: &[glam::Affine3A],
                 gt: Image|
     -> Result<(f64, f64, Image, Image), EvalError> {
        let (pred, _) = render_timed(avatar, fitted, camera, skinning)?;
        let (m, _, _, _) = score_region(&pred, &gt, None, crop_protocol, crop_size, "capacity")?;
        Ok((m.psnr, m.ssim, pred, gt))
    };
    let k_max = ks.iter().copied().max().unwrap_or(0);
    let mut points = Vec::new();
    let mut failure = None;
    let mut sheet = None;
    let mut observe = |k: usize,
                       seconds: f64,
                       avatar: &lifegom_model::avatar::Avatar|
     -> Result<bool, lifegom_train::trainer::TrainError> {
        if !ks.contains(&k) {
            return Ok(true);
        }
        let result = (|| -> Result<CapacityPoint, EvalError> {
            let (mut psnr, mut ssim, mut rows) = (0.0, 0.0, Vec::new());
            for inputs in &held_out {
                let gt = Image::from_chw(inputs.target_rgb.clone())?;
                let (p, q, pred, gt) =
                    score(avatar, &inputs.target_camera, &inputs.target_skinning, gt)?;
                psnr += p;
                ssim += q;
                if k == k_max && rows.len() < 4 {
                    let err = error_map(&pred, &gt, 4.0)?;
                    rows.push(vec![gt, pred, err]);
                }
            }
            let mut psnr_sources = 0.0;
            let n_src = fitted.sources.cameras.len();
            for v in 0..n_src {
                let gt =
                    Image::from_chw(fitted.sources.images.clone().narrow(0, v, 1).squeeze_dim(0))?;
                let (p, _, _, _) = score(
                    avatar,
                    &fitted.sources.cameras[v],
                    &fitted.sources.skinning[v],
                    gt,
                )?;
                psnr_sources += p;
            }
            if !rows.is_empty() {
                sheet = Some(grid(&rows, 2, [1.0; 3]));
            }
            let n = held_out.len() as f64;
            Ok(CapacityPoint {
                steps: k,
                psnr_held_out: psnr / n,
                ssim_held_out: ssim / n,
                psnr_sources: psnr_sources / n_src as f64,
                seconds,
            })
        })();
        match result {
            Ok(p) => {
                tracing::info!(
                    steps = p.steps,
                    psnr_held_out = p.psnr_held_out,
                    psnr_sources = p.psnr_sources,
                    "capacity"
                );
                points.push(p);
                Ok(true)
            }
            Err(e) => {
                failure = Some(e);
                Ok(false)
            }
        }
    };
    if ks.contains(&0) {
        observe(0, 0.0, &start)?;
    }
    fit(
        &start,
        fitted,
        &laplacian,
        weights,
        cfg,
        k_max,
        &mut observe,
    )?;
    if let Some(e) = failure {
        return Err(e);
    }
    Ok(Capacity { points, sheet })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ring_split_spreads_the_sources_and_holds_out_the_rest() {
        let s = ViewSplit::ring(16, 4, 64);
        assert_eq!(s.sources, [0, 4, 8, 12]);
        assert_eq!(s.held_out, (16..64).collect::<Vec<_>>());
        assert_eq!(ViewSplit::ring(16, 99, 20).sources.len(), 16);
        assert_eq!(ViewSplit::ring(16, 3, 16).held_out, Vec::<usize>::new());
    }
}
