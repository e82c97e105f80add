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
//!   its part of `[Xᵀ; 1ᵀ]·G = [∂W; ∂b]`, which the first of the two to run forms for both from
//!   the ledger's rows in one launch ([`GradientKernels::pass_gradients`], the `gradient`
//!   module): the kernel reads every pass's rows where they are, so `X` and `G` are never
//!   stacked, and the bias's sum is the row of ones' (no launch of its own).
//!
//! A layer that a frozen BatchNorm follows applies it in its product's epilogue
//! ([`OutputMap`]): `(x·W + b)·s + t` with the BN's `s = γ/√(σ²+ε)`, `t = β − μ·s`, which
//! never change and are made once per process (`crate::frozen_affine`), so nothing is folded
//! per step. Backward, `∂x = (g·diag(s))·Wᵀ` scales `g`'s columns where the product stages
//! them, and the parameters' gradient scales `G`'s where the rows are read, `∂W =
//! Xᵀ·(G·diag(s))` and `∂b = Σ_rows G·diag(s)`: the norm costs no launch either way.
//!
//! A layer whose BatchNorm's `γ`, `β` train (the image encoder's convolutions,
//! `crate::conv_norm`) is folded instead, once per reconstruction, by
//! [`SharedLinearOps::trained_fold`].
//!
//! # Split-k
//!
//! `∂W = Xᵀ·G` is a small output over a long reduction (every pass's rows), so the rows are cut
//! into chunks ([`crate::split_k`]): each chunk's cubes write a partial gradient and a sum over
//! the chunks follows. The parameter nodes of most layers run one after another at the end of
//! the backward, so the first of them forms the gradients of every layer whose passes have all
//! filed their rows (the `filing` module): one sum over the chunks for all of them, in one
//! launch, instead of one per layer.

use std::any::Any;
use std::sync::{Arc, Mutex, PoisonError};

use crate::activation::Activation;
use crate::activation::op::ReluKernels;
use crate::handoff::Handoff;
use burn::backend::AutodiffBackend;
use burn::backend::autodiff::NodeId;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, NodeGuard, Ops, OpsKind};
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use burn::tensor::Shape;
use lifegom_render::cube::deferred::float_like;
use lifegom_render::cube::deferred::{Input, Value, array, deferred};

use crate::gemm_conv::op::{PatchKernels, Patches};
use crate::split_k::SplitK;

/// Which parameter of the layer a [`SharedLinearOps::shared_parameter`] node stands for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The weight `[in, out]`: its gradient is `Xᵀ·G`.
    Weight,
    /// The bias `[out]`: its gradient is `Σ_rows G`.
    Bias,
}

/// What a shared layer's product adds to `x·W` before its activation (module docs). The
/// arguments a variant does not read may be any `[out]` tensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputMap {
    /// `x·W + b`.
    Biased,
    /// `(x·W + b)·s + t`: the layer's bias, then a frozen BatchNorm's `s`, `t`.
    NormedBias,
    /// `x·W·s + t`: a frozen BatchNorm after a layer without a bias.
    Normed,
}

impl OutputMap {
    /// Whether the map scales the product's columns.
    fn normed(self) -> bool {
        self != OutputMap::Biased
    }
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
    /// Whether the gradient carries the bias row even when the bias takes none: a trained
    /// fold's `∂γ` reads it ([`SharedLinearOps::trained_fold`]).
    bias_row_always: bool,
    /// Whether the weight or the bias takes a gradient (its parameter node is tracked).
    tracked: bool,
    /// Passes recorded in the forward while `tracked`: as many product nodes will file rows.
    expected: usize,
    /// Passes whose product node has filed its rows.
    filed: usize,
}

/// The rows filed by the product nodes, and the parameters' gradient once formed.
struct Rows<B: Backend> {
    /// `[rows, in]` per pass, or images whose `patches` are the rows, when the weight takes a
    /// gradient.
    inputs: Vec<FloatTensor<B>>,
    patches: Option<Patches>,
    /// `[rows, out]` per pass.
    grads: Vec<FloatTensor<B>>,
    /// A frozen BatchNorm's `s` `[out]` that scales `G`'s columns ([`OutputMap`]).
    scale: Option<FloatTensor<B>>,
    /// `[∂W; ∂b]` `[in + 1, out]` when both take a gradient, else the one that does (`∂b` as
    /// `[1, out]`), with `in` (module docs).
    formed: Option<Formed<B>>,
}

impl Ledger {
    fn lock(&self) -> std::sync::MutexGuard<'_, LedgerState> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl LedgerState {
    /// Whether every pass recorded has filed and nothing is formed yet: the layer's gradient
    /// can be formed with another's (see [`delivered_gradient`]).
    fn complete<B: Backend>(&mut self) -> bool {
        self.filed > 0
            && self.filed == self.expected
            && self
                .rows
                .as_mut()
                .and_then(|rows| rows.downcast_mut::<Rows<B>>())
                .is_some_and(|rows| rows.formed.is_none())
    }

    fn rows<B: Backend>(&mut self) -> &mut Rows<B> {
        self.rows
            .get_or_insert_with(|| {
                Box::new(Rows::<B> {
                    inputs: Vec::new(),
                    patches: None,
                    grads: Vec::new(),
                    scale: None,
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

/// Passes whose rows one launch of [`GradientKernels::pass_gradients`] reads; more take a
/// launch per this many.
pub const PASS_PARTS: usize = 4;

/// What a layer's parameter gradient is formed from (module docs): every pass's rows as filed.
#[doc(hidden)]
pub struct ParameterRows<B: Backend> {
    /// `[rows_t, in]` per pass, or none when the weight takes no gradient; with `patches`,
    /// images `[N, C, H, W]` whose patch columns are the rows.
    pub inputs: Vec<FloatTensor<B>>,
    /// The window when the inputs are images.
    pub patches: Option<Patches>,
    /// `[rows_t, out]` per pass, at least one.
    pub grads: Vec<FloatTensor<B>>,
    /// A folded BatchNorm's `s` `[out]`, which scales `G`'s columns.
    pub scale: Option<FloatTensor<B>>,
    /// Whether the bias takes a gradient: a row `Σ_rows G` after `∂W`'s.
    pub bias_row: bool,
    /// Rows per chunk of the split-k sum ([`SplitK`]).
    pub chunk_rows: usize,
}

/// A layer's formed parameter gradient ([`GradientKernels::pass_gradients`]): `∂W` `[in, out]`
/// when the weight takes a gradient, and the row of ones' `Σ_rows G` `[out]` (`∂b`, or what a
/// trained fold's `∂γ` reads) when the bias row was asked for.
#[derive(Debug, Clone)]
pub struct Formed<B: Backend> {
    /// `Xᵀ·(G·diag(s))` `[in, out]`.
    pub weight: Option<FloatTensor<B>>,
    /// `Σ_rows G·diag(s)` `[out]`.
    pub bias: Option<FloatTensor<B>>,
}

/// What a backend implements so that `Autodiff<B>` can form shared layers' parameter
/// gradients.
#[doc(hidden)]
pub trait GradientKernels: Backend {
    /// Per layer, `[Xᵀ; 1ᵀ]·(G·diag(s))`, `X` and `G` every pass's rows one after the other,
    /// summed over chunks of `chunk_rows` rows: one launch per layer and [`PASS_PARTS`]
    /// passes, and one sum over the chunks for all the layers that have more than one; `∂W`'s
    /// rows (when there are inputs) and the row of ones' (with `bias_row`) handed over apart.
    fn pass_gradients(layers: Vec<ParameterRows<Self>>) -> Vec<Formed<Self>>;
}

/// What the deferred op needs to rebuild a layer's [`ParameterRows`] from its flat inputs.
#[derive(Clone, Copy)]
struct RowsLayout {
    passes: usize,
    with_inputs: bool,
    scaled: bool,
    patches: Option<Patches>,
    bias_row: bool,
    chunk_rows: usize,
}

impl<B: FusionBackend + GradientKernels> GradientKernels for Fusion<B> {
    fn pass_gradients(layers: Vec<ParameterRows<Self>>) -> Vec<Formed<Self>> {
        let mut layouts = Vec::with_capacity(layers.len());
        let mut specs = Vec::with_capacity(layers.len());
        let mut tensors = Vec::new();
        for rows in layers {
            let ParameterRows {
                inputs,
                patches,
                grads,
                scale,
                bias_row,
                chunk_rows,
            } = rows;
            let width = inputs
                .first()
                .map_or(0, |x| super::gradient::input_width(&x.shape(), patches));
            let cols = grads[0].shape()[1];
            if !inputs.is_empty() {
                specs.push(float_like::<B>(&grads[0], Shape::new([width, cols])));
            }
            if bias_row {
                specs.push(float_like::<B>(&grads[0], Shape::new([cols])));
            }
            layouts.push(RowsLayout {
                passes: grads.len(),
                with_inputs: !inputs.is_empty(),
                scaled: scale.is_some(),
                patches,
                bias_row,
                chunk_rows,
            });
            tensors.extend(
                inputs
                    .into_iter()
                    .chain(grads)
                    .chain(scale)
                    .map(Input::Float),
            );
        }
        let kept = layouts.clone();
        let mut outputs = deferred::<B, _>("pass_gradients", tensors, specs, move |values| {
            let mut values = values.into_iter().map(Value::float);
            let layers = kept
                .iter()
                .map(|l| ParameterRows {
                    inputs: values
                        .by_ref()
                        .take(if l.with_inputs { l.passes } else { 0 })
                        .collect(),
                    patches: l.patches,
                    grads: values.by_ref().take(l.passes).collect(),
                    scale: if l.scaled { values.next() } else { None },
                    bias_row: l.bias_row,
                    chunk_rows: l.chunk_rows,
                })
                .collect();
            B::pass_gradients(layers)
                .into_iter()
                .flat_map(|formed| formed.weight.into_iter().chain(formed.bias))
                .map(Value::Float)
                .collect()
        })
        .into_iter();
        let mut next = |given: bool| given.then(|| outputs.next().expect("one output per part"));
        layouts
            .iter()
            .map(|l| Formed {
                weight: next(l.with_inputs),
                bias: next(l.bias_row),
            })
            .collect()
    }
}

/// What a backend implements so that `Autodiff<B>` can differentiate a trained fold
/// ([`SharedLinearOps::trained_fold`]).
#[doc(hidden)]
pub trait FoldKernels: Backend {
    /// `(∂W, ∂γ)`: `∂W` `[out, in]` as the weight is stored and `∂γ` `[out]`, from the passes'
    /// unscaled gradient, `formed` `Xᵀ·G` `[in, out]` and `formed_bias` `Σ_rows G` `[out]`, the
    /// weight, and the BatchNorm's `γ`, `μ`, `σ²` `[out]` and `ε` (the `trained_fold` module).
    #[allow(clippy::too_many_arguments)]
    fn trained_fold_backward(
        formed: FloatTensor<Self>,
        formed_bias: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

impl<B: FusionBackend + FoldKernels> FoldKernels for Fusion<B> {
    fn trained_fold_backward(
        formed: FloatTensor<Self>,
        formed_bias: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let specs = vec![
            float_like::<B>(&weight, weight.shape()),
            float_like::<B>(&gamma, gamma.shape()),
        ];
        let inputs = [formed, formed_bias, weight, gamma, mean, var]
            .into_iter()
            .map(Input::Float)
            .collect();
        let [weight_grad, gamma_grad] = array(deferred::<B, _>(
            "trained_fold_backward",
            inputs,
            specs,
            move |v| {
                let [formed, formed_bias, weight, gamma, mean, var] = array(v);
                let (weight_grad, gamma_grad) = B::trained_fold_backward(
                    formed.float(),
                    formed_bias.float(),
                    weight.float(),
                    gamma.float(),
                    mean.float(),
                    var.float(),
                    epsilon,
                );
                vec![Value::Float(weight_grad), Value::Float(gamma_grad)]
            },
        ));
        (weight_grad, gamma_grad)
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

    /// The weight `[in, out]` and bias `[out]` of a bias-free layer whose weight is stored
    /// `[out, in]` (a convolution's `[C_out, C·kh·kw]`), folded with the BatchNorm after it,
    /// whose `γ` and `β` train while its statistics stay frozen (the image encoder's):
    /// `Wᵀ·diag(s)` and `β − μ·s`, `s = γ/√(σ²+ε)`, in one launch. The parameter gradient is
    /// formed from every pass's rows without a scale and turned into `∂W`, `∂γ`, `∂β` in one
    /// launch ([`FoldKernels::trained_fold_backward`], the `trained_fold` module).
    #[allow(clippy::too_many_arguments)]
    #[fusion(meta = |weight, _gamma, beta, _mean, _var, _epsilon, _ledger| {
        (
            TensorSpec::new(Shape::new([weight.shape[1], weight.shape[0]]), weight.dtype),
            beta.clone(),
        )
    })]
    fn trained_fold(
        weight: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        ledger: Ledger,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);

    /// One pass's product, `act(map(x·W))` with the bias `b` and a frozen BatchNorm's `s`, `t`
    /// ([`OutputMap`]); `∂x` adds the gradient `handoff` brings (a later residual layer's for the
    /// same `x`, [`Self::shared_linear_residual`]) in its launch.
    #[allow(clippy::too_many_arguments)]
    #[fusion(dtype = x, shape = layer_output_shape(x, weight, patches))]
    fn shared_linear(
        x: FloatTensor<Self>,
        patches: Option<Patches>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        map: OutputMap,
        ledger: Ledger,
        activation: Activation,
        handoff: Handoff,
    ) -> FloatTensor<Self>;

    /// One pass's product with a residual `r` (`[.., out]`) added before a ReLU,
    /// `relu(map(x·W) + r)`: a residual block's last layer. The residual's gradient goes to
    /// `handoff` when it joins a product that reads `r` as its input (the block's first
    /// layer), whose `∂x` then adds it ([`crate::handoff`]).
    #[allow(clippy::too_many_arguments)]
    #[fusion(dtype = x, shape = layer_output_shape(x, weight, patches))]
    fn shared_linear_residual(
        x: FloatTensor<Self>,
        patches: Option<Patches>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        map: OutputMap,
        residual: FloatTensor<Self>,
        ledger: Ledger,
        handoff: Handoff,
    ) -> FloatTensor<Self>;
}

/// A layer's output shape: `[N·H_out·W_out, out]` for an image `x` read as its `patches`' columns,
/// else [`product_shape`].
fn layer_output_shape(x: &Shape, weight: &Shape, patches: &Option<Patches>) -> Shape {
    match patches {
        Some(patches) => Shape::new([patches.columns_shape(x)[0], weight[1]]),
        None => product_shape(x, weight),
    }
}

/// The shape of `x·W` for `x` `[.., in]` and `W` `[in, out]`: `x`'s with its last axis `out`.
fn product_shape(x: &Shape, weight: &Shape) -> Shape {
    let mut dims = x.to_vec();
    if let Some(last) = dims.last_mut() {
        *last = weight[1];
    }
    Shape::from(dims)
}

/// What a backend implements so that `Autodiff<B>` can differentiate a shared layer's `x` in
/// one launch.
#[doc(hidden)]
pub trait ProductKernels: Backend {
    /// `(∂x, g ⊙ [y > 0] when masked)` with `∂x = ((g ⊙ [y > 0])·diag(s))·Wᵀ + a`, for the
    /// gradient `grad` `[.., out]` of the layer's output, that output `y` when a ReLU follows
    /// (same shape; Burn's ReLU backward zeroes the gradient where it is `≤ 0`), the weight
    /// `[in, out]`, a frozen BatchNorm's `s` `[out]` ([`OutputMap`]) and the `addend` `a`
    /// (`[.., in]`); each optional one is absent from the formula when absent.
    fn x_gradient(
        grad: FloatTensor<Self>,
        output: Option<FloatTensor<Self>>,
        weight: FloatTensor<Self>,
        scale: Option<FloatTensor<Self>>,
        addend: Option<FloatTensor<Self>>,
    ) -> (FloatTensor<Self>, Option<FloatTensor<Self>>);
}

impl<B: FusionBackend + ProductKernels> ProductKernels for Fusion<B> {
    fn x_gradient(
        grad: FloatTensor<Self>,
        output: Option<FloatTensor<Self>>,
        weight: FloatTensor<Self>,
        scale: Option<FloatTensor<Self>>,
        addend: Option<FloatTensor<Self>>,
    ) -> (FloatTensor<Self>, Option<FloatTensor<Self>>) {
        let (masked, scaled, added) = (output.is_some(), scale.is_some(), addend.is_some());
        let mut specs = vec![float_like::<B>(
            &grad,
            product_shape(&grad.shape(), &transposed(&weight.shape())),
        )];
        if masked {
            specs.push(float_like::<B>(&grad, grad.shape()));
        }
        let inputs = [grad, weight]
            .into_iter()
            .chain(output)
            .chain(scale)
            .chain(addend)
            .map(Input::Float)
            .collect();
        let mut outputs = deferred::<B, _>("x_gradient", inputs, specs, move |v| {
            let mut v = v.into_iter();
            let mut next = |present: bool| present.then(|| v.next().map(Value::float)).flatten();
            let grad = next(true).expect("the gradient");
            let weight = next(true).expect("the weight");
            let (output, scale, addend) = (next(masked), next(scaled), next(added));
            let (dx, masked) = B::x_gradient(grad, output, weight, scale, addend);
            std::iter::once(dx)
                .chain(masked)
                .map(Value::Float)
                .collect()
        })
        .into_iter();
        let dx = outputs.next().expect("∂x");
        (dx, outputs.next())
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
    /// When `x` is an image read as the patch columns of this window.
    patches: Option<Patches>,
    weight: FloatTensor<B>,
    /// Also the bias node's placeholder.
    bias: FloatTensor<B>,
    /// A frozen BatchNorm's `s`, `t` as `map` reads them.
    scale: FloatTensor<B>,
    shift: FloatTensor<B>,
    map: OutputMap,
    ledger: Ledger,
    /// The layer's output, kept for a ReLU's mask.
    activated: Option<FloatTensor<B>>,
    /// What `x`'s gradient takes from, or the residual's gives to, another product.
    handoff: Handoff,
}

impl<B: Backend> ProductInputs<B> {
    /// The inputs, no output kept yet; `[bias, scale, shift]` as `map` reads them.
    fn new(
        (x, patches): (FloatTensor<B>, Option<Patches>),
        weight: FloatTensor<B>,
        [bias, scale, shift]: [FloatTensor<B>; 3],
        map: OutputMap,
        ledger: Ledger,
        handoff: Handoff,
    ) -> Self {
        Self {
            x,
            patches,
            weight,
            bias,
            scale,
            shift,
            map,
            ledger,
            activated: None,
            handoff,
        }
    }
}

/// A parameter node's state: its layer and its role.
#[derive(Debug, Clone)]
pub struct ParameterRole {
    ledger: Ledger,
    role: Role,
}

#[derive(Debug)]
struct ProductBackward;

impl<B: ProductKernels + ReluKernels + PatchKernels> Backward<B, 3> for ProductBackward {
    type State = ProductInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 3>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let ids = ops.parents.map(|node| node.map(|n| n.id));
        // A giver filed for the same `x` only when `x` takes a gradient.
        let addend = ids[0].and_then(|_| ops.state.handoff.take::<FloatTensor<B>>());
        product_backward(grad, ids, ops.state, addend, grads);
    }
}

/// A product node with a residual added before its ReLU
/// ([`SharedLinearOps::shared_linear_residual`]): the residual's gradient is the masked
/// gradient the product's backward forms anyway, registered or handed off.
#[derive(Debug)]
struct ResidualProductBackward;

impl<B: ProductKernels + ReluKernels + PatchKernels> Backward<B, 4> for ResidualProductBackward {
    type State = ProductInputs<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 4>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [x, weight, bias, residual] = ops.parents.map(|node| node.map(|n| n.id));
        let handoff = ops.state.handoff.clone();
        let masked = product_backward(grad, [x, weight, bias], ops.state, None, grads);
        if let Some(residual) = residual
            && !handoff.file(masked.clone())
        {
            grads.register::<B>(residual, masked);
        }
    }
}

/// A product node's backward (module docs): registers `∂x` (plus `addend`, another op's
/// gradient for `x`), files the pass's rows with the layer, and returns the gradient at the
/// activation's input (`grad` masked through a ReLU).
fn product_backward<B: ProductKernels + ReluKernels + PatchKernels>(
    grad: FloatTensor<B>,
    [x_node, weight_node, bias_node]: [Option<NodeId>; 3],
    s: ProductInputs<B>,
    addend: Option<FloatTensor<B>>,
    grads: &mut Gradients,
) -> FloatTensor<B> {
    // Through a ReLU, `∂x`'s product masks the gradient and writes the masked gradient for the
    // parameters in the same launch; without `∂x` the mask is a launch of its own. A frozen
    // BatchNorm's scale enters `∂x` where the product stages the gradient.
    let scale = s.map.normed().then_some(s.scale);
    let (dx, grad) = match (s.activated, x_node) {
        (activated, Some(_)) if s.patches.is_some() => {
            // `∂x` of the patch columns, gathered back onto the image.
            let (columns_grad, masked) = B::x_gradient(
                grad.clone(),
                activated,
                s.weight.clone(),
                scale.clone(),
                None,
            );
            let patches = s.patches.expect("an image's window");
            let dx = B::patch_columns_backward(columns_grad, s.x.shape(), patches);
            let dx = match addend {
                Some(a) => B::float_add(dx, a),
                None => dx,
            };
            (Some(dx), masked.unwrap_or(grad))
        }
        (None, Some(_)) if scale.is_none() => {
            let dx = B::linear_x_backward(s.weight.clone(), grad.clone());
            let dx = match addend {
                Some(a) => B::float_add(dx, a),
                None => dx,
            };
            (Some(dx), grad)
        }
        (None, Some(_)) => {
            let (dx, _) =
                B::x_gradient(grad.clone(), None, s.weight.clone(), scale.clone(), addend);
            (Some(dx), grad)
        }
        (None, None) => (None, grad),
        (Some(output), Some(_)) => {
            let (dx, masked) =
                B::x_gradient(grad, Some(output), s.weight.clone(), scale.clone(), addend);
            (
                Some(dx),
                masked.expect("a masked product writes its masked gradient"),
            )
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
    assert!(
        rows.formed.is_none(),
        "a pass filed rows after its layer's gradient was formed: the forward did not count it \
         (its layer's weight and bias were not tracked when it ran)"
    );
    if weight_node.is_some() {
        // An image is filed as it is: the gradient kernel reads its patch columns in place.
        rows.inputs.push(match s.patches {
            Some(_) => s.x,
            None => flatten::<B>(s.x),
        });
        rows.patches = s.patches;
    }
    rows.grads.push(flatten::<B>(grad.clone()));
    if rows.scale.is_none() {
        rows.scale = scale;
    }
    ledger.filed += 1;
    if ledger.filed == 1 {
        filing::register(&s.ledger);
    }
    grad
}

/// The layer's `[∂W; ∂b]` (module docs) and its input width `in`, for the parameter node in
/// `slot` (0 the weight, 1 the bias): the first node to ask forms it from the ledger's rows,
/// a frozen BatchNorm's scale filed with them scaling `G`'s columns, together with every other
/// layer whose passes have all filed (one sum over the chunks for all of them, see
/// [`filing`]); the rows and the gradient are freed once every seeded node has had its part.
fn delivered_gradient<B: GradientKernels>(ledger: &Ledger, slot: usize) -> Formed<B> {
    let mut state = ledger.lock();
    state.delivered[slot] = true;
    let done = (0..2).all(|i| !state.seeded[i] || state.delivered[i]);
    if state.rows::<B>().formed.is_none() {
        let others = filing::complete_besides::<B>(ledger);
        let mut others: Vec<_> = others.iter().map(Ledger::lock).collect();
        let mut batch: Vec<&mut LedgerState> = vec![&mut state];
        batch.extend(others.iter_mut().map(|guard| &mut **guard));
        // Partial gradients of a batch stay under split-k's bound for one layer's (the
        // first layer's own may exceed it alone).
        let mut partial_bytes = 0;
        let mut formed = Vec::new();
        let mut layers = Vec::new();
        for (i, layer) in batch.iter_mut().enumerate() {
            let plan = GradientPlan::of::<B>(layer);
            // A layer left out keeps its rows, and forms them when its own node asks.
            if i > 0 && partial_bytes + plan.partial_bytes > filing::batch_bytes() {
                continue;
            }
            partial_bytes += plan.partial_bytes;
            formed.push(i);
            layers.push(plan.take_rows::<B>(layer));
        }
        #[cfg(test)]
        filing::BATCHES.with_borrow_mut(|b| b.push(layers.len()));
        let gradients = B::pass_gradients(layers);
        for (i, gradient) in formed.into_iter().zip(gradients) {
            batch[i].rows::<B>().formed = Some(gradient);
        }
    }
    let rows = state.rows::<B>();
    let delivered = rows.formed.clone().expect("formed above");
    if done {
        state.rows = None;
    }
    delivered
}

/// How a layer's filed rows are formed: its `bias_row` and split-k plan, and the bytes of its
/// partial gradients.
struct GradientPlan {
    bias_row: bool,
    split: SplitK,
    partial_bytes: usize,
}

impl GradientPlan {
    fn of<B: Backend>(state: &mut LedgerState) -> Self {
        // Both parameters take a gradient: one launch answers both (module docs).
        let bias_row = state.seeded[1] || state.bias_row_always;
        let rows = state.rows::<B>();
        let filled = rows.grads.iter().map(|g| g.shape()[0]).sum();
        let outputs = rows.grads[0].shape()[1];
        let inputs = rows.inputs.first().map_or(0, |x| {
            super::gradient::input_width(&x.shape(), rows.patches)
        });
        let out_rows = inputs + usize::from(bias_row);
        let split = SplitK::plan(filled, out_rows, outputs);
        let partial_bytes = if split.chunks > 1 {
            split.chunks * out_rows * outputs * size_of::<f32>()
        } else {
            0
        };
        Self {
            bias_row,
            split,
            partial_bytes,
        }
    }

    /// The layer's rows as the gradient kernels take them (the caller forms them).
    fn take_rows<B: Backend>(&self, state: &mut LedgerState) -> ParameterRows<B> {
        let rows = state.rows::<B>();
        ParameterRows {
            inputs: std::mem::take(&mut rows.inputs),
            patches: rows.patches,
            grads: std::mem::take(&mut rows.grads),
            scale: rows.scale.take(),
            bias_row: self.bias_row,
            chunk_rows: self.split.chunk_rows,
        }
    }
}

/// The layers whose product nodes have filed rows in the backward running on this thread.
///
/// A parameter node runs after every product node of its own layer (Burn runs deeper nodes
/// first), but other layers' parameter nodes follow at once in the tape's last levels, each
/// forming its gradient with a sum over chunks of its own. The first of them forms, with its
/// own, every layer that is *complete*, whose every pass recorded in the forward has filed its
/// rows (`expected` counted in the forward, `filed` in the backward), so that their chunks are
/// summed in one launch. A layer with a pass that the backward never reaches is never complete
/// and forms its gradient alone when its own parameter node asks, as before.
pub(crate) mod filing {
    use std::cell::{Cell, RefCell};
    use std::sync::{Mutex, Weak};

    use burn::backend::Backend;

    use super::{Ledger, LedgerState};

    thread_local! {
        static FILED: RefCell<Vec<Weak<Mutex<LedgerState>>>> = const { RefCell::new(Vec::new()) };
        /// Open [`detached_passes`] scopes on this thread.
        static DETACHED: Cell<usize> = const { Cell::new(0) };
        /// The layers formed together by each formation on this thread, for the tests.
        #[cfg(test)]
        pub(crate) static BATCHES: RefCell<Vec<usize>> = const { RefCell::new(Vec::new()) };
        /// A tighter bound on a batch's partial gradients, for the tests.
        #[cfg(test)]
        pub(crate) static BATCH_BYTES: Cell<Option<usize>> = const { Cell::new(None) };
    }

    /// The most bytes a batch's partial gradients take together: split-k's bound for one
    /// layer's ([`crate::split_k::MAX_PARTIAL_BYTES`]).
    pub(super) fn batch_bytes() -> usize {
        #[cfg(test)]
        if let Some(bytes) = BATCH_BYTES.get() {
            return bytes;
        }
        crate::split_k::MAX_PARTIAL_BYTES
    }

    /// Runs `f`, whose shared layers' outputs the caller detaches from the graph (the
    /// reconstruction's rendered branch): their products record no node, keep nothing for a
    /// backward, and are not passes a layer waits for (a pass that never files would keep its
    /// layer from ever being complete). Outputs of `f` carry no gradient into the layers;
    /// other ops inside `f` are recorded as usual.
    pub fn detached_passes<T>(f: impl FnOnce() -> T) -> T {
        struct Scope;
        impl Drop for Scope {
            fn drop(&mut self) {
                DETACHED.with(|d| d.set(d.get() - 1));
            }
        }
        DETACHED.with(|d| d.set(d.get() + 1));
        let _scope = Scope;
        f()
    }

    /// Whether a [`detached_passes`] scope is open on this thread.
    pub(super) fn detached() -> bool {
        DETACHED.with(|d| d.get() > 0)
    }

    /// Lists `ledger`, whose first pass has just filed its rows.
    pub(super) fn register(ledger: &Ledger) {
        FILED.with_borrow_mut(|filed| {
            filed.retain(|l| l.strong_count() > 0);
            filed.push(std::sync::Arc::downgrade(&ledger.0));
        });
    }

    /// The listed layers other than `ledger` that are complete (module docs), taken off the
    /// list; the rest stay listed.
    pub(super) fn complete_besides<B: Backend>(ledger: &Ledger) -> Vec<Ledger> {
        FILED.with_borrow_mut(|filed| {
            let mut complete = Vec::new();
            filed.retain(|weak| {
                let Some(other) = weak.upgrade() else {
                    return false;
                };
                if std::sync::Arc::ptr_eq(&other, &ledger.0) {
                    return false;
                }
                // A ledger locked elsewhere is not this backward's to form.
                let Ok(mut state) = other.try_lock() else {
                    return true;
                };

                if state.complete::<B>() {
                    drop(state);
                    complete.push(Ledger(other));
                    false
                } else {
                    true
                }
            });
            complete
        })
    }
}

#[derive(Debug)]
struct ParameterBackward;

impl<B: GradientKernels> Backward<B, 1> for ParameterBackward {
    type State = ParameterRole;

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
        let ParameterRole { ledger, role } = ops.state;
        let slot = match role {
            Role::Weight => 0,
            Role::Bias => 1,
        };
        let formed = delivered_gradient::<B>(&ledger, slot);
        let grad = match role {
            Role::Weight => formed.weight,
            Role::Bias => formed.bias,
        }
        .expect("a seeded parameter's part is formed");
        grads.register::<B>(parent.id, grad);
    }
}

/// A trained fold's weight node's state: what `∂W` and `∂γ` are formed from
/// ([`FoldKernels::trained_fold_backward`]).
#[derive(Debug, Clone)]
pub struct TrainedFold<B: Backend> {
    ledger: Ledger,
    /// `[out, in]`, as stored.
    weight: FloatTensor<B>,
    gamma: FloatTensor<B>,
    mean: FloatTensor<B>,
    var: FloatTensor<B>,
    epsilon: f32,
}

/// The folded weight's node of a trained fold, with the weight and `γ` as parents: both
/// gradients from the passes' unscaled `[∂W'; ∂b']` in one launch.
#[derive(Debug)]
struct TrainedWeightBackward;

impl<B: GradientKernels + FoldKernels> Backward<B, 2> for TrainedWeightBackward {
    type State = TrainedFold<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 2>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        // The placeholder a product node registered.
        let _ = grads.consume::<B>(&ops.node);
        let [weight_parent, gamma_parent] = ops.parents;
        let s = ops.state;
        let formed = delivered_gradient::<B>(&s.ledger, 0);
        let (weight_grad, gamma_grad) = B::trained_fold_backward(
            formed
                .weight
                .expect("a trained fold's weight takes a gradient"),
            formed
                .bias
                .expect("a trained fold's gradient carries its bias row"),
            s.weight,
            s.gamma,
            s.mean,
            s.var,
            s.epsilon,
        );
        if let Some(parent) = weight_parent {
            grads.register::<B>(parent.id, weight_grad);
        }
        if let Some(parent) = gamma_parent {
            grads.register::<B>(parent.id, gamma_grad);
        }
    }
}

impl<
    B: GradientKernels + FoldKernels + ProductKernels + ReluKernels + PatchKernels + SharedLinearOps,
    C: CheckpointStrategy,
> SharedLinearOps for Autodiff<B, C>
{
    fn shared_parameter(value: FloatTensor<Self>, ledger: Ledger, role: Role) -> FloatTensor<Self> {
        let (value, node) = value.into_parts();
        match ParameterBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                ledger.lock().tracked = true;
                prep.finish(ParameterRole { ledger, role }, value)
            }
            OpsKind::UnTracked(prep) => prep.finish(value),
        }
    }

    fn trained_fold(
        weight: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
        ledger: Ledger,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (weight, weight_node) = weight.into_parts();
        let (gamma, gamma_node) = gamma.into_parts();
        let (beta, beta_node) = beta.into_parts();
        let [mean, var] = [mean, var].map(|t| t.into_primitive());
        let (w, b) = B::trained_fold(
            weight.clone(),
            gamma.clone(),
            beta,
            mean.clone(),
            var.clone(),
            epsilon,
            ledger.clone(),
        );
        ledger.lock().bias_row_always = true;
        let w = match TrainedWeightBackward
            .prepare::<C>([weight_node, gamma_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                ledger.lock().tracked = true;
                prep.finish(
                    TrainedFold {
                        ledger: ledger.clone(),
                        weight,
                        gamma,
                        mean,
                        var,
                        epsilon,
                    },
                    w,
                )
            }
            OpsKind::UnTracked(prep) => prep.finish(w),
        };
        let b = match ParameterBackward
            .prepare::<C>([beta_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                ledger.lock().tracked = true;
                prep.finish(
                    ParameterRole {
                        ledger,
                        role: Role::Bias,
                    },
                    b,
                )
            }
            OpsKind::UnTracked(prep) => prep.finish(b),
        };
        (w, b)
    }

    fn shared_linear(
        x: FloatTensor<Self>,
        patches: Option<Patches>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        map: OutputMap,
        ledger: Ledger,
        activation: Activation,
        handoff: Handoff,
    ) -> FloatTensor<Self> {
        if filing::detached() {
            let [x, weight, bias, scale, shift] =
                [x, weight, bias, scale, shift].map(|t| t.into_primitive());
            return <Self as AutodiffBackend>::from_inner(B::shared_linear(
                x, patches, weight, bias, scale, shift, map, ledger, activation, handoff,
            ));
        }
        let (nodes, inputs) = product_parts::<B, C>(
            (x, patches),
            weight,
            [bias, scale, shift],
            map,
            ledger,
            handoff,
        );
        record_product::<B, C, _, 3>(ProductBackward, nodes, inputs, activation, |s| {
            B::shared_linear(
                s.x, s.patches, s.weight, s.bias, s.scale, s.shift, s.map, s.ledger, activation,
                s.handoff,
            )
        })
    }

    fn shared_linear_residual(
        x: FloatTensor<Self>,
        patches: Option<Patches>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        scale: FloatTensor<Self>,
        shift: FloatTensor<Self>,
        map: OutputMap,
        residual: FloatTensor<Self>,
        ledger: Ledger,
        handoff: Handoff,
    ) -> FloatTensor<Self> {
        if filing::detached() {
            let [x, weight, bias, scale, shift, residual] =
                [x, weight, bias, scale, shift, residual].map(|t| t.into_primitive());
            return <Self as AutodiffBackend>::from_inner(B::shared_linear_residual(
                x, patches, weight, bias, scale, shift, map, residual, ledger, handoff,
            ));
        }
        let (residual, residual_node) = residual.into_parts();
        let ([x_node, weight_node, bias_node], inputs) = product_parts::<B, C>(
            (x, patches),
            weight,
            [bias, scale, shift],
            map,
            ledger,
            handoff,
        );
        record_product::<B, C, _, 4>(
            ResidualProductBackward,
            [x_node, weight_node, bias_node, residual_node],
            inputs,
            Activation::Relu,
            |s| {
                B::shared_linear_residual(
                    s.x, s.patches, s.weight, s.bias, s.scale, s.shift, s.map, residual, s.ledger,
                    s.handoff,
                )
            },
        )
    }
}

/// A pass's inputs taken apart for its product node: the nodes of `x`, `W` and `b`, and the
/// node's state (a frozen BatchNorm's map takes no gradient: its nodes are dropped). The pass
/// is counted as one its layer waits for when the weight or bias takes a gradient (see
/// [`filing`]).
fn product_parts<B: Backend, C: CheckpointStrategy>(
    (x, patches): (FloatTensor<Autodiff<B, C>>, Option<Patches>),
    weight: FloatTensor<Autodiff<B, C>>,
    [bias, scale, shift]: [FloatTensor<Autodiff<B, C>>; 3],
    map: OutputMap,
    ledger: Ledger,
    handoff: Handoff,
) -> ([NodeGuard; 3], ProductInputs<B>) {
    {
        let mut state = ledger.lock();
        if state.tracked {
            state.expected += 1;
        }
    }
    let (x, x_node) = x.into_parts();
    let (weight, weight_node) = weight.into_parts();
    let (bias, bias_node) = bias.into_parts();
    let [scale, shift] = [scale, shift].map(|t| t.into_primitive());
    let inputs = ProductInputs::new(
        (x, patches),
        weight,
        [bias, scale, shift],
        map,
        ledger,
        handoff,
    );
    ([x_node, weight_node, bias_node], inputs)
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
            // The backward masks the gradient with a ReLU's output.
            let activated = match activation {
                Activation::Identity => None,
                Activation::Relu => Some(output.clone()),
            };
            let state = ProductInputs {
                activated,
                ..inputs
            };
            prep.finish(state, output)
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(inputs)),
    }
}
