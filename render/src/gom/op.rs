//! The GoM geometry as one custom Burn op (design.md §5.6).
//!
//! [`GomGeometryOps`] is a Burn backend extension, like the rasterizer's
//! [`crate::rasterizer::op::GaussianRasterOps`]: `#[backend_extension]` generates its `Dispatch`
//! implementation, so [`super::GomMesh::gaussians`] calls it on plain tensors and it runs on the
//! backend they live on. Implemented for NdArray and Flex (both run [`super::cpu`]), for Burn's
//! CubeCL backend (wgpu; the `cube` module) and for `Autodiff<B, C>` over any backend that also
//! implements [`GomKernels`].
//!
//! The autodiff node keeps the op's inputs (tensor handles, no copies) and nothing else: the
//! backward recomputes the per-face frame and rotation, which costs about as much as reading
//! them back would.

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use std::borrow::Cow;

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::DType;

use super::cpu::{self, GeometrySlices, OUT_LANES};
use crate::cube::deferred::{Input, Value, array, deferred, float_like};
use crate::op_backward::{gradient_per_input, record};
use crate::readback::{self, HostLend};

/// Gaussians-on-Mesh geometry, fused: corner interpolation, Steiner frame, `so3` exponential,
/// mean and covariance of every high-res face in one op.
///
/// Inputs: low-res `vertices` `[V, 3]`; per face `so3`, `scales`, `offsets` `[F, 3]`; the
/// corner table `corner_index` (`[F*9]`, int) and `corner_weight` (`[F*9]`): face `f`, corner
/// `k`, slot `m` at `9f + 3k + m`, corner `k = Σ_m weight·vertices[index]`. Output `[F, 9]`:
/// mean (3) ‖ covariance (6: xx, xy, xz, yy, yz, zz), in `vertices`' float dtype. Gradients
/// flow to the first four inputs; the tables are constants. Callers check shapes first (see
/// [`super::GomMesh::gaussians`]); an out-of-range table index counts as weight 0.
///
/// The corner table inverted, for the GPU backward's vertex gradient: `vertex_corner_offsets`
/// (`[V+1]`, int) delimits each vertex's run in `corner_from_vertex_order` (`[E]`, int), the
/// table entries that read the vertex in increasing entry order (what
/// [`super::GomMesh::new`] builds). The CPU backends sum by face block instead and do
/// not read them.
#[backend_extension(NdArray, Flex, Cube, Fusion, Autodiff)]
pub trait GomGeometryOps: Backend {
    /// Builds one Gaussian per face.
    #[fusion(dtype = vertices, shape = burn::tensor::Shape::new([so3[0], OUT_LANES]))]
    // A backend extension takes its tensors one argument each (the generated dispatch needs it).
    #[allow(clippy::too_many_arguments)]
    fn gom_geometry(
        vertices: FloatTensor<Self>,
        so3: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        offsets: FloatTensor<Self>,
        corner_index: IntTensor<Self>,
        corner_weight: FloatTensor<Self>,
        vertex_corner_offsets: IntTensor<Self>,
        corner_from_vertex_order: IntTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// The op's inputs on one backend: what the forward takes and the autodiff node keeps.
#[derive(Debug, Clone)]
pub struct GomInputs<B: Backend> {
    /// `[V, 3]`.
    pub vertices: FloatTensor<B>,
    /// `[F, 3]`.
    pub so3: FloatTensor<B>,
    /// `[F, 3]`.
    pub scales: FloatTensor<B>,
    /// `[F, 3]`.
    pub offsets: FloatTensor<B>,
    /// `[F*9]`.
    pub corner_index: IntTensor<B>,
    /// `[F*9]`.
    pub corner_weight: FloatTensor<B>,
    /// `[V+1]`.
    pub vertex_corner_offsets: IntTensor<B>,
    /// `[E]`.
    pub corner_from_vertex_order: IntTensor<B>,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait GomKernels: Backend {
    /// The forward, `[F, 9]`.
    fn gom_forward(inputs: GomInputs<Self>) -> FloatTensor<Self>;

    /// Gradients w.r.t. `[vertices, so3, scales, offsets]` given `dL/d(output)`, each in its
    /// input's dtype.
    fn gom_backward(inputs: GomInputs<Self>, grad: FloatTensor<Self>) -> [FloatTensor<Self>; 4];
}

/// The inputs as host slices: lent in place where the backend allows it ([`HostLend`]).
struct HostInputs<'a> {
    vertices: Cow<'a, [f32]>,
    so3: Cow<'a, [f32]>,
    scales: Cow<'a, [f32]>,
    offsets: Cow<'a, [f32]>,
    corner_index: Cow<'a, [i32]>,
    corner_weight: Cow<'a, [f32]>,
}

impl<'a> HostInputs<'a> {
    fn lend<B: HostLend>(inputs: &'a GomInputs<B>) -> Self {
        Self {
            vertices: B::lend_float::<f32>("vertices", &inputs.vertices),
            so3: B::lend_float::<f32>("so3", &inputs.so3),
            scales: B::lend_float::<f32>("scales", &inputs.scales),
            offsets: B::lend_float::<f32>("offsets", &inputs.offsets),
            corner_index: B::lend_int("corner_index", &inputs.corner_index),
            corner_weight: B::lend_float::<f32>("corner_weight", &inputs.corner_weight),
        }
    }

    fn slices(&self) -> GeometrySlices<'_> {
        GeometrySlices {
            vertices: &self.vertices,
            so3: &self.so3,
            scales: &self.scales,
            offsets: &self.offsets,
            corner_index: &self.corner_index,
            corner_weight: &self.corner_weight,
        }
    }
}

fn cpu_forward<B: HostLend>(inputs: GomInputs<B>) -> FloatTensor<B> {
    let device = inputs.vertices.device();
    let dtype = inputs.vertices.dtype();
    let host = HostInputs::lend(&inputs);
    let slices = host.slices();
    let f = slices.num_faces();
    let out = cpu::forward(&slices);
    readback::cpu_float_from::<B, f32>(out, [f, OUT_LANES], dtype, &device)
}

fn cpu_backward<B: HostLend>(inputs: GomInputs<B>, grad: FloatTensor<B>) -> [FloatTensor<B>; 4] {
    let device = inputs.vertices.device();
    let dtypes = [
        inputs.vertices.dtype(),
        inputs.so3.dtype(),
        inputs.scales.dtype(),
        inputs.offsets.dtype(),
    ];
    let host = HostInputs::lend(&inputs);
    let slices = host.slices();
    let f = slices.num_faces();
    let v = slices.vertices.len() / 3;
    let grad = B::lend_float::<f32>("gom output gradient", &grad);
    let grads = cpu::backward(&slices, &grad);
    let tensor = |values: Vec<f32>, rows: usize, dtype: DType| {
        readback::cpu_float_from::<B, f32>(values, [rows, 3], dtype, &device)
    };
    [
        tensor(grads.vertices, v, dtypes[0]),
        tensor(grads.so3, f, dtypes[1]),
        tensor(grads.scales, f, dtypes[2]),
        tensor(grads.offsets, f, dtypes[3]),
    ]
}

/// Implements the op for a CPU backend through the shared slice functions.
macro_rules! cpu_gom_backend {
    ($backend:ty) => {
        impl GomGeometryOps for $backend {
            fn gom_geometry(
                vertices: FloatTensor<Self>,
                so3: FloatTensor<Self>,
                scales: FloatTensor<Self>,
                offsets: FloatTensor<Self>,
                corner_index: IntTensor<Self>,
                corner_weight: FloatTensor<Self>,
                vertex_corner_offsets: IntTensor<Self>,
                corner_from_vertex_order: IntTensor<Self>,
            ) -> FloatTensor<Self> {
                cpu_forward::<Self>(GomInputs {
                    vertices,
                    so3,
                    scales,
                    offsets,
                    corner_index,
                    corner_weight,
                    vertex_corner_offsets,
                    corner_from_vertex_order,
                })
            }
        }

        impl GomKernels for $backend {
            fn gom_forward(inputs: GomInputs<Self>) -> FloatTensor<Self> {
                cpu_forward::<Self>(inputs)
            }

            fn gom_backward(
                inputs: GomInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 4] {
                cpu_backward::<Self>(inputs, grad)
            }
        }
    };
}

cpu_gom_backend!(NdArray);
cpu_gom_backend!(Flex);

#[derive(Debug)]
struct GomBackward;

impl<B: GomKernels> Backward<B, 4> for GomBackward {
    type State = GomInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 4>(ops, grads, B::gom_backward);
    }
}

impl<B: GomGeometryOps + GomKernels, C: CheckpointStrategy> GomGeometryOps for Autodiff<B, C> {
    fn gom_geometry(
        vertices: FloatTensor<Self>,
        so3: FloatTensor<Self>,
        scales: FloatTensor<Self>,
        offsets: FloatTensor<Self>,
        corner_index: IntTensor<Self>,
        corner_weight: FloatTensor<Self>,
        vertex_corner_offsets: IntTensor<Self>,
        corner_from_vertex_order: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        let (vertices, vertices_node) = vertices.into_parts();
        let (so3, so3_node) = so3.into_parts();
        let (scales, scales_node) = scales.into_parts();
        let (offsets, offsets_node) = offsets.into_parts();
        // A constant of the mesh: no gradient is ever asked of it.
        let corner_weight = corner_weight.into_parts().0;
        let inputs = GomInputs {
            vertices,
            so3,
            scales,
            offsets,
            corner_index,
            corner_weight,
            vertex_corner_offsets,
            corner_from_vertex_order,
        };
        record::<B, C, _, _, 4>(
            GomBackward,
            [vertices_node, so3_node, scales_node, offsets_node],
            inputs,
            B::gom_forward,
        )
    }
}

impl<B: FusionBackend + GomKernels> GomKernels for Fusion<B> {
    fn gom_forward(inputs: GomInputs<Self>) -> FloatTensor<Self> {
        let faces = inputs.so3.shape()[0];
        let spec = float_like::<B>(&inputs.vertices, [faces, OUT_LANES]);
        let [out] = array(deferred::<B, _>(
            "gom_forward",
            gom_inputs(inputs),
            vec![spec],
            |v| vec![Value::Float(B::gom_forward(gom_values(v)))],
        ));
        out
    }

    fn gom_backward(inputs: GomInputs<Self>, grad: FloatTensor<Self>) -> [FloatTensor<Self>; 4] {
        let specs = [
            &inputs.vertices,
            &inputs.so3,
            &inputs.scales,
            &inputs.offsets,
        ]
        .map(|t| float_like::<B>(t, t.shape()))
        .into();
        let mut recorded = gom_inputs(inputs);
        recorded.push(Input::Float(grad));
        array(deferred::<B, _>(
            "gom_backward",
            recorded,
            specs,
            |mut v| {
                let grad = v.pop().expect("the gradient was recorded last").float();
                B::gom_backward(gom_values(v), grad)
                    .into_iter()
                    .map(Value::Float)
                    .collect()
            },
        ))
    }
}

/// The GoM op's eight tensors, in the order [`gom_values`] reads them back.
fn gom_inputs<B: FusionBackend>(inputs: GomInputs<Fusion<B>>) -> Vec<Input<B>> {
    vec![
        Input::Float(inputs.vertices),
        Input::Float(inputs.so3),
        Input::Float(inputs.scales),
        Input::Float(inputs.offsets),
        Input::Int(inputs.corner_index),
        Input::Float(inputs.corner_weight),
        Input::Int(inputs.vertex_corner_offsets),
        Input::Int(inputs.corner_from_vertex_order),
    ]
}

fn gom_values<B: FusionBackend>(values: Vec<Value<B>>) -> GomInputs<B> {
    let [
        vertices,
        so3,
        scales,
        offsets,
        index,
        weight,
        offsets_by_vertex,
        order,
    ] = array(values);
    GomInputs {
        vertices: vertices.float(),
        so3: so3.float(),
        scales: scales.float(),
        offsets: offsets.float(),
        corner_index: index.int(),
        corner_weight: weight.float(),
        vertex_corner_offsets: offsets_by_vertex.int(),
        corner_from_vertex_order: order.int(),
    }
}

#[cfg(test)]
mod tests {
    //! The fused op against the tensor-op reference (`GomMesh::gaussians_reference`)
    //! on the subdivided low-res template: values, and every gradient through `.autodiff()`.
    //!
    //! The yardstick is the reference evaluated in `f64` on the CPU, with the same `f32` inputs.
    //! The CPU op (f64 inside) must match it to `1e-5`. The reference in `f32` does not: where a
    //! covariance entry cancels or a frame is close to a circle it is off by up to ~1e-2 of the
    //! entry (~1e-3 with the floor of [`max_rel`]). The GPU op computes in `f32` too, so it is
    //! held to a small multiple of what the `f32` reference achieves on the same device. Every
    //! measured difference is printed.
    use burn::backend::DispatchDevice;
    use burn::tensor::{DType, Device, Tensor, TensorData};

    use crate::gom::{GomMesh, GomParams};
    use crate::template::{BodyTemplate, lowres_template_path};
    use crate::testing::{Rng, wgpu_test_device};

    const NAMES: [&str; 6] = [
        "means",
        "covariances",
        "d vertices",
        "d so3",
        "d scales",
        "d offsets",
    ];

    /// Largest `|a − b| / (|b| + floor)` over a tensor, `floor = 1e-3·max|b|`: relative error,
    /// except that entries a thousand times below the tensor's largest (a vertex gradient summed
    /// from large contributions that cancel, a covariance entry of a tiny face) are held to an
    /// absolute error at that scale.
    fn max_rel(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        let floor = 1e-3 * b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs() / (y.abs() + floor))
            .fold(0.0, f64::max)
    }

    /// Inputs and loss weights, as `f32` host vectors.
    struct Case {
        mesh_cpu: GomMesh,
        vertices: Vec<f32>,
        so3: Vec<f32>,
        scales: Vec<f32>,
        offsets: Vec<f32>,
        wm: Vec<f32>,
        wc: Vec<f32>,
    }

    impl Case {
        fn new() -> Self {
            let body = BodyTemplate::load(lowres_template_path()).expect("the low-res template");
            let mesh_cpu = GomMesh::new(&body.topology, 1, &Device::flex()).expect("subdivision");
            let f = mesh_cpu.num_gaussians();
            let mut rng = Rng::new(21);
            let mut random = |n: usize, g: &dyn Fn(&mut Rng) -> f64| -> Vec<f32> {
                (0..n).map(|_| g(&mut rng) as f32).collect()
            };
            // A third of the rotations below the θ floor, the rest up to past π.
            let so3 = random(3 * f, &|r| {
                if r.below(3) == 0 {
                    r.range(-4e-3, 4e-3)
                } else {
                    r.range(-2.5, 2.5)
                }
            });
            let scales = random(3 * f, &|r| {
                r.range(0.3, 2.0) * if r.uniform() < 0.25 { -1.0 } else { 1.0 }
            });
            let offsets = random(3 * f, &|r| r.range(-1.0, 1.0));
            let wm = random(3 * f, &|r| r.range(-1.0, 1.0));
            let wc = random(6 * f, &|r| r.range(-1.0, 1.0));
            Self {
                mesh_cpu,
                vertices: body.vertices.iter().flat_map(|v| v.to_array()).collect(),
                so3,
                scales,
                offsets,
                wm,
                wc,
            }
        }

        /// Means, covariances and the four gradients of
        /// `Σ wm·means + cov_weight·Σ wc·covariances`, through the op or the reference.
        fn run(
            &self,
            mesh: &GomMesh,
            device: &Device,
            fused: bool,
            dtype: DType,
            cov_weight: f64,
        ) -> Vec<Vec<f64>> {
            let ad = device.clone().autodiff();
            let t2 = |values: &[f32], cols: usize| {
                Tensor::<2>::from_data(
                    TensorData::new(values.to_vec(), [values.len() / cols, cols]),
                    &ad,
                )
                .cast(dtype)
            };
            let leaves = [
                t2(&self.vertices, 3).require_grad(),
                t2(&self.so3, 3).require_grad(),
                t2(&self.scales, 3).require_grad(),
                t2(&self.offsets, 3).require_grad(),
            ];
            let f = mesh.num_gaussians();
            let params = GomParams {
                so3: leaves[1].clone(),
                scales: leaves[2].clone(),
                offsets: leaves[3].clone(),
                colors: Tensor::zeros([f, 3], &ad),
                opacities: Tensor::ones([f], &ad),
            };
            let g = if fused {
                mesh.gaussians(leaves[0].clone(), &params)
            } else {
                mesh.gaussians_reference(leaves[0].clone(), &params)
            };
            let loss = (g.means.clone() * t2(&self.wm, 3)).sum()
                + (g.covariances.clone() * t2(&self.wc, 6)).sum() * cov_weight;
            let grads = loss.backward();
            let read = |t: Tensor<2>| -> Vec<f64> {
                crate::readback::read("gom test output", t).expect("reading a test tensor")
            };
            let mut out = vec![read(g.means), read(g.covariances)];
            for leaf in &leaves {
                out.push(read(leaf.grad(&grads).expect("every leaf gets a gradient")));
            }
            out
        }
    }

    fn check_op_matches_reference(device: &Device) {
        let case = Case::new();
        let mesh = GomMesh::new(&case.mesh_cpu.subdivision.lowres, 1, device).expect("mesh");
        let flex = Device::flex();
        // Weigh covariances (~|face|²) like means in the loss, so both drive every gradient. A
        // power of two keeps the output gradients exact in f32, as the op receives them.
        let plain = case.run(&case.mesh_cpu, &flex, false, DType::F64, 1.0);
        let mean_abs = plain[1].iter().map(|c| c.abs()).sum::<f64>() / plain[1].len() as f64;
        let cov_weight = 2f64.powi(-mean_abs.log2().round() as i32);
        let oracle = case.run(&case.mesh_cpu, &flex, false, DType::F64, cov_weight);
        let op = case.run(&mesh, device, true, DType::F32, cov_weight);
        let reference = case.run(&mesh, device, false, DType::F32, cov_weight);
        let f32_kernels = matches!(device.as_dispatch(), DispatchDevice::Cube(_));
        let mut failures = Vec::new();
        for (k, name) in NAMES.iter().enumerate() {
            assert!(
                op[k].iter().all(|x| x.is_finite()),
                "{name}: non-finite values"
            );
            let e_op = max_rel(&op[k], &oracle[k]);
            let e_ref = max_rel(&reference[k], &oracle[k]);
            let e_op_ref = max_rel(&op[k], &reference[k]);
            eprintln!(
                "gom op on {device:?}: {name}: max rel diff vs f64 reference {e_op:.2e} \
                 (f32 reference: {e_ref:.2e}); op vs f32 reference {e_op_ref:.2e}"
            );
            // f32 kernels: within a small factor of the f32 reference's own error.
            let tolerance = if f32_kernels {
                1e-5f64.max(4.0 * e_ref)
            } else {
                1e-5
            };
            if e_op > tolerance {
                failures.push(format!("{name}: {e_op:.2e} > {tolerance:.2e}"));
            }
        }
        assert!(failures.is_empty(), "op vs reference: {failures:?}");
    }

    crate::cpu_backend_tests!(op_matches_reference => check_op_matches_reference);

    #[test]
    fn op_matches_reference_wgpu() {
        if let Some(device) = wgpu_test_device() {
            check_op_matches_reference(&device);
        }
    }

    /// The op answers in its inputs' float dtype (output and gradients), as the reference does.
    #[test]
    fn op_answers_in_the_input_dtype() {
        let device = Device::flex();
        let body = BodyTemplate::load(lowres_template_path()).expect("the low-res template");
        let mesh = GomMesh::new(&body.topology, 0, &device).expect("subdivision");
        let f = mesh.num_gaussians();
        let ad = device.autodiff();
        let vertices = body.vertex_tensor(&ad).cast(DType::F64).require_grad();
        let mut params = GomParams::init(f, &ad);
        params.so3 = params.so3.cast(DType::F64).require_grad();
        let g = mesh.gaussians(vertices.clone(), &params);
        assert_eq!(g.means.dtype(), DType::F64);
        let grads = g.covariances.sum().backward();
        let vertex_grad = vertices.grad(&grads).expect("vertex gradient");
        assert_eq!(vertex_grad.dtype(), DType::F64);
        assert_eq!(
            params.so3.grad(&grads).expect("so3 gradient").dtype(),
            DType::F64
        );
    }
}
