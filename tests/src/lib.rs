//! Shared helpers for lifegom's cross-crate test suites (`tests/tests/*.rs`): seeded random
//! numbers, tiny scenes, and the "finite outputs and finite gradients" check.

#![allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it on purpose.

use burn::tensor::{Device, Tensor, TensorData};
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::gom::{GomParams, gaussians_from_triangles};
use lifegom_render::rasterizer::{Gaussians, RasterSettings, Rendered, rasterize};

/// The CPU devices every suite runs on.
pub fn cpu_devices() -> [(&'static str, Device); 2] {
    [("ndarray", Device::ndarray()), ("flex", Device::flex())]
}

pub use lifegom_render::rng::Rng;

/// A camera at `eye` looking at the origin with focal `f` and a centred principal point.
pub fn camera(eye: glam::Vec3, width: u32, height: u32, f: f32) -> Camera {
    let k = Intrinsics {
        fx: f,
        fy: f,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
    };
    Camera::look_at(eye, glam::Vec3::ZERO, glam::Vec3::Y, k, width, height)
        .expect("valid test camera")
}

/// A `[rows, cols]` tensor from a flat vector.
pub fn tensor2(values: Vec<f32>, cols: usize, device: &Device) -> Tensor<2> {
    let rows = values.len().checked_div(cols).unwrap_or(0);
    Tensor::from_data(TensorData::new(values, [rows, cols]), device)
}

pub use lifegom_render::testing::read;

/// Asserts every value is finite, naming what and where.
pub fn assert_finite(what: &str, values: &[f32]) {
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        panic!("{what}: non-finite value {} at {i}", values[i]);
    }
}

/// Renders Gaussians given as host data on `device.autodiff()`, backpropagates a weighted sum
/// of every output channel, and asserts the image and all four input gradients are finite.
/// Returns the image.
pub fn render_finite(
    case: &str,
    device: &Device,
    means: Vec<f32>,
    covariances: Vec<f32>,
    colors: Vec<f32>,
    opacities: Vec<f32>,
    settings: &RasterSettings,
) -> Vec<f32> {
    let ad = device.clone().autodiff();
    let n = opacities.len();
    let g = Gaussians {
        means: tensor2(means, 3, &ad).require_grad(),
        covariances: tensor2(covariances, 6, &ad).require_grad(),
        colors: tensor2(colors, 3, &ad).require_grad(),
        opacities: Tensor::<1>::from_data(TensorData::new(opacities, [n]), &ad).require_grad(),
    };
    let out: Rendered = rasterize(&g, settings).unwrap_or_else(|e| panic!("{case}: {e}"));
    let image = read(out.image.clone());
    assert_finite(&format!("{case}: image"), &image);
    let weights = Tensor::<3>::from_data(
        TensorData::new(
            (0..image.len())
                .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
                .collect(),
            out.image.dims(),
        ),
        &ad,
    );
    let grads = (out.image * weights).sum().backward();
    for (name, grad) in [
        ("means", g.means.grad(&grads)),
        ("covariances", g.covariances.grad(&grads)),
        ("colors", g.colors.grad(&grads)),
    ] {
        if let Some(grad) = grad {
            assert_finite(&format!("{case}: d/d{name}"), &read(grad));
        }
    }
    if let Some(grad) = g.opacities.grad(&grads) {
        assert_finite(&format!("{case}: d/dopacities"), &read(grad));
    }
    image
}

/// Gaussians as host data plus render settings: one scene, renderable on any device.
#[derive(Debug, Clone)]
pub struct Scene {
    /// What the scene tests, for failure messages.
    pub name: String,
    /// `[N*3]`.
    pub means: Vec<f32>,
    /// `[N*6]`.
    pub covariances: Vec<f32>,
    /// `[N*3]`.
    pub colors: Vec<f32>,
    /// `[N]`.
    pub opacities: Vec<f32>,
    /// Camera, channels, cutoff.
    pub settings: RasterSettings,
}

/// The weights of the parity loss `Σ w·image`: fixed, signed, uneven, so every channel and
/// pixel gets a distinct nonzero gradient.
pub fn loss_weights(len: usize) -> Vec<f32> {
    (0..len)
        .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
        .collect()
}

/// Renders `scene` on `device.autodiff()` and backpropagates [`loss_weights`]. Returns the image
/// and the gradients of means, covariances, colours and opacities (zeros where none reached).
pub fn render_with_grads(scene: &Scene, device: &Device) -> (Vec<f32>, [Vec<f32>; 4]) {
    let ad = device.clone().autodiff();
    let n = scene.opacities.len();
    let g = Gaussians {
        means: tensor2(scene.means.clone(), 3, &ad).require_grad(),
        covariances: tensor2(scene.covariances.clone(), 6, &ad).require_grad(),
        colors: tensor2(scene.colors.clone(), 3, &ad).require_grad(),
        opacities: Tensor::<1>::from_data(TensorData::new(scene.opacities.clone(), [n]), &ad)
            .require_grad(),
    };
    let out = rasterize(&g, &scene.settings).unwrap_or_else(|e| panic!("{}: {e}", scene.name));
    let image = read(out.image.clone());
    let weights = Tensor::<3>::from_data(
        TensorData::new(loss_weights(image.len()), out.image.dims()),
        &ad,
    );
    let grads = (out.image * weights).sum().backward();
    let grad2 = |t: &Tensor<2>, len: usize| t.grad(&grads).map(read).unwrap_or(vec![0.0; len]);
    let d_opacities = g.opacities.grad(&grads).map(read).unwrap_or(vec![0.0; n]);
    (
        image,
        [
            grad2(&g.means, 3 * n),
            grad2(&g.covariances, 6 * n),
            grad2(&g.colors, 3 * n),
            d_opacities,
        ],
    )
}

/// Forward tolerance of a backend against the CPU op: absolute, per pixel and channel.
pub const PARITY_FORWARD_ABS: f32 = 1e-4;
/// Gradient tolerance of a backend against the CPU op, relative.
///
/// Per element, `|got − want| ≤ 1e-3·(|want| + 1e-2·max|want|)`: relative to the element, with
/// a floor at 1% of the largest element of that gradient, because backends sum the per-pixel
/// contributions in different orders (GPU atomics), and an element that is a near-cancelling
/// sum of large terms carries rounding relative to the terms, not to the result.
pub const PARITY_GRAD_REL: f32 = 1e-3;

/// Renders `scene` on `device` and on the CPU reference (ndarray) and asserts the image and all
/// four gradients agree within [`PARITY_FORWARD_ABS`] and [`PARITY_GRAD_REL`]. The one test
/// body every backend runs.
pub fn assert_parity(scene: &Scene, device: &Device, device_name: &str) {
    let (want_image, want_grads) = render_with_grads(scene, &Device::ndarray());
    let (image, grads) = render_with_grads(scene, device);
    let case = format!("{device_name}/{}", scene.name);
    assert_eq!(image.len(), want_image.len(), "{case}: image size");
    assert_finite(&format!("{case}: image"), &image);
    for (i, (got, want)) in image.iter().zip(&want_image).enumerate() {
        assert!(
            (got - want).abs() <= PARITY_FORWARD_ABS,
            "{case}: image[{i}] = {got}, CPU op gives {want}"
        );
    }
    for (name, (got, want)) in ["means", "covariances", "colors", "opacities"]
        .iter()
        .zip(grads.iter().zip(&want_grads))
    {
        assert_eq!(got.len(), want.len(), "{case}: d/d{name} size");
        assert_finite(&format!("{case}: d/d{name}"), got);
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            let tol = PARITY_GRAD_REL * (w.abs() + 1e-2 * scale);
            assert!(
                (g - w).abs() <= tol,
                "{case}: d/d{name}[{i}] = {g}, CPU op gives {w} (tolerance {tol:e})"
            );
        }
    }
}

/// A seeded random scene: `n` Gaussians in front of a `width × height` camera, with random
/// anisotropic covariances (`AAᵀ` plus a small floor), colours, and opacities in `[0.05, 1]`.
pub fn random_scene(seed: u64, n: usize, width: u32, height: u32) -> Scene {
    let mut rng = Rng::new(seed);
    let mut means = Vec::with_capacity(3 * n);
    let mut covariances = Vec::with_capacity(6 * n);
    let mut colors = Vec::with_capacity(3 * n);
    let mut opacities = Vec::with_capacity(n);
    for _ in 0..n {
        means.extend([
            rng.range_f32(-0.6, 0.6),
            rng.range_f32(-0.5, 0.5),
            rng.range_f32(-0.8, 0.8),
        ]);
        let a: Vec<f32> = (0..9).map(|_| rng.range_f32(-0.12, 0.12)).collect();
        let m = |i: usize, j: usize| {
            (0..3).map(|k| a[3 * i + k] * a[3 * j + k]).sum::<f32>()
                + if i == j { 1e-4 } else { 0.0 }
        };
        covariances.extend([m(0, 0), m(0, 1), m(0, 2), m(1, 1), m(1, 2), m(2, 2)]);
        colors.extend([rng.range_f32(-0.2, 1.2), rng.next_f32(), rng.next_f32()]);
        opacities.push(rng.range_f32(0.05, 1.0));
    }
    Scene {
        name: format!("random scene {seed} ({n} Gaussians, {width}x{height})"),
        means,
        covariances,
        colors,
        opacities,
        settings: RasterSettings::new(camera(
            glam::Vec3::new(0.3, 0.2, 2.5),
            width,
            height,
            0.9 * width as f32,
        )),
    }
}

/// An isotropic 0.1-sigma covariance.
pub const ISO: [f32; 6] = [0.01, 0.0, 0.0, 0.01, 0.0, 0.01];

/// The hard suite's camera: on the +z axis at 2.5, looking at the origin, focal `0.8·w`.
pub fn front_camera(width: u32, height: u32) -> Camera {
    camera(
        glam::Vec3::new(0.0, 0.0, 2.5),
        width,
        height,
        0.8 * width as f32,
    )
}

/// Three corners (or, for per-face parameters, three 3-vectors: so3, scale, offset).
pub type Triangle = [[f32; 3]; 3];

/// The degenerate triangles of the hard suite (`hard_cases.rs`), each as the corner list.
pub fn hard_triangles() -> Vec<(&'static str, Vec<Triangle>)> {
    let eq_h = 3.0f32.sqrt() / 2.0 * 0.2;
    vec![
        ("point triangle", vec![[[0.1, 0.2, 0.0]; 3]]),
        (
            "collinear triangle",
            vec![[[0.0, 0.0, 0.0], [0.1, 0.1, 0.0], [0.2, 0.2, 0.0]]],
        ),
        (
            "two equal corners",
            vec![[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.2, 0.1, 0.0]]],
        ),
        (
            "sliver 1e-6 high",
            vec![[[-0.3, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 1e-6, 0.0]]],
        ),
        (
            "equilateral (inellipse is a circle)",
            vec![[[-0.1, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, eq_h, 0.0]]],
        ),
        (
            "micro triangle 1e-7 m",
            vec![[[0.0, 0.0, 0.0], [1e-7, 0.0, 0.0], [0.0, 1e-7, 0.0]]],
        ),
    ]
}

/// Single Gaussians in awkward places for [`front_camera`]`(40, 32)` (view depth = 2.5 − z):
/// `(name, mean, covariance)`. Shared by the hard suite (`hard_cases.rs`, which asserts what each
/// must cover) and the backend parity suite.
pub const AWKWARD_GAUSSIANS: [(&str, [f32; 3], [f32; 6]); 9] = [
    ("behind the camera", [0.0, 0.0, 4.0], ISO),
    (
        "at the near plane (view z = 0.2 up to rounding)",
        [0.0, 0.0, 2.3],
        ISO,
    ),
    ("just past the near plane", [0.0, 0.0, 2.2999], ISO),
    ("far off-screen", [1e4, -1e4, 0.0], ISO),
    (
        "centre off-screen, extent reaching in",
        [30.0, 0.0, 0.0],
        [900.0, 0.0, 0.0, 900.0, 0.0, 900.0],
    ),
    (
        "covering the whole image",
        [0.0, 0.0, 2.0],
        [4.0, 0.0, 0.0, 4.0, 0.0, 4.0],
    ),
    (
        "very large scale",
        [0.0, 0.0, 0.0],
        [1e8, 0.0, 0.0, 1e8, 0.0, 1e8],
    ),
    (
        "very small scale",
        [0.0, 0.0, 0.0],
        [1e-14, 0.0, 0.0, 1e-14, 0.0, 1e-14],
    ),
    (
        "degenerate (rank-1) covariance",
        [0.0, 0.1, 0.0],
        [0.04, 0.04, 0.0, 0.04, 0.0, 0.0],
    ),
];

/// Every rasterizer-level scene of the hard suite (`hard_cases.rs`), as host data: Gaussians in
/// awkward places, coincident and many opaque layers, empty/tiny/odd images, off-centre
/// principal points, and the Gaussians GoM builds from degenerate triangles (computed here on
/// the CPU, so every backend rasterizes the same values).
#[allow(clippy::vec_init_then_push)]
pub fn raster_hard_cases() -> Vec<Scene> {
    let mut scenes = Vec::new();
    let one = |name: &str, mean: [f32; 3], cov: [f32; 6], settings: RasterSettings| Scene {
        name: name.to_string(),
        means: mean.to_vec(),
        covariances: cov.to_vec(),
        colors: vec![0.9, 0.2, 0.1],
        opacities: vec![0.8],
        settings,
    };
    let s = RasterSettings::new(front_camera(40, 32)).with_depth();
    for (name, mean, cov) in AWKWARD_GAUSSIANS {
        scenes.push(one(name, mean, cov, s));
    }
    scenes.push(Scene {
        name: "coincident at equal depth".into(),
        means: [[0.0, 0.0, 0.0]; 2].concat(),
        covariances: [ISO; 2].concat(),
        colors: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        opacities: vec![0.6, 0.6],
        settings: s,
    });
    let k = 30;
    scenes.push(Scene {
        name: "30 opaque layers".into(),
        means: (0..k).flat_map(|i| [0.0, 0.0, i as f32 * 0.01]).collect(),
        covariances: [[1.0, 0.0, 0.0, 1.0, 0.0, 1.0]; 30].concat(),
        colors: vec![0.5; 3 * k],
        opacities: vec![1.0; k],
        settings: s,
    });
    scenes.push(Scene {
        name: "empty scene".into(),
        means: vec![],
        covariances: vec![],
        colors: vec![],
        opacities: vec![],
        settings: RasterSettings::new(front_camera(16, 16)),
    });
    let mut tiny = one(
        "1x1 image",
        [0.0; 3],
        ISO,
        RasterSettings::new(front_camera(1, 1)),
    );
    tiny.colors = vec![1.0; 3];
    tiny.opacities = vec![0.9];
    scenes.push(tiny);
    for (w, h) in [(37u32, 5u32), (3, 61), (17, 16)] {
        let mut odd = one(
            &format!("{w}x{h} image"),
            [0.05, -0.02, 0.0],
            ISO,
            RasterSettings::new(front_camera(w, h)),
        );
        odd.colors = vec![1.0; 3];
        odd.opacities = vec![0.9];
        scenes.push(odd);
    }
    for (cx, cy) in [(2.0, 30.0), (-10.0, 8.0), (60.0, -5.0)] {
        let mut cam = front_camera(32, 24);
        cam.intrinsics = Intrinsics {
            cx,
            cy,
            ..cam.intrinsics
        };
        scenes.push(Scene {
            name: format!("principal point ({cx},{cy})"),
            means: vec![0.1, 0.0, 0.0, -0.2, 0.1, 0.0],
            covariances: [ISO; 2].concat(),
            colors: vec![1.0; 6],
            opacities: vec![0.9, 0.9],
            settings: RasterSettings::new(cam),
        });
    }
    let cpu = Device::ndarray();
    let gom_settings = RasterSettings::new(front_camera(48, 40)).with_depth();
    let tri = vec![[[-0.1, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.15, 0.02]]];
    let mut geometry: Vec<(String, Vec<Triangle>, Option<Triangle>)> = hard_triangles()
        .into_iter()
        .map(|(name, tris)| (name.to_string(), tris, None))
        .collect();
    geometry.push(("zero scales".into(), tri.clone(), Some([[0.0; 3]; 3])));
    geometry.push((
        "negative scales, 2π rotation".into(),
        tri,
        Some([
            [0.0, 0.0, std::f32::consts::TAU],
            [-1.0, 2.0, -3.0],
            [0.5, -0.5, 10.0],
        ]),
    ));
    for (name, tris, params) in geometry {
        let f = tris.len();
        let corner = |k: usize| tensor2(tris.iter().flat_map(|t| t[k]).collect(), 3, &cpu);
        let mut p = GomParams::init(f, &cpu);
        if let Some([so3, scale, offset]) = params {
            let fill =
                |v: [f32; 3]| tensor2(v.iter().copied().cycle().take(3 * f).collect(), 3, &cpu);
            p.so3 = fill(so3);
            p.scales = fill(scale);
            p.offsets = fill(offset);
        }
        p.colors = tensor2(vec![0.7; 3 * f], 3, &cpu);
        let g = gaussians_from_triangles(corner(0), corner(1), corner(2), &p);
        scenes.push(Scene {
            name: format!("GoM: {name}"),
            means: read(g.means),
            covariances: read(g.covariances),
            colors: read(g.colors),
            opacities: read(g.opacities),
            settings: gom_settings,
        });
    }
    scenes
}

/// A square `size`-pixel camera on a 2.6 m orbit around the template's middle (0, 0.3, 0), at
/// `azimuth` (radians) and `rise` (the eye's height above the look-at point, in orbit radii).
pub fn body_camera(azimuth: f32, rise: f32, size: u32) -> Camera {
    let f = 1.6 * size as f32;
    let k = Intrinsics {
        fx: f,
        fy: f,
        cx: size as f32 / 2.0,
        cy: size as f32 / 2.0,
    };
    let look_at = glam::Vec3::new(0.0, 0.3, 0.0);
    let eye = look_at + 2.6 * glam::Vec3::new(azimuth.sin(), rise, azimuth.cos());
    Camera::look_at(eye, look_at, glam::Vec3::Y, k, size, size).expect("valid test camera")
}

/// The body template as a canonical subject (its own vertices, skin and skeleton).
pub fn template_subject(
    template: &lifegom_render::template::BodyTemplate,
    device: &Device,
) -> lifegom_model::reconstructor::CanonicalSubject {
    lifegom_model::reconstructor::CanonicalSubject {
        canonical_vertices: template.vertex_tensor(device),
        lbs_weights: template.skin.tensor(device),
        skeleton: template.skeleton.clone(),
    }
}

/// A known appearance for scenes whose truth must be recoverable: one colour per Gaussian of
/// `mesh`, varying smoothly with its face's centre in the canonical pose (`[F, 3]`).
pub fn pattern_colors(
    mesh: &lifegom_render::gom::GomMesh,
    canonical_vertices: Tensor<2>,
) -> Tensor<2> {
    let f = mesh.num_gaussians();
    let device = canonical_vertices.device();
    let centres = read(
        mesh.highres_vertices(canonical_vertices)
            .select(0, mesh.highres_faces().clone())
            .reshape([f, 3, 3])
            .mean_dim(1)
            .reshape([f, 3]),
    );
    let colors: Vec<f32> = centres
        .chunks_exact(3)
        .flat_map(|p| {
            [
                0.5 + 0.4 * (6.0 * p[1]).sin(),
                0.5 + 0.4 * (5.0 * p[0]).cos(),
                0.5 + 0.3 * (4.0 * (p[0] + p[1])).sin(),
            ]
        })
        .collect();
    Tensor::from_data(TensorData::new(colors, [f, 3]), &device)
}

/// The body template at `template` as an avatar at `levels` subdivisions: its own vertices,
/// skin and skeleton, the initial Gaussians, coloured by [`pattern_colors`].
pub fn patterned_avatar(
    template: &std::path::Path,
    levels: u32,
    device: &Device,
) -> lifegom_model::avatar::Avatar {
    let body = lifegom_render::template::BodyTemplate::load(template).expect("template loads");
    let mesh = lifegom_render::gom::GomMesh::new(&body.topology, levels, device)
        .expect("template subdivides");
    let subject = template_subject(&body, device);
    let mut faces = GomParams::init(mesh.num_gaussians(), device);
    faces.colors = pattern_colors(&mesh, subject.canonical_vertices.clone());
    lifegom_model::avatar::Avatar::new(
        subject.canonical_vertices,
        faces,
        subject.lbs_weights,
        subject.skeleton,
        mesh,
    )
}
