//! The no-learning reconstructions on a scene whose truth is known: a template avatar with a
//! smooth colour pattern, seen by three source cameras and one novel target camera.
//!
//! - Projective texturing must recover the pattern far better than one colour: it reads the
//!   photos.
//! - Per-scene optimisation must lower its source-view loss and improve the novel view.

use burn::tensor::Device;
use lifegom_eval::baselines::{projective_texturing, template_one_colour};
use lifegom_eval::images::Image;
use lifegom_eval::metrics::{ImageRef, psnr};
use lifegom_model::avatar::Avatar;
use lifegom_model::inputs::ModelInputs;
use lifegom_model::reconstructor::{SourceViews, render_views};
use lifegom_render::camera::Camera;
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::skeleton::BodyPose;
use lifegom_render::template::{BodyTemplate, lowres_template_path};
use lifegom_tests::{body_camera, pattern_colors, template_subject};
use lifegom_train::fit::{FitConfig, fit};
use lifegom_train::losses::{LossWeights, UniformLaplacian};

const SIZE: u32 = 48;

struct Scene {
    inputs: ModelInputs,
    mesh: GomMesh,
    template: BodyTemplate,
}

/// Ground truth rendered from the template with colours that vary smoothly over the body.
fn scene(device: &Device) -> Scene {
    let template = BodyTemplate::load(lowres_template_path()).unwrap();
    let mesh = GomMesh::new(&template.topology, 1, device).unwrap();
    let subject = template_subject(&template, device);
    let rest = template
        .skeleton
        .skinning_transforms(&BodyPose::rest(template.num_joints()))
        .unwrap();
    let f = mesh.num_gaussians();
    let mut truth = GomParams::init(f, device);
    truth.colors = pattern_colors(&mesh, subject.canonical_vertices.clone());
    let cams: Vec<Camera> = [0.0f32, 2.1, 4.2, 1.0]
        .iter()
        .map(|&a| body_camera(a, 0.0, SIZE))
        .collect();
    let bg = [0.0; 3];
    let skinning = vec![rest.clone(); 4];
    let views = render_views(
        &mesh,
        &subject.canonical_vertices,
        &truth,
        &subject,
        &cams,
        &skinning,
        bg,
    )
    .unwrap();
    let inputs = ModelInputs {
        sources: SourceViews {
            images: views.rgb.clone().narrow(0, 0, 3),
            cameras: cams[..3].to_vec(),
            skinning: skinning[..3].to_vec(),
            background: bg,
        },
        source_masks: views.alpha.clone().narrow(0, 0, 3),
        target_camera: cams[3],
        target_skinning: rest,
        target_rgb: views.rgb.narrow(0, 3, 1).squeeze_dim(0),
        target_mask: views.alpha.narrow(0, 3, 1).squeeze_dim(0),
        subject,
    };
    Scene {
        inputs,
        mesh,
        template,
    }
}

fn target_psnr(avatar: &Avatar, inputs: &ModelInputs) -> f64 {
    let (pred, _) = lifegom_eval::evaluate::render_timed(
        avatar,
        inputs,
        &inputs.target_camera,
        &inputs.target_skinning,
    )
    .unwrap();
    let gt = Image::from_chw(inputs.target_rgb.clone()).unwrap();
    let shape = [gt.height, gt.width, 3];
    psnr(
        ImageRef::new(&pred.data, shape).unwrap(),
        ImageRef::new(&gt.data, shape).unwrap(),
        1.0,
    )
    .unwrap()
}

#[test]
fn projective_texturing_reads_the_photos() {
    let device = Device::flex();
    let s = scene(&device);
    let one = template_one_colour(&s.mesh, &s.inputs, &device).unwrap();
    let projected = projective_texturing(&s.mesh, &s.inputs, &device).unwrap();
    let (a, b) = (
        target_psnr(&one.avatar, &s.inputs),
        target_psnr(&projected.avatar, &s.inputs),
    );
    assert!(b > a + 3.0, "projective {b:.2} dB vs one colour {a:.2} dB");
}

#[test]
fn per_scene_fit_lowers_its_loss_and_improves_the_novel_view() {
    let device = Device::flex();
    let s = scene(&device);
    let start = template_one_colour(&s.mesh, &s.inputs, &device)
        .unwrap()
        .avatar;
    let laplacian =
        UniformLaplacian::new(&s.template.topology.faces, s.template.num_vertices()).unwrap();
    let before = target_psnr(&start, &s.inputs);
    let mut seen = Vec::new();
    let fitted = fit(
        &start,
        &s.inputs,
        &laplacian,
        &LossWeights::new(),
        &FitConfig::new(),
        30,
        |k, seconds, _| {
            seen.push((k, seconds));
            Ok(true)
        },
    )
    .unwrap();
    let after = target_psnr(&fitted, &s.inputs);
    assert_eq!(seen.len(), 30);
    assert!(seen.windows(2).all(|w| w[1].1 >= w[0].1), "{seen:?}");
    assert!(
        after > before + 1.0,
        "fit {after:.2} dB vs start {before:.2} dB"
    );
}
