//! [`super::split_columns`] as a Burn backend extension for CubeCL devices, and the autodiff
//! nodes that join the blocks' gradients in one launch (see [`super`]).
//!
//! Listed for `Cube`, `Fusion` and `Autodiff`; the CPU backends never reach it.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, NodeGuard, Ops, OpsKind};
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::fusion::{Fusion, FusionBackend};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, TensorMetadata, backend_extension};
use burn::tensor::Shape;

use crate::cube::deferred::{Input, Value, array, deferred, float_like};
use crate::op_backward::{PassLedger, gradient_per_input, record};

/// Blocks per launch.
pub const MAX_BLOCKS: usize = 4;

/// The widths of 2 to [`MAX_BLOCKS`] blocks of consecutive columns; unused slots are 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ColumnBlocks {
    widths: [usize; MAX_BLOCKS],
}

impl ColumnBlocks {
    /// Blocks of `widths`, each positive.
    ///
    /// # Panics
    ///
    /// On more than [`MAX_BLOCKS`] widths or a zero width.
    pub fn new(widths: &[usize]) -> Self {
        assert!(
            widths.len() <= MAX_BLOCKS && widths.iter().all(|&w| w > 0),
            "1 to {MAX_BLOCKS} positive widths"
        );
        let mut all = [0; MAX_BLOCKS];
        all[..widths.len()].copy_from_slice(widths);
        Self { widths: all }
    }

    /// Block `i`'s width (0 for an unused slot).
    pub fn width(&self, i: usize) -> usize {
        self.widths[i]
    }

    /// The column after each of the first three blocks (the total for unused slots): the
    /// kernels find an element's block by comparing its column with them.
    pub fn ends(&self) -> [usize; MAX_BLOCKS - 1] {
        let mut ends = [0; MAX_BLOCKS - 1];
        let mut end = 0;
        for (slot, w) in ends.iter_mut().zip(self.widths) {
            end += w;
            *slot = end;
        }
        let total = self.total();
        ends.map(|e| e.min(total))
    }

    /// Blocks in use.
    pub fn count(&self) -> usize {
        self.widths.iter().filter(|&&w| w > 0).count()
    }

    /// All blocks' width.
    pub fn total(&self) -> usize {
        self.widths.iter().sum()
    }

    /// Block `i`'s shape for `rows` rows; `[1]` for an unused slot (never written).
    pub fn shape(&self, rows: usize, i: usize) -> Shape {
        match self.widths[i] {
            0 => Shape::new([1]),
            w => Shape::new([rows, w]),
        }
    }
}

/// `t` `[rows, Σ w]` as its blocks of columns `[rows, w_i]`, in slot order; slots past the last
/// block are `[1]` placeholders.
#[backend_extension(Cube, Fusion, Autodiff)]
pub trait SplitOps: Backend {
    /// The blocks.
    #[fusion(meta = |t, blocks| {
        let rows = t.shape[0];
        let spec = |i| TensorSpec::new(blocks.shape(rows, i), t.dtype);
        (spec(0), spec(1), spec(2), spec(3))
    })]
    fn split_columns(
        t: FloatTensor<Self>,
        blocks: ColumnBlocks,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    );

    /// The blocks `b_i` `[rows, w_i]` side by side, `[rows, Σ w]`: the split's inverse. Slots
    /// past the last block take any tensor (e.g. `b0` again) and are not read.
    #[fusion(meta = |b0, _b1, _b2, _b3, blocks| {
        TensorSpec::new(Shape::new([b0.shape[0], blocks.total()]), b0.dtype)
    })]
    fn join_columns(
        b0: FloatTensor<Self>,
        b1: FloatTensor<Self>,
        b2: FloatTensor<Self>,
        b3: FloatTensor<Self>,
        blocks: ColumnBlocks,
    ) -> FloatTensor<Self>;
}

/// What a backend implements so that `Autodiff<B>` can join the blocks' gradients.
#[doc(hidden)]
pub trait JoinKernels: Backend {
    /// `[rows, Σ w]`: each given block `[rows, w_i]` in its columns, zeros in the columns of the
    /// blocks that are `None`; at least one is given.
    fn join_given_columns(
        blocks: Vec<Option<FloatTensor<Self>>>,
        widths: ColumnBlocks,
        rows: usize,
    ) -> FloatTensor<Self>;
}

impl<B: FusionBackend + JoinKernels> JoinKernels for Fusion<B> {
    fn join_given_columns(
        blocks: Vec<Option<FloatTensor<Self>>>,
        widths: ColumnBlocks,
        rows: usize,
    ) -> FloatTensor<Self> {
        let given: Vec<bool> = blocks.iter().map(Option::is_some).collect();
        let first = blocks.iter().flatten().next().expect("a block's gradient");
        let specs = vec![float_like::<B>(first, Shape::new([rows, widths.total()]))];
        let inputs = blocks.into_iter().flatten().map(Input::Float).collect();
        let [joined] = array(deferred::<B, _>(
            "join_given_columns",
            inputs,
            specs,
            move |v| {
                let mut v = v.into_iter().map(Value::float);
                let blocks = given
                    .iter()
                    .map(|&g| if g { v.next() } else { None })
                    .collect();
                vec![Value::Float(B::join_given_columns(blocks, widths, rows))]
            },
        ));
        joined
    }
}

/// A block's node: which block, and the source's handle, its placeholder.
#[derive(Debug, Clone)]
pub struct BlockState<B: Backend> {
    /// Files `(index, ∂block)` for the source's node.
    ledger: PassLedger,
    index: usize,
    source: FloatTensor<B>,
}

/// The source's node: the blocks' widths and rows.
#[derive(Debug, Clone)]
pub struct SourceState {
    ledger: PassLedger,
    widths: ColumnBlocks,
    rows: usize,
}

#[derive(Debug)]
struct BlockBackward;

impl<B: Backend> Backward<B, 1> for BlockBackward {
    type State = BlockState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let [Some(parent)] = ops.parents else {
            return;
        };
        let s = ops.state;
        s.ledger
            .file::<B, _>(grads, parent.id, s.source, (s.index, grad));
    }
}

#[derive(Debug)]
struct SourceBackward;

impl<B: JoinKernels> Backward<B, 1> for SourceBackward {
    type State = SourceState;

    fn backward(
        self,
        ops: Ops<Self::State, 1>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        // The placeholder a block's node registered.
        let _ = grads.consume::<B>(&ops.node);
        let [Some(parent)] = ops.parents else {
            return;
        };
        let s = ops.state;
        let mut blocks: Vec<Option<FloatTensor<B>>> = (0..MAX_BLOCKS).map(|_| None).collect();
        for (index, grad) in s.ledger.take::<(usize, FloatTensor<B>)>() {
            blocks[index] = Some(grad);
        }
        let joined = B::join_given_columns(blocks, s.widths, s.rows);
        grads.register::<B>(parent.id, joined);
    }
}

impl<B: SplitOps + JoinKernels, C: CheckpointStrategy> SplitOps for Autodiff<B, C> {
    fn split_columns(
        t: FloatTensor<Self>,
        blocks: ColumnBlocks,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        let rows = t.shape()[0];
        let (t, t_node) = t.into_parts();
        let ledger = PassLedger::default();
        // The source's node: the same values (module docs).
        let source: FloatTensor<Self> = match SourceBackward
            .prepare::<C>([t_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(
                SourceState {
                    ledger: ledger.clone(),
                    widths: blocks,
                    rows,
                },
                t.clone(),
            ),
            OpsKind::UnTracked(prep) => prep.finish(t.clone()),
        };
        let (b0, b1, b2, b3) = B::split_columns(t.clone(), blocks);
        let block = |value: FloatTensor<B>, index: usize| match BlockBackward
            .prepare::<C>([source.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(
                BlockState {
                    ledger: ledger.clone(),
                    index,
                    source: t.clone(),
                },
                value,
            ),
            OpsKind::UnTracked(prep) => prep.finish(value),
        };
        (block(b0, 0), block(b1, 1), block(b2, 2), block(b3, 3))
    }

    fn join_columns(
        b0: FloatTensor<Self>,
        b1: FloatTensor<Self>,
        b2: FloatTensor<Self>,
        b3: FloatTensor<Self>,
        blocks: ColumnBlocks,
    ) -> FloatTensor<Self> {
        let [p0, p1, p2, p3] = [b0, b1, b2, b3].map(|t| t.into_parts());
        match blocks.count() {
            2 => join_node::<B, C, 2>([p0, p1], blocks),
            3 => join_node::<B, C, 3>([p0, p1, p2], blocks),
            _ => join_node::<B, C, 4>([p0, p1, p2, p3], blocks),
        }
    }
}

/// The join of `N` blocks as one node with `N` parents; its backward is the split.
fn join_node<B: SplitOps + JoinKernels, C: CheckpointStrategy, const N: usize>(
    parts: [(FloatTensor<B>, NodeGuard); N],
    blocks: ColumnBlocks,
) -> FloatTensor<Autodiff<B, C>> {
    let mut values = Vec::with_capacity(N);
    let nodes = parts.map(|(value, node)| {
        values.push(value);
        node
    });
    let rows = values[0].shape()[0];
    let forward = move |_: ColumnBlocks| {
        B::join_given_columns(values.into_iter().map(Some).collect(), blocks, rows)
    };
    record::<B, C, _, _, N>(JoinBackward::<N>, nodes, blocks, forward)
}

#[derive(Debug)]
struct JoinBackward<const N: usize>;

impl<B: SplitOps, const N: usize> Backward<B, N> for JoinBackward<N> {
    type State = ColumnBlocks;

    fn backward(
        self,
        ops: Ops<Self::State, N>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        gradient_per_input::<B, _, N>(ops, grads, |blocks, grad| {
            let (g0, g1, g2, g3) = B::split_columns(grad, blocks);
            let mut all = [g0, g1, g2, g3].into_iter();
            std::array::from_fn(|_| all.next().expect("at most four blocks"))
        });
    }
}
