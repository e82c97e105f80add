//! The shared layer's two ops as a Burn backend extension, and the autodiff nodes that defer the
//! parameters' gradients to one product (see [`super`]).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff`. Without autodiff both ops are their default
//! bodies: [`SharedLinearOps::shared_parameter`] hands its input back and
//! [`SharedLinearOps::shared_linear`] is Burn's product and broadcast bias add, which Burn's
//! fusion sees as it sees `Linear::forward`. The autodiff implementation is where the layer
//! differs from Burn's:
//!
//! - a **product node** per pass (`shared_linear`) computes `∂x = g·Wᵀ` and files `(x, g)` in
//!   the layer's [`Ledger`] instead of registering `∂W` and `∂b`. So that the parameter nodes
//!   are reached, the first product node to run registers a placeholder for each of them: the
//!   parameter's own handle, which has the right shape and costs no copy and no launch;
//! - a **parameter node** (`shared_parameter`), one for the weight and one for the bias, between
//!   the parameter (a folded weight, a stacked one or a `Param`) and every pass's product. It
//!   runs after all of them, since Burn's autodiff runs nodes deepest first and each product
//!   node is deeper than the parameter nodes it reads. It drops the placeholder and registers
//!   `∂W = Xᵀ·G` or `∂b = Σ_rows G` from the ledger's rows, stacked once for both by one
//!   launch (`stack_pass_rows`, the `cube` module). When both take a gradient, the stack
//!   appends a column of ones to `X` and one product answers both, `[X | 1]ᵀ·G = [∂W; ∂b]`:
//!   the bias's sum costs no launch of its own (two fewer per layer than summing `G` apart).
//!
//! A layer that a frozen BatchNorm follows is folded with it by [`SharedLinearOps::shared_fold`]:
//! one launch makes `W·diag(s)` and `b·s + t` (`s = γ/√(σ²+ε)`, `t = β − μ·s`) from the
//! parameters and the statistics (the `fold` module), and its two parameter nodes stand between
//! `W`, `b` and the folded values. The BN's columns scale enter the gradient where the rows are
//! stacked, `∂W = Xᵀ·(G·diag(s))` and `∂b = Σ_rows G·diag(s)`: the fold's backward costs no
//! launch of its own.
//!
//! # Split-k
//!
//! `∂W = Xᵀ·G` is a small output over a long reduction (every pass's rows), which Burn's CubeCL
//! matmul gives to a handful of cubes; so the stacking pads the rows to whole chunks with zeros
//! (in the same launch) and the weight's node forms the gradient as chunked products and a sum
//! ([`crate::split_k`]): one more launch per layer. The padding rows of `X`'s ones column are
//! zero too; a bias without a weight gradient is a sum of the padded `G`, chunked the same way.

use std::any::Any;
use std::sync::{Arc, Mutex, PoisonError};

use crate::activation::Activation;
use crate::activation::op::ReluKernels;
use burn::backend::autodiff::NodeId;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, NodeGuard, Ops, OpsKind};
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, AutodiffBackend, Backend, TensorMetadata, backend_extension};
use burn::tensor::Shape;
use lifegom_render::cube::deferred::float_like;
use lifegom_render::cube::deferred::{Input, Value, array, deferred};

use crate::split_k::SplitK;

/// Which parameter of the layer a [`SharedLinearOps::shared_parameter`] node stands for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The weight `[in, out]`: its gradient is `Xᵀ·G`.
    Weight,
    /// The bias `[out]`: its gradient is `Σ_rows G`.
    Bias,
}

/// Whether a folded layer has a bias of its own ([`SharedLinearOps::shared_fold`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FoldBias {
    /// The bias argument is the layer's bias `b`: the folded bias is `b·s + t`.
    Given,
    /// The layer has none and the bias argument is not read (pass any `[out]` tensor, e.g. the
    /// BN's `β`): the folded bias is `t`.
    Absent,
}

/// One layer's record of its passes' backward: the inputs and output gradients of every
/// product node that has run, and which parameter nodes still wait for them (module docs).
/// Clones share one record.
#[derive(Clone, Default)]
pub struct Ledger(Arc<Mutex<LedgerState>>);

impl std::fmt::Debug for Ledger {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Ledger")
    }
}

#[derive(Default)]
struct LedgerState {
    /// `Rows<B>` of the backend that runs the backward; typed on first use.
    rows: Option<Box<dyn Any + Send>>,
    /// Whether a placeholder was registered for the weight / bias node.
    seeded: [bool; 2],
    /// Parameter nodes that have taken their gradient; the rows are freed when every seeded
    /// one has.
    delivered: [bool; 2],
}

/// The rows filed by the product nodes, and their stacks once made.
struct Rows<B: Backend> {
    /// `[rows, in]` per pass, when the weight takes a gradient.
    inputs: Vec<FloatTensor<B>>,
    /// `[rows, out]` per pass.
    grads: Vec<FloatTensor<B>>,
    /// The parameters' gradients once formed: `[∂W; ∂b]` from one product when both take
    /// one, else `(X, G)` for each node to form its own (every pass's rows, one after the
    /// other, padded for the split).
    formed: Option<Formed<B>>,
}

/// How a layer's parameter gradients were formed ([`Rows::formed`]).
enum Formed<B: Backend> {
    /// `[X | 1 | 0…]ᵀ·G` `[in + BIAS_COLUMNS, out]`: `∂W` is its first `in` rows, `∂b` the next.
    Joint {
        product: FloatTensor<B>,
        inputs: usize,
    },
    /// The stacked rows, for the one parameter that takes a gradient.
    Apart {
        split: SplitK,
        x: Option<FloatTensor<B>>,
        g: FloatTensor<B>,
    },
}

impl Ledger {
    fn lock(&self) -> std::sync::MutexGuard<'_, LedgerState> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl LedgerState {
    fn rows<B: Backend>(&mut self) -> &mut Rows<B> {
        self.rows
            .get_or_insert_with(|| {
                Box::new(Rows::<B> {
                    inputs: Vec::new(),
                    grads: Vec::new(),
                    formed: None,
                })
            })
            .downcast_mut::<Rows<B>>()
            .expect("one layer's passes run on one backend")
    }
}

/// `t` `[.., c]` as `[rows, c]` (a view).
fn flatten<B: Backend>(t: FloatTensor<B>) -> FloatTensor<B> {
    let shape = t.shape();
    let c = shape[shape.num_dims() - 1];
    if shape.num_dims() == 2 {
        return t;
    }
    B::float_reshape(t, Shape::new([shape.num_elements() / c, c]))
}

/// Passes stacked by one launch of [`StackKernels::stack_pass_rows`].
pub const STACK_PARTS: usize = 4;

/// Columns appended to `X` when the bias's gradient comes from the weight's product (module
/// docs): the ones, then zeros, so that `X`'s width stays a multiple of four when the layer's
/// input width is (the width of the rows Burn's matmul reads as vectors of four).
pub const BIAS_COLUMNS: usize = 4;

/// `(X, G)`: the passes' rows one after the other (module docs), `G`'s columns times `scale`
/// for a folded layer, then zero rows up to `padded_rows`, and `extra_columns` columns after
/// `X`'s ([`BIAS_COLUMNS`] or none). A lone pass without a scale, padding or extra columns is
/// handed back; more than [`STACK_PARTS`] are stacked that many at a time, each stack then
/// being one part of the next launch (the scale, the padding and the columns applied by the
/// last).
fn stack<B: StackKernels>(
    mut inputs: Vec<FloatTensor<B>>,
    mut grads: Vec<FloatTensor<B>>,
    scale: Option<FloatTensor<B>>,
    padded_rows: usize,
    extra_columns: usize,
) -> (Option<FloatTensor<B>>, FloatTensor<B>) {
    // Without a weight gradient the gradients stand in for the inputs; their stack is dropped.
    let with_inputs = !inputs.is_empty();
    if !with_inputs {
        inputs = grads.clone();
    }
    let rows: usize = grads.iter().map(|g| g.shape()[0]).sum();
    let mut scale = scale;
    // Whether the last launch has rows or columns to add.
    let mut widen = padded_rows != rows || extra_columns > 0;
    while grads.len() > 1 || (grads.len() == 1 && (scale.is_some() || widen)) {
        let take = grads.len().min(STACK_PARTS);
        let last = take == grads.len();
        let to_rows = if last {
            padded_rows
        } else {
            grads[..take].iter().map(|g| g.shape()[0]).sum()
        };
        let (x, g) = B::stack_pass_rows(
            inputs.drain(..take).collect(),
            grads.drain(..take).collect(),
            if last { scale.take() } else { None },
            to_rows,
            if last { extra_columns } else { 0 },
        );
        if last {
            widen = false;
        }
        inputs.insert(0, x);
        grads.insert(0, g);
    }
    let g = grads.pop().expect("a pass filed its rows");
    (inputs.pop().filter(|_| with_inputs), g)
}

/// What a backend implements so that `Autodiff<B>` can stack the passes' rows.
#[doc(hidden)]
pub trait StackKernels: Backend {
    /// `(X, G)`: the rows of `xs` `[rows_t, in]` one after the other, and those of `gs`
    /// `[rows_t, out]` times `scale` `[out]` per column when given, then zero rows up to
    /// `padded_rows` (at least `Σ rows_t`), in one launch; 1 to [`STACK_PARTS`] passes, pass
    /// `t` of both with the same rows. `X` has `extra_columns` more columns: ones on the
    /// passes' rows in the first of them, zeros elsewhere (`[rows, in + extra_columns]`).
    fn stack_pass_rows(
        xs: Vec<FloatTensor<Self>>,
        gs: Vec<FloatTensor<Self>>,
        scale: Option<FloatTensor<Self>>,
        padded_rows: usize,
        extra_columns: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

impl<B: FusionBackend + StackKernels> StackKernels for Fusion<B> {
    fn stack_pass_rows(
        xs: Vec<FloatTensor<Self>>,
        gs: Vec<FloatTensor<Self>>,
        scale: Option<FloatTensor<Self>>,
        padded_rows: usize,
        extra_columns: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let passes = gs.len();
        let scaled = scale.is_some();
        let rows = padded_rows;
        let specs = vec![
            float_like::<B>(&xs[0], Shape::new([rows, xs[0].shape()[1] + extra_columns])),
            float_like::<B>(&gs[0], Shape::new([rows, gs[0].shape()[1]])),
        ];
        let inputs = xs
            .into_iter()
            .chain(gs)
            .chain(scale)
            .map(Input::Float)
            .collect();
        let [x, g] = array(deferred::<B, _>(
            "stack_pass_rows",
            inputs,
            specs,
            move |mut v| {
                let scale = if scaled {
                    v.pop().map(Value::float)
                } else {
                    None
                };
                let gs = v.split_off(passes).into_iter().map(Value::float).collect();
                let xs = v.into_iter().map(Value::float).collect();
                let (x, g) = B::stack_pass_rows(xs, gs, scale, padded_rows, extra_columns);
                vec![Value::Float(x), Value::Float(g)]
            },
        ));
        (x, g)
    }
}

/// `x·W + b` for `x` `[.., in]`, `W` `[in, out]`, `b` `[out]`, with the parameters' gradient
/// summed over every pass that reads them (see [`super`]).
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait SharedLinearOps: Backend {
    /// The parameter every pass's product reads: the same values (module docs).
    #[fusion(default)]
    fn shared_parameter(value: FloatTensor<Self>, ledger: Ledger, role: Role) -> FloatTensor<Self> {
        let _ = (ledger, role);
        value
    }

    /// The weight `[in, out]` and bias `[out]` of a layer folded with the frozen BatchNorm that
    /// follows it, as the parameters every pass's product reads (module docs): `W·diag(s)`,
    /// `b·s + t` (or `t`, see [`FoldBias`]) and `s` itself, with `s = γ/√(σ²+ε)` and
    /// `t = β − μ·s` from the BN's `γ`, `β`, running mean `μ` and variance `σ²`, each `[out]`.
    /// The statistics and `γ`, `β` take no gradient.
    #[allow(clippy::too_many_arguments)]
    #[fusion(meta = |weight, bias, _gamma, _beta, _mean, _var, _kind, _epsilon, _ledger| {
        (weight.clone(), bias.clone(), bias.clone())
    })]
    fn shared_fold(
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        kind: FoldBias,
        epsilon: f32,
        ledger: Ledger,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>);

    /// One pass's product, `act(x·W + b)`.
    #[fusion(dtype = x, shape = product_shape(x, weight))]
    fn shared_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        ledger: Ledger,
        activation: Activation,
    ) -> FloatTensor<Self>;

    /// One pass's product with a residual `r` (`[.., out]`) added before a ReLU,
    /// `relu(x·W + b + r)`: a residual block's last layer.
    #[fusion(dtype = x, shape = product_shape(x, weight))]
    fn shared_linear_residual(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        ledger: Ledger,
    ) -> FloatTensor<Self>;
}

/// The shape of `x·W` for `x` `[.., in]` and `W` `[in, out]`: `x`'s with its last axis `out`.
fn product_shape(x: &Shape, weight: &Shape) -> Shape {
    let mut dims = x.to_vec();
    if let Some(last) = dims.last_mut() {
        *last = weight[1];
    }
    Shape::from(dims)
}

/// What a backend implements so that `Autodiff<B>` can differentiate a shared layer through
/// its ReLU in one launch.
#[doc(hidden)]
pub trait ProductKernels: Backend {
    /// `(∂x, g ⊙ [y > 0])` with `∂x = (g ⊙ [y > 0])·Wᵀ`, for the gradient `grad` `[.., out]` of
    /// the layer's output `output` (same shape) and its weight `[in, out]` (Burn's ReLU
    /// backward: the gradient is zeroed where the output is `≤ 0`).
    fn relu_product_backward(
        grad: FloatTensor<Self>,
        output: FloatTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

impl<B: FusionBackend + ProductKernels> ProductKernels for Fusion<B> {
    fn relu_product_backward(
        grad: FloatTensor<Self>,
        output: FloatTensor<Self>,
        weight: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(
                &grad,
                product_shape(&grad.shape(), &transposed(&weight.shape())),
            ),
            float_like::<B>(&grad, grad.shape()),
        ];
        let inputs = vec![
            Input::Float(grad),
            Input::Float(output),
            Input::Float(weight),
        ];
        let [dx, masked] = array(deferred::<B, _>(
            "relu_product_backward",
            inputs,
            specs,
            |v| {
                let [grad, output, weight] = array(v);
                let (dx, masked) =
                    B::relu_product_backward(grad.float(), output.float(), weight.float());
                vec![Value::Float(dx), Value::Float(masked)]
            },
        ));
        (dx, masked)
    }
}

/// `[out, in]` for a weight `[in, out]`.
fn transposed(weight: &Shape) -> Shape {
    Shape::new([weight[1], weight[0]])
}

/// A product node's state.
#[derive(Debug, Clone)]
pub struct ProductInputs<B: Backend> {
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    /// Also the bias node's placeholder.
    bias: FloatTensor<B>,
    ledger: Ledger,
    /// The layer's output, kept for a ReLU's mask.
    activated: Option<FloatTensor<B>>,
}

impl<B: Backend> ProductInputs<B> {
    /// The inputs, no output kept yet.
    fn new(
        x: FloatTensor<B>,
        weight: FloatTensor<B>,
        bias: FloatTensor<B>,
        ledger: Ledger,
    ) -> Self {
        Self {
            x,
            weight,
            bias,
            ledger,
            activated: None,
        }
    }
}

/// A parameter node's state: its layer, its role, and the folded BN's scale `s` for a folded
/// layer.
#[derive(Debug, Clone)]
pub struct ParameterRole<B: Backend> {
    ledger: Ledger,
    role: Role,
    scale: Option<FloatTensor<B>>,
}

#[derive(Debug)]
struct ProductBackward;

impl<B: ProductKernels + ReluKernels> Backward<B, 3> for ProductBackward {
    type State = ProductInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let ids = ops.parents.map(|node| node.map(|n| n.id));
        product_backward(grad, ids, ops.state, grads);
    }
}

/// A product node with a residual added before its ReLU
/// ([`SharedLinearOps::shared_linear_residual`]): the residual's gradient is the masked
/// gradient the product's backward forms anyway.
#[derive(Debug)]
struct ResidualProductBackward;

impl<B: ProductKernels + ReluKernels> Backward<B, 4> for ResidualProductBackward {
    type State = ProductInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [x, weight, bias, residual] = ops.parents.map(|node| node.map(|n| n.id));
        let masked = product_backward(grad, [x, weight, bias], ops.state, grads);
        if let Some(residual) = residual {
            grads.register::<B>(residual, masked);
        }
    }
}

/// A product node's backward (module docs): registers `∂x`, files the pass's rows with the
/// layer, and returns the gradient at the activation's input (`grad` masked through a ReLU).
fn product_backward<B: ProductKernels + ReluKernels>(
    grad: FloatTensor<B>,
    [x_node, weight_node, bias_node]: [Option<NodeId>; 3],
    s: ProductInputs<B>,
    grads: &mut Gradients,
) -> FloatTensor<B> {
    // Through a ReLU, `∂x`'s product masks the gradient and writes the masked gradient for the
    // parameters in the same launch; without `∂x` the mask is a launch of its own.
    let (dx, grad) = match (s.activated, x_node) {
        (None, Some(_)) => (
            Some(B::linear_x_backward(s.weight.clone(), grad.clone())),
            grad,
        ),
        (None, None) => (None, grad),
        (Some(output), Some(_)) => {
            let (dx, masked) = B::relu_product_backward(grad, output, s.weight.clone());
            (Some(dx), masked)
        }
        (Some(output), None) => (None, B::fused_relu_backward(output, grad)),
    };
    if let (Some(node), Some(dx)) = (x_node, dx) {
        grads.register::<B>(node, dx);
    }
    if weight_node.is_none() && bias_node.is_none() {
        return grad;
    }
    let mut ledger = s.ledger.lock();
    for (slot, node, placeholder) in [(0, weight_node, &s.weight), (1, bias_node, &s.bias)] {
        if let Some(node) = node
            && !ledger.seeded[slot]
        {
            grads.register::<B>(node, placeholder.clone());
            ledger.seeded[slot] = true;
        }
    }
    let rows = ledger.rows::<B>();
    if weight_node.is_some() {
        rows.inputs.push(flatten::<B>(s.x));
    }
    rows.grads.push(flatten::<B>(grad.clone()));
    grad
}

#[derive(Debug)]
struct ParameterBackward;

impl<B: StackKernels> Backward<B, 1> for ParameterBackward {
    type State = ParameterRole<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        // The placeholder a product node registered.
        let _ = grads.consume::<B>(&ops.node);
        let [Some(parent)] = ops.parents else {
            return;
        };
        let ParameterRole {
            ledger,
            role,
            scale,
        } = ops.state;
        let mut ledger = ledger.lock();
        let slot = match role {
            Role::Weight => 0,
            Role::Bias => 1,
        };
        ledger.delivered[slot] = true;
        let done = (0..2).all(|i| !ledger.seeded[i] || ledger.delivered[i]);
        // Both parameters take a gradient: one product answers both (module docs).
        let joint = ledger.seeded == [true, true];
        let rows = ledger.rows::<B>();
        let formed = rows.formed.get_or_insert_with(|| {
            let filled = rows.grads.iter().map(|g| g.shape()[0]).sum();
            let outputs = rows.grads[0].shape()[1];
            // Without a weight gradient only the bias's sum is split.
            let inputs = rows.inputs.first().map_or(0, |x| x.shape()[1]);
            let extra = if joint { BIAS_COLUMNS } else { 0 };
            let split = SplitK::plan(filled, inputs + extra, outputs);
            let (x, g) = stack::<B>(
                std::mem::take(&mut rows.inputs),
                std::mem::take(&mut rows.grads),
                scale,
                split.padded_rows(),
                extra,
            );
            if joint {
                let x = x.expect("the weight's rows were filed");
                Formed::Joint {
                    product: split.weight_gradient::<B>(x, g),
                    inputs,
                }
            } else {
                Formed::Apart { split, x, g }
            }
        });
        let grad = match (formed, role) {
            (Formed::Joint { product, inputs }, role) => {
                let outputs = product.shape()[1];
                let (first, last) = match role {
                    Role::Weight => (0, *inputs),
                    Role::Bias => (*inputs, *inputs + 1),
                };
                let grad = B::float_slice(
                    product.clone(),
                    &[
                        burn::tensor::Slice::from(first..last),
                        burn::tensor::Slice::from(0..outputs),
                    ],
                );
                match role {
                    Role::Weight => grad,
                    Role::Bias => B::float_reshape(grad, Shape::new([outputs])),
                }
            }
            (Formed::Apart { split, x, g }, Role::Weight) => split
                .weight_gradient::<B>(x.clone().expect("the weight's rows were filed"), g.clone()),
            (Formed::Apart { split, g, .. }, Role::Bias) => split.column_sum::<B>(g.clone()),
        };
        if done {
            ledger.rows = None;
        }
        drop(ledger);
        grads.register::<B>(parent.id, grad);
    }
}

impl<B: StackKernels + ProductKernels + ReluKernels + SharedLinearOps, C: CheckpointStrategy>
    SharedLinearOps for Autodiff<B, C>
{
    fn shared_parameter(value: FloatTensor<Self>, ledger: Ledger, role: Role) -> FloatTensor<Self> {
        let (value, node) = value.into_parts();
        match ParameterBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(
                ParameterRole {
                    ledger,
                    role,
                    scale: None,
                },
                value,
            ),
            OpsKind::UnTracked(prep) => prep.finish(value),
        }
    }

    fn shared_fold(
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        kind: FoldBias,
        epsilon: f32,
        ledger: Ledger,
    ) -> (FloatTensor<Self>, FloatTensor<Self>, FloatTensor<Self>) {
        let (weight, weight_node) = weight.into_parts();
        let (bias, bias_node) = bias.into_parts();
        // Without a bias of its own the argument is `β`, which takes no gradient: the folded
        // bias's node is then untracked.
        let [gamma, beta, mean, var] = [gamma, beta, mean, var].map(|t| t.into_primitive());
        let (w, b, scale) = B::shared_fold(
            weight,
            bias,
            gamma,
            beta,
            mean,
            var,
            kind,
            epsilon,
            ledger.clone(),
        );
        let node = |value: FloatTensor<B>, node, role| match ParameterBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(
                ParameterRole {
                    ledger: ledger.clone(),
                    role,
                    scale: Some(scale.clone()),
                },
                value,
            ),
            OpsKind::UnTracked(prep) => prep.finish(value),
        };
        let w = node(w, weight_node, Role::Weight);
        let b = node(b, bias_node, Role::Bias);
        (w, b, Self::from_inner(scale))
    }

    fn shared_linear(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        ledger: Ledger,
        activation: Activation,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (weight, weight_node) = weight.into_parts();
        let (bias, bias_node) = bias.into_parts();
        record_product::<B, C, _, 3>(
            ProductBackward,
            [x_node, weight_node, bias_node],
            ProductInputs::new(x, weight, bias, ledger),
            activation,
            |s| B::shared_linear(s.x, s.weight, s.bias, s.ledger, activation),
        )
    }

    fn shared_linear_residual(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        ledger: Ledger,
    ) -> FloatTensor<Self> {
        let (x, x_node) = x.into_parts();
        let (weight, weight_node) = weight.into_parts();
        let (bias, bias_node) = bias.into_parts();
        let (residual, residual_node) = residual.into_parts();
        record_product::<B, C, _, 4>(
            ResidualProductBackward,
            [x_node, weight_node, bias_node, residual_node],
            ProductInputs::new(x, weight, bias, ledger),
            Activation::Relu,
            |s| B::shared_linear_residual(s.x, s.weight, s.bias, residual, s.ledger),
        )
    }
}

/// A product node over `nodes` (`x`, `W`, `b` and any residual): `forward` runs on the inner
/// backend, and when a node is tracked the node keeps `inputs`, and the output too when a ReLU
/// follows (its mask, see [`product_backward`]).
fn record_product<B, C, BW, const N: usize>(
    backward: BW,
    nodes: [NodeGuard; N],
    inputs: ProductInputs<B>,
    activation: Activation,
    forward: impl FnOnce(ProductInputs<B>) -> FloatTensor<B>,
) -> FloatTensor<Autodiff<B, C>>
where
    B: Backend,
    C: CheckpointStrategy,
    BW: Backward<B, N, State = ProductInputs<B>>,
{
    match backward.prepare::<C>(nodes).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let output = forward(inputs.clone());
            let activated = (activation == Activation::Relu).then(|| output.clone());
            let state = ProductInputs {
                activated,
                ..inputs
            };
            prep.finish(state, output)
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(inputs)),
    }
}
