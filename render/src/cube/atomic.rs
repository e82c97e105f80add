//! Float atomic adds in CubeCL kernels, for every op whose backward scatters into a buffer (the
//! rasterizer's 2D gradients, the row gather's source gradient).
//!
//! WGSL has no float atomics and some Vulkan devices lack them too, so each such kernel is
//! generic over its slot type ([`AtomicAddF32`]): `f32` slots add natively, `u32` slots hold
//! the bits and emulate the add with atomic exchanges. [`use_native_float_atomics`] picks one
//! per device; `rasterizer::force_emulated_float_atomics` makes tests cover the
//! emulation on devices that have both.

use std::sync::atomic::{AtomicBool, Ordering};

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::features::AtomicUsage;
use burn_cubecl::cubecl::ir::{ElemType, FloatKind};
use burn_cubecl::cubecl::prelude::*;

use super::host::ComputeClient;

/// `*slot += value` for an `f32` held in an atomic slot of type `Self`: `f32` slots use the
/// native float atomic add; `u32` slots hold the bit pattern and emulate it with atomic
/// exchanges, for runtimes without float atomics (WGSL has none).
// The `#[cube]` expansion adds an undocumented `__expand_` twin of the method.
#[allow(missing_docs)]
#[cube]
pub trait AtomicAddF32: CubePrimitive {
    /// Adds `value` to `slot`.
    fn atomic_add_f32(slot: &Atomic<Self>, value: f32);
}

#[cube]
impl AtomicAddF32 for f32 {
    fn atomic_add_f32(slot: &Atomic<Self>, value: f32) {
        slot.fetch_add(value);
    }
}

/// The emulation takes the slot's value (leaving `+0.0`), adds its own and puts the sum back.
/// The put returns whatever another thread deposited in the meantime; that amount goes round
/// again until a put lands on an empty slot. No addend is ever dropped. The textbook
/// compare-and-swap loop is not safe here: WGSL only has a *weak* compare-exchange, which may
/// fail spuriously, and CubeCL returns only its old value, not the `exchanged` flag, so a
/// spurious failure would look like success and lose the addend (Metal, through naga, really
/// is weak).
#[cube]
impl AtomicAddF32 for u32 {
    fn atomic_add_f32(slot: &Atomic<Self>, value: f32) {
        let mut pending = value;
        loop {
            let taken = slot.exchange(0u32);
            let sum = f32::reinterpret(taken) + pending;
            let back = slot.exchange(u32::reinterpret(sum));
            if back == 0u32 {
                break;
            }
            pending = f32::reinterpret(back);
        }
    }
}

/// Set by [`crate::rasterizer::force_emulated_float_atomics`]: use the exchange emulation even
/// where native float atomics exist, so tests cover both paths on one machine.
pub(crate) static FORCE_EMULATED: AtomicBool = AtomicBool::new(false);

/// Whether kernels add `f32` atomically in hardware: the runtime supports it (WGSL has no float
/// atomics; some Vulkan devices do) and the emulation is not forced.
pub fn use_native_float_atomics(client: &ComputeClient) -> bool {
    !FORCE_EMULATED.load(Ordering::Relaxed)
        && client
            .properties()
            .atomic_type_usage(Type::atomic(ElemType::Float(FloatKind::F32)))
            .contains(AtomicUsage::Add)
}
