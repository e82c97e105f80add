//! What the custom ops' autodiff nodes share (design.md §1.4).
//!
//! Every custom op here (GoM geometry, the rasterizer, and the model and training crates' ops)
//! differentiates the same way: take the node's output gradient, let the backend's hand-written
//! backward turn it into one gradient per input, and hand each to its parent when that parent is
//! tracked. [`gradient_per_input`] is that step, so the nodes only name their backward.
//! [`record`] is the forward's side: run the op and, when an input is tracked, keep its inputs
//! as the node's state.

use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, NodeGuard, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend};

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

/// Runs a custom op on `Autodiff<B, C>`: `forward(inputs)` computes the output on `B`; when any
/// of the `nodes` (the inputs' autodiff halves, in `backward`'s input order) is tracked, the
/// node keeps `inputs` as its state for `backward`. The ops whose forward is the same kernel
/// with and without a graph use this; the rasterizer saves extra state when tracked and writes
/// its own.
pub fn record<B, C, BW, S, const N: usize>(
    backward: BW,
    nodes: [NodeGuard; N],
    inputs: S,
    forward: impl FnOnce(S) -> FloatTensor<B>,
) -> FloatTensor<Autodiff<B, C>>
where
    B: Backend,
    C: CheckpointStrategy,
    S: Clone + Send + std::fmt::Debug + 'static,
    BW: Backward<B, N, State = S>,
{
    match backward.prepare::<C>(nodes).compute_bound().stateful() {
        OpsKind::Tracked(prep) => {
            let out = forward(inputs.clone());
            prep.finish(inputs, out)
        }
        OpsKind::UnTracked(prep) => prep.finish(forward(inputs)),
    }
}

/// What the nodes of several passes (or several outputs of one op) file for one node that runs
/// after all of them: the scheme of the ops whose parameters every feedback pass reads (the model
/// crate's positional weights and encoder norms) and of the column split's blocks. Each node files
/// its item; the first to file also registers a placeholder for the shared node (that node's own
/// value's handle: the right shape, no copy), so that Burn reaches it; Burn runs the shared node
/// after every filing node, since it is shallower, and it takes everything filed. Clones share one
/// record.
#[derive(Clone, Default)]
pub struct PassLedger(std::sync::Arc<std::sync::Mutex<PassLedgerState>>);

impl std::fmt::Debug for PassLedger {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("PassLedger")
    }
}

#[derive(Default)]
struct PassLedgerState {
    /// `Vec<T>` of the items the nodes file; typed on first use.
    filed: Option<Box<dyn std::any::Any + Send>>,
    /// Whether a node has filed (and so registered the placeholder).
    seeded: bool,
}

impl PassLedger {
    fn lock(&self) -> std::sync::MutexGuard<'_, PassLedgerState> {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Files one node's `item`; on the first filing also registers `placeholder` for the shared
    /// node `shared` in `grads`.
    pub fn file<B: Backend, T: Send + 'static>(
        &self,
        grads: &mut Gradients,
        shared: burn::backend::autodiff::NodeId,
        placeholder: FloatTensor<B>,
        item: T,
    ) {
        let mut state = self.lock();
        if !state.seeded {
            grads.register::<B>(shared, placeholder);
            state.seeded = true;
        }
        filed::<T>(&mut state).push(item);
    }

    /// Everything filed so far, in filing order.
    pub fn take<T: Send + 'static>(&self) -> Vec<T> {
        std::mem::take(filed::<T>(&mut self.lock()))
    }
}

fn filed<T: Send + 'static>(state: &mut PassLedgerState) -> &mut Vec<T> {
    state
        .filed
        .get_or_insert_with(|| Box::new(Vec::<T>::new()))
        .downcast_mut()
        .expect("one ledger's items have one type (its backward runs on one backend)")
}

/// Reduces `items` by launches of at most `per_launch` of them: each `launch` returns an item
/// standing for those it took (placed first for the next launch) and a result; the last launch's
/// result is returned (`None` without items). The passes' partial sums of the shared weights are
/// added so, four passes a launch.
pub fn reduce_in_launches<T, R>(
    mut items: Vec<T>,
    per_launch: usize,
    mut launch: impl FnMut(Vec<T>) -> (T, R),
) -> Option<R> {
    assert!(per_launch >= 2, "a launch reduces at least two items");
    loop {
        if items.is_empty() {
            return None;
        }
        let take = items.len().min(per_launch);
        let (item, result) = launch(items.drain(..take).collect());
        if items.is_empty() {
            return Some(result);
        }
        items.insert(0, item);
    }
}
