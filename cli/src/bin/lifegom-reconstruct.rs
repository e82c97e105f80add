//! `lifegom-reconstruct`: one person's photos (3–5 views with masks, cameras and body poses)
//! → an animatable avatar, its standard exports and renders (`lifegom_cli::reconstruct_run`).
//!
//! ```text
//! lifegom-synth --config configs/demo-v2.toml --out data/demo-v2 --json-example data/me
//! lifegom-reconstruct data/me --out out/me --motion walk
//! ```

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use lifegom_cli::reconstruct_run::{Capture, ReconstructOptions, load_subject, run};
use lifegom_data::dataset::Background;
use lifegom_data::kinematics::KinematicTree;
use lifegom_render::device::DeviceChoice;
use lifegom_render::motion::{MotionSource, PoseSequence};
use lifegom_train::config::ExperimentConfig;

#[derive(Parser, Debug)]
#[command(
    version,
    about = "Reconstruct an animatable avatar from a few photos of a person",
    after_help = "Example (a synthetic person written in the JSON layout, then reconstructed):\n  \
        lifegom-synth --config configs/demo-v2.toml --out data/demo-v2 --json-example data/me\n  \
        lifegom-reconstruct data/me --out out/me --motion walk --refine-steps 10\n\n\
        Inputs: a subject folder in the official LIFe-GoM layout (images/, masks/, cameras.pkl,\n\
        mesh_infos.pkl, canonical_joints.pkl) or a subject.json (docs/custom-data.md)."
)]
struct Args {
    /// The subject: an official-layout folder, a folder with `subject.json`, or the JSON file.
    subject: PathBuf,
    /// Output folder.
    #[arg(long, default_value = "out/reconstruct")]
    out: PathBuf,
    /// The trained model: a `.lgck`, or an official LIFe-GoM checkpoint (`.pth` from
    /// `torch.save`, or `.safetensors`) loaded into the network `--config`'s `[model]` describes.
    /// Default: by the capture. When the first 5 frames share one camera (frames of one video),
    /// the multi-frame model `assets/multiframe/multiframe.lgck`; otherwise the demo model
    /// `assets/demo/demo.lgck`.
    #[arg(long)]
    model: Option<PathBuf>,
    /// The experiment the model was trained with: its image size and test background (and, for
    /// an official checkpoint, its network: `[model]` and `[data] n_input_frames`). Default: the
    /// config shipped beside the capture's model (`assets/multiframe/config.toml` or
    /// `assets/demo/config.toml`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Input frames, by name or index (default: the first frames, as many as the model takes).
    #[arg(long, value_delimiter = ',')]
    inputs: Option<Vec<String>>,
    /// Kinematic tree of an official-layout subject (default: the config's `data.kinematic_tree`).
    #[arg(long, value_parser = parse_tree)]
    kinematic_tree: Option<KinematicTree>,
    /// Test-time refinement: gradient steps of the per-scene fit on the inputs.
    #[arg(long, default_value_t = 0)]
    refine_steps: usize,
    /// Subdivision levels (default: the model's).
    #[arg(long)]
    subdivide: Option<u32>,
    /// Frames of the turntable GIF (0: none).
    #[arg(long, default_value_t = 36)]
    turntable: usize,
    /// Motions to play as GIFs and to write into the `.glb` as animations: walk, arm-raise,
    /// squat, a pose-sequence file (docs/motions.md), or an SMPL capture file (AIST++ `.pkl` or
    /// `.npz`; retargeted to an Anny avatar); comma-separated or repeated.
    #[arg(long, value_delimiter = ',', value_parser = lifegom_data::capture::parse_motion)]
    motion: Vec<MotionSource>,
    /// Pose files (docs/motions.md) to render as stills, one PNG each; comma-separated or
    /// repeated.
    #[arg(long, value_delimiter = ',', value_parser = parse_pose)]
    pose: Vec<PoseSequence>,
    /// Backend.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
}

fn parse_pose(s: &str) -> Result<PoseSequence, String> {
    PoseSequence::load(s).map_err(|e| e.to_string())
}

fn parse_tree(s: &str) -> Result<KinematicTree, String> {
    serde_json::from_value(serde_json::Value::String(s.to_owned()))
        .map_err(|_| format!("unknown kinematic tree `{s}` (smpl, smplx, anny, stored)"))
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    let (model, config) = match (args.model, args.config) {
        (Some(model), Some(config)) => (model, config),
        (model, config) => {
            // Both shipped configs read the tree stored with the data; a capture's cameras do
            // not depend on it.
            let tree = args.kinematic_tree.unwrap_or(KinematicTree::Stored);
            let subject = load_subject(&args.subject, tree)
                .with_context(|| format!("reconstructing {}", args.subject.display()))?;
            let capture = Capture::of(&subject);
            let shipped = capture.shipped_model();
            let model = model.unwrap_or_else(|| shipped.model.into());
            let config = config.unwrap_or_else(|| shipped.config.into());
            eprintln!(
                "{capture} capture: model {}, config {}",
                model.display(),
                config.display()
            );
            (model, config)
        }
    };
    let experiment = ExperimentConfig::load(&config)?;
    let cfg = &experiment.file;
    let background = match cfg.data.test_background {
        Background::Fixed(c) => c.map(|v| f32::from(v) / 255.0),
        // A random test background has no single colour to show: white, as AIST++ uses.
        Background::Random => [1.0; 3],
    };
    let opts = ReconstructOptions {
        subject: args.subject,
        model,
        official_network: experiment.reconstructor(),
        img_size: cfg.data.img_size,
        resize: cfg.data.resize,
        background,
        kinematic_tree: args.kinematic_tree.unwrap_or(cfg.data.kinematic_tree),
        inputs: args.inputs,
        refine_steps: args.refine_steps,
        subdivide: args.subdivide,
        turntable_frames: args.turntable,
        motions: args.motion,
        poses: args.pose,
        out: args.out.clone(),
        device: args.device.device(),
    };
    let outcome =
        run(&opts).with_context(|| format!("reconstructing {}", opts.subject.display()))?;
    for warning in &outcome.warnings {
        eprintln!("warning: {warning}");
    }
    eprintln!(
        "subject `{}` from frames {}: reconstructed in {:.0} ms{}",
        outcome.subject,
        outcome.inputs.join(", "),
        outcome.reconstruct_ms,
        if opts.refine_steps > 0 {
            format!(
                " + {} refinement steps in {:.0} ms",
                opts.refine_steps, outcome.refine_ms
            )
        } else {
            String::new()
        }
    );
    eprintln!(
        "re-rendered in its input views: {:.2} dB PSNR",
        outcome.input_psnr
    );
    if let Some((frame, db)) = &outcome.held_out {
        eprintln!("held-out frame `{frame}` (not an input): {db:.2} dB PSNR");
    }
    for f in &outcome.files {
        println!("{}", args.out.join(f).display());
    }
    Ok(())
}
