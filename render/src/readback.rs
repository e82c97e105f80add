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
//!   CPU implementations of our backend extensions (rasterizer, visibility).
//!
//! ```
//! use burn::tensor::{Device, Tensor};
//! use lifegom_render::readback;
//! let t = Tensor::<2>::from_floats([[1.0, 2.0], [3.0, 4.0]], &Device::flex());
//! let values: Vec<f32> = readback::read("example", t)?;
//! assert_eq!(values, [1.0, 2.0, 3.0, 4.0]);
//! # Ok::<(), readback::ReadbackError>(())
//! ```

use burn::backend::Backend;
use burn::backend::TensorMetadata;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::tensor::kind::Basic;
use burn::tensor::{DType, Element, Shape, Tensor, TensorData};

/// A tensor whose values could not be brought to the host.
#[derive(Debug, thiserror::Error)]
#[error("reading tensor `{tensor}` back to the host failed: {reason}")]
pub struct ReadbackError {
    /// Which tensor (the caller's name for it).
    pub tensor: &'static str,
    /// Burn's account of the failure.
    pub reason: String,
}

/// The values of `t` (float, int or bool) in row-major order, converted to `E` when its dtype
/// differs.
pub fn read<E: Element, const D: usize, K: Basic>(
    tensor: &'static str,
    t: Tensor<D, K>,
) -> Result<Vec<E>, ReadbackError> {
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

    #[test]
    fn reads_float_and_int_tensors_with_conversion() {
        let device = Device::flex();
        let f = Tensor::<1>::from_floats([0.5, -1.0], &device);
        assert_eq!(read::<f64, 1, _>("f", f).unwrap(), [0.5, -1.0]);
        let i = Tensor::<1, Int>::from_ints([3, -2], &device);
        assert_eq!(read::<i64, 1, _>("i", i).unwrap(), [3, -2]);
    }
}
