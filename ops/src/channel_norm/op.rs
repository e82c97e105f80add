//! [`super::ChannelNorm`] as a Burn backend extension for CubeCL devices, and the autodiff nodes
//! that sum `γ`'s and `β`'s gradients over every pass in one launch (see [`super`]).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff`; the CPU backends never reach it.
//!
//! - a **parameter node** (`channel_norm_parameters`), with `γ` and `β` as parents, hands `γ`'s
//!   value on (no launch) to every pass; Burn runs it after every pass's node (it is shallower).
//!   It adds the passes' partial sums up in one launch (four passes a launch) and registers `∂γ`
//!   and `∂β`;
//! - a **pass node** (`channel_norm`) keeps `x`, `γ` and `β` (handles; `β` enters as a constant,
//!   its gradient comes from the parameter node). Its backward writes `∂x` and the pass's partial
//!   sums of `g·x` and `g` per channel in one launch, files the partial sums with the
//!   parameter's [`NormLedger`] and, the first time, registers a placeholder for the parameter
//!   node (`γ`'s own handle: the right shape, no copy).

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use burn::tensor::Shape;
use lifegom_render::cube::deferred::{Input, Value, array, deferred, float_like};
use lifegom_render::op_backward::{PassLedger, record, reduce_in_launches};

use crate::activation::Activation;

/// Passes' partial sums added by one launch of [`ChannelNormKernels::channel_norm_totals`].
pub const TOTAL_PARTS: usize = 4;

/// The running statistics and `ε` of one BatchNorm: `μ`, `σ²` `[C]`, constants.
#[derive(Debug, Clone)]
pub struct NormStatistics<B: Backend> {
    /// Running mean.
    pub mean: FloatTensor<B>,
    /// Running variance.
    pub var: FloatTensor<B>,
    /// `ε`.
    pub epsilon: f32,
}

/// The partial sums the passes filed for one parameter vector (module docs).
pub type NormLedger = PassLedger;

/// A BatchNorm on its running statistics over axis 1 of `[N, C, H, W]` images, with trainable
/// `γ`, `β` read by several passes (see [`super`]).
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait ChannelNormOps: Backend {
    /// `γ` `[C]` as the parameter every pass reads, standing for `γ` and `β` in the backward
    /// (module docs): no launch.
    #[allow(clippy::too_many_arguments)]
    #[fusion(meta = |gamma, _beta, _mean, _var, _epsilon, _ledger| {
        TensorSpec::new(gamma.shape.clone(), gamma.dtype)
    })]
    fn channel_norm_parameters(
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        ledger: NormLedger,
    ) -> FloatTensor<Self>;

    /// `act(x·s + t)` per channel, `s = γ/√(σ²+ε)`, `t = β − μ·s`, with `γ` from `params`
    /// (the parameter node's output) and `β` `[C]`; `x`'s shape.
    #[allow(clippy::too_many_arguments)]
    #[fusion(dtype = x, shape = x.clone())]
    fn channel_norm(
        x: FloatTensor<Self>,
        params: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        activation: Activation,
        ledger: NormLedger,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can differentiate the ops.
#[doc(hidden)]
pub trait ChannelNormKernels: Backend {
    /// One pass's `(∂x, partial sums)`: the partial sums of `g·x` and `g` (after the
    /// activation's mask) per channel, `[rows · C · 2]` (`f32`).
    #[allow(clippy::too_many_arguments)]
    fn channel_norm_backward(
        x: FloatTensor<Self>,
        params: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        epsilon: f32,
        activation: Activation,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// 1 to [`TOTAL_PARTS`] passes' partial sums added up: `(sums [C · 2], ∂γ [C], ∂β [C])`,
    /// `sums` in the partial sums' own layout (one row), for a further launch.
    fn channel_norm_totals(
        partials: Vec<FloatTensor<Self>>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);
}

impl<B: FusionBackend + ChannelNormKernels> ChannelNormKernels for Fusion<B> {
    fn channel_norm_backward(
        x: FloatTensor<Self>,
        params: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        epsilon: f32,
        activation: Activation,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let partial_len = super::cube::partial_len(&x.shape());
        let specs = vec![
            float_like::<B>(&x, x.shape()),
            float_like::<B>(&x, Shape::new([partial_len])),
        ];
        let inputs = [x, params, beta, mean, var, grad]
            .into_iter()
            .map(Input::Float)
            .collect();
        let [dx, partial] = array(deferred::<B, _>(
            "channel_norm_backward",
            inputs,
            specs,
            move |v| {
                let [x, params, beta, mean, var, grad] = array(v);
                let (dx, partial) = B::channel_norm_backward(
                    x.float(),
                    params.float(),
                    beta.float(),
                    mean.float(),
                    var.float(),
                    grad.float(),
                    epsilon,
                    activation,
                );
                vec![Value::Float(dx), Value::Float(partial)]
            },
        ));
        (dx, partial)
    }

    fn channel_norm_totals(
        partials: Vec<FloatTensor<Self>>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let c = mean.shape()[0];
        let specs = vec![
            float_like::<B>(&mean, Shape::new([2 * c])),
            float_like::<B>(&mean, Shape::new([c])),
            float_like::<B>(&mean, Shape::new([c])),
        ];
        let parts = partials.len();
        let inputs = partials
            .into_iter()
            .chain([mean, var])
            .map(Input::Float)
            .collect();
        let [sums, dgamma, dbeta] = array(deferred::<B, _>(
            "channel_norm_totals",
            inputs,
            specs,
            move |mut v| {
                let var = v.pop().map(Value::float).expect("the variance");
                let mean = v.pop().map(Value::float).expect("the mean");
                debug_assert_eq!(v.len(), parts);
                let partials = v.into_iter().map(Value::float).collect();
                let (sums, dgamma, dbeta) = B::channel_norm_totals(partials, mean, var, epsilon);
                vec![
                    Value::Float(sums),
                    Value::Float(dgamma),
                    Value::Float(dbeta),
                ]
            },
        ));
        (sums, dgamma, dbeta)
    }
}

/// A pass node's state.
#[derive(Debug, Clone)]
pub struct PassInputs<B: Backend> {
    x: FloatTensor<B>,
    params: FloatTensor<B>,
    beta: FloatTensor<B>,
    mean: FloatTensor<B>,
    var: FloatTensor<B>,
    epsilon: f32,
    activation: Activation,
    ledger: NormLedger,
}

#[derive(Debug)]
struct PassBackward;

impl<B: ChannelNormKernels> Backward<B, 2> for PassBackward {
    type State = PassInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [x_node, params_node] = ops.parents;
        let s = ops.state;
        let (dx, partial) = B::channel_norm_backward(
            s.x,
            s.params.clone(),
            s.beta,
            s.mean,
            s.var,
            grad,
            s.epsilon,
            s.activation,
        );
        if let Some(node) = x_node {
            grads.register::<B>(node.id, dx);
        }
        if let Some(node) = params_node {
            s.ledger.file::<B, _>(grads, node.id, s.params, partial);
        }
    }
}

/// The parameter node's state.
#[derive(Debug, Clone)]
pub struct ParameterState<B: Backend> {
    mean: FloatTensor<B>,
    var: FloatTensor<B>,
    epsilon: f32,
    ledger: NormLedger,
}

#[derive(Debug)]
struct ParameterBackward;

impl<B: ChannelNormKernels> Backward<B, 2> for ParameterBackward {
    type State = ParameterState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        // The placeholder a pass node registered.
        let _ = grads.consume::<B>(&ops.node);
        let s = ops.state;
        let partials = s.ledger.take::<FloatTensor<B>>();
        let Some((dgamma, dbeta)) = reduce_in_launches(partials, TOTAL_PARTS, |parts| {
            let (sums, dgamma, dbeta) =
                B::channel_norm_totals(parts, s.mean.clone(), s.var.clone(), s.epsilon);
            (sums, (dgamma, dbeta))
        }) else {
            return;
        };
        let [gamma_node, beta_node] = ops.parents;
        for (node, grad) in [(gamma_node, dgamma), (beta_node, dbeta)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: ChannelNormOps + ChannelNormKernels, C: CheckpointStrategy> ChannelNormOps
    for Autodiff<B, C>
{
    fn channel_norm_parameters(
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        ledger: NormLedger,
    ) -> FloatTensor<Self> {
        let (gamma, gamma_node) = gamma.into_parts();
        let (beta, beta_node) = beta.into_parts();
        // The statistics are constants (frozen): their nodes are dropped.
        let [mean, var] = [mean, var].map(|t| t.into_primitive());
        let value = B::channel_norm_parameters(
            gamma,
            beta,
            mean.clone(),
            var.clone(),
            epsilon,
            ledger.clone(),
        );
        match ParameterBackward
            .prepare::<C>([gamma_node, beta_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(
                ParameterState {
                    mean,
                    var,
                    epsilon,
                    ledger,
                },
                value,
            ),
            OpsKind::UnTracked(prep) => prep.finish(value),
        }
    }

    fn channel_norm(
        x: FloatTensor<Self>,
        params: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        activation: Activation,
        ledger: NormLedger,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (params, params_node) = params.into_parts();
        // `β`'s gradient comes from the parameter node, which has it as a parent.
        let [beta, mean, var] = [beta, mean, var].map(|t| t.into_primitive());
        record::<B, C, _, _, 2>(
            PassBackward,
            [x_node, params_node],
            PassInputs {
                x,
                params,
                beta,
                mean,
                var,
                epsilon,
                activation,
                ledger,
            },
            |s| {
                B::channel_norm(
                    s.x,
                    s.params,
                    s.beta,
                    s.mean,
                    s.var,
                    s.epsilon,
                    s.activation,
                    s.ledger,
                )
            },
        )
    }
}
