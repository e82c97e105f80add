//! The fusion layers' attention core and residual LayerNorm as custom Burn ops on the CPU
//! backends (design.md §7.4).
//!
//! [`FusionAttentionOps`] and [`AddLayerNormOps`] are backend extensions like the sampling op
//! ([`crate::sampling`]): `#[backend_extension]` generates their `Dispatch` implementations,
//! they are implemented for NdArray and Flex (both run [`super::kernels`]) and for
//! `Autodiff<B, C>` over them, with the hand-written backwards of that module. Burn's autodiff
//! runs attention and LayerNorm as compositions of small ops (reshapes, batched matmuls of
//! `N×d_k` matrices, a five-op softmax; eight ops per LayerNorm), each with its own node and
//! intermediate; on a CPU those cost more than the arithmetic (BENCHMARKS.md, "Training step
//! profile").
//!
//! On CubeCL devices the residual LayerNorm is this op too, as CubeCL kernels (`super::cube`),
//! while the attention core keeps the tensor-op composition ([`super::FusionKernel`] says which
//! runs where); the compositions are the reference the ops are tested against. The autodiff
//! nodes keep the inputs (handles, no copies) and recompute what the backward needs.

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use burn::backend::TensorMetadata;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Flex, NdArray, backend_extension};
use burn::tensor::Element;
use bytemuck::Pod;
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};

use super::kernels::{self, AttentionShape, Real};
use lifegom_render::in_precision;
use lifegom_render::op_backward::{gradient_per_input, record};
use lifegom_render::readback::{HostLend, cpu_float_from};

/// Multi-head scaled dot-product attention over short sequences, without mask or dropout.
///
/// Inputs: `query` `[B, L_q, D]`, `key` and `value` `[B, L_k, D]` (already projected, heads
/// side by side in the channels); output `[B, L_q, D]` in `query`'s dtype. Gradients flow to all
/// three. Callers check shapes (see [`super::AttentionLayer`]).
#[backend_extension(NdArray, Flex, Cube, Fusion, Autodiff)]
pub trait FusionAttentionOps: Backend {
    /// Attends every problem's queries to its keys, `heads` heads at once.
    #[fusion(dtype = query, shape = query)]
    fn fusion_attention(
        query: FloatTensor<Self>,
        key: FloatTensor<Self>,
        value: FloatTensor<Self>,
        heads: AttentionHeads,
    ) -> FloatTensor<Self>;
}

/// How many heads the channels split into.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AttentionHeads(pub usize);

/// `LayerNorm(x + residual)·γ + β` over the last dimension.
///
/// Inputs: `x` and `residual` of one shape `[.., D]`, `gamma` and `beta` `[D]`; output the
/// shape of `x`. Gradients flow to all four.
#[backend_extension(NdArray, Flex, Cube, Fusion, Autodiff)]
pub trait AddLayerNormOps: Backend {
    /// Normalises the residual sum.
    #[fusion(dtype = x, shape = x)]
    fn add_layer_norm(
        x: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: LayerNormEpsilon,
    ) -> FloatTensor<Self>;
}

/// The LayerNorm's `ε`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LayerNormEpsilon(pub f64);

/// The attention op's inputs on one backend: what the forward takes and the node keeps.
#[derive(Debug, Clone)]
pub struct AttentionInputs<B: Backend> {
    pub(super) query: FloatTensor<B>,
    pub(super) key: FloatTensor<B>,
    pub(super) value: FloatTensor<B>,
    pub(super) heads: usize,
}

/// The LayerNorm op's inputs on one backend.
#[derive(Debug, Clone)]
pub struct LayerNormInputs<B: Backend> {
    pub(super) x: FloatTensor<B>,
    pub(super) residual: FloatTensor<B>,
    pub(super) gamma: FloatTensor<B>,
    pub(super) beta: FloatTensor<B>,
    pub(super) epsilon: f64,
}

/// What a backend implements so that `Autodiff<B>` can differentiate the attention op.
#[doc(hidden)]
pub trait AttentionKernels: Backend {
    /// The attention forward.
    fn attention_forward(inputs: AttentionInputs<Self>) -> FloatTensor<Self>;
    /// `[∂query, ∂key, ∂value]`.
    fn attention_backward(
        inputs: AttentionInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3];
}

/// What a backend implements so that `Autodiff<B>` can differentiate the LayerNorm op.
#[doc(hidden)]
pub trait LayerNormKernels: Backend {
    /// The LayerNorm forward.
    fn layer_norm_forward(inputs: LayerNormInputs<Self>) -> FloatTensor<Self>;
    /// `[∂(x + residual), ∂γ, ∂β]`.
    fn layer_norm_backward(
        inputs: LayerNormInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3];
}

fn attention_shape<B: Backend>(inputs: &AttentionInputs<B>) -> AttentionShape {
    let (q, k) = (inputs.query.shape(), inputs.key.shape());
    AttentionShape {
        batch: q[0],
        len_q: q[1],
        len_k: k[1],
        d_model: q[2],
        heads: inputs.heads,
    }
}

fn cpu_attention_forward<B: HostLend>(inputs: AttentionInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.query.dtype(), cpu_attention_forward_in(inputs))
}

fn cpu_attention_forward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: AttentionInputs<B>,
) -> FloatTensor<B> {
    let (device, dtype, shape) = (
        inputs.query.device(),
        inputs.query.dtype(),
        inputs.query.shape(),
    );
    let dims = attention_shape(&inputs);
    let q = B::lend_float::<T>("attention query", &inputs.query);
    let k = B::lend_float::<T>("attention key", &inputs.key);
    let v = B::lend_float::<T>("attention value", &inputs.value);
    let out = kernels::attention_forward(&q, &k, &v, dims);
    cpu_float_from::<B, T>(out, shape, dtype, &device)
}

fn cpu_attention_backward<B: HostLend>(
    inputs: AttentionInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 3] {
    in_precision!(
        inputs.query.dtype(),
        cpu_attention_backward_in(inputs, grad)
    )
}

fn cpu_attention_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: AttentionInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 3] {
    let device = inputs.query.device();
    let dims = attention_shape(&inputs);
    let shapes = [
        (inputs.query.shape(), inputs.query.dtype()),
        (inputs.key.shape(), inputs.key.dtype()),
        (inputs.value.shape(), inputs.value.dtype()),
    ];
    let g = B::lend_float::<T>("attention gradient", &grad);
    let q = B::lend_float::<T>("attention query", &inputs.query);
    let k = B::lend_float::<T>("attention key", &inputs.key);
    let v = B::lend_float::<T>("attention value", &inputs.value);
    let (dq, dk, dv) = kernels::attention_backward(&q, &k, &v, &g, dims);
    let [(sq, tq), (sk, tk), (sv, tv)] = shapes;
    [
        cpu_float_from::<B, T>(dq, sq, tq, &device),
        cpu_float_from::<B, T>(dk, sk, tk, &device),
        cpu_float_from::<B, T>(dv, sv, tv, &device),
    ]
}

fn cpu_layer_norm_forward<B: HostLend>(inputs: LayerNormInputs<B>) -> FloatTensor<B> {
    in_precision!(inputs.x.dtype(), cpu_layer_norm_forward_in(inputs))
}

fn cpu_layer_norm_forward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: LayerNormInputs<B>,
) -> FloatTensor<B> {
    let (device, dtype, shape) = (inputs.x.device(), inputs.x.dtype(), inputs.x.shape());
    let x = B::lend_float::<T>("layer norm input", &inputs.x);
    let r = B::lend_float::<T>("layer norm residual", &inputs.residual);
    let gamma = B::lend_float::<T>("layer norm gamma", &inputs.gamma);
    let beta = B::lend_float::<T>("layer norm beta", &inputs.beta);
    let out = kernels::add_layer_norm_forward(&x, &r, &gamma, &beta, inputs.epsilon);
    cpu_float_from::<B, T>(out, shape, dtype, &device)
}

fn cpu_layer_norm_backward<B: HostLend>(
    inputs: LayerNormInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 3] {
    in_precision!(inputs.x.dtype(), cpu_layer_norm_backward_in(inputs, grad))
}

fn cpu_layer_norm_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: LayerNormInputs<B>,
    grad: FloatTensor<B>,
) -> [FloatTensor<B>; 3] {
    let device = inputs.x.device();
    let (x_shape, x_dtype) = (inputs.x.shape(), inputs.x.dtype());
    let (p_shape, p_dtype) = (inputs.gamma.shape(), inputs.gamma.dtype());
    let b_dtype = inputs.beta.dtype();
    let g = B::lend_float::<T>("layer norm gradient", &grad);
    let x = B::lend_float::<T>("layer norm input", &inputs.x);
    let r = B::lend_float::<T>("layer norm residual", &inputs.residual);
    let gamma = B::lend_float::<T>("layer norm gamma", &inputs.gamma);
    let (dz, dgamma, dbeta) = kernels::add_layer_norm_backward(&x, &r, &gamma, &g, inputs.epsilon);
    [
        cpu_float_from::<B, T>(dz, x_shape, x_dtype, &device),
        cpu_float_from::<B, T>(dgamma, p_shape.clone(), p_dtype, &device),
        cpu_float_from::<B, T>(dbeta, p_shape, b_dtype, &device),
    ]
}

/// Implements both ops for a CPU backend through the shared slice kernels.
macro_rules! cpu_fusion_backend {
    ($backend:ty) => {
        impl FusionAttentionOps for $backend {
            fn fusion_attention(
                query: FloatTensor<Self>,
                key: FloatTensor<Self>,
                value: FloatTensor<Self>,
                heads: AttentionHeads,
            ) -> FloatTensor<Self> {
                cpu_attention_forward::<Self>(AttentionInputs {
                    query,
                    key,
                    value,
                    heads: heads.0,
                })
            }
        }

        impl AddLayerNormOps for $backend {
            fn add_layer_norm(
                x: FloatTensor<Self>,
                residual: FloatTensor<Self>,
                gamma: FloatTensor<Self>,
                beta: FloatTensor<Self>,
                epsilon: LayerNormEpsilon,
            ) -> FloatTensor<Self> {
                cpu_layer_norm_forward::<Self>(LayerNormInputs {
                    x,
                    residual,
                    gamma,
                    beta,
                    epsilon: epsilon.0,
                })
            }
        }

        impl AttentionKernels for $backend {
            fn attention_forward(inputs: AttentionInputs<Self>) -> FloatTensor<Self> {
                cpu_attention_forward::<Self>(inputs)
            }

            fn attention_backward(
                inputs: AttentionInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 3] {
                cpu_attention_backward::<Self>(inputs, grad)
            }
        }

        impl LayerNormKernels for $backend {
            fn layer_norm_forward(inputs: LayerNormInputs<Self>) -> FloatTensor<Self> {
                cpu_layer_norm_forward::<Self>(inputs)
            }

            fn layer_norm_backward(
                inputs: LayerNormInputs<Self>,
                grad: FloatTensor<Self>,
            ) -> [FloatTensor<Self>; 3] {
                cpu_layer_norm_backward::<Self>(inputs, grad)
            }
        }
    };
}

cpu_fusion_backend!(NdArray);
cpu_fusion_backend!(Flex);

#[derive(Debug)]
struct AttentionBackward;

impl<B: AttentionKernels> Backward<B, 3> for AttentionBackward {
    type State = AttentionInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, 3>(ops, grads, B::attention_backward);
    }
}

impl<B: FusionAttentionOps + AttentionKernels, C: CheckpointStrategy> FusionAttentionOps
    for Autodiff<B, C>
{
    fn fusion_attention(
        query: FloatTensor<Self>,
        key: FloatTensor<Self>,
        value: FloatTensor<Self>,
        heads: AttentionHeads,
    ) -> FloatTensor<Self> {
        let (query, q_node) = query.into_parts();
        let (key, k_node) = key.into_parts();
        let (value, v_node) = value.into_parts();
        let inputs = AttentionInputs {
            query,
            key,
            value,
            heads: heads.0,
        };
        record::<B, C, _, _, 3>(
            AttentionBackward,
            [q_node, k_node, v_node],
            inputs,
            B::attention_forward,
        )
    }
}

#[derive(Debug)]
struct LayerNormBackward;

impl<B: LayerNormKernels> Backward<B, 4> for LayerNormBackward {
    type State = LayerNormInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [x_parent, r_parent, gamma_parent, beta_parent] = ops.parents;
        let [dz, dgamma, dbeta] = B::layer_norm_backward(ops.state, grad);
        // The residual sum's two terms share one gradient.
        match (x_parent, r_parent) {
            (Some(x), Some(r)) => {
                grads.register::<B>(x.id, dz.clone());
                grads.register::<B>(r.id, dz);
            }
            (Some(p), None) | (None, Some(p)) => grads.register::<B>(p.id, dz),
            (None, None) => {}
        }
        if let Some(parent) = gamma_parent {
            grads.register::<B>(parent.id, dgamma);
        }
        if let Some(parent) = beta_parent {
            grads.register::<B>(parent.id, dbeta);
        }
    }
}

impl<B: AddLayerNormOps + LayerNormKernels, C: CheckpointStrategy> AddLayerNormOps
    for Autodiff<B, C>
{
    fn add_layer_norm(
        x: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: LayerNormEpsilon,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (residual, r_node) = residual.into_parts();
        let (gamma, gamma_node) = gamma.into_parts();
        let (beta, beta_node) = beta.into_parts();
        let inputs = LayerNormInputs {
            x,
            residual,
            gamma,
            beta,
            epsilon: epsilon.0,
        };
        record::<B, C, _, _, 4>(
            LayerNormBackward,
            [x_node, r_node, gamma_node, beta_node],
            inputs,
            B::layer_norm_forward,
        )
    }
}

impl<B: FusionBackend + AttentionKernels> AttentionKernels for Fusion<B> {
    fn attention_forward(inputs: AttentionInputs<Self>) -> FloatTensor<Self> {
        let spec = float_like::<B>(&inputs.query, inputs.query.shape());
        let heads = inputs.heads;
        let [out] = array(deferred::<B, _>(
            "attention_forward",
            attention_inputs(inputs),
            vec![spec],
            move |v| {
                vec![Value::Float(B::attention_forward(attention_values(
                    v, heads,
                )))]
            },
        ));
        out
    }

    fn attention_backward(
        inputs: AttentionInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3] {
        let specs = vec![
            float_like::<B>(&inputs.query, inputs.query.shape()),
            float_like::<B>(&inputs.key, inputs.key.shape()),
            float_like::<B>(&inputs.value, inputs.value.shape()),
        ];
        let heads = inputs.heads;
        let mut recorded = attention_inputs(inputs);
        recorded.push(Input::Float(grad));
        array(deferred::<B, _>(
            "attention_backward",
            recorded,
            specs,
            move |mut v| {
                let grad = v.pop().expect("the gradient was recorded last").float();
                B::attention_backward(attention_values(v, heads), grad)
                    .map(Value::Float)
                    .into()
            },
        ))
    }
}

/// The attention op's tensors as a deferred op records them.
fn attention_inputs<B: FusionBackend>(inputs: AttentionInputs<Fusion<B>>) -> Vec<Input<B>> {
    vec![
        Input::Float(inputs.query),
        Input::Float(inputs.key),
        Input::Float(inputs.value),
    ]
}

/// The attention op's inputs back from a deferred op's values (in [`attention_inputs`]' order).
fn attention_values<B: FusionBackend>(values: Vec<Value<B>>, heads: usize) -> AttentionInputs<B> {
    let [query, key, value] = array(values);
    AttentionInputs {
        query: query.float(),
        key: key.float(),
        value: value.float(),
        heads,
    }
}

impl<B: FusionBackend + LayerNormKernels> LayerNormKernels for Fusion<B> {
    fn layer_norm_forward(inputs: LayerNormInputs<Self>) -> FloatTensor<Self> {
        let spec = float_like::<B>(&inputs.x, inputs.x.shape());
        let epsilon = inputs.epsilon;
        let [out] = array(deferred::<B, _>(
            "layer_norm_forward",
            layer_norm_inputs(inputs),
            vec![spec],
            move |v| {
                vec![Value::Float(B::layer_norm_forward(layer_norm_values(
                    v, epsilon,
                )))]
            },
        ));
        out
    }

    fn layer_norm_backward(
        inputs: LayerNormInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3] {
        let specs = vec![
            float_like::<B>(&inputs.x, inputs.x.shape()),
            float_like::<B>(&inputs.gamma, inputs.gamma.shape()),
            float_like::<B>(&inputs.beta, inputs.beta.shape()),
        ];
        let epsilon = inputs.epsilon;
        let mut recorded = layer_norm_inputs(inputs);
        recorded.push(Input::Float(grad));
        array(deferred::<B, _>(
            "layer_norm_backward",
            recorded,
            specs,
            move |mut v| {
                let grad = v.pop().expect("the gradient was recorded last").float();
                let grads = B::layer_norm_backward(layer_norm_values(v, epsilon), grad);
                grads.into_iter().map(Value::Float).collect()
            },
        ))
    }
}

/// The LayerNorm op's four tensors, in the order [`layer_norm_values`] reads them back.
fn layer_norm_inputs<B: FusionBackend>(inputs: LayerNormInputs<Fusion<B>>) -> Vec<Input<B>> {
    [inputs.x, inputs.residual, inputs.gamma, inputs.beta]
        .into_iter()
        .map(Input::Float)
        .collect()
}

fn layer_norm_values<B: FusionBackend>(values: Vec<Value<B>>, epsilon: f64) -> LayerNormInputs<B> {
    let [x, residual, gamma, beta] = array(values);
    LayerNormInputs {
        x: x.float(),
        residual: residual.float(),
        gamma: gamma.float(),
        beta: beta.float(),
        epsilon,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Tensor, TensorData};
    use lifegom_render::rng::Rng;
    use lifegom_render::testing::read;

    /// The op against its `f64` definition (`kernels::add_layer_norm_*`), output and all four
    /// gradients, on any device: on CubeCL devices this runs the row and column kernels of
    /// `super::cube`, elsewhere the host kernels. The shapes cover a row shorter and longer than
    /// a row kernel's cube (64 threads), fewer and more rows than a column chunk (64), and more
    /// rows than one dispatch row of cubes holds (65,535).
    fn add_layer_norm_matches_f64_definition(device: &burn::tensor::Device) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(11);
        let eps = 1e-5;
        for (rows, d) in [(1, 1), (5, 200), (150, 24), (130, 1152), (70_000, 3)] {
            // Values the f32 tensors hold exactly, so the f64 reference sees the same inputs.
            let mut draw = |n: usize| -> Vec<f64> {
                (0..n)
                    .map(|_| f64::from((rng.uniform() * 2.0 - 1.0) as f32))
                    .collect()
            };
            let (mut x, r, w) = (draw(rows * d), draw(rows * d), draw(rows * d));
            // Odd channels shifted by 5, so that every row of two or more channels has a variance
            // of at least 1/4: a row of nearly equal values is ill-conditioned in f32 (its output
            // divides rounding errors by its spread) whatever the kernel.
            for (i, v) in x.iter_mut().enumerate() {
                if i % d % 2 == 1 {
                    *v = f64::from((*v + 5.0) as f32);
                }
            }
            let (gamma, beta) = (draw(d), draw(d));
            let f32s = |v: &[f64]| v.iter().map(|&a| a as f32).collect::<Vec<f32>>();
            let matrix = |v: &[f64]| {
                Tensor::<2>::from_data(TensorData::new(f32s(v), [rows, d]), &ad).require_grad()
            };
            let vector = |v: &[f64]| {
                Tensor::<1>::from_data(TensorData::new(f32s(v), [d]), &ad).require_grad()
            };
            let (xt, rt, gt, bt) = (matrix(&x), matrix(&r), vector(&gamma), vector(&beta));
            let y = Tensor::<2>::from_dispatch(
                <burn::backend::Dispatch as AddLayerNormOps>::add_layer_norm(
                    xt.clone().into_dispatch(),
                    rt.clone().into_dispatch(),
                    gt.clone().into_dispatch(),
                    bt.clone().into_dispatch(),
                    LayerNormEpsilon(eps),
                ),
            );
            let grads = (y.clone() * matrix(&w).detach()).sum().backward();

            let want_y = kernels::add_layer_norm_forward(&x, &r, &gamma, &beta, eps);
            let (want_dz, want_dgamma, want_dbeta) =
                kernels::add_layer_norm_backward(&x, &r, &gamma, &w, eps);
            // Within 1e-5 of the largest value; the column sums (f32 sums over up to 70,000 rows,
            // in another order than f64's) within 1e-5 of the row count times the largest `∂z`
            // (at least 1), a bound on their terms' magnitudes summed.
            let check = |what: &str, got: Vec<f32>, want: &[f64], scale: f64| {
                for (i, (&g, &e)) in got.iter().zip(want).enumerate() {
                    assert!(
                        (f64::from(g) - e).abs() <= 1e-5 * scale,
                        "{what}[{i}] ({rows} × {d}): {g} vs {e}"
                    );
                }
            };
            let max_abs = |v: &[f64]| v.iter().fold(1e-3f64, |m, a| m.max(a.abs()));
            let column_scale = (rows as f64).max(1.0) * max_abs(&want_dz).max(1.0);
            check("y", read(y), &want_y, max_abs(&want_y));
            let dz_scale = max_abs(&want_dz);
            check(
                "dx",
                read(xt.grad(&grads).expect("x gradient")),
                &want_dz,
                dz_scale,
            );
            check(
                "dr",
                read(rt.grad(&grads).expect("r gradient")),
                &want_dz,
                dz_scale,
            );
            check(
                "dgamma",
                read(gt.grad(&grads).expect("gamma gradient")),
                &want_dgamma,
                column_scale,
            );
            check(
                "dbeta",
                read(bt.grad(&grads).expect("beta gradient")),
                &want_dbeta,
                column_scale,
            );
        }
    }

    lifegom_render::cpu_backend_tests!(add_layer_norm => add_layer_norm_matches_f64_definition);

    #[test]
    fn add_layer_norm_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            add_layer_norm_matches_f64_definition(&device);
        }
    }
}
