//! Tests of the rasterizer op. Every test body takes a device and runs on ndarray and Flex.

#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData};
use glam::Affine3A;

use super::cpu::{self, GaussianSlices};
use super::*;
use crate::camera::{Camera, Intrinsics};
use crate::rng::Rng;

crate::cpu_backend_tests!(
    isotropic_gaussian_renders_the_expected_bump,
    culled_and_transparent_gaussians_leave_the_image_unchanged,
    output_is_deterministic_and_order_independent,
    gradients_match_central_differences,
    depth_channel_and_its_gradient,
    non_finite_inputs_are_rejected,
);

/// Camera at the origin looking down +z (world = camera frame).
pub(crate) fn axis_camera(width: u32, height: u32, f: f32) -> Camera {
    let k = Intrinsics {
        fx: f,
        fy: f,
        cx: width as f32 / 2.0,
        cy: height as f32 / 2.0,
    };
    Camera::new(k, Affine3A::IDENTITY, width, height).unwrap()
}

/// Flat scene data on the host.
#[derive(Clone, Debug)]
pub(crate) struct Scene {
    pub means: Vec<f32>,
    pub covs: Vec<f32>,
    pub colors: Vec<f32>,
    pub opacities: Vec<f32>,
}

impl Scene {
    pub(crate) fn random(rng: &mut Rng, n: usize) -> Self {
        let mut s = Scene {
            means: vec![],
            covs: vec![],
            colors: vec![],
            opacities: vec![],
        };
        for _ in 0..n {
            s.means.extend([
                rng.range_f32(-0.4, 0.4),
                rng.range_f32(-0.3, 0.3),
                rng.range_f32(2.0, 4.0),
            ]);
            // Σ = L Lᵀ + small diagonal: symmetric positive definite, anisotropic.
            let l = [
                rng.range_f32(0.03, 0.15),
                rng.range_f32(-0.05, 0.05),
                rng.range_f32(0.03, 0.15),
                rng.range_f32(-0.05, 0.05),
                rng.range_f32(-0.05, 0.05),
                rng.range_f32(0.03, 0.15),
            ];
            let m = [[l[0], 0.0, 0.0], [l[1], l[2], 0.0], [l[3], l[4], l[5]]];
            let dot = |i: usize, j: usize| (0..3).map(|k| m[i][k] * m[j][k]).sum::<f32>();
            s.covs.extend([
                dot(0, 0),
                dot(0, 1),
                dot(0, 2),
                dot(1, 1),
                dot(1, 2),
                dot(2, 2),
            ]);
            s.colors.extend([
                rng.range_f32(0.0, 1.0),
                rng.range_f32(0.0, 1.0),
                rng.range_f32(0.0, 1.0),
            ]);
            s.opacities.push(rng.range_f32(0.3, 0.8));
        }
        s
    }

    pub(crate) fn len(&self) -> usize {
        self.opacities.len()
    }

    pub(crate) fn push(&mut self, mean: [f32; 3], cov: [f32; 6], color: [f32; 3], opacity: f32) {
        self.means.extend(mean);
        self.covs.extend(cov);
        self.colors.extend(color);
        self.opacities.push(opacity);
    }

    pub(crate) fn slices(&self) -> GaussianSlices<'_> {
        GaussianSlices {
            means: &self.means,
            covariances: &self.covs,
            colors: &self.colors,
            opacities: &self.opacities,
        }
    }

    pub(crate) fn gaussians(&self, device: &Device) -> Gaussians {
        let n = self.len();
        Gaussians {
            means: Tensor::from_data(TensorData::new(self.means.clone(), [n, 3]), device),
            covariances: Tensor::from_data(TensorData::new(self.covs.clone(), [n, 6]), device),
            colors: Tensor::from_data(TensorData::new(self.colors.clone(), [n, 3]), device),
            opacities: Tensor::from_data(TensorData::new(self.opacities.clone(), [n]), device),
        }
    }
}

pub(crate) use crate::testing::read;

fn isotropic_gaussian_renders_the_expected_bump(device: &Device) {
    let (w, h, f) = (40u32, 30u32, 50.0f32);
    let cam = axis_camera(w, h, f);
    let (z, sigma, opacity) = (2.0f32, 0.08f32, 0.7f32);
    let mut scene = Scene {
        means: vec![],
        covs: vec![],
        colors: vec![],
        opacities: vec![],
    };
    let v = sigma * sigma;
    scene.push(
        [0.0, 0.0, z],
        [v, 0.0, 0.0, v, 0.0, v],
        [0.2, 0.5, 1.0],
        opacity,
    );
    let out = rasterize(&scene.gaussians(device), &RasterSettings::new(cam)).unwrap();
    let img = read(out.image);
    // On the optical axis J = diag(f/z), so the 2D variance is (fσ/z)² + 0.3 in both axes, and
    // the projected centre (w/2, h/2) sits at (w/2 − ½, h/2 − ½) in the pixel-sampling frame.
    let var2 = (f * sigma / z).powi(2) + cpu::DILATION;
    let radius = (3.0 * var2.sqrt()).ceil();
    let (cx, cy) = (w as f32 / 2.0 - 0.5, h as f32 / 2.0 - 0.5);
    let mut checked = 0;
    for py in 0..h as usize {
        for px in 0..w as usize {
            let (dx, dy) = (px as f32 - cx, py as f32 - cy);
            let mut alpha = opacity * (-0.5 * (dx * dx + dy * dy) / var2).exp();
            if alpha < cpu::ALPHA_MIN || dx.abs() > radius + 16.0 || dy.abs() > radius + 16.0 {
                alpha = 0.0;
            }
            let p = &img[(py * w as usize + px) * 4..][..4];
            if dx.abs() <= radius && dy.abs() <= radius {
                assert!(
                    (p[3] - alpha).abs() < 1e-5,
                    "alpha at ({px},{py}): {} vs {alpha}",
                    p[3]
                );
                assert!((p[2] - alpha).abs() < 1e-5 && (p[0] - 0.2 * alpha).abs() < 1e-5);
                checked += 1;
            }
        }
    }
    assert!(checked > 50);
    // The peak is at the centre pixel pair and equals the opacity exp(-(½²+½²)/2/var).
    let centre = &img[((h as usize / 2) * w as usize + w as usize / 2) * 4..][..4];
    assert!((centre[3] - opacity * (-0.25 / var2).exp()).abs() < 1e-5);
}

fn culled_and_transparent_gaussians_leave_the_image_unchanged(device: &Device) {
    let cam = axis_camera(48, 32, 40.0);
    let mut rng = Rng::new(7);
    let scene = Scene::random(&mut rng, 12);
    let base = read(
        rasterize(&scene.gaussians(device), &RasterSettings::new(cam))
            .unwrap()
            .image,
    );
    let mut more = scene.clone();
    let cov = [0.01, 0.0, 0.0, 0.01, 0.0, 0.01];
    more.push([0.0, 0.0, -2.0], cov, [1.0, 0.0, 0.0], 0.9); // behind the camera
    more.push([0.0, 0.0, 0.1], cov, [1.0, 0.0, 0.0], 0.9); // in front of the near plane
    more.push([50.0, 0.0, 2.0], cov, [1.0, 0.0, 0.0], 0.9); // far off-screen
    more.push([0.0, 0.0, 3.0], cov, [1.0, 0.0, 0.0], 0.0); // fully transparent
    more.push([0.0, 0.0, 3.0], cov, [1.0, 0.0, 0.0], 0.002); // below the alpha cutoff everywhere
    let with_hidden = read(
        rasterize(&more.gaussians(device), &RasterSettings::new(cam))
            .unwrap()
            .image,
    );
    assert_eq!(base, with_hidden, "hidden Gaussians changed the image");

    // A Gaussian behind a saturated wall: pixels stop blending before they reach it.
    let mut wall = Scene {
        means: vec![],
        covs: vec![],
        colors: vec![],
        opacities: vec![],
    };
    for _ in 0..4 {
        wall.push(
            [0.0, 0.0, 2.0],
            [4.0, 0.0, 0.0, 4.0, 0.0, 0.01],
            [0.5, 0.5, 0.5],
            1.0,
        );
    }
    let walled = read(
        rasterize(&wall.gaussians(device), &RasterSettings::new(cam))
            .unwrap()
            .image,
    );
    wall.push([0.0, 0.0, 5.0], cov, [1.0, 0.0, 0.0], 0.9);
    let behind = read(
        rasterize(&wall.gaussians(device), &RasterSettings::new(cam))
            .unwrap()
            .image,
    );
    assert_eq!(walled, behind);
}

fn output_is_deterministic_and_order_independent(device: &Device) {
    let cam = axis_camera(64, 48, 50.0);
    let mut rng = Rng::new(11);
    let scene = Scene::random(&mut rng, 40);
    let render = |s: &Scene| {
        read(
            rasterize(&s.gaussians(device), &RasterSettings::new(cam))
                .unwrap()
                .image,
        )
    };
    let a = render(&scene);
    assert_eq!(a, render(&scene));
    // Reverse the input order: blending follows depth, so the image is bit-identical.
    let n = scene.len();
    let mut rev = Scene {
        means: vec![],
        covs: vec![],
        colors: vec![],
        opacities: vec![],
    };
    for i in (0..n).rev() {
        rev.push(
            scene.means[3 * i..3 * i + 3].try_into().unwrap(),
            scene.covs[6 * i..6 * i + 6].try_into().unwrap(),
            scene.colors[3 * i..3 * i + 3].try_into().unwrap(),
            scene.opacities[i],
        );
    }
    assert_eq!(a, render(&rev));
}

/// Central differences of `Σ W·image` (in f64) against the op's backward, for every input.
fn gradients_match_central_differences(device: &Device) {
    for (seed, (w, h)) in [(1u64, (32u32, 24u32)), (2, (24, 36)), (3, (17, 9))] {
        let mut rng = Rng::new(seed);
        let mut cam = axis_camera(w, h, 30.0);
        cam.intrinsics.cx += rng.range_f32(-3.0, 3.0); // off-centre principal point
        let scene = Scene::random(&mut rng, 5);
        let settings = RasterSettings::new(cam)
            .with_depth()
            .with_cutoff(AlphaCutoff::Smooth);
        let weights: Vec<f32> = (0..(w * h * 5) as usize)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        check_gradients(device, &scene, &settings, &weights);
    }
}

#[allow(clippy::needless_range_loop)] // `i` indexes the analytic gradient and a perturbed copy
pub(crate) fn check_gradients(
    device: &Device,
    scene: &Scene,
    settings: &RasterSettings,
    weights: &[f32],
) {
    let ad = device.clone().autodiff();
    let g = scene.gaussians(&ad);
    let g = Gaussians {
        means: g.means.require_grad(),
        covariances: g.covariances.require_grad(),
        colors: g.colors.require_grad(),
        opacities: g.opacities.require_grad(),
    };
    let out = rasterize(&g, settings).unwrap();
    let [hh, ww, cc] = out.image.dims();
    let wt = Tensor::<3>::from_data(TensorData::new(weights.to_vec(), [hh, ww, cc]), &ad);
    let grads = (out.image * wt).sum().backward();
    let analytic = [
        read(g.means.grad(&grads).unwrap()),
        read(g.covariances.grad(&grads).unwrap()),
        read(g.colors.grad(&grads).unwrap()),
        read(g.opacities.grad(&grads).unwrap()),
    ];
    let cfg = settings.config();
    let loss = |s: &Scene| -> f64 {
        let (img, _) = cpu::forward(&cfg, &s.slices());
        img.iter()
            .zip(weights)
            .map(|(a, b)| *a as f64 * *b as f64)
            .sum()
    };
    let names = ["means", "covariances", "colors", "opacities"];
    let mut worst = 0.0f64;
    let mut skipped = Vec::new();
    let total: usize =
        scene.means.len() + scene.covs.len() + scene.colors.len() + scene.opacities.len();
    for (which, name) in names.iter().enumerate() {
        let len = [
            scene.means.len(),
            scene.covs.len(),
            scene.colors.len(),
            scene.opacities.len(),
        ][which];
        for i in 0..len {
            let eps = [1e-3, 1e-4, 1e-3, 1e-3][which];
            // Central differences in f32 trade truncation (h²) against rounding (1/h); Richardson
            // extrapolation cancels the h² term so a step large enough to beat rounding still works.
            fn field(s: &mut Scene, which: usize) -> &mut Vec<f32> {
                match which {
                    0 => &mut s.means,
                    1 => &mut s.covs,
                    2 => &mut s.colors,
                    _ => &mut s.opacities,
                }
            }
            let central = |h: f32| {
                let mut plus = scene.clone();
                let mut minus = scene.clone();
                field(&mut plus, which)[i] += h;
                field(&mut minus, which)[i] -= h;
                (loss(&plus) - loss(&minus)) / (2.0 * h as f64)
            };
            let (coarse, fine) = (central(eps), central(eps / 2.0));
            let numeric = (4.0 * fine - coarse) / 3.0;
            let a = analytic[which][i] as f64;
            let err = (a - numeric).abs();
            // The f32 forward rounds each pixel, which the difference quotient divides by `h`:
            // how much the two step sizes disagree is a measured error bar of the estimate.
            let noise = (fine - coarse).abs();
            let base_tol =
                2e-2 * a.abs().max(numeric.abs()) + 2e-3 * (1.0 + 1e-3 / eps as f64).min(5.0);
            let tol = base_tol + 2.0 * noise;
            // The forward has genuine jumps (two Gaussians swapping depth order, a pixel's
            // transmittance crossing the early-stop threshold). A jump within `h` of the sample
            // point makes the difference quotient grow like 1/h, so the two step sizes disagree
            // wildly; there is no derivative to compare with there. Such parameters are counted
            // and must stay rare.
            if noise > 0.25 * fine.abs().max(coarse.abs()) + 10.0 * base_tol {
                skipped.push(format!("{name}[{i}] ({coarse:.3} at h, {fine:.3} at h/2)"));
                continue;
            }
            assert!(
                err <= tol,
                "{name}[{i}]: analytic {a} vs numeric {numeric} (|err| {err:.2e} > {tol:.2e})"
            );
            let rel = err / (a.abs().max(numeric.abs()) + 1e-3);
            worst = worst.max(rel);
        }
    }
    assert!(analytic.iter().all(|g| g.iter().all(|v| v.is_finite())));
    assert!(
        analytic[0].iter().any(|v| v.abs() > 1e-3),
        "means got no gradient at all"
    );
    eprintln!(
        "finite differences: worst relative error {worst:.2e}; {} of {total} inputs at a jump of the forward: {skipped:?}",
        skipped.len()
    );
    assert!(
        skipped.len() * 20 <= total,
        "more than 5 % of the inputs sit at a jump of the forward: {skipped:?}"
    );
}

fn depth_channel_and_its_gradient(device: &Device) {
    let cam = axis_camera(32, 32, 40.0);
    let mut scene = Scene {
        means: vec![],
        covs: vec![],
        colors: vec![],
        opacities: vec![],
    };
    // One nearly opaque wide Gaussian: depth ≈ z·alpha.
    scene.push(
        [0.0, 0.0, 2.5],
        [1.0, 0.0, 0.0, 1.0, 0.0, 1e-4],
        [1.0, 1.0, 1.0],
        0.95,
    );
    let out = rasterize(
        &scene.gaussians(device),
        &RasterSettings::new(cam).with_depth(),
    )
    .unwrap();
    let depth = read(out.depth().unwrap());
    let alpha = read(out.alpha());
    for (d, a) in depth.iter().zip(&alpha) {
        assert!((d - 2.5 * a).abs() < 1e-4, "{d} vs {}", 2.5 * a);
    }
    assert!(
        out.clone().depth().is_some() && RasterSettings::new(cam).channels == Channels::RgbAlpha
    );
}

/// The value checks on wgpu, where a one-scalar check on the device comes first
/// ([`Gaussians::check_values`]).
#[test]
fn non_finite_inputs_are_rejected_on_wgpu() {
    if let Some(device) = crate::testing::wgpu_test_device() {
        non_finite_inputs_are_rejected(&device);
    }
}

fn non_finite_inputs_are_rejected(device: &Device) {
    let cam = axis_camera(16, 16, 20.0);
    let mut rng = Rng::new(3);
    let scene = Scene::random(&mut rng, 4);
    let bounds = Scene {
        opacities: vec![0.0, 1.0, 0.5, 1.0],
        ..scene.clone()
    };
    for good in [&scene, &bounds] {
        assert!(!good.gaussians(device).any_bad_value().unwrap());
        assert!(good.gaussians(device).check_values().is_ok());
    }
    for (which, name) in ["means", "covariances", "colors", "opacities"]
        .iter()
        .enumerate()
    {
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut s = scene.clone();
            match which {
                0 => s.means[4] = bad,
                1 => s.covs[4] = bad,
                2 => s.colors[4] = bad,
                _ => s.opacities[2] = bad,
            }
            assert!(
                s.gaussians(device).any_bad_value().unwrap(),
                "{name} = {bad}"
            );
            let err = rasterize(&s.gaussians(device), &RasterSettings::new(cam)).unwrap_err();
            let msg = err.to_string();
            assert!(msg.contains(name) && msg.contains("non-finite"), "{msg}");
            // Without validation the kernels cull the bad Gaussian instead of panicking.
            let out = rasterize(
                &s.gaussians(device),
                &RasterSettings::new(cam).with_validation(Validation::ShapesOnly),
            )
            .unwrap();
            assert!(
                read(out.image).iter().all(|v| v.is_finite()),
                "{name} = {bad} leaked into the image"
            );
        }
    }
    let bad_shape = Gaussians {
        means: Tensor::zeros([3, 2], device),
        ..scene.gaussians(device)
    };
    assert!(
        rasterize(&bad_shape, &RasterSettings::new(cam))
            .unwrap_err()
            .to_string()
            .contains("`means`")
    );
    let out_of_range = Scene {
        opacities: vec![1.5, 0.5, 0.5, 0.5],
        ..scene.clone()
    };
    assert!(out_of_range.gaussians(device).any_bad_value().unwrap());
    assert!(rasterize(&out_of_range.gaussians(device), &RasterSettings::new(cam)).is_err());
    let below_zero = Scene {
        opacities: vec![0.5, 0.5, -1e-7, 0.5],
        ..scene.clone()
    };
    let msg = rasterize(&below_zero.gaussians(device), &RasterSettings::new(cam))
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("index 2") && msg.contains("outside [0, 1]"),
        "{msg}"
    );
    // +inf and -inf in one tensor: the first is named.
    let mut both_infinities = scene.clone();
    both_infinities.colors[1] = f32::INFINITY;
    both_infinities.colors[7] = f32::NEG_INFINITY;
    let msg = rasterize(
        &both_infinities.gaussians(device),
        &RasterSettings::new(cam),
    )
    .unwrap_err()
    .to_string();
    assert!(msg.contains("colors") && msg.contains("index 1"), "{msg}");
    // No Gaussians at all is valid input: an empty (transparent) image.
    let empty = Scene::random(&mut rng, 0);
    let out = rasterize(&empty.gaussians(device), &RasterSettings::new(cam)).unwrap();
    assert!(read(out.image).iter().all(|&v| v == 0.0));
}

/// [`composite_views`] of three views on lavapipe (one batched call) against Flex (a call per
/// view): the same colour and alpha within float rounding, `[n, H, W, C]` each.
#[test]
fn composite_views_match_across_backends_wgpu() {
    let Some(device) = crate::testing::wgpu_test_device() else {
        return;
    };
    let scene = Scene::random(&mut Rng::new(3), 24);
    let settings: Vec<RasterSettings> = [40.0, 50.0, 60.0]
        .iter()
        .map(|&f| RasterSettings::new(axis_camera(20, 16, f)))
        .collect();
    let render = |device: &Device| {
        let (rgb, alpha) = composite_views(&scene.gaussians(device), &settings, [0.2, 0.4, 0.6])
            .expect("valid views");
        assert_eq!(rgb.dims(), [3, 16, 20, 3]);
        assert_eq!(alpha.dims(), [3, 16, 20, 1]);
        (read(rgb), read(alpha))
    };
    let (want_rgb, want_alpha) = render(&Device::flex());
    let (got_rgb, got_alpha) = render(&device);
    for (got, want) in [(got_rgb, want_rgb), (got_alpha, want_alpha)] {
        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
            assert!((a - b).abs() <= 1e-5, "value {i}: {a} against {b}");
        }
    }
}
