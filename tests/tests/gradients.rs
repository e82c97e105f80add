//! End-to-end gradient checks.
//!
//! - Low-res vertices → 1→4 subdivision → Steiner frames → Gaussians → rasterizer → weighted
//!   loss, against central differences. Uses the test-only smooth alpha cutoff so the rendered
//!   image is C¹ in the vertices.
//! - A whole training step's loss and gradients with the fused GoM op against the same step on
//!   the tensor-op specification (`step_parity`).

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

/// Issue 12: the fused GoM op changes a training step only by float reordering. One step of the
/// tiny reconstructor (all T feedback steps, every render, every loss, the backward) on a fixed
/// scene, with the mesh's geometry once fused and once the tensor-op specification in `f64`
/// (`GomGeometry::ReferenceF64`); same weights, same dropout masks. The `f32` specification would
/// not do as the yardstick: it is itself off by up to ~2e-2 on covariance entries that cancel.
mod step_parity {
    use burn::module::{Module, ModuleVisitor, Param};
    use burn::optim::GradientsParams;
    use burn::tensor::{Device, Tensor};
    use lifegom_model::inputs::ModelInputs;
    use lifegom_model::reconstructor::{
        MeshPurpose, ReconstructorConfig, SourceViews, render_views,
    };
    use lifegom_render::camera::Camera;
    use lifegom_render::gom::{GomGeometry, GomMesh, GomParams};
    use lifegom_render::skeleton::BodyPose;
    use lifegom_render::template::{BodyTemplate, lowres_template_path};
    use lifegom_tests::{body_camera, pattern_colors, read, template_subject};
    use lifegom_train::config::TrainSection;
    use lifegom_train::losses::UniformLaplacian;
    use lifegom_train::trainer::Trainer;

    const SIZE: u32 = 32;

    /// Two source views and a target of the template with a smooth colour pattern, rendered
    /// through `mesh`; the network starts far from it, so every loss term has a gradient.
    fn inputs(template: &BodyTemplate, mesh: &GomMesh, device: &Device) -> ModelInputs {
        let subject = template_subject(template, device);
        let rest = template
            .skeleton
            .skinning_transforms(&BodyPose::rest(template.num_joints()))
            .unwrap();
        let f = mesh.num_gaussians();
        let mut truth = GomParams::init(f, device);
        truth.colors = pattern_colors(mesh, subject.canonical_vertices.clone());
        truth.scales = truth.scales * 0.8;
        let cams: Vec<Camera> = [0.3f32, 2.4, 1.2]
            .iter()
            .map(|&a| body_camera(a, 0.1, SIZE))
            .collect();
        let bg = [0.2, 0.1, 0.3];
        let skinning = vec![rest.clone(); 3];
        let views = render_views(
            mesh,
            &subject.canonical_vertices,
            &truth,
            &subject,
            &cams,
            &skinning,
            bg,
        )
        .unwrap();
        let views_rgb = views.rgb.detach();
        let views_alpha = views.alpha.detach();
        ModelInputs {
            sources: SourceViews {
                images: views_rgb.clone().narrow(0, 0, 2),
                cameras: cams[..2].to_vec(),
                skinning: skinning[..2].to_vec(),
                background: bg,
            },
            source_masks: views_alpha.clone().narrow(0, 0, 2),
            target_camera: cams[2],
            target_skinning: rest,
            target_rgb: views_rgb.narrow(0, 2, 1).squeeze_dim(0),
            target_mask: views_alpha.narrow(0, 2, 1).squeeze_dim(0),
            subject,
        }
    }

    /// Every parameter's gradient, named by its module path and position in it.
    struct Collect<'a> {
        grads: &'a GradientsParams,
        path: Vec<String>,
        out: Vec<(String, Vec<f32>)>,
    }

    impl ModuleVisitor for Collect<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let value = param.val();
            if !value.is_require_grad() {
                return; // frozen (the Point Transformer's batch norms)
            }
            let name = format!("{}#{}", self.path.join("."), self.out.len());
            // No gradient at all is a parameter the loss does not reach, a zero gradient.
            let grad = self
                .grads
                .get::<D>(param.id)
                .map(read)
                .unwrap_or_else(|| vec![0.0; value.shape().num_elements()]);
            self.out.push((name, grad));
        }
    }

    /// Burn initialises parameters lazily, on first use, from the RNG that a step re-seeds for
    /// its dropout masks: a model's first step draws its masks interleaved with its weights and
    /// a second step on the same model draws other masks. Reading every parameter once fixes
    /// the weights first, so both steps draw the same masks.
    struct Materialise;

    impl ModuleVisitor for Materialise {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            param.val();
        }
    }

    /// The step's total loss and every parameter's gradient.
    fn step(
        trainer: &Trainer,
        inputs: &ModelInputs,
        mesh: &GomMesh,
        laplacian: &UniformLaplacian,
    ) -> (f64, Vec<(String, Vec<f32>)>) {
        let out = trainer.step_loss(inputs, mesh, laplacian).unwrap();
        let total = f64::from(read(out.loss.total.clone())[0]);
        println!("{:?}", out.loss.scalars().unwrap());
        let grads = GradientsParams::from_grads(out.loss.total.backward(), &trainer.model);
        let mut collect = Collect {
            grads: &grads,
            path: Vec::new(),
            out: Vec::new(),
        };
        trainer.model.visit(&mut collect);
        (total, collect.out)
    }

    fn norm(v: impl Iterator<Item = f64>) -> f64 {
        v.map(|x| x * x).sum::<f64>().sqrt()
    }

    #[test]
    fn fused_geometry_changes_a_training_step_only_by_rounding() {
        let device = Device::flex();
        let template = BodyTemplate::load(lowres_template_path()).unwrap();
        // Two feedback steps, as the tiny experiment config: the second step's inputs include
        // the first step's renders, so a difference in the geometry would compound.
        let trainer = Trainer::new(
            ReconstructorConfig::tiny(2).with_iterations(2),
            template.num_vertices(),
            &TrainSection::default(),
            &device,
        )
        .unwrap();
        trainer.model.visit(&mut Materialise);
        let fused = trainer
            .config
            .mesh(&template.topology, MeshPurpose::Training, trainer.device())
            .unwrap();
        assert_eq!(fused.geometry(), GomGeometry::Fused);
        let reference = fused.clone().with_geometry(GomGeometry::ReferenceF64);
        let laplacian =
            UniformLaplacian::new(&template.topology.faces, template.num_vertices()).unwrap();
        let inputs = inputs(&template, &fused, trainer.device());

        let (loss_fused, grads_fused) = step(&trainer, &inputs, &fused, &laplacian);
        let (loss_ref, grads_ref) = step(&trainer, &inputs, &reference, &laplacian);

        let loss_rel = (loss_fused - loss_ref).abs() / loss_ref.abs();
        println!("loss: fused {loss_fused}, reference {loss_ref}, relative {loss_rel:.2e}");
        assert!(
            loss_ref > 0.0 && loss_rel <= 1e-5,
            "loss: relative {loss_rel:.2e}"
        );

        assert_eq!(grads_fused.len(), grads_ref.len());
        let sizes: Vec<f64> = grads_ref
            .iter()
            .map(|(_, g)| norm(g.iter().map(|&x| f64::from(x))))
            .collect();
        let largest = sizes.iter().copied().fold(0.0, f64::max);
        let nonzero = sizes.iter().filter(|&&n| n > 0.0).count();
        // A zero gradient is legitimate behind a ReLU that is dead for this input, but rare.
        assert!(
            nonzero * 10 >= sizes.len() * 9,
            "only {nonzero} of {} trainable tensors have a gradient",
            sizes.len()
        );
        // The forward is bit-identical (every mean and covariance, hence the loss); the two
        // backwards round differently by ~1 ulp, and cancellation downstream amplifies that.
        // So each tensor is held to its own norm, except tensors a million times below the
        // step's largest (~2), held to an absolute error at that level instead: gradients that
        // are zero or nearly so analytically, left as rounding noise of cancelling terms. The
        // key biases of the fusion attention and the last bias before each Point Transformer
        // softmax (shift-invariant) measure ~1e-12 with relative differences up to 3; a few
        // attention weights and biases at 1e-8 to 1e-6 up to 8e-6. Measured with T = 2: every
        // tensor above the floor within 4.3e-7, all gradients together 1.8e-7, the worst
        // tensor against the floor 1.9e-6. (The f32 tensor reference would miss 1e-5: 1.8e-4
        // on the vertex head, 1.3e-4 together.)
        let floor = 1e-6 * largest;
        let (mut all_diff, mut all_size) = (0.0f64, 0.0f64);
        let mut worst = (String::new(), 0.0f64);
        for (((name, a), (_, b)), size) in grads_fused.iter().zip(&grads_ref).zip(&sizes) {
            assert_eq!(a.len(), b.len(), "{name}");
            let diff = norm(a.iter().zip(b).map(|(x, y)| f64::from(*x) - f64::from(*y)));
            all_diff = all_diff.hypot(diff);
            all_size = all_size.hypot(*size);
            let rel = diff / size.max(floor);
            if rel > worst.1 {
                worst = (name.clone(), rel);
            }
        }
        let all_rel = all_diff / all_size;
        println!(
            "gradients of {} tensors: all together relative {all_rel:.2e}; worst tensor {} at \
             {:.2e}",
            sizes.len(),
            worst.0,
            worst.1
        );
        assert!(all_rel <= 1e-5, "all gradients: relative {all_rel:.2e}");
        assert!(
            worst.1 <= 1e-5,
            "gradient of {}: relative {:.2e}",
            worst.0,
            worst.1
        );
    }
}
