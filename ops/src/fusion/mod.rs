//! The fusion layers' fused ops (design.md §7.4): the attention core (scores, softmax, weighted
//! values, for all heads) and each residual `LN(a + b)`, as custom ops with hand-written
//! backwards ([`op`]): slice code on the CPU backends (math in [`kernels`]), CubeCL kernels on
//! the devices. [`attention`], [`add_layer_norm`] and [`add_dropped_layer_norm`] call them on
//! plain tensors; [`attention_reference`] is the attention's tensor-op composition. The layers
//! themselves are `lifegom_model::fusion`.

mod attention_cube;
mod cube;
pub mod kernels;
pub mod op;

use burn::backend::Dispatch;
use burn::tensor::Tensor;
use burn::tensor::activation::softmax;
use lifegom_render::device::runs_on_host;

use op::{
    AddDroppedLayerNormOps, AddLayerNormOps, AttentionHeads, DropoutSlot, FusionAttentionOps,
    LayerNormEpsilon,
};

/// Scaled dot-product attention of projected `q` `[B, Lq, D]` over `k`, `v` `[B, Lk, D]`, with
/// `heads` heads side by side in the channels; `[B, Lq, D]`. One op; on a CubeCL device more
/// keys than the kernels hold (one query's scores live in a local array) take
/// [`attention_reference`].
pub fn attention(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, heads: usize) -> Tensor<3> {
    if !runs_on_host(&k.device()) && k.dims()[1] > attention_cube::MAX_KEYS {
        return attention_reference(q, k, v, heads);
    }
    Tensor::from_dispatch(<Dispatch as FusionAttentionOps>::fusion_attention(
        q.into_dispatch(),
        k.into_dispatch(),
        v.into_dispatch(),
        AttentionHeads(heads),
    ))
}

/// [`attention`] as Burn tensor ops: per head `softmax(q·kᵀ/√d_k)·v`.
pub fn attention_reference(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, heads: usize) -> Tensor<3> {
    let [b, lq, d] = q.dims();
    let [_, lk, _] = k.dims();
    let h = heads;
    let dk = d / h;
    let split = |t: Tensor<3>, l: usize| t.reshape([b, l, h, dk]).swap_dims(1, 2); // [B,H,L,dk]
    let (q, k, v) = (split(q, lq), split(k, lk), split(v, lk));
    let scores = q.matmul(k.swap_dims(2, 3)) / (dk as f64).sqrt();
    softmax(scores, 3)
        .matmul(v) // [B,H,Lq,dk]
        .swap_dims(1, 2)
        .reshape([b, lq, d])
}

/// `LayerNorm(x + residual)·γ + β` over the last dimension, one op.
pub fn add_layer_norm(
    x: Tensor<3>,
    residual: Tensor<3>,
    gamma: Tensor<1>,
    beta: Tensor<1>,
    epsilon: f64,
) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as AddLayerNormOps>::add_layer_norm(
        x.into_dispatch(),
        residual.into_dispatch(),
        gamma.into_dispatch(),
        beta.into_dispatch(),
        LayerNormEpsilon(epsilon),
    ))
}

/// `LayerNorm(x + Dropout(residual))·γ + β`, the dropout mask drawn inside the op from
/// `draws[slot]` ([`crate::dropout`]), keeping an element with probability `keep`.
pub fn add_dropped_layer_norm(
    x: Tensor<3>,
    residual: Tensor<3>,
    gamma: Tensor<1>,
    beta: Tensor<1>,
    (draws, slot): (Tensor<1>, usize),
    keep: f64,
    epsilon: f64,
) -> Tensor<3> {
    Tensor::from_dispatch(
        <Dispatch as AddDroppedLayerNormOps>::add_dropped_layer_norm(
            x.into_dispatch(),
            residual.into_dispatch(),
            gamma.into_dispatch(),
            beta.into_dispatch(),
            draws.into_dispatch(),
            DropoutSlot { slot, keep },
            LayerNormEpsilon(epsilon),
        ),
    )
}
