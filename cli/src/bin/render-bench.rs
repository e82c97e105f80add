//! `render-bench`: how long the Gaussian rasterizer takes on a body template, and what each
//! optional piece of work costs (input validation, the depth channel, the backward pass); also
//! the triangle-ID visibility pass over the same subdivided mesh, as the feedback loop runs it
//! once per source view.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin render-bench -- --size 512 --subdiv 2 --json
//! ```
//!
//! Renders the template's Gaussians in the initial GoM state (rotation 0, scale 1, offset 0,
//! opacity 1) from one camera 2.5 m in front of the body with `fx = 0.8·W`, and prints one JSON
//! line. Every time is the median of `--runs` runs after one warm-up, and includes reading the
//! result back to the host (touching the bytes: see `device::wait_for_values`), so lazy
//! backends cannot hide work.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use burn::tensor::{Device, Tensor};
use clap::Parser;
use glam::Vec3;
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::device::DeviceChoice;
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::rasterizer::{Gaussians, RasterSettings, Validation, rasterize};
use lifegom_render::template::{BodyTemplate, full_template_path};
use lifegom_render::visibility::rasterize_on_device;

#[derive(Parser, Debug)]
#[command(about = "Benchmark the Gaussian rasterizer on a body template")]
struct Args {
    /// Body template (.glb); defaults to the shipped full-resolution template.
    #[arg(long)]
    template: Option<PathBuf>,
    /// Image side in pixels (square images).
    #[arg(long, default_value_t = 512)]
    size: u32,
    /// Midpoint subdivision levels applied to the template (each ×4 Gaussians).
    #[arg(long, default_value_t = 2)]
    subdiv: u32,
    /// Backend: ndarray, flex or wgpu (a GPU, or Mesa lavapipe on the CPU).
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
    /// Timed runs per measurement (the median is reported).
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Print one JSON line (otherwise a human-readable summary as well).
    #[arg(long)]
    json: bool,
    /// Pixel groups per tile in the GPU backward (1, 2, 4 or 8; by default 8). `1` is the
    /// one-cube-per-tile backward of 954c62a (2026-11-28) and before.
    #[arg(long)]
    pixel_groups: Option<u32>,
}

fn median_ms(runs: usize, mut f: impl FnMut()) -> f64 {
    f(); // warm-up: first-touch allocations, thread-pool start
    let mut times: Vec<f64> = (0..runs.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

fn sync<const D: usize>(t: Tensor<D>) -> usize {
    lifegom_render::device::wait_for_values(t)
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    lifegom_render::rasterizer::force_backward_pixel_groups(args.pixel_groups)
        .context("--pixel-groups")?;
    let template_path = args.template.clone().unwrap_or_else(full_template_path);
    let body = BodyTemplate::load(&template_path)
        .with_context(|| format!("loading {}", template_path.display()))?;
    if args.device == DeviceChoice::Wgpu && !lifegom_render::device::wgpu_available() {
        anyhow::bail!(
            "--device wgpu: no wgpu adapter (no GPU, and Mesa lavapipe is not installed)"
        );
    }
    let device: Device = args.device.device();
    let size = args.size;
    let f = 0.8 * size as f32;
    let camera = Camera::look_at(
        Vec3::new(0.0, 0.1, 2.5),
        Vec3::new(0.0, 0.1, 0.0),
        Vec3::Y,
        Intrinsics::centered(f, size, size),
        size,
        size,
    )?;

    let mesh = GomMesh::new(&body.topology, args.subdiv, &device)?;
    let n = mesh.num_gaussians();
    let params = GomParams::init(n, &device);
    let vertices = body.vertex_tensor(&device);
    let gom_ms = median_ms(args.runs, || {
        let g = mesh.gaussians(vertices.clone(), &params);
        sync(g.covariances);
    });
    let gaussians = mesh.gaussians(vertices.clone(), &params);

    let base = RasterSettings::new(camera).with_validation(Validation::ShapesOnly);
    let forward_ms = median_ms(args.runs, || {
        sync(rasterize(&gaussians, &base).expect("render").image);
    });
    let forward_validated_ms = median_ms(args.runs, || {
        sync(
            rasterize(&gaussians, &base.with_validation(Validation::Full))
                .expect("render")
                .image,
        );
    });
    let forward_depth_ms = median_ms(args.runs, || {
        sync(
            rasterize(&gaussians, &base.with_depth())
                .expect("render")
                .image,
        );
    });

    // Visibility as the feedback loop computes it: triangle IDs of the high-res mesh, then the
    // per-vertex mask, on the device.
    let highres = mesh.highres_vertices(vertices.clone());
    let faces = mesh.highres_faces().clone().reshape([n, 3]);
    let num_highres = mesh.subdivision.highres.num_vertices;
    let visibility_ms = median_ms(args.runs, || {
        let ids = rasterize_on_device(highres.clone(), faces.clone(), &camera).expect("ids");
        let visible = ids.visible_vertices(faces.clone(), num_highres);
        sync(visible.float());
    });
    // Sanity figure, comparable across backends: how many high-res vertices this view sees.
    let visible_vertices: i64 = {
        let ids = rasterize_on_device(highres.clone(), faces.clone(), &camera)?;
        ids.visible_vertices(faces.clone(), num_highres)
            .sum()
            .into_scalar::<i64>()
    };

    let ad = device.clone().autodiff();
    let leaf = |t: Tensor<2>| Tensor::<2>::from_data(t.into_data(), &ad).require_grad();
    let tracked = Gaussians {
        means: leaf(gaussians.means.clone()),
        covariances: leaf(gaussians.covariances.clone()),
        colors: leaf(gaussians.colors.clone()),
        opacities: Tensor::<1>::from_data(gaussians.opacities.clone().into_data(), &ad)
            .require_grad(),
    };
    let fwd_bwd_ms = median_ms(args.runs, || {
        let out = rasterize(&tracked, &base).expect("render");
        let grads = out.image.sum().backward();
        sync(tracked.means.grad(&grads).expect("mean gradient"));
        sync(
            tracked
                .covariances
                .grad(&grads)
                .expect("covariance gradient"),
        );
    });

    // The end-to-end differentiable path: low-res vertices → Gaussians → image → gradient.
    let vertices_ad = Tensor::<2>::from_data(vertices.into_data(), &ad).require_grad();
    let params_ad = GomParams::init(n, &ad);
    let mesh_ad = GomMesh::new(&body.topology, args.subdiv, &ad)?;
    let gom_fwd_bwd_ms = median_ms(args.runs.min(3), || {
        let g = mesh_ad.gaussians(vertices_ad.clone(), &params_ad);
        let out = rasterize(&g, &base).expect("render");
        let grads = out.image.sum().backward();
        sync(vertices_ad.grad(&grads).expect("vertex gradient"));
    });

    let line = serde_json::json!({
        "bench": "render",
        "backend": args.device.name(),
        "template": template_path.file_name().map(|s| s.to_string_lossy().into_owned()),
        "subdiv": args.subdiv,
        "gaussians": n,
        "size": size,
        "runtime": lifegom_render::device::cube_runtime_name(&device),
        "kernel_fusion": lifegom_render::device::KernelFusion::on_device(&device).map(|k| k.name()),
        "threads": rayon::current_num_threads(),
        "runs": args.runs,
        "pixel_groups": args.pixel_groups.map_or_else(|| "default".to_owned(), |g| g.to_string()),
        "forward_ms": round(forward_ms),
        "fwd_bwd_ms": round(fwd_bwd_ms),
        "backward_extra_ms": round(fwd_bwd_ms - forward_ms),
        "validation_extra_ms": round(forward_validated_ms - forward_ms),
        "depth_extra_ms": round(forward_depth_ms - forward_ms),
        "gom_geometry_ms": round(gom_ms),
        "gom_render_fwd_bwd_ms": round(gom_fwd_bwd_ms),
        "visibility_ms": round(visibility_ms),
        "visible_vertices": visible_vertices,
    });
    if !args.json {
        eprintln!(
            "{n} Gaussians at {size}² on {}: forward {forward_ms:.1} ms, forward+backward \
             {fwd_bwd_ms:.1} ms, visibility {visibility_ms:.1} ms",
            args.device.name()
        );
    }
    println!("{line}");
    Ok(())
}

fn round(ms: f64) -> f64 {
    (ms * 100.0).round() / 100.0
}
