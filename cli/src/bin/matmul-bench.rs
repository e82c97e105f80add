//! `matmul-bench`: Burn's matrix product on one device, for the shapes a training step issues.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin matmul-bench -- --device wgpu --runs 20
//! ```
//!
//! On an H200 a quickstart training step spent 220 of its 409 ms of kernel time in Burn's matmul,
//! 364 µs a launch, though its products are small (at most `[3,687 × 144]·[144 × 432]`;
//! BENCHMARKS.md, "On a GPU (NVIDIA H200, 2026-11-28, 954c62a → 6ad3593)"). The shapes below
//! are the ones `BURN_FUSION_LOG=full` lists for that step, plus the paper network's largest, in
//! the three forms a step uses them:
//!
//! - `forward`: `[m, k]·[k, n]`, a layer's product;
//! - `weight_grad`: `xᵀ·g` with `x: [k, m]` read through a transposed view, a layer's weight
//!   gradient as Burn's autodiff forms it: a small `[m, n]` output over a long `k`. A product
//!   tiled over its output gets a handful of cubes for it, each walking all of `k`;
//! - `split_k`: the same weight gradient as `S` products over `k`-chunks of `c` rows (128, 256
//!   and 512: a batched product `[S, m, c]·[S, c, n]`) and a sum over `S`: what a layer's
//!   backward could launch instead. The inputs are padded to whole chunks outside the timed
//!   region, so the figure is the two kernels' cost, not the padding's;
//! - `batched`: `[b, m, k]·[1, k, n]`, the Point Transformer's per-group products;
//! - `layer`: `relu(x·W + b)`, a layer with its bias and ReLU, as Burn's product and
//!   elementwise ops (`"kernel": "burn"`) and as the shared layer's product kernel with both in
//!   its launch (`"kernel": "shared"`, `lifegom_ops::shared_linear`);
//! - `layer_backward`: the same layer run by [`PASSES`] passes (as the feedback loop runs the
//!   Point Transformer's), forward and backward: `∂x` of each pass, `∂W` and `∂b`. Burn's
//!   autodiff (`"kernel": "burn"`: per pass a product for `∂x`, a weight-gradient product, a
//!   bias sum and the ReLU's mask, then additions) against the shared layer (`"shared"`: per
//!   pass one masked product, then one gradient kernel over every pass's rows and a sum over
//!   its chunks);
//! - `column_sum`: `Σ_rows g` of `g: [k, n]`, a layer's bias gradient (`m` = 1), as one
//!   `sum_dim(0)`; `chunked_column_sum`: the same as sums within `c`-row chunks, then over the
//!   chunks (`[S, c, n]` → `[S, 1, n]` → `[1, 1, n]`, the input padded outside the timed region).
//!
//! Every case runs `--runs` times after three warm-ups; each run's output is read back, so the
//! wall time per run includes a round trip. On CubeCL devices each launch is also timed on the
//! device (`lifegom_cli::launches`, resolved timing: kernels run one at a time), and the line
//! gives the device time per run of every kernel the case launched. Prints one JSON line per
//! case.

use std::time::Instant;

use anyhow::Context;
use burn::tensor::{Distribution, Tensor};
use clap::Parser;
use lifegom_cli::launches::{KernelTiming, LaunchCounter, LaunchTally};
use lifegom_ops::activation::Activation;
use lifegom_ops::shared_linear::SharedLinear;
use lifegom_render::device::{DeviceChoice, wait_for_values};

#[derive(Parser, Debug)]
#[command(about = "Benchmark Burn's matmul for the shapes of a training step")]
struct Args {
    /// Backend: ndarray, flex or wgpu (a GPU, or Mesa lavapipe on the CPU).
    #[arg(long, default_value = "wgpu")]
    device: DeviceChoice,
    /// Timed runs per case.
    #[arg(long, default_value_t = 20)]
    runs: usize,
    /// Leave out the paper network's shapes (seconds on a CPU).
    #[arg(long)]
    skip_paper: bool,
}

/// How a case forms its product.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Form {
    Forward,
    WeightGrad,
    SplitK { chunk: usize },
    Batched { batch: usize },
    ColumnSum,
    ChunkedColumnSum { chunk: usize },
    Layer { kernel: LayerKernel },
    LayerBackward { kernel: LayerKernel },
}

/// Passes through one layer in the `layer_backward` form.
const PASSES: usize = 3;

/// Which kernels run a `layer` case.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LayerKernel {
    /// Burn's product, then its elementwise ops for the bias and the ReLU.
    Burn,
    /// [`SharedLinear::forward_with`]: one launch on CubeCL devices.
    Shared,
}

impl Form {
    fn name(self) -> &'static str {
        match self {
            Form::Forward => "forward",
            Form::WeightGrad => "weight_grad",
            Form::SplitK { .. } => "split_k",
            Form::Batched { .. } => "batched",
            Form::ColumnSum => "column_sum",
            Form::ChunkedColumnSum { .. } => "chunked_column_sum",
            Form::Layer { .. } => "layer",
            Form::LayerBackward { .. } => "layer_backward",
        }
    }
}

/// One product `[m, k]·[k, n]` in one form.
#[derive(Debug, Clone, Copy)]
struct Case {
    form: Form,
    m: usize,
    k: usize,
    n: usize,
    /// Part of the paper network rather than the quickstart's tiny one.
    paper: bool,
}

impl Case {
    /// Floating-point operations: a multiply and an add per term of a product, an add per
    /// element of a column sum.
    fn flop(&self) -> f64 {
        let terms = (self.m * self.k * self.n) as f64;
        match self.form {
            Form::Batched { batch } => 2.0 * terms * batch as f64,
            Form::ColumnSum | Form::ChunkedColumnSum { .. } => terms,
            // Forward, `∂x` and `∂W` per pass.
            Form::LayerBackward { .. } => 6.0 * terms * PASSES as f64,
            _ => 2.0 * terms,
        }
    }
}

/// Rows of `k` per chunk in the split-k forms.
const SPLIT_K_CHUNKS: [usize; 3] = [128, 256, 512];

fn cases() -> Vec<Case> {
    let case = |form, m, k, n, paper| Case {
        form,
        m,
        k,
        n,
        paper,
    };
    let mut out = vec![
        // Forward products of the quickstart step (fusion log), largest first.
        case(Form::Forward, 3687, 144, 432, false),
        case(Form::Forward, 3687, 144, 144, false),
        case(Form::Forward, 1229, 144, 144, false),
        case(Form::Forward, 307, 16, 48, false),
        case(Form::Forward, 1229, 8, 8, false),
        case(Form::Forward, 4, 64, 64, false),
        case(Form::Batched { batch: 1229 }, 8, 2, 8, false),
        case(Form::Batched { batch: 76 }, 16, 8, 32, false),
        case(Form::Batched { batch: 307 }, 16, 4, 16, false),
        case(Form::Forward, 41154, 1152, 1152, true),
    ];
    // Layers with a bias and a ReLU: the quickstart's and the paper Point Transformer's widest.
    for (m, k, n, paper) in [
        (3687, 144, 144, false),
        (1229, 144, 144, false),
        (1229, 8, 8, false),
        (41154, 144, 144, true),
    ] {
        for kernel in [LayerKernel::Burn, LayerKernel::Shared] {
            out.push(case(Form::Layer { kernel }, m, k, n, paper));
        }
        for kernel in [LayerKernel::Burn, LayerKernel::Shared] {
            out.push(case(Form::LayerBackward { kernel }, m, k, n, paper));
        }
    }
    // Weight gradients: `[m, k]·[k, n]` with k the rows of the layer's input.
    for (m, k, n, paper) in [
        (144, 3687, 144, false),
        (144, 3687, 432, false),
        (8, 3687, 8, false),
        (16, 921, 16, false),
        (32, 228, 32, false),
        (64, 57, 64, false),
        (1152, 41154, 1152, true),
    ] {
        out.push(case(Form::WeightGrad, m, k, n, paper));
        for chunk in SPLIT_K_CHUNKS {
            if k > chunk {
                out.push(case(Form::SplitK { chunk }, m, k, n, paper));
            }
        }
    }
    // Bias gradients: the quickstart's stacked rows (3 passes × 3,712) and the paper's.
    for (k, n, paper) in [(11136, 144, false), (3712, 8, false), (41154, 1152, true)] {
        out.push(case(Form::ColumnSum, 1, k, n, paper));
        for chunk in SPLIT_K_CHUNKS {
            out.push(case(Form::ChunkedColumnSum { chunk }, 1, k, n, paper));
        }
    }
    out
}

/// The case's inputs, made before timing, and its product.
enum Inputs {
    Forward(Tensor<2>, Tensor<2>),
    /// `x: [k, m]`, `g: [k, n]`.
    WeightGrad(Tensor<2>, Tensor<2>),
    /// `x: [S, m, c]` (a transposed view, as the weight gradient reads it), `g: [S, c, n]`.
    SplitK(Tensor<3>, Tensor<3>),
    Batched(Tensor<3>, Tensor<3>),
    ColumnSum(Tensor<2>),
    /// `g: [S, c, n]`.
    ChunkedColumnSum(Tensor<3>),
    /// `x`, `W`, `b`.
    BurnLayer(Tensor<2>, Tensor<2>, Tensor<1>),
    /// `x` and the layer.
    SharedLayer(Tensor<2>, Box<SharedLinear>),
    /// Every pass's `x` `[m, k]`, `W`, `b` and the output weights `r` `[m, n]`, on the device
    /// with autodiff.
    LayerBackward {
        kernel: LayerKernel,
        xs: Vec<Tensor<2>>,
        w: Tensor<2>,
        b: Tensor<1>,
        r: Tensor<2>,
    },
}

impl Inputs {
    fn new(case: &Case, device: &burn::tensor::Device) -> Self {
        let normal = Distribution::Normal(0.0, 1.0);
        let Case { m, k, n, .. } = *case;
        match case.form {
            Form::Forward => Inputs::Forward(
                Tensor::random([m, k], normal, device),
                Tensor::random([k, n], normal, device),
            ),
            Form::WeightGrad => Inputs::WeightGrad(
                Tensor::random([k, m], normal, device),
                Tensor::random([k, n], normal, device),
            ),
            Form::SplitK { chunk } => {
                let x = padded(Tensor::random([k, m], normal, device), chunk).swap_dims(1, 2);
                let g = padded(Tensor::random([k, n], normal, device), chunk);
                Inputs::SplitK(x, g)
            }
            Form::ColumnSum => Inputs::ColumnSum(Tensor::random([k, n], normal, device)),
            Form::ChunkedColumnSum { chunk } => {
                Inputs::ChunkedColumnSum(padded(Tensor::random([k, n], normal, device), chunk))
            }
            Form::Layer { kernel } => {
                let x = Tensor::random([m, k], normal, device);
                let w = Tensor::random([k, n], normal, device);
                let b = Tensor::random([n], normal, device);
                match kernel {
                    LayerKernel::Burn => Inputs::BurnLayer(x, w, b),
                    LayerKernel::Shared => {
                        Inputs::SharedLayer(x, Box::new(SharedLinear::new(w, b)))
                    }
                }
            }
            Form::LayerBackward { kernel } => {
                let ad = device.clone().autodiff();
                let xs = (0..PASSES)
                    .map(|_| Tensor::random([m, k], normal, &ad).require_grad())
                    .collect();
                Inputs::LayerBackward {
                    kernel,
                    xs,
                    w: Tensor::random([k, n], normal, &ad).require_grad(),
                    b: Tensor::random([n], normal, &ad).require_grad(),
                    r: Tensor::random([m, n], normal, &ad),
                }
            }
            Form::Batched { batch } => Inputs::Batched(
                Tensor::random([batch, m, k], normal, device),
                Tensor::random([1, k, n], normal, device),
            ),
        }
    }

    /// One product, read back.
    fn run(&self) -> usize {
        match self {
            Inputs::Forward(a, b) => wait_for_values(a.clone().matmul(b.clone())),
            Inputs::WeightGrad(x, g) => wait_for_values(x.clone().transpose().matmul(g.clone())),
            Inputs::SplitK(x, g) => wait_for_values(x.clone().matmul(g.clone()).sum_dim(0)),
            Inputs::Batched(a, b) => wait_for_values(a.clone().matmul(b.clone())),
            Inputs::ColumnSum(g) => wait_for_values(g.clone().sum_dim(0)),
            Inputs::ChunkedColumnSum(g) => wait_for_values(g.clone().sum_dim(1).sum_dim(0)),
            Inputs::BurnLayer(x, w, b) => wait_for_values(burn::tensor::activation::relu(
                x.clone().matmul(w.clone()) + b.clone().unsqueeze_dim(0),
            )),
            Inputs::SharedLayer(x, layer) => {
                wait_for_values(layer.forward_with(x.clone(), Activation::Relu))
            }
            Inputs::LayerBackward {
                kernel,
                xs,
                w,
                b,
                r,
            } => {
                // One shared layer per reconstruction, as the model makes them.
                let shared = (*kernel == LayerKernel::Shared)
                    .then(|| SharedLinear::new(w.clone(), b.clone()));
                let total = xs
                    .iter()
                    .map(|x| {
                        let y = match &shared {
                            Some(layer) => layer.forward_with(x.clone(), Activation::Relu),
                            None => burn::tensor::activation::relu(
                                x.clone().matmul(w.clone()) + b.clone().unsqueeze_dim(0),
                            ),
                        };
                        (y * r.clone()).sum()
                    })
                    .reduce(|a, b| a + b)
                    .expect("at least one pass");
                let grads = total.backward();
                let read = |t: Option<Tensor<2>>| wait_for_values(t.expect("a gradient"));
                xs.iter().map(|x| read(x.grad(&grads))).sum::<usize>()
                    + read(w.grad(&grads))
                    + wait_for_values(b.grad(&grads).expect("a bias gradient"))
            }
        }
    }
}

/// `t` `[k, cols]` padded with zero rows to whole chunks of `chunk` rows, as `[S, chunk, cols]`.
fn padded(t: Tensor<2>, chunk: usize) -> Tensor<3> {
    let [k, cols] = t.dims();
    let s = k.div_ceil(chunk);
    let rows = s * chunk;
    let device = t.device();
    Tensor::cat(vec![t, Tensor::zeros([rows - k, cols], &device)], 0).reshape([s, chunk, cols])
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    let device = args.device.device();
    let runs = args.runs.max(1);
    for case in cases() {
        if args.skip_paper && case.paper {
            continue;
        }
        let inputs = Inputs::new(&case, &device);
        for _ in 0..3 {
            inputs.run();
        }
        // Wall times first, without device timing (which runs kernels one at a time).
        let mut wall: Vec<f64> = (0..runs)
            .map(|_| {
                let t = Instant::now();
                inputs.run();
                t.elapsed().as_secs_f64() * 1e6
            })
            .collect();
        wall.sort_by(f64::total_cmp);
        let mut line = serde_json::json!({
            "bench": "matmul",
            "backend": args.device.name(),
            "kernel_fusion": lifegom_render::device::KernelFusion::on_device(&device).map(|k| k.name()),
            "form": case.form.name(),
            "m": case.m,
            "k": case.k,
            "n": case.n,
            "gflop": case.flop() / 1e9,
            "runs": runs,
            "wall_us_median": (wall[runs / 2] * 10.0).round() / 10.0,
            "wall_us_min": (wall[0] * 10.0).round() / 10.0,
        });
        if let Form::Batched { batch } = case.form {
            line["batch"] = serde_json::json!(batch);
        }
        if let Form::Layer { kernel } | Form::LayerBackward { kernel } = case.form {
            line["kernel"] = serde_json::json!(match kernel {
                LayerKernel::Burn => "burn",
                LayerKernel::Shared => "shared",
            });
        }
        if let Form::SplitK { chunk } | Form::ChunkedColumnSum { chunk } = case.form {
            line["chunk"] = serde_json::json!(chunk);
            line["chunks"] = serde_json::json!(case.k.div_ceil(chunk));
        }
        if let Some(counter) = LaunchCounter::on_cube_device(&device, KernelTiming::Resolved) {
            inputs.run();
            counter.take();
            let per_run: Vec<LaunchTally> = (0..runs)
                .map(|_| {
                    inputs.run();
                    counter.take()
                })
                .collect();
            let fields = counter.json_fields(&per_run, 4);
            for key in [
                "kernel_launches",
                "kernel_device_ms_per_step",
                "top_kernels",
            ] {
                if let Some(v) = fields.get(key) {
                    line[key] = v.clone();
                }
            }
        }
        println!(
            "{}",
            serde_json::to_string(&line).context("formatting the JSON line")?
        );
    }
    Ok(())
}
