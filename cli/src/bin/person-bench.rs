//! `person-bench`: the person graphs on photos whose truth is known: is the person found, how
//! well each mask (the landmark model's, the selfie model's) overlaps the stored mask, and how
//! long each stage takes.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin lifegom-synth -- --config configs/demo-v4.toml --out data/demo-v4
//! cargo run --release -p lifegom-cli --bin person-bench -- data/demo-v4/held_out_val --json
//! ```
//!
//! The folder holds subjects, each with `images/` and `masks/` of the same file names (the
//! official layout, as `lifegom-synth` writes it). One JSON line per photo, then one summary
//! line: photos, persons found, mean and worst IoU of each mask against the stored mask (both
//! thresholded at 0.5), and the median milliseconds of the person pipeline (detector, crop,
//! landmark model, mask) and of the selfie model, read-backs included.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Parser;
use lifegom_estimate::graphs::{self, PersonGraph};
use lifegom_estimate::person::{PersonError, PersonGraphs};
use lifegom_estimate::{overlay, selfie};
use lifegom_render::device::DeviceChoice;
use serde_json::json;

#[derive(Parser, Debug)]
#[command(about = "Score and time the person graphs on photos with known masks")]
struct Args {
    /// A folder of subjects with `images/` and `masks/`.
    data: PathBuf,
    /// Backend: ndarray, flex or wgpu.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// The folder of fetched graphs (default: $LIFEGOM_WEIGHTS, else weights/).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// At most this many photos (all by default).
    #[arg(long)]
    limit: Option<usize>,
    /// Only the JSON lines.
    #[arg(long)]
    json: bool,
    /// Also write each photo's overlay (mask edge, skeleton) into this folder, as
    /// `<subject>_<photo>.png`.
    #[arg(long)]
    overlays: Option<PathBuf>,
}

/// IoU of two masks thresholded at 0.5.
fn iou(a: &[f32], b: &[f32]) -> f64 {
    let (mut inter, mut union) = (0usize, 0usize);
    for (x, y) in a.iter().zip(b) {
        let (x, y) = (*x >= 0.5, *y >= 0.5);
        inter += usize::from(x && y);
        union += usize::from(x || y);
    }
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

fn photos(root: &Path) -> anyhow::Result<Vec<(PathBuf, PathBuf)>> {
    let mut subjects: Vec<PathBuf> = std::fs::read_dir(root)
        .with_context(|| format!("reading {}", root.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("images").is_dir() && p.join("masks").is_dir())
        .collect();
    subjects.sort();
    let mut out = Vec::new();
    for s in subjects {
        let mut names: Vec<PathBuf> = std::fs::read_dir(s.join("images"))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "png"))
            .collect();
        names.sort();
        for image in names {
            let mask = s.join("masks").join(image.file_name().unwrap_or_default());
            if mask.is_file() {
                out.push((image, mask));
            }
        }
    }
    if out.is_empty() {
        bail!(
            "{}: no subject folders with images/ and masks/",
            root.display()
        );
    }
    Ok(out)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::init_tracing();
    let args = Args::parse();
    let device = args.device.device();
    let dir = args
        .weights
        .clone()
        .unwrap_or_else(lifegom_data::registry::weights_dir);
    let person_graphs = PersonGraphs::load(&dir, &device)?;
    let selfie_graph = graphs::load(&dir, PersonGraph::Selfie, &device)?;
    let mut all = photos(&args.data)?;
    if let Some(n) = args.limit {
        all.truncate(n);
    }
    let (mut found, mut pose_ious, mut selfie_ious) = (0, Vec::new(), Vec::new());
    let (mut t_person, mut t_selfie) = (Vec::new(), Vec::new());
    if let Some(dir) = &args.overlays {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    for (image, mask) in &all {
        let rgb = image::open(image)
            .with_context(|| format!("reading {}", image.display()))?
            .to_rgb8();
        let truth: Vec<f32> = image::open(mask)
            .with_context(|| format!("reading {}", mask.display()))?
            .to_luma8()
            .as_raw()
            .iter()
            .map(|&v| f32::from(v) / 255.0)
            .collect();
        let (w, h) = (rgb.width() as usize, rgb.height() as usize);
        let start = Instant::now();
        let person = match person_graphs.estimate(image, rgb.as_raw(), w, h) {
            Ok(p) => Some(p),
            Err(PersonError::NoPerson { .. }) => None,
            Err(e) => return Err(e.into()),
        };
        t_person.push(start.elapsed().as_secs_f64() * 1e3);
        if let (Some(dir), Some(p)) = (&args.overlays, &person) {
            let subject = image
                .parent()
                .and_then(|d| d.parent())
                .and_then(|d| d.file_name())
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let stem = image.file_stem().unwrap_or_default().to_string_lossy();
            let out = dir.join(format!("{subject}_{stem}.png"));
            overlay::draw(&rgb, p)
                .save(&out)
                .with_context(|| format!("writing {}", out.display()))?;
        }
        let start = Instant::now();
        let selfie_mask = selfie::mask(&selfie_graph, rgb.as_raw(), w, h, &device)?;
        t_selfie.push(start.elapsed().as_secs_f64() * 1e3);
        let selfie_iou = iou(&selfie_mask, &truth);
        selfie_ious.push(selfie_iou);
        let pose_iou = person.as_ref().map(|p| iou(&p.pose.mask, &truth));
        if let Some(v) = pose_iou {
            found += 1;
            pose_ious.push(v);
        }
        println!(
            "{}",
            json!({
                "photo": image.display().to_string(),
                "found": person.is_some(),
                "detection_score": person.as_ref().map(|p| p.detection.score),
                "presence": person.as_ref().map(|p| p.pose.presence),
                "landmark_mask_iou": pose_iou,
                "selfie_mask_iou": selfie_iou,
            })
        );
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let worst = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    println!(
        "{}",
        json!({
            "bench": "person",
            "data": args.data.display().to_string(),
            "device": format!("{:?}", args.device),
            "photos": all.len(),
            "found": found,
            "landmark_mask_iou_mean": mean(&pose_ious),
            "landmark_mask_iou_worst": worst(&pose_ious),
            "selfie_mask_iou_mean": mean(&selfie_ious),
            "selfie_mask_iou_worst": worst(&selfie_ious),
            "person_ms": median(t_person),
            "selfie_ms": median(t_selfie),
        })
    );
    if !args.json {
        eprintln!(
            "{found} of {} photos: person found; masks scored against the stored ones",
            all.len()
        );
    }
    Ok(())
}
