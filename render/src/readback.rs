//! Reading tensor values back to the host: the one place that does it.
//!
//! Burn reports a failed read-back (a lost device, a storage access error, an element type
//! that cannot be converted) as an error value. Everything in the workspace that needs host
//! values goes through these functions, so such a failure reaches the caller as a
//! [`ReadbackError`] naming the tensor; it never turns into an empty vector that would then
//! pass validation as "no values, so no bad values".
//!
//! Two levels:
//! - [`read`] takes a `Tensor<D>` (model, train, eval and binaries);
//! - [`read_float_primitive`] / [`read_int_primitive`] take a backend primitive, for the
//!   CPU implementations of our backend extensions (rasterizer, visibility);
//! - [`HostLend`] lends a CPU backend's primitive to a host kernel, in place where the backend
//!   allows it (Flex), for the ops that run every step.
//!
//! On a CubeCL device (a GPU) a read-back is a sync: it waits for every kernel queued before
//! it, and the card then idles until the host has queued more work. [`read`] and
//! [`crate::cube::host::read_u32`] count the read-backs they make from such a device per tensor
//! name ([`take_device_reads`]), so the benchmarks can report syncs per step beside kernel
//! launches; the CPU backends' reads are not syncs and are not counted.
//!
//! ```
//! use burn::tensor::{Device, Tensor};
//! use lifegom_render::readback;
//! let t = Tensor::<2>::from_floats([[1.0, 2.0], [3.0, 4.0]], &Device::flex());
//! let values: Vec<f32> = readback::read("example", t)?;
//! assert_eq!(values, [1.0, 2.0, 3.0, 4.0]);
//! # Ok::<(), readback::ReadbackError>(())
//! ```

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::sync::{Mutex, PoisonError};

use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{Backend, Flex};
use burn::tensor::kind::Basic;
use burn::tensor::{DType, Element, Shape, Tensor, TensorData};
use bytemuck::Pod;

/// A tensor whose values could not be brought to the host.
#[derive(Debug, thiserror::Error)]
#[error("reading tensor `{tensor}` back to the host failed: {reason}")]
pub struct ReadbackError {
    /// Which tensor (the caller's name for it).
    pub tensor: &'static str,
    /// Burn's account of the failure.
    pub reason: String,
}

/// Device read-backs per tensor name not yet taken by [`take_device_reads`].
static DEVICE_READS: Mutex<BTreeMap<&'static str, u64>> = Mutex::new(BTreeMap::new());

/// Counts one read-back of `tensor` from a CubeCL device (module docs).
pub(crate) fn note_device_read(tensor: &'static str) {
    *DEVICE_READS
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .entry(tensor)
        .or_default() += 1;
}

/// The read-backs from CubeCL devices since the last call (or since the process started), per
/// tensor name: each one a sync of the device's queue (module docs). Process-wide, like CubeCL's
/// launch observer: the benchmarks take it once per step.
pub fn take_device_reads() -> BTreeMap<&'static str, u64> {
    std::mem::take(&mut *DEVICE_READS.lock().unwrap_or_else(PoisonError::into_inner))
}

/// The values of `t` (float, int or bool) in row-major order, converted to `E` when its dtype
/// differs.
pub fn read<E: Element, const D: usize, K: Basic>(
    tensor: &'static str,
    t: Tensor<D, K>,
) -> Result<Vec<E>, ReadbackError> {
    if !crate::device::runs_on_host(&t.device()) {
        note_device_read(tensor);
    }
    t.try_into_vec_as::<E>().map_err(|e| ReadbackError {
        tensor,
        reason: e.to_string(),
    })
}

/// The values of a float primitive as `f32` (converted when the backend stores another float).
pub fn read_float_primitive<B: Backend>(
    tensor: &'static str,
    t: FloatTensor<B>,
) -> Result<Vec<f32>, ReadbackError> {
    let fail = |reason: String| ReadbackError { tensor, reason };
    let data =
        burn::tensor::read_sync(B::float_into_data(t)).map_err(|e| fail(format!("{e:?}")))?;
    data.try_into_vec_as::<f32>()
        .map_err(|e| fail(e.to_string()))
}

/// The values of an int primitive as `i64`.
pub fn read_int_primitive<B: Backend>(
    tensor: &'static str,
    t: IntTensor<B>,
) -> Result<Vec<i64>, ReadbackError> {
    let fail = |reason: String| ReadbackError { tensor, reason };
    let data = burn::tensor::read_sync(B::int_into_data(t)).map_err(|e| fail(format!("{e:?}")))?;
    data.try_into_vec_as::<i64>()
        .map_err(|e| fail(e.to_string()))
}

/// Why the CPU implementations of our backend extensions may `expect` a read-back: their
/// tensors already live in host memory, so [`read_float_primitive`] cannot fail there.
const CPU_READ: &str = "CPU backend tensors are in host memory: reading them back cannot fail";

/// A CPU backend's tensor values lent to a host kernel without a copy where the backend allows
/// it: Flex keeps a contiguous tensor's values in one shared buffer, which a kernel can read in
/// place when the element type is the one it computes in. Everything else (ndarray, a strided
/// view, another dtype) is read back and converted, as [`cpu_float_as`] does.
///
/// The GoM op's corner table (`[F·9]` indices and weights: 47 MB per call at two subdivisions of
/// the full template while the indices were `i64`) was copied, and widened, on every call; lent,
/// it costs nothing.
pub trait HostLend: Backend {
    /// `t`'s values as `E` (`f32`, or `f64` in the precision tests), in row-major order. By
    /// default a copy; a backend that can lend overrides this.
    fn lend_float<'a, E: Element + Pod>(
        tensor: &'static str,
        t: &'a FloatTensor<Self>,
    ) -> Cow<'a, [E]> {
        copied_float::<Self, E>(tensor, t)
    }

    /// `t`'s values as `i32`, in row-major order. A value outside `i32` becomes `-1`: the host
    /// kernels index tables with these and treat a negative index as out of range. By default a
    /// copy; a backend that can lend overrides this.
    fn lend_int<'a>(tensor: &'static str, t: &'a IntTensor<Self>) -> Cow<'a, [i32]> {
        copied_int::<Self>(tensor, t)
    }
}

/// [`HostLend`]'s copy: read back and converted.
fn copied_float<'a, B: Backend, E: Element + Pod>(
    tensor: &'static str,
    t: &FloatTensor<B>,
) -> Cow<'a, [E]> {
    Cow::Owned(cpu_float_as::<B, E>(tensor, t.clone()))
}

/// [`HostLend`]'s copy of indices: read back and narrowed to `i32` (-1 outside).
fn copied_int<'a, B: Backend>(tensor: &'static str, t: &IntTensor<B>) -> Cow<'a, [i32]> {
    let values = cpu_int::<B>(tensor, t.clone());
    Cow::Owned(
        values
            .into_iter()
            .map(|v| i32::try_from(v).unwrap_or(-1))
            .collect(),
    )
}

/// Flex lends a contiguous buffer of the asked type and falls back to the copy otherwise.
impl HostLend for Flex {
    fn lend_float<'a, E: Element + Pod>(
        tensor: &'static str,
        t: &'a FloatTensor<Self>,
    ) -> Cow<'a, [E]> {
        t.as_slice::<E>()
            .map_or_else(|| copied_float::<Self, E>(tensor, t), Cow::Borrowed)
    }

    fn lend_int<'a>(tensor: &'static str, t: &'a IntTensor<Self>) -> Cow<'a, [i32]> {
        t.as_slice::<i32>()
            .map_or_else(|| copied_int::<Self>(tensor, t), Cow::Borrowed)
    }
}

// NdArray is deprecated in Burn 0.22 in favour of Flex; it stays the CI backend (design.md §1.4).
// Its tensors are copied (the default methods).
#[allow(deprecated)]
impl HostLend for burn::backend::NdArray {}

/// [`read_float_primitive`] for a CPU backend's op implementation, which cannot return errors.
pub(crate) fn cpu_float<B: Backend>(tensor: &'static str, t: FloatTensor<B>) -> Vec<f32> {
    read_float_primitive::<B>(tensor, t).expect(CPU_READ)
}

/// The values of a float primitive on a CPU backend as `E` (converted when it stores another
/// float), for op implementations that compute in the input's precision.
pub fn cpu_float_as<B: Backend, E: Element>(tensor: &'static str, t: FloatTensor<B>) -> Vec<E> {
    burn::tensor::read_sync(B::float_into_data(t))
        .map_err(|e| format!("{e:?}"))
        .and_then(|data| data.try_into_vec_as::<E>().map_err(|e| e.to_string()))
        .unwrap_or_else(|reason| panic!("{CPU_READ}; reading `{tensor}`: {reason}"))
}

/// Host values as a float primitive of `shape` in `dtype` on a CPU backend's `device`: the way
/// back of [`cpu_float_as`], for op implementations that compute in `f32` or `f64` and answer
/// in their inputs' float type (a cast only when the types differ).
pub fn cpu_float_from<B: Backend, E: Element>(
    values: Vec<E>,
    shape: impl Into<Shape>,
    dtype: DType,
    device: &B::Device,
) -> FloatTensor<B> {
    let t = B::float_from_data(TensorData::new(values, shape), device);
    if t.dtype() == dtype {
        t
    } else {
        B::float_cast(t, dtype.into())
    }
}

/// [`read_int_primitive`] for a CPU backend's op implementation, which cannot return errors.
pub(crate) fn cpu_int<B: Backend>(tensor: &'static str, t: IntTensor<B>) -> Vec<i64> {
    read_int_primitive::<B>(tensor, t).expect(CPU_READ)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, Int};

    /// A read from a CubeCL device is counted under its tensor's name, once per read; a read
    /// from a CPU backend is not (it is no sync). This is the only test of the crate that
    /// takes the process-wide counts, so other tests' reads only add other names.
    #[test]
    fn device_reads_are_counted_per_tensor() {
        let counted = "readback counting test";
        let values = [1.0f32, 2.0, 3.0];
        let host = Tensor::<1>::from_floats(values, &Device::flex());
        assert_eq!(read::<f32, 1, _>(counted, host).unwrap(), values);
        assert_eq!(
            take_device_reads().get(counted),
            None,
            "host reads are no syncs"
        );
        let Some(device) = crate::testing::wgpu_test_device() else {
            return;
        };
        for _ in 0..2 {
            let t = Tensor::<1>::from_floats(values, &device);
            assert_eq!(read::<f32, 1, _>(counted, t).unwrap(), values);
        }
        assert_eq!(take_device_reads().get(counted), Some(&2));
        assert_eq!(
            take_device_reads().get(counted),
            None,
            "taking resets the count"
        );
    }

    /// Flex lends a contiguous buffer of the asked type in place; a strided view, another
    /// float type and wide indices are read back instead, with the same values as ndarray's
    /// copies. An index outside `i32` reads as -1 (out of range for the host kernels).
    #[test]
    #[allow(deprecated)] // ndarray, the CI backend (design.md §1.4)
    fn flex_lends_in_place_and_falls_back_to_a_copy() {
        use burn::backend::NdArray;
        use burn::backend::ops::{FloatTensorOps, IntTensorOps};

        let flex = Default::default();
        let values: Vec<f32> = (0..6).map(|i| i as f32 - 2.5).collect();
        let t = Flex::float_from_data(TensorData::new(values.clone(), [2, 3]), &flex);
        let lent = Flex::lend_float::<f32>("t", &t);
        assert!(matches!(lent, Cow::Borrowed(_)), "contiguous f32 is lent");
        assert_eq!(lent.as_ptr(), t.bytes().as_ptr().cast::<f32>(), "in place");
        assert_eq!(&*lent, values.as_slice());

        let wide = Flex::lend_float::<f64>("t", &t);
        assert!(
            matches!(wide, Cow::Owned(_)),
            "another float type is converted"
        );
        assert_eq!(wide[5], 2.5);

        let swapped = Flex::float_swap_dims(t, 0, 1);
        let strided = Flex::lend_float::<f32>("swapped", &swapped);
        assert!(
            matches!(strided, Cow::Owned(_)),
            "a strided view is read back"
        );
        assert_eq!(&*strided, &[-2.5, 0.5, -1.5, 1.5, -0.5, 2.5]);

        let nd =
            NdArray::float_from_data(TensorData::new(values.clone(), [2, 3]), &Default::default());
        assert_eq!(&*NdArray::lend_float::<f32>("nd", &nd), values.as_slice());

        let narrow = Flex::int_from_data(TensorData::new(vec![4i32, -1, 7], [3]), &flex);
        assert!(matches!(
            Flex::lend_int("i32", &narrow),
            Cow::Borrowed([4, -1, 7])
        ));
        let wide = Flex::int_from_data(TensorData::new(vec![4i64, 1 << 40, 7], [3]), &flex);
        assert_eq!(&*Flex::lend_int("i64", &wide), &[4, -1, 7]);
    }

    #[test]
    fn reads_float_and_int_tensors_with_conversion() {
        let device = Device::flex();
        let f = Tensor::<1>::from_floats([0.5, -1.0], &device);
        assert_eq!(read::<f64, 1, _>("f", f).unwrap(), [0.5, -1.0]);
        let i = Tensor::<1, Int>::from_ints([3, -2], &device);
        assert_eq!(read::<i64, 1, _>("i", i).unwrap(), [3, -2]);
    }
}
