//! The fusion layers' fused ops (design.md §7.4): the attention core (scores, softmax, weighted
//! values, for all heads) and each residual `LN(a + b)`, as custom ops with hand-written
//! backwards ([`op`]): slice code on the CPU backends (math in [`kernels`]), CubeCL kernels on
//! the devices. The layers themselves, and the tensor-op composition the ops are tested
//! against, are `lifegom_model::fusion`.

mod attention_cube;
mod cube;
pub mod kernels;
pub mod op;

pub use attention_cube::MAX_KEYS;
