//! `lifegom-metrics`: two folders of images scored against each other, as
//! `python -m pytorch_fid A B` and the lpips package's scripts do.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin lifegom-metrics -- runs/quickstart/preds runs/quickstart/gt --json
//! ```
//!
//! Images are paired by file name for PSNR, SSIM and LPIPS (alex, vgg); FID compares the two
//! sets (any sizes, resized to 299² as pytorch-fid does). The weights come from `--weights`,
//! `$LIFEGOM_WEIGHTS` or `weights/` (`lifegom-weights fetch`); a figure whose weights are
//! missing is printed as missing, never replaced.

use std::path::PathBuf;
use std::time::Instant;

use clap::Parser;
use lifegom_eval::folders::score_folders;
use lifegom_eval::perceptual::PerceptualModels;
use lifegom_render::device::DeviceChoice;

#[derive(Parser, Debug)]
#[command(about = "PSNR, SSIM, LPIPS and FID between two folders of images")]
struct Args {
    /// First folder (e.g. predictions).
    a: PathBuf,
    /// Second folder (e.g. ground truth), with the same file names.
    b: PathBuf,
    /// One JSON line with every figure, the counts and the time.
    #[arg(long)]
    json: bool,
    /// Weights folder (default: $LIFEGOM_WEIGHTS, else weights/).
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Backend: flex, ndarray or wgpu.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    let device = args.device.device();
    let dir = args.weights.unwrap_or_else(PerceptualModels::default_dir);
    let models = PerceptualModels::discover(&dir, &device)?;
    let start = Instant::now();
    let s = score_folders(&args.a, &args.b, &models, &device)?;
    let seconds = start.elapsed().as_secs_f64();
    if args.json {
        let mut v = serde_json::to_value(&s)?;
        v["seconds"] = serde_json::json!(seconds);
        v["lpips_star_vgg"] = serde_json::json!(s.lpips_vgg.map(|x| x * 1000.0));
        if let Some(obj) = v.as_object_mut() {
            obj.remove("per_pair");
        }
        println!("{v}");
        return Ok(());
    }
    let show = |x: Option<f64>, digits: usize| {
        x.map_or_else(
            || "not computed (weights missing)".to_string(),
            |v| format!("{v:.digits$}"),
        )
    };
    println!(
        "pairs          {} ({} identical)",
        s.pairs, s.identical_pairs
    );
    println!("PSNR           {}", show(s.psnr, 2));
    println!("SSIM           {:.4}", s.ssim);
    println!("LPIPS-alex     {}", show(s.lpips_alex, 4));
    println!("LPIPS-vgg      {}  (LPIPS* = ×1000)", show(s.lpips_vgg, 4));
    println!(
        "FID            {}  ({} vs {} images; comparable only at equal counts)",
        show(s.fid, 2),
        s.fid_images_a,
        s.fid_images_b
    );
    for m in &s.missing_weights {
        println!("missing weights: {m} (run `lifegom-weights fetch`)");
    }
    println!("{seconds:.1} s");
    Ok(())
}
