//! Evaluating a trained reconstructor on a validation split (design.md §10).
//!
//! For every subject the avatar is reconstructed once from its deterministic inputs (the first
//! N frames; every target of a subject shares them, so re-running per target as the reference
//! does would give the same avatar), then every target view is rendered at the last iteration
//! over the split's fixed background and scored:
//!
//! - **THuman2.0 / XHuman** (design.md §10.2): the prediction and ground truth are cropped to the GT's
//!   non-black bounding box grown to 1000×500 at 1024² (scaled proportionally for smaller images,
//!   e.g. 250×125 at 256²), then PSNR and skimage SSIM on the float crop, LPIPS and FID on the
//!   crops.
//! - **AIST++** (design.md §10.3): full images, white background.
//!
//! Timings are host wall clock around the reconstruction (encoder + T feedback steps + the final
//! source render the reference always performs) and around the target render (skinning,
//! subdivision, Gaussians, rasterisation, read back). On eager CPU backends they are the cost.

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

use burn::tensor::Device;
use lifegom_data::dataset::{Dataset, Protocol, Sample, SampleIndex};
use lifegom_model::avatar::Avatar;
use lifegom_model::inputs::{ModelInputs, SubjectRig, model_inputs};
use lifegom_model::reconstructor::{Reconstructor, ReconstructorConfig, render_views};
use lifegom_render::gom::GomMesh;
use lifegom_render::rng::Rng;
use lifegom_train::fit::{FitConfig, fit};
use lifegom_train::losses::{LossWeights, UniformLaplacian};
use serde::{Deserialize, Serialize};

use crate::baselines;
use crate::error::EvalError;
use crate::images::{Image, error_map, grid};
use crate::metrics::{
    ErrorByRegion, ImageMetrics, ImageRef, SILHOUETTE_BAND_PX, crop, error_by_region,
    full_image_metrics, thuman_crop_box,
};

/// What to evaluate and where to write it.
#[derive(Debug, Clone)]
pub struct EvalSettings {
    /// Output folder.
    pub out: PathBuf,
    /// Subdivisions of the Gaussians' mesh (`None`: the model's `subdivide_test`).
    pub subdivide: Option<u32>,
    /// Feedback steps (`None`: the model's own T).
    pub iterations: Option<usize>,
    /// Write prediction PNGs (`preds/scene_<subject>_<frame>.png`).
    pub save_predictions: bool,
    /// Comparison sheets to write (GT | prediction | error), at most: one per subject (its
    /// first target), so they show different people; all of them also go, one row each,
    /// into `sheets.png`.
    pub sheets: usize,
    /// Evaluate at most this many subjects (`None`: all).
    pub max_subjects: Option<usize>,
    /// Test-time refinement: after the method's avatar is built, this many gradient steps of
    /// the per-scene fit on the source views ([`lifegom_train::fit`], default learning rates
    /// and loss weights); 0 = none. Its time counts in the reconstruction time.
    pub refine_steps: usize,
}

/// Scores of one target view.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ViewScore {
    /// Subject.
    pub subject: String,
    /// `scene_<subject>_<frame>`.
    pub frame_name: String,
    /// PSNR (dB) on the protocol's region.
    pub psnr: f64,
    /// skimage SSIM on the protocol's region.
    pub ssim: f64,
    /// LPIPS-Alex on the region (`None` when weights are missing).
    pub lpips_alex: Option<f64>,
    /// LPIPS-VGG on the region.
    pub lpips_vgg: Option<f64>,
    /// Reconstruction wall time of the subject's avatar (ms).
    pub recon_ms: f64,
    /// Render wall time of this view (ms).
    pub render_ms: f64,
    /// The region's MSE split by the silhouette (a diagnosis, not a protocol metric).
    #[serde(default)]
    pub regions: Option<ErrorByRegion>,
}

/// The crops (or full images) that metrics were computed on, for FID and LPIPS.
#[derive(Debug, Clone, Default)]
pub struct MetricImages {
    /// Predictions.
    pub pred: Vec<Image>,
    /// Ground truth.
    pub gt: Vec<Image>,
}

/// Everything one evaluation produced.
#[derive(Debug, Clone)]
pub struct SplitScores {
    /// Per view.
    pub views: Vec<ViewScore>,
    /// The metric regions, in `views` order.
    pub images: MetricImages,
    /// Gaussians rendered per view.
    pub num_gaussians: usize,
    /// Feedback steps used.
    pub iterations: usize,
    /// Subdivisions used.
    pub subdivide: u32,
}

/// THuman's 1000×500 crop scaled to an `h × w` image (never larger than the image).
pub fn thuman_crop_size(h: usize, w: usize) -> [usize; 2] {
    let ch = (1000.0 * h as f64 / 1024.0).round() as usize;
    let cw = (500.0 * w as f64 / 1024.0).round() as usize;
    [ch.clamp(1, h), cw.clamp(1, w)]
}

/// The protocol's metric region of a prediction/ground-truth pair, after the uint8 round trip
/// the reference scores (THuman/XHuman: the GT box grown to `crop_size`; AIST++ or an all-black
/// GT: the full image), PSNR/SSIM on it, and, given the target's mask (`[H, W]`,
/// [`target_mask`]), where in it the error sits against the silhouette.
pub(crate) fn score_region(
    pred: &Image,
    gt: &Image,
    mask: Option<&[f32]>,
    crop_protocol: bool,
    crop_size: [usize; 2],
    frame: &str,
) -> Result<(ImageMetrics, Option<ErrorByRegion>, Image, Image), EvalError> {
    let (pred_q, gt_q) = (pred.quantized(), gt.quantized());
    let shape = [gt.height, gt.width, 3];
    let bbox = if crop_protocol {
        let bbox = thuman_crop_box(ImageRef::new(&gt_q.data, shape)?, crop_size)?;
        if bbox.is_none() {
            tracing::warn!(
                frame,
                "ground truth is all black: no crop, scored on the full image"
            );
        }
        bbox
    } else {
        None
    };
    let (p_img, g_img) = match bbox {
        Some(bbox) => {
            let (p, s) = crop(ImageRef::new(&pred_q.data, shape)?, bbox)?;
            let (g, _) = crop(ImageRef::new(&gt_q.data, shape)?, bbox)?;
            let image = |data| Image {
                width: s[1],
                height: s[0],
                data,
            };
            (image(p), image(g))
        }
        None => (pred_q, gt_q),
    };
    let region_shape = [p_img.height, p_img.width, 3];
    let (p_ref, g_ref) = (
        ImageRef::new(&p_img.data, region_shape)?,
        ImageRef::new(&g_img.data, region_shape)?,
    );
    let m = full_image_metrics(p_ref, g_ref)?;
    let regions = match mask {
        Some(mask) => {
            let full = ImageRef::new(mask, [gt.height, gt.width, 1])?;
            let cropped = match bbox {
                Some(bbox) => crop(full, bbox)?.0,
                None => mask.to_vec(),
            };
            let cropped = ImageRef::new(&cropped, [p_img.height, p_img.width, 1])?;
            Some(error_by_region(p_ref, g_ref, cropped, SILHOUETTE_BAND_PX)?)
        }
        None => None,
    };
    Ok((m, regions, p_img, g_img))
}

/// The target's mask of `inputs`, `[H, W]` row-major, for [`score_region`].
pub(crate) fn target_mask(inputs: &ModelInputs) -> Result<Vec<f32>, EvalError> {
    Ok(lifegom_render::readback::read(
        "target mask",
        inputs.target_mask.clone(),
    )?)
}

/// One sample of a validation split, ready for a model.
pub struct ValidationSample {
    /// Its subject and frames.
    pub index: SampleIndex,
    /// The preprocessed views.
    pub sample: Sample,
    /// The views as model inputs.
    pub inputs: ModelInputs,
}

/// The samples of a validation split in order, under the split's deterministic rule (the fixed
/// inputs and background), leaving out subjects from `max_subjects` on: what the evaluation,
/// the per-step validation and the per-scene fit all iterate over.
pub fn validation_samples<'a>(
    dataset: &'a Dataset,
    rigs: &'a [SubjectRig],
    max_subjects: Option<usize>,
    device: &'a Device,
) -> impl Iterator<Item = Result<ValidationSample, EvalError>> + 'a {
    let (w, h) = (dataset.img_size.0, dataset.img_size.1);
    let max_subjects = max_subjects.unwrap_or(usize::MAX);
    let mut rng = Rng::new(0);
    (0..dataset.len())
        .map_while(move |i| {
            let index = dataset.index(i, &mut rng)?;
            if index.subject >= max_subjects {
                return Some(None);
            }
            let sample = match dataset.sample(i, &mut rng) {
                Ok(s) => s,
                Err(e) => return Some(Some(Err(e.into()))),
            };
            Some(Some(
                model_inputs(&rigs[index.subject], &sample, w, h, device)
                    .map_err(EvalError::from)
                    .map(|inputs| ValidationSample {
                        index,
                        sample,
                        inputs,
                    }),
            ))
        })
        .flatten()
}

/// A reconstructed avatar and how long it took.
pub struct Reconstructed {
    /// The avatar (canonical state + mesh).
    pub avatar: Avatar,
    /// Wall time (ms).
    pub ms: f64,
}

/// Reconstructs the avatar of `inputs` (no autodiff) and times it.
pub fn reconstruct_timed(
    model: &Reconstructor,
    mesh: &GomMesh,
    inputs: &lifegom_model::inputs::ModelInputs,
) -> Result<Reconstructed, EvalError> {
    let start = Instant::now();
    let avatar = model.reconstruct(&inputs.subject, mesh, &inputs.sources)?;
    // Force the result to exist before stopping the clock (matters on lazy backends).
    lifegom_render::device::wait_for_values(avatar.xyz.clone().sum());
    Ok(Reconstructed {
        avatar,
        ms: start.elapsed().as_secs_f64() * 1e3,
    })
}

/// Renders the avatar in a view given as camera + skinning, composited over `background`;
/// returns the image and the wall time (ms).
pub fn render_timed(
    avatar: &Avatar,
    inputs: &lifegom_model::inputs::ModelInputs,
    camera: &lifegom_render::camera::Camera,
    skinning: &[glam::Affine3A],
) -> Result<(Image, f64), EvalError> {
    let start = Instant::now();
    let subject = lifegom_model::reconstructor::CanonicalSubject {
        canonical_vertices: avatar.xyz.clone(),
        lbs_weights: avatar.lbs_weights.clone(),
        skeleton: avatar.skeleton.clone(),
    };
    let rendered = render_views(
        &avatar.mesh,
        &avatar.xyz,
        &avatar.faces,
        &subject,
        std::slice::from_ref(camera),
        &[skinning.to_vec()],
        inputs.sources.background,
    )?;
    let img = Image::from_chw(rendered.rgb.squeeze_dim::<3>(0))?;
    Ok((img, start.elapsed().as_secs_f64() * 1e3))
}

/// What produces the avatar that a split is scored on.
pub enum Method<'a> {
    /// A trained reconstructor (its `T` may be overridden by [`EvalSettings::iterations`]).
    Model {
        /// The network.
        model: &'a Reconstructor,
        /// Its configuration (for `subdivide_test`).
        config: &'a ReconstructorConfig,
    },
    /// The template-only baseline: the canonical template with the Gaussians' initial
    /// parameters, painted the mean colour of the source foreground (the best constant colour
    /// a template can have), i.e. what the network starts from. Shows what training buys.
    TemplateBaseline {
        /// Subdivisions of its Gaussians' mesh.
        subdivide: u32,
    },
    /// Projective texturing: the template coloured from the source pixels each vertex projects
    /// to in the views that see it ([`crate::baselines::projective_texturing`]). What reading
    /// the photos gives without learning.
    ProjectiveTexturing {
        /// Subdivisions of its Gaussians' mesh.
        subdivide: u32,
    },
}

/// Evaluates `method` on every target of `dataset` (a validation split): one avatar per
/// subject and input set, every target view rendered over the split's background and scored on
/// the protocol's region. Predictions and sheets are written for [`Method::Model`] only.
pub fn evaluate_split(
    method: &Method,
    dataset: &Dataset,
    settings: &EvalSettings,
    device: &Device,
) -> Result<SplitScores, EvalError> {
    let _span = tracing::info_span!("evaluate_split", samples = dataset.len()).entered();
    let (model, subdivide) = match method {
        Method::Model { model, config } => (
            Some(match settings.iterations {
                Some(t) => (*model).clone().with_iterations(t),
                None => (*model).clone(),
            }),
            settings.subdivide.unwrap_or(config.subdivide_test),
        ),
        Method::TemplateBaseline { subdivide } | Method::ProjectiveTexturing { subdivide } => {
            (None, *subdivide)
        }
    };
    let bodies = SubjectRig::for_split(dataset)?;
    let mesh = GomMesh::new(&bodies[0].topology, subdivide, device)?;
    let laplacian = (settings.refine_steps > 0)
        .then(|| UniformLaplacian::new(&bodies[0].topology.faces, bodies[0].num_vertices()))
        .transpose()
        .map_err(|e| EvalError::Fit(e.into()))?;
    let (w, h) = (dataset.img_size.0, dataset.img_size.1);
    let crop_size = thuman_crop_size(h as usize, w as usize);
    let crop_protocol = dataset.rule.protocol != Protocol::Aistpp;
    let mut cache: HashMap<(usize, Vec<usize>), Reconstructed> = HashMap::new();
    let mut views = Vec::new();
    let mut images = MetricImages::default();
    let mut sheets = Vec::new();
    let mut sheet_rows: Vec<(usize, Vec<Image>)> = Vec::new();
    for item in validation_samples(dataset, &bodies, settings.max_subjects, device) {
        let ValidationSample {
            index,
            sample,
            inputs,
        } = item?;
        let key = (index.subject, index.inputs.clone());
        if !cache.contains_key(&key) {
            let rec = match (&model, method) {
                (Some(model), _) => reconstruct_timed(model, &mesh, &inputs),
                (None, Method::ProjectiveTexturing { .. }) => {
                    baselines::projective_texturing(&mesh, &inputs, device)
                }
                (None, _) => baselines::template_one_colour(&mesh, &inputs, device),
            }
            .map_err(|e| EvalError::Frame {
                frame: sample.frame_name.clone(),
                source: Box::new(e),
            })?;
            let rec = refine(rec, &inputs, laplacian.as_ref(), settings.refine_steps)?;
            cache.clear();
            cache.insert(key.clone(), rec);
        }
        let rec = &cache[&key];
        let (pred, render_ms) = render_timed(
            &rec.avatar,
            &inputs,
            &inputs.target_camera,
            &inputs.target_skinning,
        )?;
        let gt = Image::from_chw(inputs.target_rgb.clone())?;
        let (m, regions, p_img, g_img) = score_region(
            &pred,
            &gt,
            Some(&target_mask(&inputs)?),
            crop_protocol,
            crop_size,
            &sample.frame_name,
        )?;
        if model.is_some() && settings.save_predictions {
            // Ground truth beside it under the same name: `lifegom-metrics preds gt` pairs them.
            let name = format!("{}.png", sample.frame_name);
            pred.save_png(&settings.out.join("preds").join(&name))?;
            gt.save_png(&settings.out.join("gt").join(&name))?;
        }
        if model.is_some()
            && sheets.len() < settings.sheets
            && !sheet_rows.iter().any(|(s, _)| *s == index.subject)
        {
            let row = vec![gt.clone(), pred.clone(), error_map(&pred, &gt, 4.0)?];
            let path = settings
                .out
                .join("sheets")
                .join(format!("{}.png", sample.frame_name));
            grid(std::slice::from_ref(&row), 2, [1.0; 3]).save_png(&path)?;
            sheets.push(path);
            sheet_rows.push((index.subject, row));
        }
        views.push(ViewScore {
            subject: sample.subject.clone(),
            frame_name: sample.frame_name.clone(),
            psnr: m.psnr,
            ssim: m.ssim,
            lpips_alex: None,
            lpips_vgg: None,
            recon_ms: rec.ms,
            render_ms,
            regions,
        });
        images.pred.push(p_img);
        images.gt.push(g_img);
    }
    if sheet_rows.len() > 1 {
        let rows: Vec<Vec<Image>> = sheet_rows.into_iter().map(|(_, row)| row).collect();
        grid(&rows, 2, [1.0; 3]).save_png(&settings.out.join("sheets.png"))?;
    }
    Ok(SplitScores {
        views,
        images,
        num_gaussians: mesh.num_gaussians(),
        iterations: model.as_ref().map_or(0, |m| m.iterations()),
        subdivide,
    })
}

/// Test-time refinement of a reconstruction (`steps` = 0: unchanged): the per-scene fit started
/// from `rec.avatar`, its wall time added to `rec.ms`.
pub fn refine(
    rec: Reconstructed,
    inputs: &ModelInputs,
    laplacian: Option<&UniformLaplacian>,
    steps: usize,
) -> Result<Reconstructed, EvalError> {
    let Some(laplacian) = laplacian.filter(|_| steps > 0) else {
        return Ok(rec);
    };
    let clock = Instant::now();
    let avatar = fit(
        &rec.avatar,
        inputs,
        laplacian,
        &LossWeights::new(),
        &FitConfig::new(),
        steps,
        |_, _, _| Ok(true),
    )
    .map_err(EvalError::Fit)?;
    Ok(Reconstructed {
        avatar,
        ms: rec.ms + clock.elapsed().as_secs_f64() * 1e3,
    })
}

/// Mean of `f` over the views that have a value.
pub fn mean_of(views: &[ViewScore], f: impl Fn(&ViewScore) -> Option<f64>) -> Option<f64> {
    let vals: Vec<f64> = views
        .iter()
        .filter_map(&f)
        .filter(|v| v.is_finite())
        .collect();
    (!vals.is_empty()).then(|| vals.iter().sum::<f64>() / vals.len() as f64)
}

/// Per-subject means, in first-seen order: `(subject, views, psnr, ssim, lpips_alex, lpips_vgg, recon_ms, render_ms)`.
pub fn per_subject(views: &[ViewScore]) -> Vec<(String, Vec<ViewScore>)> {
    let mut order: Vec<String> = Vec::new();
    let mut groups: HashMap<String, Vec<ViewScore>> = HashMap::new();
    for v in views {
        if !groups.contains_key(&v.subject) {
            order.push(v.subject.clone());
        }
        groups.entry(v.subject.clone()).or_default().push(v.clone());
    }
    order
        .into_iter()
        .map(|s| {
            let g = groups.remove(&s).unwrap_or_default();
            (s, g)
        })
        .collect()
}
