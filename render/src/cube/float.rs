//! Finiteness in kernels, read from a float's bits.
//!
//! Comparisons cannot test it: WGSL lets a compiler assume that no value is NaN or infinite, and
//! on wgpu's OpenGL backend (Mesa's GLSL compiler) `!(x <= f32::MAX)` let a NaN colour through
//! the rasterizer's culling (`non_finite_inputs_are_rejected_on_wgpu` with only OpenGL), where
//! Vulkan's compiler kept the test. An exponent of all ones is NaN or ±Inf on every backend.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

/// The exponent bits of an f32: all ones for NaN and ±Inf.
const EXPONENT_BITS: u32 = 0x7f80_0000;

/// Whether `x` is finite (neither NaN nor ±Inf).
#[cube]
pub(crate) fn finite(x: f32) -> bool {
    (u32::reinterpret(x) & EXPONENT_BITS) != EXPONENT_BITS
}
