//! The `lifegom-eval` command as a library function (the quickstart calls it too).
//!
//! Loads a trained-model file, opens the config's validation split, scores every target
//! ([`lifegom_eval::evaluate`]), optionally the baselines (template in one colour, projective
//! texturing, per-scene optimisation after K steps), a free-view turntable, novel-pose
//! motions (procedural or pose-sequence files) and the accuracy-vs-time sweep, and writes CSVs, `summary.json` and
//! `report.md` with pictures into `--out`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use burn::tensor::Device;
use lifegom_data::dataset::{DataConfig, Dataset, Split};
use lifegom_model::inputs::{SubjectRig, model_inputs};
use lifegom_model::reconstructor::{Reconstructor, ReconstructorConfig};
use lifegom_model::trained;
use lifegom_render::gom::GomMesh;
use lifegom_render::motion::{MotionSource, known_joint_names, with_known_joint_names};
use lifegom_render::rng::Rng;

use lifegom_eval::animate::{orbit_camera, posed_joint};
use lifegom_eval::evaluate::{
    EvalSettings, Method, SplitScores, evaluate_split, reconstruct_timed, render_timed,
};
use lifegom_eval::images::save_gif;
use lifegom_eval::per_scene::{FitPoint, PerSceneFit, score_per_scene_fit};
use lifegom_eval::perceptual_scores::{PerceptualOutcome, score_perceptual};
use lifegom_eval::report::{Report, Summary, SweepRow, write_csvs};
use lifegom_eval::validation::score_feedback_steps;
use lifegom_train::fit::FitConfig;
use lifegom_train::losses::LossWeights;

/// Options of one evaluation.
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// The `[data]` section (root already overridden).
    pub data: DataConfig,
    /// Trained-model file: a `.lgck`, or an official checkpoint (`.pth` / `.safetensors`).
    pub checkpoint: PathBuf,
    /// The network an official checkpoint's weights are loaded into (the experiment's
    /// `[model]` for its number of input views); a `.lgck` carries its own.
    pub official_network: ReconstructorConfig,
    /// Output folder.
    pub out: PathBuf,
    /// Device (no autodiff needed).
    pub device: Device,
    /// Subdivisions override.
    pub subdivide: Option<u32>,
    /// Feedback steps override.
    pub iterations: Option<usize>,
    /// Comparison sheets to write.
    pub sheets: usize,
    /// Frames of the free-view turntable (0 = none).
    pub freeview_frames: usize,
    /// Novel-pose motions to render (procedural or files; empty: none).
    pub motions: Vec<MotionSource>,
    /// Run the accuracy-vs-time sweep over T ∈ 1..=5 and subdivisions 0..=2.
    pub sweep: bool,
    /// Extra image sides for the sweep (empty = the config's size only).
    pub sweep_sizes: Vec<u32>,
    /// Subjects the sweep scores (`None`: as many as the evaluation, so that its points and
    /// the baselines are scored on the same people). Each size costs 15 evaluations.
    pub sweep_subjects: Option<usize>,
    /// Other trained models (`.lgck`) to score on the same views beside the checkpoint, e.g.
    /// an earlier demo model: table rows and points of the accuracy-vs-time chart.
    pub other_models: Vec<PathBuf>,
    /// Also score the baselines (template in one colour, projective texturing).
    pub baseline: bool,
    /// Score the per-scene optimisation baseline after each of these step counts (empty: no).
    pub per_scene: Vec<usize>,
    /// Subjects the per-scene optimisation fits (`None`: as many as the evaluation).
    pub per_scene_subjects: Option<usize>,
    /// Evaluate at most this many subjects.
    pub max_subjects: Option<usize>,
    /// Test-time refinement: gradient steps of the per-scene fit after the feed-forward pass
    /// (0 = none); applies to the model and the baselines alike.
    pub refine_steps: usize,
    /// Folder with the converted LPIPS/Inception weights.
    pub weights_dir: PathBuf,
    /// Lines to put under the report heading (command line, machine).
    pub context: Vec<String>,
    /// Also score every trained model after each feedback step `t = 1..T` (one more
    /// reconstruction per subject; the report's "Every feedback step" table).
    pub feedback_steps: bool,
}

/// Result of [`run`].
#[derive(Debug, Clone)]
pub struct EvalOutcome {
    /// The model's summary.
    pub summary: Summary,
    /// The baselines' summaries (name, summary), if asked.
    pub baselines: Vec<(String, Summary)>,
    /// Sweep rows, if asked.
    pub sweep: Vec<SweepRow>,
    /// The per-scene optimisation's points, if asked.
    pub per_scene: Vec<FitPoint>,
    /// The report that was written.
    pub report: PathBuf,
}

fn settings(opts: &EvalOptions, out: &Path) -> EvalSettings {
    EvalSettings {
        out: out.to_path_buf(),
        subdivide: opts.subdivide,
        iterations: opts.iterations,
        save_predictions: true,
        sheets: opts.sheets,
        max_subjects: opts.max_subjects,
        refine_steps: opts.refine_steps,
    }
}

/// Runs the evaluation (module docs).
pub fn run(opts: &EvalOptions) -> anyhow::Result<EvalOutcome> {
    let _span = tracing::info_span!("eval", out = %opts.out.display()).entered();
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    let loaded = trained::load_any(&opts.checkpoint, &opts.official_network, &opts.device)?;
    let dataset = Dataset::open(&opts.data, Split::Val)?;
    if let Some(subject) = dataset.subjects.first() {
        let rig = SubjectRig::new(&subject.name, &subject.canonical)?;
        loaded
            .check_template(&opts.checkpoint, rig.num_vertices())
            .with_context(|| format!("validation subject `{}`", subject.name))?;
    }
    let provenance = loaded.provenance();
    let (model, config) = (loaded.model, loaded.config);
    let mut report = Report {
        title: "LIFe-GoM evaluation".into(),
        context: opts.context.clone(),
        ..Default::default()
    };
    report.context.push(format!(
        "checkpoint `{}` ({}), split `{}` ({} subjects, {:?}), {}×{} px",
        opts.checkpoint.display(),
        provenance,
        opts.data.split_paths(Split::Val).0.display(),
        dataset.subjects.len(),
        dataset.rule.protocol,
        dataset.img_size.0,
        dataset.img_size.1
    ));

    if opts.refine_steps > 0 {
        report.context.push(format!(
            "test-time refinement: every avatar below (model and baselines) is refined by {} gradient steps on its source views (design.md §10.9); recon ms includes them",
            opts.refine_steps
        ));
    }

    let perceptual = lifegom_eval::perceptual_scores::load_models(&opts.weights_dir, &opts.device);
    if let Some(note) = perceptual.note() {
        eprintln!("{note}");
        report.notes.push(note);
    }

    let clock = Instant::now();
    let progress = |what: &str, summary: &Summary| {
        eprintln!(
            "        {what:<28} PSNR {:6.2}  SSIM {:.3}  ({} views, {:.0} s)",
            summary.psnr,
            summary.ssim,
            summary.views,
            clock.elapsed().as_secs_f64()
        );
    };
    let mut scores = evaluate_split(
        &Method::Model {
            model: &model,
            config: &config,
        },
        &dataset,
        &settings(opts, &opts.out),
        &opts.device,
    )?;
    let PerceptualOutcome { fid } = score_perceptual(&perceptual, &mut scores, &opts.device)?;
    let summary = Summary::of(&scores, fid);
    progress(&format!("model, T = {}", scores.iterations), &summary);
    write_csvs(&opts.out, &scores.views)?;
    report.summary = Some(summary.clone());
    report.sheets = list_relative(&opts.out, "sheets");

    for path in &opts.other_models {
        let other = trained::load_any(path, &opts.official_network, &opts.device)?;
        let mut s = evaluate_split(
            &Method::Model {
                model: &other.model,
                config: &other.config,
            },
            &dataset,
            // Its predictions and sheets would overwrite the checkpoint's.
            &EvalSettings {
                save_predictions: false,
                sheets: 0,
                ..settings(opts, &opts.out)
            },
            &opts.device,
        )?;
        let PerceptualOutcome { fid } = score_perceptual(&perceptual, &mut s, &opts.device)?;
        let summary = Summary::of(&s, fid);
        // Plain text: the chart's legend shows it too, in a font without backquotes.
        let name = format!("{} ({})", path.display(), other.provenance());
        progress(&format!("other model, T = {}", s.iterations), &summary);
        report.other_models.push((name, summary));
    }

    if opts.feedback_steps {
        let subdivide = opts.subdivide.unwrap_or(config.subdivide_test);
        let lpips = perceptual.lpips_alex();
        let mut named = vec![("model".to_owned(), &model)];
        let others = opts
            .other_models
            .iter()
            .map(|p| {
                Ok((
                    p.display().to_string(),
                    trained::load_any(p, &opts.official_network, &opts.device)?.model,
                ))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        named.extend(others.iter().map(|(n, m)| (n.clone(), m)));
        for (name, m) in named {
            // `--iterations` sets T here as in the scores above.
            let overridden;
            let m = match opts.iterations {
                Some(t) => {
                    overridden = m.clone().with_iterations(t);
                    &overridden
                }
                None => m,
            };
            let steps = score_feedback_steps(
                m,
                &dataset,
                subdivide,
                opts.max_subjects,
                lpips,
                &opts.device,
            )?;
            let psnr: Vec<String> = steps.iter().map(|s| format!("{:.2}", s.psnr)).collect();
            eprintln!(
                "        {name}: PSNR after each feedback step {}",
                psnr.join(" / ")
            );
            report.feedback_steps.push((name, steps));
        }
    }

    let mut baselines = Vec::new();
    if opts.baseline {
        let subdivide = opts.subdivide.unwrap_or(config.subdivide_test);
        for (name, method) in [
            (BASELINE_TEMPLATE, Method::TemplateBaseline { subdivide }),
            (
                BASELINE_PROJECTIVE,
                Method::ProjectiveTexturing { subdivide },
            ),
        ] {
            let mut b =
                evaluate_split(&method, &dataset, &settings(opts, &opts.out), &opts.device)?;
            let PerceptualOutcome { fid } = score_perceptual(&perceptual, &mut b, &opts.device)?;
            let summary = Summary::of(&b, fid);
            progress(name, &summary);
            baselines.push((name.to_string(), summary));
        }
        report.baselines = baselines.clone();
    }

    if opts.freeview_frames > 0 || !opts.motions.is_empty() {
        let names: Vec<String> = opts.motions.iter().map(MotionSource::name).collect();
        eprintln!(
            "        rendering novel views ({} frames) and poses ({})",
            opts.freeview_frames,
            if names.is_empty() {
                "none".to_owned()
            } else {
                names.join(", ")
            }
        );
        let pictures = animations(opts, &model, &dataset, config.subdivide_test)?;
        report.pictures.extend(pictures);
    }

    let mut sweep = Vec::new();
    if opts.sweep {
        sweep = run_sweep(opts, &model, &config, &perceptual)?;
        report.sweep = sweep.clone();
    }

    let mut per_scene = Vec::new();
    if !opts.per_scene.is_empty() {
        eprintln!(
            "per-scene optimisation: fitting each subject for up to {} steps",
            opts.per_scene.iter().max().unwrap_or(&0)
        );
        per_scene = score_per_scene_fit(
            &dataset,
            &PerSceneFit {
                ks: opts.per_scene.clone(),
                subdivide: opts.subdivide.unwrap_or(config.subdivide_test),
                cfg: FitConfig::new(),
                weights: LossWeights::new(),
                max_subjects: opts.per_scene_subjects.or(opts.max_subjects),
            },
            &perceptual,
            &opts.device,
        )?;
        for p in &per_scene {
            eprintln!(
                "        {:<28} PSNR {:6.2}  SSIM {:.3}  ({} subjects, {:.1} s each)",
                format!("per-scene fit, K = {}", p.steps),
                p.psnr,
                p.ssim,
                p.subjects,
                p.ms / 1e3
            );
        }
        report.per_scene = per_scene.clone();
    }

    let json = serde_json::json!({
        "model": summary,
        "baselines": baselines_json(&baselines),
        "sweep": sweep,
        "per_scene": per_scene,
        "feedback_steps": report.feedback_steps,
        "checkpoint": opts.checkpoint.display().to_string(),
        "perceptual": perceptual.note().unwrap_or_else(|| "computed".into()),
    });
    let path = opts.out.join("summary.json");
    lifegom_render::atomic_file::write_atomic(
        &path,
        serde_json::to_string_pretty(&json)?.as_bytes(),
    )
    .with_context(|| format!("writing {}", path.display()))?;
    report.write(&opts.out)?;
    Ok(EvalOutcome {
        summary,
        baselines,
        sweep,
        per_scene,
        report: opts.out.join("report.md"),
    })
}

/// Name of the template-in-one-colour baseline in reports.
pub const BASELINE_TEMPLATE: &str = "template, one colour";
/// Name of the projective-texturing baseline in reports.
pub const BASELINE_PROJECTIVE: &str = "projective texturing";

/// `{name: summary}` of the baselines.
pub fn baselines_json(baselines: &[(String, Summary)]) -> serde_json::Value {
    serde_json::Value::Object(
        baselines
            .iter()
            .map(|(n, s)| (n.clone(), serde_json::json!(s)))
            .collect(),
    )
}

fn list_relative(out: &Path, dir: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(out.join(dir))
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| PathBuf::from(dir).join(e.file_name()))
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Frames of one cycle of a procedural motion.
const PROCEDURAL_FRAMES: usize = 24;
/// Playback rate of a procedural motion's GIF (80 ms a frame).
const PROCEDURAL_FPS: f32 = 12.5;

/// Free-view turntable and novel-pose motions of the first validation subject.
fn animations(
    opts: &EvalOptions,
    model: &Reconstructor,
    dataset: &Dataset,
    subdivide: u32,
) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let mut rng = Rng::new(0);
    let sample = dataset.sample(0, &mut rng)?;
    let subject = &dataset.subjects[0];
    let body = SubjectRig::new(&subject.name, &subject.canonical)?;
    let (w, h) = dataset.img_size;
    let inputs = model_inputs(&body, &sample, w, h, &opts.device)?;
    let mesh = GomMesh::new(
        &body.topology,
        opts.subdivide.unwrap_or(subdivide),
        &opts.device,
    )?;
    let rec = reconstruct_timed(model, &mesh, &inputs)?;
    let mut pictures = Vec::new();
    if opts.freeview_frames > 0 {
        let pivot = posed_joint(&inputs.target_skinning, body.skeleton.rest_joints[0], 0);
        let mut frames = Vec::new();
        for k in 0..opts.freeview_frames {
            let cam = orbit_camera(&inputs.target_camera, pivot, k, opts.freeview_frames);
            let (img, _) = render_timed(&rec.avatar, &inputs, &cam, &inputs.target_skinning)?;
            img.save_png(&opts.out.join("freeview").join(format!("frame_{k:04}.png")))?;
            frames.push(img);
        }
        save_gif(&opts.out.join("freeview.gif"), &frames, 80)?;
        pictures.push((
            format!("Free view of {}", subject.name),
            PathBuf::from("freeview.gif"),
        ));
    }
    if !opts.motions.is_empty() {
        // Rigs read from data carry only parents; a known rig gets its joint names back, so a
        // motion file that names its joints is checked against them.
        let known = known_joint_names(body.skeleton.num_joints());
        let rig = with_known_joint_names(&body.skeleton);
        for source in &opts.motions {
            let name = source.name();
            let seq = match source.sequence(&rig, PROCEDURAL_FRAMES, PROCEDURAL_FPS) {
                // Name the joints in the written file where the rig's names are known, so it
                // can be edited by name and is checked against the rig it is played on.
                Ok(seq) => match (&seq.joint_names, &known) {
                    (None, Some(names)) => seq.with_joint_names(names.clone()),
                    _ => seq,
                },
                Err(e) => {
                    eprintln!("--motion {name}: {e}; skipped");
                    continue;
                }
            };
            let dir = opts.out.join("motion").join(&name);
            // The poses that were rendered, as a file `--motion` reads back (docs/motions.md).
            let seq = seq.subsampled(lifegom_render::motion::PoseSequence::MAX_PREVIEW_FRAMES);
            seq.save(dir.join("poses.json"))?;
            let mut frames = Vec::new();
            for (k, pose) in seq.poses().iter().enumerate() {
                let skinning = body.skeleton.skinning_transforms(pose)?;
                let cam = &inputs.sources.cameras[0];
                let (img, _) = render_timed(&rec.avatar, &inputs, cam, &skinning)?;
                img.save_png(&dir.join(format!("frame_{k:04}.png")))?;
                frames.push(img);
            }
            let gif = PathBuf::from(format!("motion_{name}.gif"));
            let delay_ms = (1000.0 / seq.fps).clamp(20.0, 1000.0) as u32;
            save_gif(&opts.out.join(&gif), &frames, delay_ms)?;
            pictures.push((format!("Novel pose: {name}"), gif));
        }
    }
    Ok(pictures)
}

/// T ∈ 1..=5 × subdivisions 0..=2 (× sizes) on the first `sweep_subjects` subjects (all that
/// the evaluation scores, by default).
fn run_sweep(
    opts: &EvalOptions,
    model: &Reconstructor,
    config: &lifegom_model::reconstructor::ReconstructorConfig,
    perceptual: &lifegom_eval::perceptual_scores::Models,
) -> anyhow::Result<Vec<SweepRow>> {
    let mut sizes = vec![opts.data.img_size[0]];
    for s in &opts.sweep_sizes {
        if !sizes.contains(s) {
            sizes.push(*s);
        }
    }
    let mut rows = Vec::new();
    for size in sizes {
        let mut data = opts.data.clone();
        let aspect = opts.data.img_size[1] as f64 / opts.data.img_size[0] as f64;
        data.img_size = [size, ((size as f64 * aspect).round() as u32).max(1)];
        let dataset = Dataset::open(&data, Split::Val)?;
        for subdivide in 0..=2u32 {
            for t in 1..=5usize {
                let settings = EvalSettings {
                    out: opts.out.join("sweep"),
                    subdivide: Some(subdivide),
                    iterations: Some(t),
                    save_predictions: false,
                    sheets: 0,
                    max_subjects: opts.sweep_subjects.map(|n| n.max(1)).or(opts.max_subjects),
                    refine_steps: 0,
                };
                let mut scores: SplitScores = evaluate_split(
                    &Method::Model { model, config },
                    &dataset,
                    &settings,
                    &opts.device,
                )?;
                let PerceptualOutcome { fid: _ } =
                    score_perceptual(perceptual, &mut scores, &opts.device)?;
                let summary = Summary::of(&scores, None);
                eprintln!(
                    "sweep size {size} T={t} subdiv={subdivide}: PSNR {:.2} recon {:.0} ms render {:.1} ms",
                    summary.psnr, summary.recon_ms, summary.render_ms
                );
                rows.push(SweepRow { size, summary });
            }
        }
    }
    Ok(rows)
}
