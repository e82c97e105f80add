//! The reconstruct command: one person's photos → an animatable avatar and everything made
//! from it (the `lifegom-reconstruct` binary; README).
//!
//! 1. **Subject**: a folder in the official layout (`images/`, `masks/`, three pickles) or the
//!    custom JSON layout (`subject.json`, docs/custom-data.md), validated by `lifegom-data`;
//!    each input camera must face the body.
//! 2. **Inputs**: the model takes exactly as many views as it was trained with; by default the
//!    subject's first frames (in the official layout, frame-name order; in the JSON layout, file
//!    order). A frame left over becomes a held-out view the avatar is scored on, so a user sees
//!    how it does on a view it never saw.
//! 3. **Avatar**: one feed-forward pass (T feedback steps), then `--refine-steps` gradient
//!    steps of the per-scene fit on the inputs (design.md §10.9).
//! 4. **Outputs** in `--out`: `avatar.lgom` (ours), `avatar.ply` (3D Gaussian splatting, canonical
//!    T-pose, with each Gaussian's rig), `avatar.glb` (the rigged canonical surface that glTF
//!    tools pose; docs/export.md), `inputs.png` (each input beside the avatar re-rendered in its view, and the
//!    held-out view when there is one), `turntable.gif`, one GIF per `--motion` (procedural or a
//!    pose-sequence file, docs/motions.md), one PNG per `--pose` file, and `reconstruct.json`
//!    (timings, scores, files).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use burn::tensor::Device;
use lifegom_data::dataset::{exposure_warning, load_sample};
use lifegom_data::format::{FrameCamera, Subject};
use lifegom_data::kinematics::KinematicTree;
use lifegom_eval::animate::{orbit_camera, posed_joint};
use lifegom_eval::evaluate::{reconstruct_timed, refine, render_timed};
use lifegom_eval::images::{Image, grid, save_gif};
use lifegom_eval::metrics::{ImageRef, psnr};
use lifegom_model::avatar::Avatar;
use lifegom_model::inputs::{SubjectRig, model_inputs};
use lifegom_model::reconstructor::ReconstructorConfig;
use lifegom_model::rig_export::RigAnimation;
use lifegom_model::trained;
use lifegom_render::atomic_file::write_atomic;
use lifegom_render::gom::GomMesh;
use lifegom_render::motion::{MotionSource, PoseSequence, with_known_joint_names};
use lifegom_render::skeleton::BodyPose;
use lifegom_train::losses::UniformLaplacian;

/// Frames of one cycle of a procedural motion, and its playback rate.
const MOTION_FRAMES: usize = 24;
const MOTION_FPS: f32 = 12.5;

/// What to reconstruct, with what, and where the outputs go.
#[derive(Debug, Clone)]
pub struct ReconstructOptions {
    /// A subject folder (official layout, or holding `subject.json`) or a `subject.json`.
    pub subject: PathBuf,
    /// The trained model: a `.lgck`, or an official checkpoint (`.pth` / `.safetensors`),
    /// told apart by content.
    pub model: PathBuf,
    /// The network an official checkpoint's weights are loaded into (the experiment's
    /// `[model]` for its number of input views); a `.lgck` carries its own.
    pub official_network: ReconstructorConfig,
    /// Image size the model works at (the experiment's `data.img_size`), `[W, H]`.
    pub img_size: [u32; 2],
    /// How larger photos are shrunk to it (the experiment's `data.resize`).
    pub resize: lifegom_data::preprocess::ResizeMode,
    /// Background the images are composited over, in `[0, 1]`.
    pub background: [f32; 3],
    /// Kinematic tree of an official-layout subject (the JSON layout is always the Anny rig).
    pub kinematic_tree: KinematicTree,
    /// Input frames by name or index; `None`: the first frames.
    pub inputs: Option<Vec<String>>,
    /// Test-time refinement steps after the feed-forward pass.
    pub refine_steps: usize,
    /// Subdivision levels of the avatar (`None`: the model's `subdivide_test`).
    pub subdivide: Option<u32>,
    /// Frames of the turntable GIF (0: none).
    pub turntable_frames: usize,
    /// Motions to play, one GIF each: procedural, or pose-sequence files (docs/motions.md).
    pub motions: Vec<MotionSource>,
    /// Pose files to render as stills, one PNG each (every frame of the file, side by side).
    pub poses: Vec<PoseSequence>,
    /// Output folder.
    pub out: PathBuf,
    /// Where the network runs.
    pub device: Device,
}

/// What a reconstruction produced, also written as `reconstruct.json`.
#[derive(Debug, Clone)]
pub struct ReconstructOutcome {
    /// Subject name.
    pub subject: String,
    /// The input frames used.
    pub inputs: Vec<String>,
    /// Feed-forward reconstruction wall time (ms).
    pub reconstruct_ms: f64,
    /// Refinement wall time (ms; 0 without refinement).
    pub refine_ms: f64,
    /// Mean PSNR (dB) of the avatar re-rendered in the input views.
    pub input_psnr: f64,
    /// The held-out frame and the avatar's PSNR (dB) there, when the subject has one.
    pub held_out: Option<(String, f64)>,
    /// Files written, relative to the output folder.
    pub files: Vec<PathBuf>,
    /// What looked wrong in the input without stopping it (the binary prints each as
    /// `warning: …`): views exposed very differently.
    pub warnings: Vec<String>,
}

/// Reads the subject in whichever layout `path` is (module docs).
pub fn load_subject(path: &Path, tree: KinematicTree) -> anyhow::Result<Subject> {
    let json = if path.is_dir() {
        path.join("subject.json")
    } else {
        path.to_path_buf()
    };
    if json.is_file() {
        return Ok(lifegom_data::custom::load_subject(&json)?);
    }
    if !path.is_dir() {
        bail!(
            "{}: no such subject: expected a folder in the official layout, or a subject.json (docs/custom-data.md)",
            path.display()
        );
    }
    Ok(Subject::load(path, tree)?)
}

/// How the photos were taken, which picks the shipped model that suits them (README, "Your
/// own people"; design.md §10.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Capture {
    /// Views from cameras around the person (THuman-style): the demo model (`assets/demo/`).
    MultiView,
    /// Frames of one video, the person moving before one camera (AIST++-style): the multi-frame
    /// model (`assets/multiframe/`), which takes its first [`ONE_CAMERA_FRAMES`] frames.
    OneCamera,
}

/// Input frames of the multi-frame model: a subject whose first this many frames share one
/// camera is a [`Capture::OneCamera`] capture.
pub const ONE_CAMERA_FRAMES: usize = 5;

/// A shipped model and the experiment config it was trained with, relative to the repository.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShippedModel {
    /// The `.lgck`.
    pub model: &'static str,
    /// Its config (image size, test background, kinematic tree).
    pub config: &'static str,
}

impl Capture {
    /// [`Capture::OneCamera`] when the first [`ONE_CAMERA_FRAMES`] frames share a camera.
    pub fn of(subject: &Subject) -> Self {
        match subject.cameras.get(..ONE_CAMERA_FRAMES) {
            Some([first, rest @ ..]) if rest.iter().all(|c| same_camera(c, first)) => {
                Self::OneCamera
            }
            _ => Self::MultiView,
        }
    }

    /// The shipped model for this kind of capture.
    pub fn shipped_model(self) -> ShippedModel {
        match self {
            Self::MultiView => ShippedModel {
                model: "assets/demo/demo.lgck",
                config: "assets/demo/config.toml",
            },
            Self::OneCamera => ShippedModel {
                model: "assets/multiframe/multiframe.lgck",
                config: "assets/multiframe/config.toml",
            },
        }
    }
}

impl std::fmt::Display for Capture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::MultiView => "multi-view",
            Self::OneCamera => "one-camera",
        })
    }
}

/// Same intrinsics and extrinsics up to what a camera file's rounding leaves.
fn same_camera(a: &FrameCamera, b: &FrameCamera) -> bool {
    let close = |x: f64, y: f64| (x - y).abs() <= 1e-6 * x.abs().max(y.abs()).max(1.0);
    a.k.iter()
        .flatten()
        .zip(b.k.iter().flatten())
        .all(|(&x, &y)| close(x, y))
        && a.e
            .iter()
            .flatten()
            .zip(b.e.iter().flatten())
            .all(|(&x, &y)| close(x, y))
}

/// Frame indices of the inputs: the named or numbered frames, or the first `n`.
pub fn choose_inputs(
    subject: &Subject,
    requested: Option<&[String]>,
    n: usize,
) -> anyhow::Result<Vec<usize>> {
    let frames = &subject.frames;
    let Some(requested) = requested else {
        if frames.len() < n {
            bail!(
                "subject `{}` ({}) has {} frames, but the model takes {n} input views",
                subject.name,
                subject.dir.display(),
                frames.len()
            );
        }
        return Ok((0..n).collect());
    };
    if requested.len() != n {
        bail!(
            "--inputs names {} frames, but the model takes exactly {n} input views",
            requested.len()
        );
    }
    requested
        .iter()
        .map(|r| {
            frames
                .iter()
                .position(|f| f == r)
                .or_else(|| r.parse::<usize>().ok().filter(|&i| i < frames.len()))
                .with_context(|| {
                    format!(
                        "--inputs: subject `{}` has no frame `{r}` (frames: {} .. {}, or indices 0..{})",
                        subject.name,
                        frames[0],
                        frames[frames.len() - 1],
                        frames.len()
                    )
                })
        })
        .collect()
}

fn mean_psnr(pred: &Image, gt: &Image) -> anyhow::Result<f64> {
    let shape = [gt.height, gt.width, 3];
    Ok(psnr(
        ImageRef::new(&pred.data, shape)?,
        ImageRef::new(&gt.data, shape)?,
        1.0,
    )?)
}

/// Runs the reconstruction (module docs).
pub fn run(opts: &ReconstructOptions) -> anyhow::Result<ReconstructOutcome> {
    let _span = tracing::info_span!("reconstruct", subject = %opts.subject.display()).entered();
    let loaded = trained::load_any(&opts.model, &opts.official_network, &opts.device)?;
    let subject = load_subject(&opts.subject, opts.kinematic_tree)?;
    let inputs_at = choose_inputs(&subject, opts.inputs.as_deref(), loaded.config.num_views)?;
    let source = if opts.subject.is_dir() && !opts.subject.join("subject.json").is_file() {
        opts.subject.join("cameras.pkl")
    } else {
        opts.subject.clone()
    };
    for &f in &inputs_at {
        subject.check_camera_sees_body(f, &source)?;
    }
    let held_out = (0..subject.frames.len()).find(|f| !inputs_at.contains(f));

    let rig = SubjectRig::new(&subject.name, &subject.canonical)?;
    loaded
        .check_template(&opts.model, rig.num_vertices())
        .with_context(|| format!("subject `{}`", subject.name))?;
    // Motion and pose files are checked against the rig (by joint count, and by joint name
    // where the rig is a known one) before any work is done.
    let named = with_known_joint_names(&rig.skeleton);
    let motions = opts
        .motions
        .iter()
        .map(|source| {
            let seq = source
                .sequence(&named, MOTION_FRAMES, MOTION_FPS)
                .with_context(|| format!("--motion {}", source.name()))?;
            Ok((source.name(), seq))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    for seq in &opts.poses {
        seq.validate_for(&named)
            .with_context(|| format!("--pose {}", seq.source.display()))?;
    }

    let [w, h] = opts.img_size;
    let bg = opts.background;
    // `model_inputs` takes the inputs and one target; the held-out frame is the target when
    // there is one, otherwise the first input stands in and is not scored.
    let target = held_out.unwrap_or(inputs_at[0]);
    let sample = load_sample(
        &subject,
        &inputs_at,
        target,
        bg.map(|c| c * 255.0),
        (w, h),
        opts.resize,
    )?;
    let warnings: Vec<String> = exposure_warning(&sample.views[..inputs_at.len()])
        .map(|w| format!("{}: {w}", opts.subject.display()))
        .into_iter()
        .collect();
    let inputs = model_inputs(&rig, &sample, w, h, &opts.device)?;
    let subdivide = opts.subdivide.unwrap_or(loaded.config.subdivide_test);
    let mesh = GomMesh::new(&rig.topology, subdivide, &opts.device)?;

    let rec = reconstruct_timed(&loaded.model, &mesh, &inputs)?;
    let reconstruct_ms = rec.ms;
    let rec = if opts.refine_steps > 0 {
        let laplacian = UniformLaplacian::new(&rig.topology.faces, rig.num_vertices())?;
        refine(rec, &inputs, Some(&laplacian), opts.refine_steps)?
    } else {
        rec
    };
    let refine_ms = rec.ms - reconstruct_ms;
    // The rig's joint names where it is a known one (Anny's bone labels, SMPL's joints): rigs
    // read from data carry only parents, and other tools retarget motions by bone name.
    let avatar = Avatar {
        skeleton: named,
        ..rec.avatar
    };

    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    let mut files = Vec::new();
    let mut write = |name: &str| {
        files.push(PathBuf::from(name));
        opts.out.join(name)
    };
    avatar.save(write("avatar.lgom"))?;
    avatar.export_ply(
        &BodyPose::rest(rig.skeleton.num_joints()),
        write("avatar.ply"),
    )?;
    // The motions ride along as glTF animations, one each: other tools retarget them by the
    // bones' names.
    let animations: Vec<RigAnimation<'_>> = motions
        .iter()
        .map(|(name, seq)| RigAnimation {
            name,
            fps: seq.fps,
            poses: seq.poses(),
            root_translations: seq.root_translations.as_deref(),
        })
        .collect();
    avatar.export_glb_animated(write("avatar.glb"), &animations)?;

    // Inputs beside their re-renders; the held-out view last.
    let mut rows = Vec::new();
    let mut scores = Vec::new();
    for (k, view) in sample.views.iter().enumerate() {
        let is_target = k == inputs_at.len();
        if is_target && held_out.is_none() {
            continue;
        }
        let (camera, skinning) = if is_target {
            (&inputs.target_camera, &inputs.target_skinning)
        } else {
            (&inputs.sources.cameras[k], &inputs.sources.skinning[k])
        };
        let (pred, _) = render_timed(&avatar, &inputs, camera, skinning)?;
        let gt = Image {
            width: w as usize,
            height: h as usize,
            data: view.rgb.clone(),
        };
        scores.push(mean_psnr(&pred, &gt)?);
        rows.push(vec![gt, pred]);
    }
    grid(&rows, 2, [1.0; 3]).save_png(&write("inputs.png"))?;
    let input_psnr = scores[..inputs_at.len()].iter().sum::<f64>() / inputs_at.len() as f64;
    let held_out = held_out.map(|f| (subject.frames[f].clone(), scores[inputs_at.len()]));

    // Free view around the body in the first input's pose, then the motions from its camera.
    let camera = &inputs.sources.cameras[0];
    if opts.turntable_frames > 0 {
        let skinning = &inputs.sources.skinning[0];
        let pivot = posed_joint(skinning, rig.skeleton.rest_joints[0], 0);
        let frames = (0..opts.turntable_frames)
            .map(|k| {
                let cam = orbit_camera(camera, pivot, k, opts.turntable_frames);
                Ok(render_timed(&avatar, &inputs, &cam, skinning)?.0)
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        save_gif(&write("turntable.gif"), &frames, 80)?;
    }
    // Poses and motions from the first input's camera.
    let render_pose = |pose: &BodyPose| -> anyhow::Result<Image> {
        let skinning = rig.skeleton.skinning_transforms(pose)?;
        Ok(render_timed(&avatar, &inputs, camera, &skinning)?.0)
    };
    for (name, seq) in &motions {
        let seq = seq.subsampled(PoseSequence::MAX_PREVIEW_FRAMES);
        let frames = seq
            .poses()
            .iter()
            .map(&render_pose)
            .collect::<anyhow::Result<Vec<_>>>()?;
        let delay_ms = (1000.0 / seq.fps).clamp(20.0, 1000.0) as u32;
        save_gif(&write(&format!("motion_{name}.gif")), &frames, delay_ms)?;
    }
    for seq in &opts.poses {
        let stills = seq
            .poses()
            .iter()
            .map(&render_pose)
            .collect::<anyhow::Result<Vec<_>>>()?;
        let rows: Vec<Vec<Image>> = stills.chunks(8).map(<[Image]>::to_vec).collect();
        grid(&rows, 2, [1.0; 3]).save_png(&write(&format!("pose_{}.png", seq.name())))?;
    }

    files.push(PathBuf::from("reconstruct.json"));
    let outcome = ReconstructOutcome {
        subject: subject.name.clone(),
        inputs: inputs_at
            .iter()
            .map(|&f| subject.frames[f].clone())
            .collect(),
        reconstruct_ms,
        refine_ms,
        input_psnr,
        held_out,
        files,
        warnings,
    };
    let json = opts.out.join("reconstruct.json");
    let report = serde_json::json!({
        "subject": outcome.subject,
        "warnings": outcome.warnings,
        "model": opts.model,
        "inputs": outcome.inputs,
        "refine_steps": opts.refine_steps,
        "subdivide": subdivide,
        "reconstruct_ms": outcome.reconstruct_ms,
        "refine_ms": outcome.refine_ms,
        "input_psnr": outcome.input_psnr,
        "held_out": outcome.held_out.as_ref().map(|(f, db)| serde_json::json!({"frame": f, "psnr": db})),
        "files": outcome.files,
    });
    write_atomic(&json, serde_json::to_string_pretty(&report)?.as_bytes())
        .with_context(|| format!("writing {}", json.display()))?;
    Ok(outcome)
}
