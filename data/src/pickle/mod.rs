//! Python pickles of numpy arrays, read and written natively (no Python at run time).
//!
//! * [`reader`]: a pickle VM for protocols 0–5 that rebuilds numpy arrays (numpy 1.x
//!   `numpy.core.*` and 2.x `numpy._core.*` module names) into [`Value`]s;
//! * [`writer`]: the inverse for the synthetic generator, readable by Python's `pickle.load`;
//! * [`value`]: the value model and typed accessors.

pub mod reader;
pub mod torch_zip;
pub mod value;
pub mod writer;

use std::path::Path;

pub use value::{DType, Elements, NdArray, TensorRef, Value};

use crate::error::{DataError, Location, Result};

/// Reads and parses the pickle at `path`; errors name the file (and the byte offset).
pub fn load(path: &Path) -> Result<Value> {
    let bytes =
        std::fs::read(path).map_err(|source| DataError::io(Location::file(path), source))?;
    reader::from_slice(&bytes).map_err(|e| DataError::Pickle {
        location: Box::new(Location::file(path)),
        offset: e.offset,
        reason: e.reason,
    })
}

/// Writes `value` as a pickle at `path`, atomically (a failed write leaves the old file whole).
pub fn save(path: &Path, value: &Value) -> Result<()> {
    let bytes =
        writer::to_vec(value).map_err(|reason| DataError::invalid(Location::file(path), reason))?;
    lifegom_render::atomic_file::write_atomic(path, &bytes)
        .map_err(|source| DataError::write(Location::file(path), source))
}
