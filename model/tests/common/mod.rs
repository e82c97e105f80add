//! The tests' shared fixture: a tiny model reconstructing the low-res template from random
//! images. Each test binary using it holds one test, because Burn's device RNG is process-wide:
//! tests running in parallel in one process would draw from it between `seed` and `init`.

// Each test binary uses part of the fixture.
#![allow(dead_code)]

use burn::tensor::{Device, Distribution, Tensor};
use glam::Vec3;
use lifegom_model::reconstructor::{
    CanonicalSubject, HostConcurrency, ReconstructorConfig, SourceViews,
};
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::gom::GomMesh;
use lifegom_render::skeleton::BodyPose;
use lifegom_render::template::{BodyTemplate, lowres_template_path};

/// [`reconstruct_with`] for one view in the default mode.
pub fn reconstruct(device: &Device, seed: u64) -> Vec<f32> {
    reconstruct_with(device, seed, 1, HostConcurrency::default())
}

/// The avatar's vertices and colours for `views` source views; on an autodiff device (training:
/// dropout draws masks) also the gradient of their sum at the vertex embedding.
pub fn reconstruct_with(
    device: &Device,
    seed: u64,
    views: usize,
    concurrency: HostConcurrency,
) -> Vec<f32> {
    reconstruct_parts(device, seed, views, concurrency)
        .into_iter()
        .flat_map(|(_, values)| values)
        .collect()
}

/// [`reconstruct_with`]'s values, named: `xyz`, `colors`, and on an autodiff device
/// `vertex_embed_grad`.
pub fn reconstruct_parts(
    device: &Device,
    seed: u64,
    views: usize,
    concurrency: HostConcurrency,
) -> Vec<(&'static str, Vec<f32>)> {
    device.seed(seed);
    let body = BodyTemplate::load(lowres_template_path()).unwrap();
    let k = Intrinsics {
        fx: 25.6,
        fy: 25.6,
        cx: 16.0,
        cy: 16.0,
    };
    let cameras: Vec<Camera> = [Vec3::new(0.0, 0.1, 2.5), Vec3::new(2.0, 0.1, -1.5)]
        .into_iter()
        .take(views)
        .map(|eye| Camera::look_at(eye, Vec3::new(0.0, 0.1, 0.0), Vec3::Y, k, 32, 32).unwrap())
        .collect();
    let rest = body
        .skeleton
        .skinning_transforms(&BodyPose::rest(body.num_joints()))
        .unwrap();
    let subject = CanonicalSubject {
        canonical_vertices: body.vertex_tensor(device),
        lbs_weights: body.skin.tensor(device),
        skeleton: body.skeleton.clone(),
    };
    let sources = SourceViews {
        images: Tensor::random([views, 3, 32, 32], Distribution::Uniform(0.0, 1.0), device),
        skinning: vec![rest; cameras.len()],
        cameras,
        background: [1.0; 3],
    };
    let mesh = GomMesh::new(&body.topology, 0, device).unwrap();
    let model = ReconstructorConfig::tiny(views)
        .with_iterations(2)
        .init(body.num_vertices(), device)
        .unwrap()
        .with_concurrency(concurrency);
    let avatar = model.reconstruct(&subject, &mesh, &sources).unwrap();
    let values = |t: Tensor<2>| t.into_data().try_into_vec_as::<f32>().unwrap();
    let mut out = vec![
        ("xyz", values(avatar.xyz.clone())),
        ("colors", values(avatar.faces.colors.clone())),
    ];
    if device.is_autodiff() {
        let grads = (avatar.xyz.sum() + avatar.faces.colors.sum()).backward();
        let embed = model
            .vertex_embed
            .val()
            .grad(&grads)
            .expect("the embedding takes part");
        out.push(("vertex_embed_grad", values(embed)));
    }
    out
}
