//! `lifegom-synth --config <toml> --out <dir> [--seed N] [--contact-sheet <png>] [--json-example
//! <dir>]`: generates a synthetic split in the official processed layout (see
//! `lifegom_data::synth`): THuman-style static people on a camera ring, or with `[synthetic]
//! setting = "multi_frame"` AIST++-style people moving in front of one camera
//! (`configs/synthetic-multiframe.toml`). `--json-example` also writes the first validation
//! subject in the custom JSON layout (`lifegom_data::custom`, docs/custom-data.md).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use lifegom_data::config::ConfigFile;
use lifegom_data::synth;

/// Generate a synthetic THuman-style (multi-view) or AIST++-style (multi-frame) dataset.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Config file with `[data]` and `[synthetic]` sections (configs/synthetic-*.toml).
    #[arg(long)]
    config: PathBuf,
    /// Output dataset root (replaces `data.root`).
    #[arg(long)]
    out: PathBuf,
    /// Seed (replaces `synthetic.seed`).
    #[arg(long)]
    seed: Option<u64>,
    /// Also write a contact sheet (images then masks of four frames of up to 6 training
    /// subjects: ring views 0, 4, 8, 12, or four times spread over a sequence) to this PNG.
    #[arg(long)]
    contact_sheet: Option<PathBuf>,
    /// Also write a contact sheet of the held-out subjects (design.md §8.11; up to 8, every
    /// view, images then masks) to this PNG.
    #[arg(long)]
    held_out_sheet: Option<PathBuf>,
    /// Also write the first validation subject in the custom JSON layout (`subject.json` and
    /// its pictures) to this folder: the worked example of docs/custom-data.md.
    #[arg(long)]
    json_example: Option<PathBuf>,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    let cfg = ConfigFile::load(&args.config)?.with_root(&args.out);
    let Some(synth_cfg) = cfg.synthetic.clone() else {
        bail!(
            "{}: no [synthetic] section: not a synthetic-data config",
            args.config.display()
        );
    };
    let seed = args.seed.unwrap_or(synth_cfg.seed);
    let held_out = if cfg.data.held_out().is_some() {
        synth_cfg.held_out_subjects
    } else {
        0
    };
    let total = (synth_cfg.train_subjects + synth_cfg.val_subjects + held_out) as u64;
    let bar = ProgressBar::new(total).with_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} subjects, eta {eta}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let start = Instant::now();
    let summary = synth::generate_split(&synth_cfg, &cfg.data, &args.out, seed, &|| bar.inc(1))?;
    bar.finish();
    eprintln!(
        "wrote {} train + {} val + {} held-out subjects, {} frames, to {} in {:.1} s",
        summary.train.len(),
        summary.val.len(),
        summary.held_out.len(),
        summary.frames,
        args.out.display(),
        start.elapsed().as_secs_f64()
    );
    if let Some(path) = args.contact_sheet {
        let dir = args.out.join(&cfg.data.train_dir);
        let subjects: Vec<String> = summary.train.iter().take(6).cloned().collect();
        let views: Vec<usize> = match synth_cfg.setting {
            synth::SynthSetting::MultiView => vec![0, 4, 8, 12],
            synth::SynthSetting::MultiFrame => {
                (0..4).map(|k| k * synth_cfg.sequence_frames / 4).collect()
            }
        };
        let (w, h, rgb) = synth::contact_sheet(&dir, &subjects, &views)?;
        lifegom_render::atomic_file::write_png(&path, &rgb, w, h, image::ExtendedColorType::Rgb8)
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("contact sheet: {}", path.display());
    }
    if let (Some(path), Some(held)) = (args.held_out_sheet, cfg.data.held_out()) {
        let dir = args.out.join(&held.val_dir);
        let subjects: Vec<String> = summary.held_out.iter().take(8).cloned().collect();
        let views: Vec<usize> = (0..cfg.data.n_input_frames + synth_cfg.val_target_views).collect();
        let (w, h, rgb) = synth::contact_sheet(&dir, &subjects, &views)?;
        lifegom_render::atomic_file::write_png(&path, &rgb, w, h, image::ExtendedColorType::Rgb8)
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("held-out contact sheet: {}", path.display());
    }
    if let Some(dir) = args.json_example {
        let Some(first) = summary.val.first() else {
            bail!("--json-example needs a validation subject; the config writes none");
        };
        let (split_dir, _) = cfg.data.split_paths(lifegom_data::dataset::Split::Val);
        let subject =
            lifegom_data::format::Subject::load(&split_dir.join(first), cfg.data.kinematic_tree)?;
        let path = lifegom_data::custom::write_subject(&subject, synth_cfg.template, &dir)?;
        eprintln!("JSON-layout example subject: {}", path.display());
    }
    Ok(())
}
