//! End-to-end gradient check: low-res vertices → 1→4 subdivision → Steiner frames → Gaussians →
//! rasterizer → weighted loss, against central differences. Uses the test-only smooth alpha cutoff so the rendered image
//! is C¹ in the vertices.

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec3;
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::mesh::MeshTopology;
use lifegom_render::rasterizer::{AlphaCutoff, RasterSettings, rasterize};
use lifegom_tests::{Rng, camera, cpu_devices, read, tensor2};

/// An octahedron of radius ~0.25 m, slightly irregular so no face is special.
fn octahedron(rng: &mut Rng) -> (MeshTopology, Vec<f32>) {
    let (mesh, unit) = lifegom_render::testing::octahedron();
    let vertices = unit
        .iter()
        .flat_map(|d| d.to_array().map(|c| c * 0.25 + rng.range_f32(-0.03, 0.03)))
        .collect();
    (mesh, vertices)
}

fn check(device: &Device) {
    let mut rng = Rng::new(5);
    let (topology, vertices) = octahedron(&mut rng);
    let (w, h) = (40u32, 32u32);
    let settings = RasterSettings::new(camera(Vec3::new(0.4, 0.3, 1.6), w, h, 40.0))
        .with_cutoff(AlphaCutoff::Smooth);
    let ad = device.clone().autodiff();
    let mesh = GomMesh::new(&topology, 1, &ad).unwrap();
    let f = mesh.num_gaussians();
    let colors: Vec<f32> = (0..3 * f).map(|_| rng.range_f32(0.1, 1.0)).collect();
    let weights: Vec<f32> = (0..(w * h * 4) as usize)
        .map(|_| rng.range_f32(-1.0, 1.0))
        .collect();
    let params = |dev: &Device| {
        let mut p = GomParams::init(f, dev);
        p.colors = tensor2(colors.clone(), 3, dev);
        // Thin-ish Gaussians: scales below 1 keep the opacity of overlaps away from the 0.99 clamp.
        p.scales = p.scales * 0.6;
        p.opacities = p.opacities * 0.7;
        p
    };
    let render = |v: &[f32], dev: &Device| {
        let g = mesh.gaussians(tensor2(v.to_vec(), 3, dev), &params(dev));
        rasterize(&g, &settings).unwrap().image
    };
    let loss_host = |v: &[f32]| -> f64 {
        let img = read(render(v, &ad));
        img.iter()
            .zip(&weights)
            .map(|(a, b)| *a as f64 * *b as f64)
            .sum()
    };

    let leaf = tensor2(vertices.clone(), 3, &ad).require_grad();
    let g = mesh.gaussians(leaf.clone(), &params(&ad));
    let image = rasterize(&g, &settings).unwrap().image;
    assert!(
        read(image.clone()).chunks(4).filter(|p| p[3] > 0.1).count() > 50,
        "the mesh must be in view"
    );
    let wt = Tensor::<3>::from_data(TensorData::new(weights.clone(), image.dims()), &ad);
    let grads = (image * wt).sum().backward();
    let analytic = read(leaf.grad(&grads).expect("vertex gradient"));
    for i in 0..vertices.len() {
        let central = |step: f32| {
            let (mut plus, mut minus) = (vertices.clone(), vertices.clone());
            plus[i] += step;
            minus[i] -= step;
            (loss_host(&plus) - loss_host(&minus)) / (2.0 * step as f64)
        };
        // Depth sorting makes splatting piecewise: two overlapping Gaussians whose depths cross
        // swap blending order and the image jumps. On this mesh such a crossing lies within
        // ±5e-4 m of two coordinates (seen as a wrong difference at that step), so the step must
        // stay below it; 1e-4 m still beats the f32 rounding noise.
        let numeric = central(1e-4);
        let a = analytic[i] as f64;
        let tol = 2e-2 * a.abs().max(numeric.abs()) + 0.05;
        assert!(
            (a - numeric).abs() <= tol,
            "vertex coordinate {i}: analytic {a} vs numeric {numeric}"
        );
    }
    assert!(
        analytic.iter().map(|g| g.abs()).fold(0.0, f32::max) > 1.0,
        "gradients must be non-trivial: {analytic:?}"
    );
}

#[test]
fn vertices_to_image_gradients_match_finite_differences() {
    for (_, device) in cpu_devices() {
        check(&device);
    }
}
