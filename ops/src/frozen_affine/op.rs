//! The frozen affine as a Burn backend extension (see [`super`]).
//!
//! Listed for `Cube` and `Fusion`: the caller strips autodiff (the values are constants), and the
//! CPU backends never come here.

use burn::backend::fusion::custom::TensorSpec;
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, backend_extension};

/// `(s, t)` of a frozen BatchNorm.
#[backend_extension(Cube, Fusion)]
pub trait FrozenAffineOps: Backend {
    /// `s = γ/√(σ²+ε)` and `t = β − μ·s` from `gamma`, `beta`, `mean`, `var`, each `[C]`;
    /// the same buffers as the previous call with the same input buffers (module docs).
    #[fusion(meta = |gamma, _beta, _mean, _var, _epsilon| {
        (
            TensorSpec::new(gamma.shape.clone(), gamma.dtype),
            TensorSpec::new(gamma.shape.clone(), gamma.dtype),
        )
    })]
    fn frozen_affine(
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}
