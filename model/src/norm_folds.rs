//! Frozen BatchNorm statistics folded into per-channel `(scale, shift)`, kept for a whole
//! reconstruction (design.md §7.5, §7.1).
//!
//! Every BatchNorm of the network runs on its running statistics (the image encoder's γ/β still
//! learn, the Point Transformer's are frozen too), so within one reconstruction each BN is the
//! same per-channel affine map `x·scale + shift` with `scale = γ/√(σ²+ε)`,
//! `shift = β − μ·scale`, and each `Linear` a BN follows can be folded with it. A reconstruction
//! runs the encoder on the sources and on every feedback step's renders, and the Point
//! Transformer once per step, with the same weights: [`NormFolds`] makes each fold on first use
//! and hands it out after. On a GPU each fold is five to eight kernel launches (BENCHMARKS.md,
//! "Kernel launches per training step"). In training a kept fold is one autodiff node used
//! several times, so its parameters' gradient is summed before the fold's product rather than
//! after: the same gradient up to float order.

use std::any::Any;
use std::cell::RefCell;
use std::collections::HashMap;
use std::marker::PhantomData;

use burn::nn::{BatchNorm, Linear};
use burn::tensor::{Device, Tensor};

use lifegom_ops::activation::Activation;
use lifegom_ops::activation::relu;
use lifegom_ops::shared_linear::{SharedLinear, stacked};

/// Anything a reconstruction keeps under a layer's address and a name ([`NormFolds::keep`]).
type KeptValue = Box<dyn Any>;

/// BatchNorms on running statistics as per-channel `(scale, shift)`, and the `Linear` layers
/// they follow folded with them, each computed on first use and then reused (module docs).
///
/// Entries are keyed by the layers' addresses; the borrow `'a` of every layer passed in keeps
/// them in place and unchanged while the folds live, so a key cannot come to name another
/// layer. Folding is exact reuse: the same ops on the same values as folding on every use.
#[derive(Debug, Default)]
pub struct NormFolds<'a> {
    /// By `BatchNorm` address: `(scale, shift)`, each `[C]`.
    affine: RefCell<HashMap<usize, (Tensor<1>, Tensor<1>)>>,
    /// By `Linear` address: the folded `(weight [in, out], bias [out])` of `linear_bn`.
    linear: RefCell<HashMap<usize, (Tensor<2>, Tensor<1>)>>,
    /// By a layer's address and a name: layers every pass runs, with one parameter gradient for
    /// all passes on devices ([`SharedLinear`]).
    shared: RefCell<HashMap<(usize, &'static str), SharedLinear>>,
    /// By a layer's address and a name: anything else a reconstruction's passes share (the
    /// update heads' stacked and block-diagonal weights, the Point Transformer's
    /// positional-encoding weights, the encoder's norms).
    kept: RefCell<HashMap<(usize, &'static str), KeptValue>>,
    layers: PhantomData<&'a ()>,
}

impl<'a> NormFolds<'a> {
    /// No folds yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// What `make` builds, kept under `anchor`'s address and `name` for every later pass (module
    /// docs).
    ///
    /// # Panics
    ///
    /// If a value of another type was kept under the same key.
    pub(crate) fn keep<T: Clone + 'static, A>(
        &self,
        anchor: &'a A,
        name: &'static str,
        make: impl FnOnce() -> T,
    ) -> T {
        let key = (std::ptr::from_ref(anchor) as usize, name);
        if let Some(found) = self.kept.borrow().get(&key) {
            return found
                .downcast_ref::<T>()
                .expect("one type per kept name")
                .clone();
        }
        let made = make();
        self.kept.borrow_mut().insert(key, Box::new(made.clone()));
        made
    }

    /// The layer `(weight, bias)` made by `make`, kept under `anchor`'s address and `name` as a
    /// [`SharedLinear`]: every pass that runs it through these folds shares its parameter
    /// gradient (one product for all passes on devices).
    pub(crate) fn shared(
        &self,
        anchor: &'a Linear,
        name: &'static str,
        make: impl FnOnce() -> (Tensor<2>, Tensor<1>),
    ) -> SharedLinear {
        self.shared_made(anchor, name, || {
            let (weight, bias) = make();
            SharedLinear::new(weight, bias)
        })
    }

    /// `layers` (which read the same input, like `x`'s) as one shared layer with their weights
    /// side by side ([`stacked`]), kept under the first layer and `name`: one product and a
    /// split of its output replace a product per layer. `None` where the products stay apart
    /// ([`SharedLinear::stacks_on`]) and for layers without biases.
    pub(crate) fn stacked(
        &self,
        layers: &[&'a Linear],
        name: &'static str,
        device: &Device,
    ) -> Option<SharedLinear> {
        if !SharedLinear::stacks_on(device) || layers.iter().any(|l| l.bias.is_none()) {
            return None;
        }
        Some(self.shared(layers[0], name, || stacked(layers, device)))
    }

    /// The shared layer `make` builds, kept as [`Self::shared`] keeps its own.
    fn shared_made(
        &self,
        anchor: &'a Linear,
        name: &'static str,
        make: impl FnOnce() -> SharedLinear,
    ) -> SharedLinear {
        let key = (std::ptr::from_ref(anchor) as usize, name);
        if let Some(found) = self.shared.borrow().get(&key) {
            return found.clone();
        }
        let made = make();
        self.shared.borrow_mut().insert(key, made.clone());
        made
    }

    /// `BN(Linear(·))` folded as a shared layer ([`SharedLinear::folded`]).
    pub(crate) fn shared_fold(
        &self,
        linear: &'a Linear,
        bn: &'a BatchNorm,
        device: &Device,
    ) -> SharedLinear {
        self.shared_made(linear, "folded", || {
            SharedLinear::folded(linear, bn, device)
        })
    }

    /// A `Linear` with a bias as a shared layer.
    ///
    /// # Panics
    ///
    /// If the layer has no bias.
    pub(crate) fn shared_layer(&self, linear: &'a Linear) -> SharedLinear {
        self.shared(linear, "layer", || {
            let bias = linear.bias.as_ref().expect("a shared layer has a bias");
            (linear.weight.val(), bias.val())
        })
    }

    /// `linear` applied to `x`: as a shared layer when it has a bias ([`Self::shared_layer`]),
    /// else Burn's `Linear`.
    pub(crate) fn apply<const D: usize>(&self, linear: &'a Linear, x: Tensor<D>) -> Tensor<D> {
        self.apply_with(linear, x, Activation::Identity)
    }

    /// `act(linear(x))`, the activation in a shared layer's product ([`Self::apply`]).
    pub(crate) fn apply_with<const D: usize>(
        &self,
        linear: &'a Linear,
        x: Tensor<D>,
        activation: Activation,
    ) -> Tensor<D> {
        match (&linear.bias, activation) {
            (Some(_), _) => self.shared_layer(linear).forward_with(x, activation),
            (None, Activation::Identity) => lifegom_ops::linear_op::forward(linear, x),
            (None, Activation::Relu) => relu(lifegom_ops::linear_op::forward(linear, x)),
        }
    }

    /// How many values are kept: BN folds with everything else kept under a layer
    /// (`Self::keep`: the encoder's norms, …), and `Linear` folds with shared layers.
    pub fn kept(&self) -> (usize, usize) {
        (
            self.affine.borrow().len() + self.kept.borrow().len(),
            self.linear.borrow().len() + self.shared.borrow().len(),
        )
    }

    /// The eval-mode BN as `x·scale + shift` per channel: `scale = γ/√(σ²+ε)`,
    /// `shift = β − μ·scale`, each `[C]`.
    pub(crate) fn affine(&self, bn: &'a BatchNorm, device: &Device) -> (Tensor<1>, Tensor<1>) {
        let key = std::ptr::from_ref(bn) as usize;
        if let Some(found) = self.affine.borrow().get(&key) {
            return found.clone();
        }
        let (scale, shift) = lifegom_ops::frozen_affine::frozen_affine(bn, device);
        self.affine
            .borrow_mut()
            .insert(key, (scale.clone(), shift.clone()));
        (scale, shift)
    }

    /// `BN(Linear(·))` as one affine layer: `(W·diag(scale), b·scale + shift)` (`b = 0` for a
    /// layer without bias).
    pub(crate) fn linear(
        &self,
        linear: &'a Linear,
        bn: &'a BatchNorm,
        device: &Device,
    ) -> (Tensor<2>, Tensor<1>) {
        let key = std::ptr::from_ref(linear) as usize;
        if let Some(found) = self.linear.borrow().get(&key) {
            return found.clone();
        }
        let (scale, shift) = self.affine(bn, device);
        let weight = linear.weight.val() * scale.clone().unsqueeze_dim(0);
        let bias = match &linear.bias {
            Some(b) => b.val() * scale + shift,
            None => shift,
        };
        self.linear
            .borrow_mut()
            .insert(key, (weight.clone(), bias.clone()));
        (weight, bias)
    }
}
