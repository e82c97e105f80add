//! Reconstruct an avatar from source views and render it in a new pose and view.
//!
//! ```text
//! cargo run --release -p lifegom-model --example reconstruct -- out/example
//! ```
//!
//! Without trained weights (the train command comes in a later issue) the network is randomly
//! initialised, so the avatar is the body template with untrained colours: this example shows
//! the API and the data flow, not reconstruction quality. It writes the source view it was
//! given, the avatar in a new pose, a `.lgom` file, a standard 3DGS `.ply` (with the Gaussians'
//! rig) and a rigged `.glb` of the canonical avatar that glTF tools pose (docs/export.md).

use std::path::PathBuf;

use burn::tensor::{Device, Tensor};
use glam::Vec3;
use lifegom_model::reconstructor::{CanonicalSubject, ReconstructorConfig, SourceViews};
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::rasterizer::{RasterSettings, rasterize};
use lifegom_render::skeleton::BodyPose;
use lifegom_render::template::{BodyTemplate, lowres_template_path};

fn save_png(path: &std::path::Path, rgb_hw3: Tensor<3>) -> anyhow::Result<()> {
    let [h, w, _] = rgb_hw3.dims();
    let v = rgb_hw3.into_data().try_into_vec_as::<f32>()?;
    let px: Vec<u8> = v
        .iter()
        .map(|x| (x.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect();
    image::save_buffer(
        path,
        &px,
        w as u32,
        h as u32,
        image::ExtendedColorType::Rgb8,
    )?;
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let out = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "out/example".into()),
    );
    std::fs::create_dir_all(&out)?;
    let device = Device::flex();
    let body = BodyTemplate::load(lowres_template_path())?;
    let size = 96u32;
    let k = Intrinsics {
        fx: 0.8 * size as f32,
        fy: 0.8 * size as f32,
        cx: size as f32 / 2.0,
        cy: size as f32 / 2.0,
    };
    let camera = |eye: Vec3| Camera::look_at(eye, Vec3::new(0.0, 0.1, 0.0), Vec3::Y, k, size, size);

    // Source views: here, renders of the grey template from three sides (stand-ins for photos).
    let rest = body
        .skeleton
        .skinning_transforms(&BodyPose::rest(body.num_joints()))?;
    let mesh = GomMesh::new(&body.topology, 1, &device)?;
    let mut grey = GomParams::init(mesh.num_gaussians(), &device);
    grey.colors = grey.colors.ones_like() * 0.6;
    let cameras: Vec<Camera> = [
        Vec3::new(0.0, 0.1, 2.5),
        Vec3::new(2.2, 0.1, -1.2),
        Vec3::new(-2.2, 0.1, -1.2),
    ]
    .into_iter()
    .map(camera)
    .collect::<Result<_, _>>()?;
    let mut images = Vec::new();
    for cam in &cameras {
        let g = mesh.gaussians(body.vertex_tensor(&device), &grey);
        images.push(
            rasterize(&g, &RasterSettings::new(*cam))?
                .over([1.0; 3])
                .permute([2, 0, 1]),
        );
    }
    let sources = SourceViews {
        images: Tensor::stack(images, 0),
        cameras,
        skinning: vec![rest; 3],
        background: [1.0; 3],
    };
    save_png(
        &out.join("source_0.png"),
        sources
            .images
            .clone()
            .narrow(0, 0, 1)
            .squeeze_dim(0)
            .permute([1, 2, 0]),
    )?;

    let subject = CanonicalSubject {
        canonical_vertices: body.vertex_tensor(&device),
        lbs_weights: body.skin.tensor(&device),
        skeleton: body.skeleton.clone(),
    };
    let model = ReconstructorConfig::tiny(3)
        .with_iterations(2)
        .init(body.num_vertices(), &device)?;
    eprintln!("no trained weights given: the reconstructor is randomly initialised");
    let avatar = model.reconstruct(&subject, &mesh, &sources)?;

    let mut pose = BodyPose::rest(body.num_joints());
    for (name, angle) in [("upperarm01.L", -1.0f32), ("upperarm01.R", 1.0)] {
        if let Some(j) = body.skeleton.joint_index(name) {
            pose.joint_rotations[j] = Vec3::new(0.0, 0.0, angle);
        }
    }
    let novel = avatar.render(&pose, &camera(Vec3::new(1.5, 0.6, 2.0))?)?;
    save_png(&out.join("novel_pose.png"), novel.over([1.0; 3]))?;
    avatar.save(out.join("avatar.lgom"))?;
    avatar.export_ply(&pose, out.join("avatar.ply"))?;
    avatar.export_glb(out.join("avatar.glb"))?;
    println!("wrote {}", out.display());
    Ok(())
}
