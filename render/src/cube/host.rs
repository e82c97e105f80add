//! Host-side helpers for launching CubeCL kernels on Burn's CubeCL backend, shared by every
//! CubeCL op of the workspace (the rasterizers, the GoM geometry, the row gather, the fused Adam
//! step).
//!
//! The kernels index flat, contiguous buffers, so the helpers here do three things:
//! - bring Burn tensors into that layout ([`prepare`], [`prepare_i32`]) and wrap kernel outputs
//!   back into tensors ([`tensor_of`], [`tensor_f32`], [`cast_to`] the caller's dtype);
//! - allocate buffers and turn them into kernel arguments ([`empty_u32`], [`zeros_f32`],
//!   [`arg`], [`tensor_arg`], [`u32_bytes`] for uploads);
//! - shape 1D launches ([`THREADS_1D`], [`count_1d`], [`count_cubes`]) and read single values back
//!   ([`read_u32`]).
//!
//! Zero-sized bindings are invalid on some runtimes, so every allocation and argument here is
//! at least one element long; kernels guard their thread index against the real length.

use burn::backend::TensorMetadata;
use burn::backend::ops::{FloatTensorOps, IntTensorOps};
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::{DType, FloatDType, IntDType, Shape};
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{CubeBackend, CubeDevice};

/// Client type used by the host functions.
pub type ComputeClient = burn_cubecl::cubecl::client::Client;

/// Threads per cube of the 1D kernels (one thread per Gaussian, face, pixel, chunk, ...).
pub const THREADS_1D: u32 = 256;

/// Largest number of cubes along one dispatch dimension.
const MAX_CUBES_PER_DIM: u32 = 65_535;

/// A 1D launch of `units` threads, split over a 2D grid of cubes where one row would exceed the
/// 65535-cube dispatch limit. Kernels index with `ABSOLUTE_POS` and guard `< units`.
pub fn count_1d(units: usize) -> CubeCount {
    count_cubes(units.div_ceil(THREADS_1D as usize))
}

/// `cubes` cubes (at least one) over a 2D grid where one row would exceed the 65535-cube
/// dispatch limit: for kernels that give each cube one item (a row, a tile) and find it as
/// `CUBE_POS_Y·CUBE_COUNT_X + CUBE_POS_X`, guarding `< cubes`.
pub fn count_cubes(cubes: usize) -> CubeCount {
    let cubes = cubes.max(1) as u32;
    let x = cubes.min(MAX_CUBES_PER_DIM);
    CubeCount::Static(x, cubes.div_ceil(x), 1)
}

/// f32 and contiguous, the layout every float kernel argument is indexed in.
pub fn prepare(t: FloatTensor<CubeBackend>) -> CubeTensor {
    let t = if t.dtype() == DType::F32 {
        t
    } else {
        CubeBackend::float_cast(t, FloatDType::F32)
    };
    into_contiguous(t)
}

/// `t` in `dtype` (a no-op when it already is): the kernels compute in `f32`, and an op answers
/// in its inputs' float type.
pub fn cast_to(t: CubeTensor, dtype: DType) -> CubeTensor {
    if t.dtype() == dtype {
        t
    } else {
        CubeBackend::float_cast(t, dtype.into())
    }
}

/// i32 and contiguous, the layout every int kernel argument is indexed in.
pub fn prepare_i32(t: IntTensor<CubeBackend>) -> CubeTensor {
    let t = if t.dtype() == DType::I32 {
        t
    } else {
        CubeBackend::int_cast(t, IntDType::I32)
    };
    into_contiguous(t)
}

/// Little-endian bytes of `values`, for `client.create_from_slice`.
pub fn u32_bytes(values: &[u32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// A contiguous tensor of `dtype` over a kernel's output buffer.
pub fn tensor_of(
    client: &ComputeClient,
    device: &CubeDevice,
    handle: Handle,
    shape: &[usize],
    dtype: DType,
) -> CubeTensor {
    CubeTensor::new_contiguous(
        client.clone(),
        device.clone(),
        Shape::from(shape.to_vec()),
        handle,
        dtype,
    )
}

/// An f32 tensor over a kernel's output buffer.
pub fn tensor_f32(
    client: &ComputeClient,
    device: &CubeDevice,
    handle: Handle,
    shape: &[usize],
) -> CubeTensor {
    tensor_of(client, device, handle, shape, DType::F32)
}

/// The kernel argument for a whole (prepared, contiguous) tensor.
pub fn tensor_arg(t: &CubeTensor) -> BufferArg {
    t.clone().into_buffer_arg()
}

/// A buffer of `len` u32 (or any other 4-byte element; at least one element).
pub fn empty_u32(client: &ComputeClient, len: usize) -> Handle {
    client.empty(4 * len.max(1))
}

/// A zero-filled f32 buffer of `len` elements (at least one).
pub fn zeros_f32(client: &ComputeClient, device: &CubeDevice, len: usize) -> Handle {
    burn_cubecl::ops::numeric::zeros_client(
        client.clone(),
        device.clone(),
        Shape::from(vec![len.max(1)]),
        DType::F32,
    )
    .handle
}

/// The kernel argument for the first `len` elements of `handle`.
pub fn arg(handle: &Handle, len: usize) -> BufferArg {
    // SAFETY: every handle passed here was allocated with at least `max(len, 1)` 4-byte elements.
    unsafe { BufferArg::from_raw_parts(handle.clone(), len.max(1)) }
}

/// Reads the first `u32` of `handle` back to the host: a device sync, counted under `what`
/// ([`crate::readback::take_device_reads`]). `what` also names the value for the panic message;
/// the callers are backend-extension ops, which cannot return errors, and a failed read here
/// means the device itself is gone.
pub fn read_u32(client: &ComputeClient, handle: Handle, what: &'static str) -> u32 {
    crate::readback::note_device_read(what);
    let bytes = client
        .read_one(handle)
        .unwrap_or_else(|e| panic!("reading {what} back from the device: {e:?}"));
    u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])
}
