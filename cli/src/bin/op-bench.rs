//! `op-bench`: what the small CPU custom ops save against the Burn ops they replace, at the
//! sizes of a quickstart training step (design.md §1.4, §7.4).
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin op-bench
//! ```
//!
//! Each case runs one op forward and backward on the autodiff Flex device (output summed,
//! backward, the input's gradient read back), once through the custom op and once through Burn's
//! ops on the same input, alternating within one process: the VM's speed drifts between runs by
//! more than these differences. Prints one JSON line per case with both medians.
//!
//! - `dropout`: [`dropout_with`] (the host op: mask drawn and applied in one pass, kept as bits)
//!   against drawing the same mask into a float tensor and multiplying, which it replaced.
//! - `gather`: [`select_rows`] along the first dimension (the host gather op, whose backward
//!   sums on rayon's threads) against Burn's `select`.

use std::time::Instant;

use anyhow::Context;
use burn::nn::DropoutConfig;
use burn::tensor::{Device, Distribution, Int, Tensor, TensorData};
use clap::Parser;
use lifegom_model::dropout::{MaskSeed, MaskStream, dropout_with};
use lifegom_render::readback;
use lifegom_render::select::select_rows;

#[derive(Parser, Debug)]
#[command(about = "Benchmark the small CPU custom ops against the Burn ops they replace")]
struct Args {
    /// Timed calls per variant (medians reported), after one warm-up each.
    #[arg(long, default_value_t = 40)]
    runs: usize,
}

/// One forward + backward, in milliseconds.
type Call<'a> = Box<dyn Fn() -> anyhow::Result<f64> + 'a>;

/// Times `f`: forward, sum, backward, the gradient of `x` read back.
fn timed<const D: usize, const E: usize>(
    x: &Tensor<D>,
    f: impl Fn(Tensor<D>) -> Tensor<E>,
) -> anyhow::Result<f64> {
    let start = Instant::now();
    let grads = f(x.clone()).sum().backward();
    let grad = x.grad(&grads).context("the input takes part")?;
    readback::read::<f32, D, _>("input gradient", grad)?;
    Ok(start.elapsed().as_secs_f64() * 1e3)
}

/// Medians of the two calls, alternated `runs` times after a warm-up each.
fn compare(ours: Call<'_>, burns: Call<'_>, runs: usize) -> anyhow::Result<[f64; 2]> {
    ours()?;
    burns()?;
    let mut times = [Vec::new(), Vec::new()];
    for _ in 0..runs.max(1) {
        times[0].push(ours()?);
        times[1].push(burns()?);
    }
    Ok(times.map(|mut t| {
        t.sort_by(f64::total_cmp);
        (t[t.len() / 2] * 1000.0).round() / 1000.0
    }))
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    let device = Device::flex().autodiff();
    let normal = Distribution::Normal(0.0, 1.0);
    let print = |case: serde_json::Value, [ours, burns]: [f64; 2]| {
        let mut line = case;
        line["custom_op_ms"] = ours.into();
        line["burn_ops_ms"] = burns.into();
        println!("{line}");
    };

    // The fusion's dropouts at the quickstart's size (1229 vertices, N = 3, D = 144): per call
    // two over the views' tokens and two over the query, six calls per training step.
    let layer = DropoutConfig::new(0.1).init();
    for shape in [[1229, 3, 144], [1229, 1, 144]] {
        let x = Tensor::<3>::random(shape, normal, &device).require_grad();
        let stream = MaskStream { keep: 0.9, seed: 7 };
        let n = shape.iter().product();
        let ours: Call = Box::new(|| {
            timed(&x, |x| {
                dropout_with(&layer, x, MaskSeed::Given(stream.seed))
            })
        });
        let burns: Call = Box::new(|| {
            timed(&x, |x| {
                x * Tensor::<3>::from_data(TensorData::new(stream.values(n), shape), &device)
            })
        });
        let case = serde_json::json!({
            "bench": "op", "op": "dropout", "shape": shape,
        });
        print(case, compare(ours, burns, args.runs)?);
    }

    // Gathers the size of the Point Transformer's at its first level (8 neighbours of each of
    // 1229 points, 8 or 32 channels) and of the face heads' corners (3 of 4914 vertices for each
    // of 9816 faces).
    for (rows, n, width) in [
        (1229, 1229 * 8, 8),
        (1229, 1229 * 8, 32),
        (4914, 9816 * 3, 32),
    ] {
        let x = Tensor::<2>::random([rows, width], normal, &device).require_grad();
        let index: Vec<i64> = (0..n as i64).map(|i| (i * 7919) % rows as i64).collect();
        let index = Tensor::<1, Int>::from_data(TensorData::new(index, [n]), &device);
        let ours: Call = Box::new(|| timed(&x, |x| select_rows(x, 0, index.clone())));
        let burns: Call = Box::new(|| timed(&x, |x| x.select(0, index.clone())));
        let case = serde_json::json!({
            "bench": "op", "op": "gather", "rows": rows, "indices": n, "width": width,
        });
        print(case, compare(ours, burns, args.runs)?);
    }
    Ok(())
}
