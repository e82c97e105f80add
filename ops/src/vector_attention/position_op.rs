//! The Point Transformer layer's positional encoding ([`super::position_encoding`]) as a Burn
//! backend extension for CubeCL devices (design.md §7.5).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff` only: the CPU backends keep the two Linear layers,
//! and the public functions never route them here. The four weights travel as one parameter
//! vector `p = [W₃, b₃, W₀, b₀]` (`4c + 12`), whose gradient is a sum over every row of every
//! pass that reads it. As for the shared layers (`crate::shared_linear`), two kinds of node split
//! that sum:
//!
//! - a **product node** per pass (`position_encoding`) keeps `rel` and `p` (handles) and, in its
//!   backward, recomputes the hidden layer, registers `∂rel`, and files the pass's partial sums
//!   of the weights' gradient (one per `ROWS_PER_CHUNK` rows, the `position_cube` module) with the
//!   vector's [`PositionLedger`]; the first one registers a placeholder for the vector's node
//!   (`p`'s own handle: the right shape, no copy) so that Burn reaches it;
//! - a **parameter node** (`position_weights`) that makes the vector from the four weights in
//!   one launch, `W₀` and `b₀` folded with the frozen BatchNorm after them on the way
//!   (`W₀·diag(s)`, `b₀·s + t`; `s = 1`, `t = 0` without one). Burn runs it after every pass's
//!   node (it is shallower); it adds all filed partial sums up in one launch (four passes a
//!   launch), scales `W₀`'s and `b₀`'s columns by `s`, and registers the four gradients.
//!
//! Per layer and step that is two launches per pass and two in all, where one op per pass cost
//! three per pass, Burn's sums of the four weights' per-pass gradients four per further pass,
//! and the fold three forward and two backward.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use burn::tensor::Shape;
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{PassLedger, record, reduce_in_launches};

/// Passes' partial sums added by one launch of
/// [`PositionEncodingKernels::position_weight_totals`].
pub const TOTAL_PARTS: usize = 4;

/// The partial sums the passes' product nodes filed for one parameter vector (module docs).
pub type PositionLedger = PassLedger;

/// `relu(rel·W₀ + b₀)·W₃ + b₃` over the last axis of `rel` (`[.., 3]`), with the weights in one
/// vector `p = [W₃ (3·c, row-major [3, c]), b₃ (c), W₀ (9, row-major [3, 3]), b₀ (3)]`; the
/// output is `rel`'s shape with `c` last, in `rel`'s float dtype. Callers check shapes.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait PositionEncodingOps: Backend {
    /// The parameter vector every pass reads (module docs): `[W₃, b₃, W₀·diag(s), b₀·s + t]`
    /// from `w3` `[3, c]`, `b3` `[c]`, `w0` `[3, 3]`, `b0` `[3]` and the constants `scale` =
    /// `s`, `shift` = `t` `[3]`, which take no gradient.
    #[allow(clippy::too_many_arguments)]
    #[fusion(meta = |w3, _b3, _w0, _b0, _scale, _shift, _ledger| {
        burn::backend::fusion::custom::TensorSpec::new(
            Shape::new([4 * w3.shape[1] + 12]),
            w3.dtype,
        )
    })]
    fn position_weights(
        w3: FloatTensor<Self>,
        b3: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        ledger: PositionLedger,
    ) -> FloatTensor<Self>;

    /// One pass's encoding.
    #[fusion(dtype = rel, shape = {
        let mut shape = rel.clone();
        let last = shape.num_dims() - 1;
        shape[last] = (weights[0] - 12) / 4;
        shape
    })]
    fn position_encoding(
        rel: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        ledger: PositionLedger,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the op.
#[doc(hidden)]
pub trait PositionEncodingKernels: Backend {
    /// One pass's `(∂rel, partial sums)` for the output's gradient: the partial sums are
    /// `[chunks · (4c + 12)]` (`f32`), the weights' gradient over each chunk of rows.
    fn position_encoding_backward(
        rel: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// 1 to [`TOTAL_PARTS`] passes' partial sums added up: `(sums [4c + 12], [∂W₃, ∂b₃, ∂W₀,
    /// ∂b₀])`, `sums` in the partial sums' layout (one chunk) for a further launch, the
    /// gradients with `W₀`'s and `b₀`'s columns times `scale`.
    fn position_weight_totals(
        partials: Vec<FloatTensor<Self>>,
        scale: FloatTensor<Self>,
        c: usize,
    ) -> (FloatTensor<Self>, [FloatTensor<Self>; 4]);
}

impl<B: FusionBackend + PositionEncodingKernels> PositionEncodingKernels for Fusion<B> {
    fn position_encoding_backward(
        rel: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let outputs = weights.shape()[0];
        let rows = rel.shape().num_elements() / 3;
        let chunks = rows.div_ceil(super::position_cube::ROWS_PER_CHUNK).max(1);
        let specs = vec![
            float_like::<B>(&rel, rel.shape()),
            float_like::<B>(&weights, Shape::new([chunks * outputs])),
        ];
        let inputs = vec![Input::Float(rel), Input::Float(weights), Input::Float(grad)];
        let [rel_grad, partial] = array(deferred::<B, _>(
            "position_encoding_backward",
            inputs,
            specs,
            |v| {
                let [rel, weights, grad] = array(v);
                let (rel_grad, partial) =
                    B::position_encoding_backward(rel.float(), weights.float(), grad.float());
                vec![Value::Float(rel_grad), Value::Float(partial)]
            },
        ));
        (rel_grad, partial)
    }

    fn position_weight_totals(
        partials: Vec<FloatTensor<Self>>,
        scale: FloatTensor<Self>,
        c: usize,
    ) -> (FloatTensor<Self>, [FloatTensor<Self>; 4]) {
        let outputs = 4 * c + 12;
        let specs = vec![
            float_like::<B>(&partials[0], Shape::new([outputs])),
            float_like::<B>(&scale, Shape::new([3, c])),
            float_like::<B>(&scale, Shape::new([c])),
            float_like::<B>(&scale, Shape::new([3, 3])),
            float_like::<B>(&scale, Shape::new([3])),
        ];
        let inputs = partials
            .into_iter()
            .chain([scale])
            .map(Input::Float)
            .collect();
        let [sums, w3, b3, w0, b0] = array(deferred::<B, _>(
            "position_weight_totals",
            inputs,
            specs,
            move |mut v| {
                let scale = v.pop().map(Value::float).expect("the scale");
                let partials = v.into_iter().map(Value::float).collect();
                let (sums, grads) = B::position_weight_totals(partials, scale, c);
                std::iter::once(sums)
                    .chain(grads)
                    .map(Value::Float)
                    .collect()
            },
        ));
        (sums, [w3, b3, w0, b0])
    }
}

/// A product node's state.
#[derive(Debug, Clone)]
pub struct PositionInputs<B: Backend> {
    rel: FloatTensor<B>,
    weights: FloatTensor<B>,
    ledger: PositionLedger,
}

#[derive(Debug)]
struct PositionBackward;

impl<B: PositionEncodingKernels> Backward<B, 2> for PositionBackward {
    type State = PositionInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [rel_node, weights_node] = ops.parents;
        let s = ops.state;
        let (rel_grad, partial) = B::position_encoding_backward(s.rel, s.weights.clone(), grad);
        if let Some(node) = rel_node {
            grads.register::<B>(node.id, rel_grad);
        }
        if let Some(node) = weights_node {
            s.ledger.file::<B, _>(grads, node.id, s.weights, partial);
        }
    }
}

/// The parameter node's state: its ledger, the width `c`, and the fold's scale `s`.
#[derive(Debug, Clone)]
pub struct WeightsState<B: Backend> {
    ledger: PositionLedger,
    c: usize,
    scale: FloatTensor<B>,
}

#[derive(Debug)]
struct WeightsBackward;

impl<B: PositionEncodingKernels> Backward<B, 4> for WeightsBackward {
    type State = WeightsState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        // The placeholder a product node registered.
        let _ = grads.consume::<B>(&ops.node);
        let s = ops.state;
        let partials = s.ledger.take::<FloatTensor<B>>();
        let Some(weight_grads) = reduce_in_launches(partials, TOTAL_PARTS, |parts| {
            B::position_weight_totals(parts, s.scale.clone(), s.c)
        }) else {
            return;
        };
        for (parent, grad) in ops.parents.into_iter().zip(weight_grads) {
            if let Some(parent) = parent {
                grads.register::<B>(parent.id, grad);
            }
        }
    }
}

impl<B: PositionEncodingOps + PositionEncodingKernels, C: CheckpointStrategy> PositionEncodingOps
    for Autodiff<B, C>
{
    fn position_weights(
        w3: FloatTensor<Self>,
        b3: FloatTensor<Self>,
        w0: FloatTensor<Self>,
        b0: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        ledger: PositionLedger,
    ) -> FloatTensor<Self> {
        let c = w3.shape()[1];
        let [(w3, w3_node), (b3, b3_node), (w0, w0_node), (b0, b0_node)] =
            [w3, b3, w0, b0].map(|t| t.into_parts());
        // The frozen BatchNorm's constants: their nodes are dropped.
        let [scale, shift] = [scale, shift].map(|t| t.into_primitive());
        let value = B::position_weights(w3, b3, w0, b0, scale.clone(), shift, ledger.clone());
        match WeightsBackward
            .prepare::<C>([w3_node, b3_node, w0_node, b0_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(WeightsState { ledger, c, scale }, value),
            OpsKind::UnTracked(prep) => prep.finish(value),
        }
    }

    fn position_encoding(
        rel: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        ledger: PositionLedger,
    ) -> FloatTensor<Self> {
        let (rel, rel_node) = rel.into_parts();
        let (weights, weights_node) = weights.into_parts();
        record::<B, C, _, _, 2>(
            PositionBackward,
            [rel_node, weights_node],
            PositionInputs {
                rel,
                weights,
                ledger,
            },
            |s| B::position_encoding(s.rel, s.weights, s.ledger),
        )
    }
}
