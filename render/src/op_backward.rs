//! What the custom ops' autodiff nodes share (design.md §1.4).
//!
//! Every custom op here (GoM geometry, the rasterizer, and the model crate's attention and
//! Linear ops) differentiates the same way: take the node's output gradient, let the backend's
//! hand-written backward turn it into one gradient per input, and hand each to its parent when
//! that parent is tracked. [`gradient_per_input`] is that step, so the nodes only name their
//! backward.

use burn::backend::Backend;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::Ops;
use burn::backend::tensor::FloatTensor;

/// Consumes the gradient of `ops`'s output, runs `backward(state, ∂output)` and registers its
/// `i`-th result as the gradient of input `i` (inputs that need no gradient are skipped).
pub fn gradient_per_input<B: Backend, S, const N: usize>(
    ops: Ops<S, N>,
    grads: &mut Gradients,
    backward: impl FnOnce(S, FloatTensor<B>) -> [FloatTensor<B>; N],
) {
    let grad = grads.consume::<B>(&ops.node);
    let input_grads = backward(ops.state, grad);
    for (parent, grad) in ops.parents.into_iter().zip(input_grads) {
        if let Some(parent) = parent {
            grads.register::<B>(parent.id, grad);
        }
    }
}
