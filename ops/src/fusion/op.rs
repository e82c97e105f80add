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
//! On CubeCL devices both are these ops too, as CubeCL kernels (`super::cube`,
//! `super::attention_cube`), except attention over more keys than the kernels hold, which keeps
//! the tensor-op composition ([`super::attention`] says which runs where); the compositions are
//! the reference the ops are tested against. The autodiff
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
/// three. Callers check shapes (see `lifegom_model::fusion::AttentionLayer`).
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

/// `LayerNorm(x + Dropout(residual))·γ + β` over the last dimension, the dropout mask drawn
/// inside the kernels from `draws[mask.slot]` ([`crate::dropout::kernel_mask`]): on a CubeCL
/// device the mask costs no launch of its own, forward or backward (design.md §7.4).
///
/// Inputs as [`AddLayerNormOps`], plus `draws` (`[k]` uniform draws in `[0, 1)`, `slot < k`);
/// gradients flow to `x`, `residual`, `gamma` and `beta`, not to `draws`.
#[backend_extension(NdArray, Flex, Cube, Fusion, Autodiff)]
pub trait AddDroppedLayerNormOps: Backend {
    /// Normalises the residual sum with the residual dropped.
    #[fusion(dtype = x, shape = x)]
    fn add_dropped_layer_norm(
        x: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        draws: FloatTensor<Self>,
        mask: DropoutSlot,
        epsilon: LayerNormEpsilon,
    ) -> FloatTensor<Self>;
}

/// Which of the `draws` seeds a kernel-drawn dropout mask, and the probability of keeping an
/// element.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DropoutSlot {
    /// The draw's index.
    pub slot: usize,
    /// `1 − p`, in `(0, 1]`.
    pub keep: f64,
}

/// A kernel-drawn dropout mask on one backend's tensors.
#[derive(Debug, Clone)]
pub struct KernelDropout<B: Backend> {
    pub(super) draws: FloatTensor<B>,
    pub(super) mask: DropoutSlot,
}

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
    /// Dropout on `residual`, its mask drawn in the kernels; `None` for none.
    pub(super) dropout: Option<KernelDropout<B>>,
}

impl<B: Backend> LayerNormInputs<B> {
    /// The inputs `[x, residual, γ, β]`, with the residual dropped by the mask of `dropout`'s
    /// draws and slot, if any.
    pub(super) fn new(
        [x, residual, gamma, beta]: [FloatTensor<B>; 4],
        epsilon: LayerNormEpsilon,
        dropout: Option<(FloatTensor<B>, DropoutSlot)>,
    ) -> Self {
        Self {
            x,
            residual,
            gamma,
            beta,
            epsilon: epsilon.0,
            dropout: dropout.map(|(draws, mask)| KernelDropout { draws, mask }),
        }
    }
}

/// The LayerNorm op's gradients: `[∂x, ∂residual, ∂γ, ∂β]` (the first two equal without
/// dropout).
pub type LayerNormGrads<B> = [FloatTensor<B>; 4];

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
    /// `[∂x, ∂residual, ∂γ, ∂β]`.
    fn layer_norm_backward(
        inputs: LayerNormInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> LayerNormGrads<Self>;
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
    let out = match cpu_mask::<B, T>(&inputs) {
        Some(mask) => {
            let dropped: Vec<T> = r.iter().zip(&mask).map(|(&v, &m)| v * m).collect();
            kernels::add_layer_norm_forward(&x, &dropped, &gamma, &beta, inputs.epsilon)
        }
        None => kernels::add_layer_norm_forward(&x, &r, &gamma, &beta, inputs.epsilon),
    };
    cpu_float_from::<B, T>(out, shape, dtype, &device)
}

/// The kernel-drawn dropout mask of `inputs`, if any, on the host, in `T`
/// ([`crate::dropout::kernel_mask`]).
fn cpu_mask<B: HostLend, T: Real + Element + Pod>(inputs: &LayerNormInputs<B>) -> Option<Vec<T>> {
    let dropout = inputs.dropout.as_ref()?;
    let draws = B::lend_float::<f32>("dropout draws", &dropout.draws);
    let n = inputs.residual.shape().num_elements();
    let mask = crate::dropout::kernel_mask(n, dropout.mask.keep, draws[dropout.mask.slot]);
    // `{0, 1/keep}` in f32, widened exactly to f64 in the precision tests.
    Some(
        mask.into_iter()
            .map(|m| num_traits::cast::<f32, T>(m).unwrap_or_else(T::zero))
            .collect(),
    )
}

fn cpu_layer_norm_backward<B: HostLend>(
    inputs: LayerNormInputs<B>,
    grad: FloatTensor<B>,
) -> LayerNormGrads<B> {
    in_precision!(inputs.x.dtype(), cpu_layer_norm_backward_in(inputs, grad))
}

fn cpu_layer_norm_backward_in<B: HostLend, T: Real + Element + Pod>(
    inputs: LayerNormInputs<B>,
    grad: FloatTensor<B>,
) -> LayerNormGrads<B> {
    let device = inputs.x.device();
    let (x_shape, x_dtype) = (inputs.x.shape(), inputs.x.dtype());
    let (r_shape, r_dtype) = (inputs.residual.shape(), inputs.residual.dtype());
    let (p_shape, p_dtype) = (inputs.gamma.shape(), inputs.gamma.dtype());
    let b_dtype = inputs.beta.dtype();
    let mask = cpu_mask::<B, T>(&inputs);
    let g = B::lend_float::<T>("layer norm gradient", &grad);
    let x = B::lend_float::<T>("layer norm input", &inputs.x);
    let r = B::lend_float::<T>("layer norm residual", &inputs.residual);
    let gamma = B::lend_float::<T>("layer norm gamma", &inputs.gamma);
    let (dz, dgamma, dbeta) = match &mask {
        Some(mask) => {
            let dropped: Vec<T> = r.iter().zip(mask).map(|(&v, &m)| v * m).collect();
            kernels::add_layer_norm_backward(&x, &dropped, &gamma, &g, inputs.epsilon)
        }
        None => kernels::add_layer_norm_backward(&x, &r, &gamma, &g, inputs.epsilon),
    };
    let dx = cpu_float_from::<B, T>(dz.clone(), x_shape, x_dtype, &device);
    let dr = match mask {
        Some(mask) => {
            let dr = dz.iter().zip(&mask).map(|(&v, &m)| v * m).collect();
            cpu_float_from::<B, T>(dr, r_shape, r_dtype, &device)
        }
        None => dx.clone(),
    };
    [
        dx,
        dr,
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
                cpu_layer_norm_forward::<Self>(LayerNormInputs::new(
                    [x, residual, gamma, beta],
                    epsilon,
                    None,
                ))
            }
        }

        impl AddDroppedLayerNormOps for $backend {
            fn add_dropped_layer_norm(
                x: FloatTensor<Self>,
                residual: FloatTensor<Self>,
                gamma: FloatTensor<Self>,
                beta: FloatTensor<Self>,
                draws: FloatTensor<Self>,
                mask: DropoutSlot,
                epsilon: LayerNormEpsilon,
            ) -> FloatTensor<Self> {
                cpu_layer_norm_forward::<Self>(LayerNormInputs::new(
                    [x, residual, gamma, beta],
                    epsilon,
                    Some((draws, mask)),
                ))
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
            ) -> LayerNormGrads<Self> {
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
        // Without dropout the residual sum's two terms share one gradient (two handles of one
        // buffer).
        gradient_per_input::<B, _, 4>(ops, grads, B::layer_norm_backward);
    }
}

/// The residual LayerNorm on `Autodiff<B, C>`, with or without a kernel-drawn dropout on the
/// residual: the node keeps the inputs (the draws take no gradient, and have no node here).
fn record_layer_norm<B: LayerNormKernels, C: CheckpointStrategy>(
    tensors: [FloatTensor<Autodiff<B, C>>; 4],
    epsilon: LayerNormEpsilon,
    dropout: Option<(FloatTensor<Autodiff<B, C>>, DropoutSlot)>,
) -> FloatTensor<Autodiff<B, C>> {
    let [
        (x, x_node),
        (residual, r_node),
        (gamma, gamma_node),
        (beta, beta_node),
    ] = tensors.map(|t| t.into_parts());
    let dropout = dropout.map(|(draws, mask)| (draws.into_parts().0, mask));
    record::<B, C, _, _, 4>(
        LayerNormBackward,
        [x_node, r_node, gamma_node, beta_node],
        LayerNormInputs::new([x, residual, gamma, beta], epsilon, dropout),
        B::layer_norm_forward,
    )
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
        record_layer_norm::<B, C>([x, residual, gamma, beta], epsilon, None)
    }
}

impl<B: AddDroppedLayerNormOps + LayerNormKernels, C: CheckpointStrategy> AddDroppedLayerNormOps
    for Autodiff<B, C>
{
    fn add_dropped_layer_norm(
        x: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        draws: FloatTensor<Self>,
        mask: DropoutSlot,
        epsilon: LayerNormEpsilon,
    ) -> FloatTensor<Self> {
        record_layer_norm::<B, C>([x, residual, gamma, beta], epsilon, Some((draws, mask)))
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
        let (epsilon, mask) = (inputs.epsilon, inputs.dropout.as_ref().map(|d| d.mask));
        let [out] = array(deferred::<B, _>(
            "layer_norm_forward",
            layer_norm_inputs(inputs),
            vec![spec],
            move |v| {
                vec![Value::Float(B::layer_norm_forward(layer_norm_values(
                    v, epsilon, mask,
                )))]
            },
        ));
        out
    }

    fn layer_norm_backward(
        inputs: LayerNormInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> LayerNormGrads<Self> {
        let (epsilon, mask) = (inputs.epsilon, inputs.dropout.as_ref().map(|d| d.mask));
        let mut specs = vec![float_like::<B>(&inputs.x, inputs.x.shape())];
        // Without dropout `∂residual` is `∂x`: one output for both.
        if mask.is_some() {
            specs.push(float_like::<B>(&inputs.residual, inputs.residual.shape()));
        }
        specs.push(float_like::<B>(&inputs.gamma, inputs.gamma.shape()));
        specs.push(float_like::<B>(&inputs.beta, inputs.beta.shape()));
        let mut recorded = layer_norm_inputs(inputs);
        recorded.push(Input::Float(grad));
        let mut out = deferred::<B, _>("layer_norm_backward", recorded, specs, move |mut v| {
            let grad = v.pop().expect("the gradient was recorded last").float();
            let [dx, dr, dgamma, dbeta] =
                B::layer_norm_backward(layer_norm_values(v, epsilon, mask), grad);
            let mut grads = vec![Value::Float(dx)];
            if mask.is_some() {
                grads.push(Value::Float(dr));
            }
            grads.extend([Value::Float(dgamma), Value::Float(dbeta)]);
            grads
        });
        if mask.is_none() {
            let dx = out[0].clone();
            out.insert(1, dx);
        }
        array(out)
    }
}

/// The LayerNorm op's tensors (the draws last, with dropout), in the order
/// [`layer_norm_values`] reads them back.
fn layer_norm_inputs<B: FusionBackend>(inputs: LayerNormInputs<Fusion<B>>) -> Vec<Input<B>> {
    [inputs.x, inputs.residual, inputs.gamma, inputs.beta]
        .into_iter()
        .chain(inputs.dropout.map(|d| d.draws))
        .map(Input::Float)
        .collect()
}

fn layer_norm_values<B: FusionBackend>(
    mut values: Vec<Value<B>>,
    epsilon: f64,
    mask: Option<DropoutSlot>,
) -> LayerNormInputs<B> {
    let dropout = mask.map(|mask| {
        let draws = values.pop().expect("the draws were recorded last").float();
        (draws, mask)
    });
    let tensors = array::<_, 4>(values).map(Value::float);
    LayerNormInputs::new(tensors, LayerNormEpsilon(epsilon), dropout)
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
    ///
    /// With dropout ([`AddDroppedLayerNormOps`], every shape a second time, slot 1 of two draws
    /// and keep 0.7) the reference drops the residual with the host's mask
    /// ([`crate::dropout::kernel_mask`]) and `∂residual = ∂z·m`: the kernels hash the same
    /// bits as the host.
    fn add_layer_norm_matches_f64_definition(device: &burn::tensor::Device) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(11);
        let eps = 1e-5;
        let (draws, keep) = ([0.3f32, 0.712_5], 0.7);
        let shapes = [(1, 1), (5, 200), (150, 24), (130, 1152), (70_000, 3)];
        for ((rows, d), dropped) in shapes
            .into_iter()
            .flat_map(|shape| [(shape, false), (shape, true)])
        {
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
            let y = if dropped {
                Tensor::<2>::from_dispatch(
                    <burn::backend::Dispatch as AddDroppedLayerNormOps>::add_dropped_layer_norm(
                        xt.clone().into_dispatch(),
                        rt.clone().into_dispatch(),
                        gt.clone().into_dispatch(),
                        bt.clone().into_dispatch(),
                        Tensor::<1>::from_floats(draws, &ad).into_dispatch(),
                        DropoutSlot { slot: 1, keep },
                        LayerNormEpsilon(eps),
                    ),
                )
            } else {
                Tensor::<2>::from_dispatch(
                    <burn::backend::Dispatch as AddLayerNormOps>::add_layer_norm(
                        xt.clone().into_dispatch(),
                        rt.clone().into_dispatch(),
                        gt.clone().into_dispatch(),
                        bt.clone().into_dispatch(),
                        LayerNormEpsilon(eps),
                    ),
                )
            };
            let grads = (y.clone() * matrix(&w).detach()).sum().backward();

            let mask: Vec<f64> = if dropped {
                crate::dropout::kernel_mask(rows * d, keep, draws[1])
                    .into_iter()
                    .map(f64::from)
                    .collect()
            } else {
                vec![1.0; rows * d]
            };
            if dropped && rows * d > 1000 {
                let kept = mask.iter().filter(|&&m| m != 0.0).count() as f64 / mask.len() as f64;
                assert!((kept - keep).abs() < 0.05, "kept {kept} of {rows} × {d}");
            }
            let r_dropped: Vec<f64> = r.iter().zip(&mask).map(|(v, m)| v * m).collect();
            let want_y = kernels::add_layer_norm_forward(&x, &r_dropped, &gamma, &beta, eps);
            let (want_dz, want_dgamma, want_dbeta) =
                kernels::add_layer_norm_backward(&x, &r_dropped, &gamma, &w, eps);
            let want_dr: Vec<f64> = want_dz.iter().zip(&mask).map(|(g, m)| g * m).collect();
            // Within 1e-5 of the largest value; the column sums (f32 sums over up to 70,000 rows,
            // in another order than f64's) within 1e-5 of the row count times the largest `∂z`
            // (at least 1), a bound on their terms' magnitudes summed.
            let check = |what: &str, got: Vec<f32>, want: &[f64], scale: f64| {
                for (i, (&g, &e)) in got.iter().zip(want).enumerate() {
                    assert!(
                        (f64::from(g) - e).abs() <= 1e-5 * scale,
                        "{what}[{i}] ({rows} × {d}, dropout {dropped}): {g} vs {e}"
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
                &want_dr,
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
