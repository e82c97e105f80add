//! Custom ops on Burn's fusion backend, as deferred operations (design.md §1.4).
//!
//! With Burn's `fusion` feature a CubeCL tensor is a lazy [`FusionTensor`]: an op only records
//! itself in its thread's stream, and the stream later runs the recorded ops, merging runs of
//! elementwise ops, reductions and matmul epilogues into one kernel each. A custom op takes part
//! as an opaque step of that stream: it names its input and output tensors in a [`CustomOpIr`],
//! and when the stream reaches it, it fetches the inputs' concrete `CubeBackend` tensors, runs
//! the unfused implementation on them and publishes the outputs. Nothing is read back and nothing
//! waits: the op is recorded with output shapes known in advance, as every Burn op is.
//!
//! The stream runs on Burn's fusion thread, not on the thread that recorded the op; a deferred op
//! enters the span that was open where it was recorded, so its kernel launches still count under
//! the model's stage (`lifegom_cli::launches`). Burn's own ops carry no span there.
//!
//! The public ops use `#[backend_extension(…, Fusion)]` with `#[fusion(meta = …)]`, which
//! generates exactly this. [`deferred`] is the same recording for the hidden kernel traits the
//! autodiff nodes call (their inputs are records with private fields and their outputs arrays,
//! which the macro does not describe): one place instead of a copy per op.

use burn::backend::TensorMetadata;
use burn::backend::fusion::ExecutionError;
use burn::backend::fusion::custom::{
    CustomOpIr, HandleContainer, Operation, OperationIr, StreamId, TensorIr, TensorSpec,
};
use burn::backend::fusion::{Fusion, FusionBackend, FusionRuntime, FusionTensor};
use burn::backend::tensor::{FloatTensor, IntTensor};
use std::fmt;

/// A tensor of the inner backend `B`, tagged with its kind, as a deferred op receives and
/// returns it.
pub enum Value<B: FusionBackend> {
    /// A float tensor.
    Float(FloatTensor<B>),
    /// An int tensor.
    Int(IntTensor<B>),
}

impl<B: FusionBackend> Value<B> {
    /// The float tensor; a deferred op's inputs are in the order it recorded them, so a kind
    /// mismatch is a bug in that op.
    pub fn float(self) -> FloatTensor<B> {
        match self {
            Value::Float(t) => t,
            Value::Int(_) => unreachable!("a deferred op asked for a float input that is an int"),
        }
    }

    /// The int tensor (see [`Value::float`]).
    pub fn int(self) -> IntTensor<B> {
        match self {
            Value::Int(t) => t,
            Value::Float(_) => unreachable!("a deferred op asked for an int input that is a float"),
        }
    }
}

/// An input of a deferred op: a lazy tensor of `Fusion<B>` and its kind.
pub enum Input<B: FusionBackend> {
    /// A float tensor.
    Float(FloatTensor<Fusion<B>>),
    /// An int tensor.
    Int(IntTensor<Fusion<B>>),
}

impl<B: FusionBackend> Input<B> {
    fn tensor(&self) -> &FusionTensor<B::FusionRuntime> {
        match self {
            Input::Float(t) | Input::Int(t) => t,
        }
    }
}

#[derive(Clone, Copy)]
enum Kind {
    Float,
    Int,
}

/// The recorded step: the inputs' and outputs' IR and the closure that runs the unfused op.
struct DeferredOp<B: FusionBackend, F> {
    name: &'static str,
    inputs: Vec<(TensorIr, Kind)>,
    outputs: Vec<(TensorIr, Kind)>,
    run: F,
    /// The span open where the op was recorded, and the subscriber it belongs to (a thread's
    /// own, in tests): the stream runs the op on Burn's fusion thread, whose own spans say
    /// nothing about which stage of the model asked for it.
    span: tracing::Span,
    dispatch: tracing::Dispatch,
    _backend: std::marker::PhantomData<fn() -> B>,
}

impl<B: FusionBackend, F> fmt::Debug for DeferredOp<B, F> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "DeferredOp({})", self.name)
    }
}

type Handles<B> =
    HandleContainer<<<B as FusionBackend>::FusionRuntime as FusionRuntime>::FusionHandle>;

impl<B, F> Operation<B::FusionRuntime> for DeferredOp<B, F>
where
    B: FusionBackend,
    F: Fn(Vec<Value<B>>) -> Vec<Value<B>> + Send + Sync,
{
    fn execute(&self, handles: &mut Handles<B>) -> Result<(), ExecutionError> {
        tracing::dispatcher::with_default(&self.dispatch, || {
            let _stage = self.span.enter();
            self.run_recorded(handles)
        })
    }
}

impl<B, F> DeferredOp<B, F>
where
    B: FusionBackend,
    F: Fn(Vec<Value<B>>) -> Vec<Value<B>> + Send + Sync,
{
    fn run_recorded(&self, handles: &mut Handles<B>) -> Result<(), ExecutionError> {
        let values = self
            .inputs
            .iter()
            .map(|(ir, kind)| match kind {
                Kind::Float => Value::Float(handles.get_float_tensor::<B>(ir)),
                Kind::Int => Value::Int(handles.get_int_tensor::<B>(ir)),
            })
            .collect();
        let results = (self.run)(values);
        if results.len() != self.outputs.len() {
            return Err(ExecutionError::generic(format!(
                "deferred op {} returned {} tensors, recorded {}",
                self.name,
                results.len(),
                self.outputs.len()
            )));
        }
        for ((ir, kind), value) in self.outputs.iter().zip(results) {
            match (kind, value) {
                (Kind::Float, Value::Float(t)) => handles.register_float_tensor::<B>(&ir.id, t),
                (Kind::Int, Value::Int(t)) => handles.register_int_tensor::<B>(&ir.id, t),
                _ => {
                    return Err(ExecutionError::generic(format!(
                        "deferred op {} returned a tensor of the wrong kind",
                        self.name
                    )));
                }
            }
        }
        Ok(())
    }
}

/// An output of a deferred op: its spec and kind.
pub enum Output {
    /// A float tensor of this shape and dtype.
    Float(TensorSpec),
    /// An int tensor of this shape and dtype.
    Int(TensorSpec),
}

/// Records `run` as one step of the calling thread's fusion stream and returns its outputs as
/// lazy tensors, in the order of `outputs`.
///
/// `run` receives the inputs' concrete tensors in the order of `inputs` and must return tensors of
/// exactly the recorded kinds, shapes and dtypes. It runs later, on the stream's executor, after
/// every op that writes its inputs; it may launch kernels and read back as the unfused op does.
///
/// # Panics
/// When `inputs` is empty: the step needs an input for its device and stream.
pub fn deferred<B, F>(
    name: &'static str,
    inputs: Vec<Input<B>>,
    outputs: Vec<Output>,
    run: F,
) -> Vec<FusionTensor<B::FusionRuntime>>
where
    B: FusionBackend,
    F: Fn(Vec<Value<B>>) -> Vec<Value<B>> + Send + Sync + 'static,
{
    let client = inputs
        .first()
        .expect("a deferred op needs an input tensor")
        .tensor()
        .client
        .clone();
    let inputs: Vec<(TensorIr, Kind)> = inputs
        .into_iter()
        .map(|input| match input {
            Input::Float(t) => (t.into_ir(), Kind::Float),
            Input::Int(t) => (t.into_ir(), Kind::Int),
        })
        .collect();
    let outputs: Vec<(TensorIr, Kind)> = outputs
        .into_iter()
        .map(|output| {
            let (spec, kind) = match output {
                Output::Float(spec) => (spec, Kind::Float),
                Output::Int(spec) => (spec, Kind::Int),
            };
            let id = client.create_empty_handle();
            (TensorIr::uninit(id, spec.shape, spec.dtype), kind)
        })
        .collect();
    let desc = CustomOpIr {
        id: name.to_string(),
        inputs: inputs.iter().map(|(ir, _)| ir.clone()).collect(),
        outputs: outputs.iter().map(|(ir, _)| ir.clone()).collect(),
        scalars: Vec::new(),
    };
    let op = DeferredOp::<B, F> {
        name,
        inputs,
        outputs,
        run,
        span: tracing::Span::current(),
        dispatch: tracing::dispatcher::get_default(Clone::clone),
        _backend: std::marker::PhantomData,
    };
    client.register(StreamId::current(), OperationIr::Custom(desc), op)
}

/// The spec of a float output with this shape and the dtype of `like`.
pub fn float_like<B: FusionBackend>(
    like: &FloatTensor<Fusion<B>>,
    shape: impl Into<burn::tensor::Shape>,
) -> Output {
    Output::Float(TensorSpec::new(shape.into(), like.dtype()))
}

/// The `N` tensors of a deferred op's inputs or outputs as an array, in recorded order.
///
/// # Panics
/// When there are not exactly `N` (a bug in the op that recorded them).
pub fn array<T, const N: usize>(values: Vec<T>) -> [T; N] {
    let len = values.len();
    values
        .try_into()
        .unwrap_or_else(|_| panic!("a deferred op has {len} tensors where {N} were recorded"))
}
