//! What the CubeCL ops share: the rasterizer's [`crate::rasterizer`] GPU path
//! (`rasterizer::cube`), the triangle-ID rasterizer's (`visibility::cube`), the GoM geometry's
//! (`gom::cube`), the row gather's (`select::cube`), and the other crates' kernels (the fused
//! Adam step of `lifegom-train`), which use [`host`] as their one home for launch plumbing.
//!
//! - [`atomic`]: float atomic adds in kernels, native or emulated with exchanges, and which
//!   one a device gets (public for the other crates' scatter kernels, as [`host`] is).
//! - [`deferred`]: the ops on Burn's fusion backend, recorded as opaque steps of its stream.
//! - [`image`]: image tensors read in the layout they come in (channels-last views of
//!   convolutions' outputs) instead of copied to row-major order first.
//! - [`host`]: host-side plumbing — tensor preparation, buffer allocation, kernel arguments,
//!   1D launch shapes, small read-backs. Nothing here is specific to one op.
//! - `float` (crate-private): finiteness read from a float's bits, which no shader compiler may
//!   assume away (comparisons with NaN may be).
//! - `view` (crate-private): the camera record every projecting kernel takes (`ViewArgs`),
//!   passed as launch scalars with named fields instead of a flat `&[f32]` with magic offsets.

pub mod atomic;
pub mod deferred;
pub(crate) mod float;
pub mod host;
pub mod image;
pub(crate) mod view;
