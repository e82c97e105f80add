//! `turntable`: renders the body template as Gaussians-on-Mesh from a ring of views, to PNGs.
//!
//! ```text
//! cargo run --release -p lifegom-cli --bin turntable -- --out out/turntable
//! ```
//!
//! The whole forward path runs: the template is posed (arms lowered) by forward kinematics and
//! linear blend skinning, subdivided, turned into one Gaussian per face on its Steiner frame,
//! and splatted. The turn is a global body rotation folded into the camera (as the reference
//! does with `Rh`), and each face is shaded by its normal under a light fixed to the camera.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use burn::tensor::{Tensor, TensorData};
use clap::Parser;
use glam::Vec3;
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::device::DeviceChoice;
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::rasterizer::{RasterSettings, rasterize};
use lifegom_render::skeleton::BodyPose;
use lifegom_render::skinning::skin_points;
use lifegom_render::template::{BodyTemplate, full_template_path};

#[derive(Parser, Debug)]
#[command(about = "Render the body template as a turntable of PNGs")]
struct Args {
    /// Body template (.glb); defaults to the shipped full-resolution template.
    #[arg(long)]
    template: Option<PathBuf>,
    /// Output folder.
    #[arg(long, default_value = "out/turntable")]
    out: PathBuf,
    /// Number of views around the body.
    #[arg(long, default_value_t = 8)]
    frames: usize,
    /// Image side, pixels.
    #[arg(long, default_value_t = 384)]
    size: u32,
    /// Subdivision levels (each ×4 Gaussians).
    #[arg(long, default_value_t = 1)]
    subdiv: u32,
    /// Backend: ndarray or flex.
    #[arg(long, default_value = "flex")]
    device: DeviceChoice,
}

fn main() -> anyhow::Result<()> {
    lifegom_cli::allocator::keep_freed_memory();
    lifegom_cli::init_tracing();
    let args = Args::parse();
    // SAFETY: the first thing `main` does after parsing; no thread has started yet.
    unsafe { lifegom_cli::make_default_device(args.device) };
    let path = args.template.clone().unwrap_or_else(full_template_path);
    let body = BodyTemplate::load(&path).with_context(|| format!("loading {}", path.display()))?;
    let device = args.device.device();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;

    // Lower both arms from the T-pose by 65° about the body's forward axis.
    let mut pose = BodyPose::rest(body.num_joints());
    for name in ["upperarm01.L", "upperarm01.R"] {
        let j = body
            .skeleton
            .joint_index(name)
            .with_context(|| format!("template has no joint {name}"))?;
        let side = body.skeleton.rest_joints[j].x.signum();
        pose.joint_rotations[j] = Vec3::Z * (-side * 65f32.to_radians());
    }
    let transforms = body.skeleton.skinning_transforms(&pose)?;
    let posed = skin_points(&body.vertices, &body.skin, &transforms)?;

    let mesh = GomMesh::new(&body.topology, args.subdiv, &device)?;
    let highres = mesh.subdivision.highres_vertices_cpu(&posed);
    let normals: Vec<Vec3> = mesh
        .subdivision
        .highres
        .faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| highres[i as usize]);
            (b - a).cross(c - a).normalize_or_zero()
        })
        .collect();
    let n = mesh.num_gaussians();
    let vertices = Tensor::<2>::from_data(
        TensorData::new(
            posed.iter().flat_map(|v| v.to_array()).collect::<Vec<_>>(),
            [posed.len(), 3],
        ),
        &device,
    );

    let size = args.size;
    let f = 0.8 * size as f32;
    let base = Camera::look_at(
        Vec3::new(0.0, 0.1, 2.6),
        Vec3::new(0.0, 0.1, 0.0),
        Vec3::Y,
        Intrinsics::centered(f, size, size),
        size,
        size,
    )?;
    let skin = Vec3::new(0.85, 0.66, 0.55);
    let light_world = Vec3::new(0.3, 0.5, 1.0).normalize();
    for frame in 0..args.frames {
        let start = Instant::now();
        let angle = frame as f32 / args.frames as f32 * std::f32::consts::TAU;
        let rh = Vec3::Y * angle;
        let camera = base.with_body_transform(rh, Vec3::ZERO)?;
        // The light is fixed to the camera; in the body frame it turns the other way.
        let light = lifegom_render::skeleton::rodrigues(rh).transpose() * light_world;
        let colors: Vec<f32> = normals
            .iter()
            .flat_map(|nrm| (skin * (0.3 + 0.7 * nrm.dot(light).abs())).to_array())
            .collect();
        let mut params = GomParams::init(n, &device);
        params.colors = Tensor::from_data(TensorData::new(colors, [n, 3]), &device);
        let gaussians = mesh.gaussians(vertices.clone(), &params);
        let rendered = rasterize(&gaussians, &RasterSettings::new(camera))?;
        let rgb: Vec<f32> =
            lifegom_render::readback::read("turntable frame", rendered.over([1.0, 1.0, 1.0]))?;
        let pixels: Vec<u8> = rgb
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
            .collect();
        let file = args.out.join(format!("frame_{frame:03}.png"));
        lifegom_render::atomic_file::write_png(
            &file,
            &pixels,
            size,
            size,
            image::ExtendedColorType::Rgb8,
        )
        .with_context(|| format!("writing {}", file.display()))?;
        println!(
            "{}",
            serde_json::json!({"frame": frame, "file": file.display().to_string(), "gaussians": n, "size": size, "ms": start.elapsed().as_secs_f64() * 1e3})
        );
    }
    Ok(())
}
