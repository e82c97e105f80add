//! The aggregation step of the Point Transformer's vector attention (design.md §7.5): each
//! point's output is the sum over its `k` neighbours of their values, weighted per channel by a
//! softmax over the neighbours,
//!
//! `out[i, s, j] = Σ_κ softmax_κ(w[i, ·, j])[κ] · v[i, κ, s, j]`,
//!
//! with `v` `[n, k, S, C/S]` (the S value channels that share one weight channel, `share_planes`)
//! and the attention logits `w` `[n, k, C/S]`; the result is `[n, C]` (`s`-major).
//!
//! [`aggregate`] computes it:
//! - on the CPU backends as the plain tensor-op composition ([`aggregate_reference`]: softmax,
//!   broadcast product, sum over the neighbours), whose autodiff nodes are cheap there and whose
//!   numerics are the network's since it was written;
//! - on CubeCL devices through the [`op::VectorAttentionOps`] extension: one forward kernel and
//!   one backward kernel (`cube`) in place of the composition's eight forward and about a dozen
//!   backward launches per layer and pass.
//!
//! On CubeCL devices the layer's neighbourhood work around the attention-weight MLP runs as two
//! more ops ([`neighbour_op`]), so that the gathered keys and values are never materialised:
//! - [`relation`]: the input of `MLP_w`, `relu(BN₀(k_j − q_i + δ_ij))`, from the layer's one
//!   `[n, 3c]` product of queries, keys and values, the neighbour table and the positional
//!   encoding `δ`;
//! - [`aggregate_gathered`]: [`aggregate`] with the values `v_j + δ_ij` gathered inside.
//!
//! - [`position_encoding`]: `MLP_p`'s two layers, `δ = relu(rel·W₀ + b₀)·W₃ + b₃` (three hidden
//!   units), as one forward and one backward launch per pass, plus one for the weights'
//!   gradient of all the passes that share a [`PositionWeights`] ([`position_op`]).
//!
//! The first two each replace two gathers, their scatter-add backwards and zero-fills, and the broadcast
//! arithmetic between them (about twenty launches per layer and pass in all) with one forward and
//! two backward launches. The CPU backends compose the same maths from tensor ops
//! ([`relation_reference`], [`aggregate_gathered_reference`]), which are also the test reference.

mod cube;
mod neighbour_cube;
pub mod neighbour_op;
pub mod op;
mod position_cube;
pub mod position_op;

use burn::tensor::activation::softmax;
use burn::tensor::{Int, Tensor, TensorData};
use lifegom_render::device::runs_on_host;
use lifegom_render::select::select_rows;
use lifegom_render::split::join_columns;

/// `Σ_κ softmax_κ(logits)·values` (module docs): `values` `[n, k, S, C/S]`, `logits`
/// `[n, k, C/S]` → `[n, C]`.
///
/// # Panics
///
/// If the shapes do not match as above.
pub fn aggregate(values: Tensor<4>, logits: Tensor<3>) -> Tensor<2> {
    let [n, k, s, cs] = values.dims();
    assert_eq!(
        logits.dims(),
        [n, k, cs],
        "vector attention: logits must be [n, k, C/S] for values {:?}",
        values.dims()
    );
    if runs_on_host(&values.device()) {
        return aggregate_reference(values, logits);
    }
    let out: Tensor<3> = Tensor::from_dispatch(
        <burn::backend::Dispatch as op::VectorAttentionOps>::attention_aggregate(
            values.into_dispatch(),
            logits.into_dispatch(),
        ),
    );
    out.reshape([n, s * cs])
}

/// [`aggregate`] as Burn tensor ops: the specification, and the implementation on the CPU
/// backends.
pub fn aggregate_reference(values: Tensor<4>, logits: Tensor<3>) -> Tensor<2> {
    let [n, _, s, cs] = values.dims();
    let weights = softmax(logits, 1);
    (values * weights.unsqueeze_dim::<4>(2))
        .sum_dim(1)
        .reshape([n, s * cs])
}

/// The relation of the Point Transformer layer through its frozen BatchNorm and ReLU (the first
/// two steps of `MLP_w`): for point `i` and its κ-th neighbour `j = neighbours[i·k + κ]`,
/// `relu((k_j − q_i + δ[i, κ])·scale + shift)` per channel.
///
/// `qkv` `[n, 3c]` holds the queries, keys and values in its column blocks `0..c`, `c..2c`,
/// `2c..3c`; `neighbours` `[n·k]` (every index in `0..n`); `delta` `[n, k, c]`; `scale`,
/// `shift` `[c]` are constants (no gradient reaches them on CubeCL devices: callers pass a
/// frozen BatchNorm's fold). Returns `[n, k, c]`.
///
/// # Panics
///
/// If the shapes do not match as above, or `k = 0`.
pub fn relation(
    qkv: Tensor<2>,
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    scale: Tensor<1>,
    shift: Tensor<1>,
) -> Tensor<3> {
    relation_paired(
        qkv,
        neighbours,
        delta,
        scale,
        shift,
        neighbour_op::AttentionPair::unpaired(),
    )
}

/// A frozen BatchNorm's per-channel `scale` and `shift` (`[c]`, constants) and a ReLU after the
/// layer's output: the Point Transformer block's `relu(BN₂(·))`, which [`attend`] applies in the
/// aggregation's launch on CubeCL devices.
#[derive(Debug, Clone)]
pub struct OutputNorm {
    /// `γ/√(σ²+ε)`.
    pub scale: Tensor<1>,
    /// `β − μ·scale`.
    pub shift: Tensor<1>,
}

/// The layer's queries, keys and values, `[n, c]` each: one `[n, 3c]` product's output where
/// products stack (`crate::shared_linear::SharedLinear::stacks_on`), else three.
#[derive(Debug, Clone)]
pub enum QueryKeyValue {
    /// `[n, 3c]`, the column blocks `0..c`, `c..2c`, `2c..3c`.
    Stacked(Box<Tensor<2>>),
    /// `[q, k, v]`.
    Apart(Box<[Tensor<2>; 3]>),
}

/// The whole neighbourhood part of the layer: [`relation`], then `mlp` (the rest of `MLP_w`) on
/// it for the logits, then [`aggregate_gathered`], then `relu(··scale + shift)` with
/// `output_norm`'s when given; `[n, c]`. On CubeCL devices the two ops are paired
/// ([`neighbour_op::AttentionPair`]): their gradients for `qkv` and `δ` are added inside the
/// relation's backward instead of by two more launches; and the norm and ReLU are the
/// aggregation's, forward and backward. `mlp` must use its input (the pairing relies on the
/// relation's backward running).
///
/// # Panics
///
/// As [`relation`] and [`aggregate_gathered`], or if the norm's vectors are not `[c]`.
pub fn attend(
    qkv: QueryKeyValue,
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    scale: Tensor<1>,
    shift: Tensor<1>,
    mlp: impl FnOnce(Tensor<3>) -> Tensor<3>,
    output_norm: Option<OutputNorm>,
) -> Tensor<2> {
    let qkv = match qkv {
        QueryKeyValue::Apart(parts) if runs_on_host(&parts[0].device()) => {
            let h = attend_reference(*parts, neighbours, delta, scale, shift, mlp);
            return match output_norm {
                Some(OutputNorm { scale, shift }) => {
                    crate::activation::relu(h * scale.unsqueeze_dim(0) + shift.unsqueeze_dim(0))
                }
                None => h,
            };
        }
        QueryKeyValue::Apart(parts) => join_columns(Vec::from(*parts)),
        QueryKeyValue::Stacked(qkv) => *qkv,
    };
    let pair = neighbour_op::AttentionPair::new();
    let related = relation_paired(
        qkv.clone(),
        neighbours.clone(),
        delta.clone(),
        scale,
        shift,
        pair.clone(),
    );
    aggregate_gathered_paired(qkv, neighbours, delta, mlp(related), pair, output_norm)
}

/// [`attend`] without an output norm as the CPU backends compose it from queries, keys and
/// values apart: each neighbour's key and value gathered, `relu((k_j − q_i + δ)·scale + shift)`
/// into `mlp`, and [`aggregate`] of `v_j + δ`.
pub fn attend_reference(
    [q, k, v]: [Tensor<2>; 3],
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    scale: Tensor<1>,
    shift: Tensor<1>,
    mlp: impl FnOnce(Tensor<3>) -> Tensor<3>,
) -> Tensor<2> {
    let [n, kn, c] = delta.dims();
    let keys = select_rows(k, 0, neighbours.clone()).reshape([n, kn, c]);
    let values = select_rows(v, 0, neighbours).reshape([n, kn, c]);
    let w = keys - q.unsqueeze_dim::<3>(1) + delta.clone();
    let w = crate::activation::relu(w * scale.reshape([1, 1, c]) + shift.reshape([1, 1, c]));
    let w = mlp(w); // [n, k, c/s]
    let cs = w.dims()[2];
    aggregate((values + delta).reshape([n, kn, c / cs, cs]), w)
}

fn relation_paired(
    qkv: Tensor<2>,
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    scale: Tensor<1>,
    shift: Tensor<1>,
    pair: neighbour_op::AttentionPair,
) -> Tensor<3> {
    check_gathered_shapes(&qkv, &neighbours, &delta);
    let c = delta.dims()[2];
    assert_eq!(scale.dims(), [c], "relation: scale must be [c]");
    assert_eq!(shift.dims(), [c], "relation: shift must be [c]");
    if runs_on_host(&qkv.device()) {
        return relation_reference(qkv, neighbours, delta, scale, shift);
    }
    Tensor::from_dispatch(
        <burn::backend::Dispatch as neighbour_op::NeighbourAttentionOps>::attention_relation(
            qkv.into_dispatch(),
            neighbours.into_dispatch(),
            delta.into_dispatch(),
            scale.into_dispatch(),
            shift.into_dispatch(),
            pair,
        ),
    )
}

/// [`aggregate`] of the gathered values `v_j + δ[i, κ]` (`qkv`, `neighbours`, `delta` as in
/// [`relation`]) with `logits` `[n, k, C/S]`; returns `[n, c]`.
///
/// # Panics
///
/// If the shapes do not match, or `C/S` does not divide `c`.
pub fn aggregate_gathered(
    qkv: Tensor<2>,
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    logits: Tensor<3>,
) -> Tensor<2> {
    aggregate_gathered_paired(
        qkv,
        neighbours,
        delta,
        logits,
        neighbour_op::AttentionPair::unpaired(),
        None,
    )
}

fn aggregate_gathered_paired(
    qkv: Tensor<2>,
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    logits: Tensor<3>,
    pair: neighbour_op::AttentionPair,
    output_norm: Option<OutputNorm>,
) -> Tensor<2> {
    check_gathered_shapes(&qkv, &neighbours, &delta);
    let [n, k, c] = delta.dims();
    let cs = logits.dims()[2];
    assert!(
        logits.dims() == [n, k, cs] && cs > 0 && c.is_multiple_of(cs),
        "vector attention: logits {:?} must be [n, k, C/S] for delta {:?}",
        logits.dims(),
        delta.dims()
    );
    if let Some(norm) = &output_norm {
        assert!(
            norm.scale.dims() == [c] && norm.shift.dims() == [c],
            "vector attention: the output norm's scale and shift must be [c]"
        );
    }
    if runs_on_host(&qkv.device()) {
        let h = aggregate_gathered_reference(qkv, neighbours, delta, logits);
        return match output_norm {
            Some(OutputNorm { scale, shift }) => {
                crate::activation::relu(h * scale.unsqueeze_dim(0) + shift.unsqueeze_dim(0))
            }
            None => h,
        };
    }
    // Without a norm the op reads neither vector: `δ`'s handle is passed in their place.
    let (ending, out_scale, out_shift) = match output_norm {
        Some(OutputNorm { scale, shift }) => (
            neighbour_op::AggregateEnding::NormRelu,
            scale.into_dispatch(),
            shift.into_dispatch(),
        ),
        None => (
            neighbour_op::AggregateEnding::Plain,
            delta.clone().into_dispatch(),
            delta.clone().into_dispatch(),
        ),
    };
    Tensor::from_dispatch(
        <burn::backend::Dispatch as neighbour_op::NeighbourAttentionOps>::attention_aggregate_gathered(
            qkv.into_dispatch(),
            neighbours.into_dispatch(),
            delta.into_dispatch(),
            logits.into_dispatch(),
            out_scale,
            out_shift,
            ending,
            pair,
        ),
    )
}

/// The positional encoding `δ = relu(rel·W₀ + b₀)·W₃ + b₃` of the Point Transformer layer
/// (`MLP_p` with its BatchNorm folded into `W₀`, `b₀`) for neighbour offsets `rel` `[n, k, 3]`,
/// `w0` `[3, 3]`, `b0` `[3]`, `w3` `[3, c]`, `b3` `[c]` (Burn's `[in, out]` layout); returns
/// `[n, k, c]`. Gradients reach every input.
///
/// # Panics
///
/// If the shapes do not match as above.
pub fn position_encoding(
    rel: Tensor<3>,
    w0: Tensor<2>,
    b0: Tensor<1>,
    w3: Tensor<2>,
    b3: Tensor<1>,
) -> Tensor<3> {
    PositionWeights::new(w0, b0, w3, b3).apply(rel)
}

/// `W₀` `[3, 3]`, `b₀` `[3]`, `W₃` `[3, c]`, `b₃` `[c]`.
fn check_position_weights(w0: &Tensor<2>, b0: &Tensor<1>, w3: &Tensor<2>, b3: &Tensor<1>) {
    let c = w3.dims()[1];
    assert!(
        w0.dims() == [3, 3] && b0.dims() == [3] && w3.dims() == [3, c] && b3.dims() == [c],
        "position encoding: W0 {:?}, b0 {:?}, W3 {:?}, b3 {:?} must be [3, 3], [3], [3, c], [c]",
        w0.dims(),
        b0.dims(),
        w3.dims(),
        b3.dims()
    );
}

/// `MLP_p`'s weights ([`position_encoding`]), kept for every pass of a reconstruction: on
/// CubeCL devices as one parameter vector whose gradient is summed over all the passes that
/// apply it in one launch ([`position_op`]).
#[derive(Debug, Clone)]
pub struct PositionWeights(Kept);

#[derive(Debug, Clone)]
enum Kept {
    /// `(W₀, b₀, W₃, b₃)`, run as two affine layers.
    Host(Box<(Tensor<2>, Tensor<1>, Tensor<2>, Tensor<1>)>),
    /// `[W₃, b₃, W₀, b₀]` after its parameter node, and the ledger its passes file with.
    Device(Box<(Tensor<1>, position_op::PositionLedger)>),
}

impl PositionWeights {
    /// The weights `W₀` `[3, 3]`, `b₀` `[3]`, `W₃` `[3, c]`, `b₃` `[c]` (Burn's `[in, out]`).
    ///
    /// # Panics
    ///
    /// If the shapes do not match as above.
    pub fn new(w0: Tensor<2>, b0: Tensor<1>, w3: Tensor<2>, b3: Tensor<1>) -> Self {
        if runs_on_host(&w0.device()) {
            check_position_weights(&w0, &b0, &w3, &b3);
            return Self(Kept::Host(Box::new((w0, b0, w3, b3))));
        }
        let device = w0.device();
        let ones = Tensor::<1>::from_data(TensorData::from([1.0f32; 3]), &device);
        let zeros = Tensor::<1>::from_data(TensorData::from([0.0f32; 3]), &device);
        Self::folded(w0, b0, ones, zeros, w3, b3)
    }

    /// The weights with `MLP_p`'s BatchNorm folded into the first layer: `W₀·diag(scale)`,
    /// `b₀·scale + shift`, for a frozen BatchNorm's `scale`, `shift` `[3]` (constants: no
    /// gradient reaches them on CubeCL devices). On a device the fold is part of the one launch
    /// that makes the parameter vector, and its backward part of the one that sums the passes'
    /// gradients ([`position_op`]).
    ///
    /// # Panics
    ///
    /// If the shapes do not match as in [`Self::new`].
    pub fn folded(
        w0: Tensor<2>,
        b0: Tensor<1>,
        scale: Tensor<1>,
        shift: Tensor<1>,
        w3: Tensor<2>,
        b3: Tensor<1>,
    ) -> Self {
        check_position_weights(&w0, &b0, &w3, &b3);
        assert!(
            scale.dims() == [3] && shift.dims() == [3],
            "position encoding: the fold's scale and shift must be [3]"
        );
        if runs_on_host(&w0.device()) {
            let w0 = w0 * scale.clone().unsqueeze_dim(0);
            let b0 = b0 * scale + shift;
            return Self(Kept::Host(Box::new((w0, b0, w3, b3))));
        }
        let ledger = position_op::PositionLedger::default();
        let vector = Tensor::from_dispatch(
            <burn::backend::Dispatch as position_op::PositionEncodingOps>::position_weights(
                w3.into_dispatch(),
                b3.into_dispatch(),
                w0.into_dispatch(),
                b0.into_dispatch(),
                scale.into_dispatch(),
                shift.into_dispatch(),
                ledger.clone(),
            ),
        );
        Self(Kept::Device(Box::new((vector, ledger))))
    }

    /// The encoding of `rel` `[n, k, 3]`, `[n, k, c]`.
    ///
    /// # Panics
    ///
    /// If `rel`'s last axis is not 3.
    pub fn apply(&self, rel: Tensor<3>) -> Tensor<3> {
        assert_eq!(
            rel.dims()[2],
            3,
            "position encoding: rel {:?} must be [n, k, 3]",
            rel.dims()
        );
        match &self.0 {
            Kept::Host(weights) => {
                let (w0, b0, w3, b3) = weights.as_ref().clone();
                position_encoding_reference(rel, w0, b0, w3, b3)
            }
            Kept::Device(kept) => {
                let (vector, ledger) = kept.as_ref();
                Tensor::from_dispatch(
                    <burn::backend::Dispatch as position_op::PositionEncodingOps>::position_encoding(
                        rel.into_dispatch(),
                        vector.clone().into_dispatch(),
                        ledger.clone(),
                    ),
                )
            }
        }
    }
}

/// [`position_encoding`] as the two affine layers the network runs on the CPU backends.
pub fn position_encoding_reference(
    rel: Tensor<3>,
    w0: Tensor<2>,
    b0: Tensor<1>,
    w3: Tensor<2>,
    b3: Tensor<1>,
) -> Tensor<3> {
    let hidden = burn::tensor::activation::relu(crate::linear_op::affine(rel, w0, Some(b0)));
    crate::linear_op::affine(hidden, w3, Some(b3))
}

/// `qkv` `[n, 3c]`, `neighbours` `[n·k]`, `delta` `[n, k, c]` with `k ≥ 1`.
fn check_gathered_shapes(qkv: &Tensor<2>, neighbours: &Tensor<1, Int>, delta: &Tensor<3>) {
    let [n, k, c] = delta.dims();
    assert!(
        qkv.dims() == [n, 3 * c] && neighbours.dims() == [n * k] && k > 0,
        "vector attention: qkv {:?} and neighbours {:?} must be [n, 3c] and [n·k] for delta {:?}",
        qkv.dims(),
        neighbours.dims(),
        delta.dims()
    );
}

/// The neighbours' rows of `qkv`, `[n, k, 3c]`.
fn gather_neighbours(qkv: Tensor<2>, neighbours: Tensor<1, Int>, k: usize) -> Tensor<3> {
    let [n, c3] = qkv.dims();
    select_rows(qkv, 0, neighbours).reshape([n, k, c3])
}

/// [`relation`] as Burn tensor ops.
pub fn relation_reference(
    qkv: Tensor<2>,
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    scale: Tensor<1>,
    shift: Tensor<1>,
) -> Tensor<3> {
    let [n, k, c] = delta.dims();
    let q = qkv.clone().slice([0..n, 0..c]);
    let keys = gather_neighbours(qkv, neighbours, k).slice([0..n, 0..k, c..2 * c]);
    let pre = keys - q.unsqueeze_dim::<3>(1) + delta;
    burn::tensor::activation::relu(pre * scale.reshape([1, 1, c]) + shift.reshape([1, 1, c]))
}

/// [`aggregate_gathered`] as Burn tensor ops.
pub fn aggregate_gathered_reference(
    qkv: Tensor<2>,
    neighbours: Tensor<1, Int>,
    delta: Tensor<3>,
    logits: Tensor<3>,
) -> Tensor<2> {
    let [n, k, c] = delta.dims();
    let cs = logits.dims()[2];
    let values = gather_neighbours(qkv, neighbours, k).slice([0..n, 0..k, 2 * c..3 * c]) + delta;
    aggregate_reference(values.reshape([n, k, c / cs, cs]), logits)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::rng::Rng;
    use lifegom_render::testing::read;

    /// [`aggregate`] against [`aggregate_reference`] computed on Flex: values and the gradients
    /// of both inputs, with logits large enough that the softmax's max shift matters and one
    /// neighbour set where every logit is equal.
    fn check_matches_reference(device: &Device) {
        let (n, k, s, cs) = (37usize, 5usize, 3usize, 4usize);
        let mut rng = Rng::new(11);
        let values: Vec<f32> = (0..n * k * s * cs)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let mut logits: Vec<f32> = (0..n * k * cs)
            .map(|_| rng.range_f32(-30.0, 30.0))
            .collect();
        for kk in 0..k {
            for j in 0..cs {
                logits[kk * cs + j] = 2.5;
            }
        }
        let weight: Vec<f32> = (0..n * s * cs).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let run = |device: &Device, fused: bool| {
            let ad = device.clone().autodiff();
            let v = Tensor::<4>::from_data(TensorData::new(values.clone(), [n, k, s, cs]), &ad)
                .require_grad();
            let w = Tensor::<3>::from_data(TensorData::new(logits.clone(), [n, k, cs]), &ad)
                .require_grad();
            let out = if fused {
                aggregate(v.clone(), w.clone())
            } else {
                aggregate_reference(v.clone(), w.clone())
            };
            assert_eq!(out.dims(), [n, s * cs]);
            let g = Tensor::<2>::from_data(TensorData::new(weight.clone(), [n, s * cs]), &ad);
            let grads = (out.clone() * g).sum().backward();
            [
                read(out),
                read(v.grad(&grads).expect("values gradient")),
                read(w.grad(&grads).expect("logits gradient")),
            ]
        };
        let want = run(&Device::flex(), false);
        let got = run(device, true);
        for (name, (a, b)) in ["values", "values gradient", "logits gradient"]
            .iter()
            .zip(got.iter().zip(&want))
        {
            assert_eq!(a.len(), b.len(), "{name}");
            let diff = a
                .iter()
                .zip(b)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(diff <= 1e-5, "{name} on {device:?}: max diff {diff:.2e}");
        }
        assert!(
            got[2].iter().any(|g| g.abs() > 1e-3),
            "logit gradients vanished"
        );
    }

    lifegom_render::cpu_backend_tests!(aggregate_matches_reference => check_matches_reference);

    /// [`relation`] and [`aggregate_gathered`] against their references computed on Flex, chained
    /// as a layer chains them (one `qkv` and one `δ` feeding both, so their gradients add up):
    /// values and the gradients of `qkv`, `δ` and the logits. Neighbour lists repeat points, hold
    /// the point itself, and leave some points ungathered; the BatchNorm's scale is negative on
    /// some channels and its shift puts about half of the ReLU's inputs below zero.
    fn check_gathered_match_reference(device: &Device) {
        let (n, k, c, cs) = (37usize, 5usize, 12usize, 4usize);
        let mut rng = Rng::new(23);
        let mut uniform = |len: usize, lo: f32, hi: f32| -> Vec<f32> {
            (0..len).map(|_| rng.range_f32(lo, hi)).collect()
        };
        let qkv = uniform(n * 3 * c, -1.0, 1.0);
        let delta = uniform(n * k * c, -1.0, 1.0);
        let logits = uniform(n * k * cs, -4.0, 4.0);
        let scale = uniform(c, -1.5, 1.5);
        let shift = uniform(c, -0.3, 0.3);
        let out_weight = uniform(n * c, -1.0, 1.0);
        let relation_weight = uniform(n * k * c, -1.0, 1.0);
        let neighbours: Vec<i64> = (0..n * k)
            .map(|ik| {
                let (i, kk) = (ik / k, ik % k);
                if kk == 0 {
                    i as i64
                } else {
                    ((i * 7 + kk * kk * 3) % (n - 4)) as i64
                }
            })
            .collect();
        let run = |device: &Device, fused: bool| {
            let ad = device.clone().autodiff();
            fn t<const D: usize>(v: &[f32], shape: [usize; D], device: &Device) -> Tensor<D> {
                Tensor::from_data(TensorData::new(v.to_vec(), shape), device)
            }
            let qkv = t(&qkv, [n, 3 * c], &ad).require_grad();
            let delta = t(&delta, [n, k, c], &ad).require_grad();
            let logits = t(&logits, [n, k, cs], &ad).require_grad();
            let nbr = Tensor::<1, burn::tensor::Int>::from_data(
                TensorData::new(neighbours.clone(), [n * k]),
                &ad,
            );
            let (scale, shift) = (t(&scale, [c], &ad), t(&shift, [c], &ad));
            let (rel, out) = if fused {
                (
                    relation(qkv.clone(), nbr.clone(), delta.clone(), scale, shift),
                    aggregate_gathered(qkv.clone(), nbr, delta.clone(), logits.clone()),
                )
            } else {
                (
                    relation_reference(qkv.clone(), nbr.clone(), delta.clone(), scale, shift),
                    aggregate_gathered_reference(qkv.clone(), nbr, delta.clone(), logits.clone()),
                )
            };
            let loss = (out.clone() * t(&out_weight, [n, c], &ad)).sum()
                + (rel.clone() * t(&relation_weight, [n, k, c], &ad)).sum();
            let grads = loss.backward();
            [
                read(rel),
                read(out),
                read(qkv.grad(&grads).expect("qkv gradient")),
                read(delta.grad(&grads).expect("delta gradient")),
                read(logits.grad(&grads).expect("logits gradient")),
            ]
        };
        let want = run(&Device::flex(), false);
        let got = run(device, true);
        let names = [
            "relation",
            "aggregate",
            "qkv gradient",
            "delta gradient",
            "logits gradient",
        ];
        for (name, (a, b)) in names.iter().zip(got.iter().zip(&want)) {
            assert_eq!(a.len(), b.len(), "{name}");
            let diff = a
                .iter()
                .zip(b)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(diff <= 1e-5, "{name} on {device:?}: max diff {diff:.2e}");
        }
        let zeros = want[0].iter().filter(|v| **v == 0.0).count();
        assert!(
            zeros > want[0].len() / 5 && zeros < want[0].len() * 4 / 5,
            "the ReLU should cut part of the relation: {zeros} of {} are zero",
            want[0].len()
        );
    }

    /// [`PositionWeights`] applied by 1, 3 and 6 passes (six: more than one launch adds the
    /// passes' partial sums) against the reference on Flex: values and the gradients of every
    /// input, over more rows than one partial sum covers (the backward's two-stage sums, the
    /// last chunk short), with about half of the hidden units cut by the ReLU; at 10 channels
    /// and at 70, where the weights' gradient (292 elements) has more elements than a chunk's
    /// cube has threads.
    fn check_position_encoding_matches_reference(device: &Device) {
        for (n, k, c) in [(97, 7, 10), (40, 8, 70)] {
            check_position_encoding(device, n, k, c);
        }
    }

    fn check_position_encoding(device: &Device, n: usize, k: usize, c: usize) {
        let mut rng = Rng::new(31);
        let mut uniform = |len: usize, lo: f32, hi: f32| -> Vec<f32> {
            (0..len).map(|_| rng.range_f32(lo, hi)).collect()
        };
        let rel = uniform(n * k * 3, -0.5, 0.5);
        let w0 = uniform(9, -2.0, 2.0);
        let b0 = uniform(3, -0.3, 0.3);
        let w3 = uniform(3 * c, -1.0, 1.0);
        let b3 = uniform(c, -1.0, 1.0);
        let probe = uniform(n * k * c, -1.0, 1.0);
        let (fold_scale, fold_shift) = (uniform(3, -1.5, 1.5), uniform(3, -0.3, 0.3));
        let run = |device: &Device, op: bool, passes: usize, fold: bool| {
            let ad = device.clone().autodiff();
            fn t<const D: usize>(v: &[f32], shape: [usize; D], device: &Device) -> Tensor<D> {
                Tensor::from_data(TensorData::new(v.to_vec(), shape), device).require_grad()
            }
            let rel = t(&rel, [n, k, 3], &ad);
            let (w0, b0) = (t(&w0, [3, 3], &ad), t(&b0, [3], &ad));
            let (w3, b3) = (t(&w3, [3, c], &ad), t(&b3, [c], &ad));
            // With `fold`, a frozen BatchNorm's scale and shift folded into the first layer.
            let (scale, shift) = if fold {
                (
                    Tensor::<1>::from_data(TensorData::new(fold_scale.clone(), [3]), &ad),
                    Tensor::<1>::from_data(TensorData::new(fold_shift.clone(), [3]), &ad),
                )
            } else {
                (Tensor::<1>::ones([3], &ad), Tensor::<1>::zeros([3], &ad))
            };
            let kept = match fold {
                true => PositionWeights::folded(
                    w0.clone(),
                    b0.clone(),
                    scale.clone(),
                    shift.clone(),
                    w3.clone(),
                    b3.clone(),
                ),
                false => PositionWeights::new(w0.clone(), b0.clone(), w3.clone(), b3.clone()),
            };
            let (w0f, b0f) = (
                w0.clone() * scale.clone().unsqueeze_dim(0),
                b0.clone() * scale + shift,
            );
            let mut out = None;
            for pass in 0..passes {
                // Each pass reads other offsets, as the feedback passes' meshes differ.
                let rel = rel.clone() * (1.0 - 0.2 * pass as f32);
                let y = if op {
                    kept.apply(rel)
                } else {
                    position_encoding_reference(
                        rel,
                        w0f.clone(),
                        b0f.clone(),
                        w3.clone(),
                        b3.clone(),
                    )
                };
                out = Some(match out {
                    None => y,
                    Some(o) => o + y.tanh(),
                });
            }
            let out = out.expect("a pass");
            let grads = (out.clone() * t(&probe, [n, k, c], &ad)).sum().backward();
            let g = |name: &str, t: Option<Tensor<1>>| read(t.unwrap_or_else(|| panic!("{name}")));
            [
                read(out),
                read(rel.grad(&grads).expect("rel gradient")),
                read(w0.grad(&grads).expect("W0 gradient")),
                g("b0 gradient", b0.grad(&grads)),
                read(w3.grad(&grads).expect("W3 gradient")),
                g("b3 gradient", b3.grad(&grads)),
            ]
        };
        for (passes, fold) in [(1, false), (3, false), (6, false), (1, true), (3, true)] {
            let want = run(&Device::flex(), false, passes, fold);
            let got = run(device, true, passes, fold);
            let names = ["encoding", "rel", "W0", "b0", "W3", "b3"];
            for (name, (a, b)) in names.iter().zip(got.iter().zip(&want)) {
                assert_eq!(a.len(), b.len(), "{name}");
                let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1.0);
                let diff = a
                    .iter()
                    .zip(b)
                    .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
                assert!(
                    diff <= 1e-5 * scale,
                    "{name} on {device:?}, {passes} passes, fold {fold}: max diff {diff:.2e}"
                );
            }
        }
    }

    lifegom_render::cpu_backend_tests!(position_encoding_matches_reference => check_position_encoding_matches_reference);

    #[test]
    fn position_encoding_matches_reference_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            check_position_encoding_matches_reference(&device);
        }
    }

    /// [`attend`] (on CubeCL devices the paired ops, whose `qkv` and `δ` gradients add up in
    /// the relation's backward) against the reference composition on Flex: the output and the
    /// gradients of `qkv`, `δ` and a tensor the logits also read, with an MLP that mixes the
    /// relation's channels into the logits; with and without the block's norm and ReLU after
    /// it ([`OutputNorm`], whose shift puts part of the outputs under zero).
    fn check_attend_matches_reference(device: &Device) {
        for normed in [false, true] {
            check_attend(device, normed);
        }
    }

    fn check_attend(device: &Device, normed: bool) {
        let (n, k, c, cs) = (37usize, 5usize, 12usize, 4usize);
        let mut rng = Rng::new(29);
        let mut uniform = |len: usize, lo: f32, hi: f32| -> Vec<f32> {
            (0..len).map(|_| rng.range_f32(lo, hi)).collect()
        };
        let qkv = uniform(n * 3 * c, -1.0, 1.0);
        let delta = uniform(n * k * c, -1.0, 1.0);
        let bias = uniform(n * k * cs, -2.0, 2.0);
        let scale = uniform(c, -1.5, 1.5);
        let shift = uniform(c, -0.3, 0.3);
        let out_weight = uniform(n * c, -1.0, 1.0);
        let out_scale = uniform(c, -1.5, 1.5);
        let out_shift = uniform(c, -0.5, 0.2);
        let neighbours: Vec<i64> = (0..n * k)
            .map(|ik| ((ik / k) * 5 + (ik % k) * 11) as i64 % n as i64)
            .collect();
        let run = |device: &Device, paired: bool| {
            let ad = device.clone().autodiff();
            fn t<const D: usize>(v: &[f32], shape: [usize; D], device: &Device) -> Tensor<D> {
                Tensor::from_data(TensorData::new(v.to_vec(), shape), device)
            }
            let qkv = t(&qkv, [n, 3 * c], &ad).require_grad();
            let delta = t(&delta, [n, k, c], &ad).require_grad();
            let bias = t(&bias, [n, k, cs], &ad).require_grad();
            let nbr = Tensor::<1, burn::tensor::Int>::from_data(
                TensorData::new(neighbours.clone(), [n * k]),
                &ad,
            );
            let (scale, shift) = (t(&scale, [c], &ad), t(&shift, [c], &ad));
            let mlp = |related: Tensor<3>| {
                related
                    .reshape([n, k, c / cs, cs])
                    .sum_dim(2)
                    .reshape([n, k, cs])
                    * 0.7
                    + bias.clone()
            };
            let norm = normed.then(|| OutputNorm {
                scale: t(&out_scale, [c], &ad),
                shift: t(&out_shift, [c], &ad),
            });
            let out = if paired {
                attend(
                    QueryKeyValue::Stacked(Box::new(qkv.clone())),
                    nbr,
                    delta.clone(),
                    scale,
                    shift,
                    mlp,
                    norm,
                )
            } else {
                let related =
                    relation_reference(qkv.clone(), nbr.clone(), delta.clone(), scale, shift);
                let h = aggregate_gathered_reference(qkv.clone(), nbr, delta.clone(), mlp(related));
                match norm {
                    Some(OutputNorm { scale, shift }) => burn::tensor::activation::relu(
                        h * scale.unsqueeze_dim(0) + shift.unsqueeze_dim(0),
                    ),
                    None => h,
                }
            };
            let grads = (out.clone() * t(&out_weight, [n, c], &ad)).sum().backward();
            [
                read(out),
                read(qkv.grad(&grads).expect("qkv gradient")),
                read(delta.grad(&grads).expect("delta gradient")),
                read(bias.grad(&grads).expect("logit bias gradient")),
            ]
        };
        let want = run(&Device::flex(), false);
        let got = run(device, true);
        let names = [
            "output",
            "qkv gradient",
            "delta gradient",
            "logit bias gradient",
        ];
        for (name, (a, b)) in names.iter().zip(got.iter().zip(&want)) {
            assert_eq!(a.len(), b.len(), "{name}");
            let diff = a
                .iter()
                .zip(b)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(
                diff <= 1e-5,
                "{name} on {device:?}, normed {normed}: max diff {diff:.2e}"
            );
        }
    }

    lifegom_render::cpu_backend_tests!(attend_matches_reference => check_attend_matches_reference);

    #[test]
    fn attend_matches_reference_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            check_attend_matches_reference(&device);
        }
    }

    lifegom_render::cpu_backend_tests!(gathered_match_reference => check_gathered_match_reference);

    #[test]
    fn gathered_match_reference_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            check_gathered_match_reference(&device);
        }
    }

    #[test]
    fn aggregate_matches_reference_wgpu() {
        if let Some(device) = lifegom_render::testing::wgpu_test_device() {
            check_matches_reference(&device);
        }
    }
}
