//! The Python values a pickle of "dicts of numpy arrays" can hold, and typed accessors on them.
//!
//! Arrays are decoded once, at load time, into C-order (row-major) element vectors of one of
//! three kinds (float, signed integer, bool), whatever the stored byte order, memory order or
//! width; [`NdArray::dtype`] still says what the file stored. Accessors convert on demand
//! (`to_f32`, `to_i64`) and refuse lossy conversions (a float array read as integers).

use std::fmt;

/// Element type of a numpy array as stored in the file (byte order is normalised away).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DType {
    /// `bool` (`|b1`).
    Bool,
    /// `int8`.
    I8,
    /// `uint8`.
    U8,
    /// `int16`.
    I16,
    /// `uint16`.
    U16,
    /// `int32`.
    I32,
    /// `uint32`.
    U32,
    /// `int64`.
    I64,
    /// `uint64` (values above `i64::MAX` are rejected when read).
    U64,
    /// `float16`.
    F16,
    /// `float32`.
    F32,
    /// `float64`.
    F64,
}

impl DType {
    /// Parses a numpy type string without byte-order prefix (`f4`, `i8`, `b1`, `u1`, ...).
    pub fn from_code(code: &str) -> Option<Self> {
        Some(match code {
            "b1" | "?" => Self::Bool,
            "i1" => Self::I8,
            "u1" => Self::U8,
            "i2" => Self::I16,
            "u2" => Self::U16,
            "i4" => Self::I32,
            "u4" => Self::U32,
            "i8" => Self::I64,
            "u8" => Self::U64,
            "f2" => Self::F16,
            "f4" => Self::F32,
            "f8" => Self::F64,
            _ => return None,
        })
    }

    /// The numpy type string without byte order (`f4`).
    pub fn code(self) -> &'static str {
        match self {
            Self::Bool => "b1",
            Self::I8 => "i1",
            Self::U8 => "u1",
            Self::I16 => "i2",
            Self::U16 => "u2",
            Self::I32 => "i4",
            Self::U32 => "u4",
            Self::I64 => "i8",
            Self::U64 => "u8",
            Self::F16 => "f2",
            Self::F32 => "f4",
            Self::F64 => "f8",
        }
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            Self::Bool | Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 | Self::F16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::I64 | Self::U64 | Self::F64 => 8,
        }
    }

    /// Whether byte order matters for this type.
    pub fn has_byte_order(self) -> bool {
        self.size() > 1
    }
}

/// Decoded array elements, C order.
#[derive(Debug, Clone, PartialEq)]
pub enum Elements {
    /// Any float dtype, widened to f64.
    Float(Vec<f64>),
    /// Any integer dtype, widened to i64.
    Int(Vec<i64>),
    /// `bool`.
    Bool(Vec<bool>),
}

impl Elements {
    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            Self::Float(v) => v.len(),
            Self::Int(v) => v.len(),
            Self::Bool(v) => v.len(),
        }
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A numpy array: the stored dtype, its shape, and its elements in C order.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    /// The dtype the file stored.
    pub dtype: DType,
    /// The shape (empty for a 0-d array or a numpy scalar).
    pub shape: Vec<usize>,
    /// The elements, C order; `elements.len()` is the product of `shape`.
    pub elements: Elements,
}

impl NdArray {
    /// A float64 array (shape is checked against the element count).
    pub fn from_f64(shape: Vec<usize>, values: Vec<f64>) -> Option<Self> {
        (shape.iter().product::<usize>() == values.len()).then_some(Self {
            dtype: DType::F64,
            shape,
            elements: Elements::Float(values),
        })
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.elements.len()
    }

    /// Whether the array has no elements.
    pub fn is_empty(&self) -> bool {
        self.elements.is_empty()
    }

    /// Elements as f64 (integers and bools convert exactly enough for data files).
    pub fn to_f64(&self) -> Vec<f64> {
        match &self.elements {
            Elements::Float(v) => v.clone(),
            Elements::Int(v) => v.iter().map(|&x| x as f64).collect(),
            Elements::Bool(v) => v.iter().map(|&x| f64::from(u8::from(x))).collect(),
        }
    }

    /// Elements as f32.
    pub fn to_f32(&self) -> Vec<f32> {
        self.to_f64().into_iter().map(|x| x as f32).collect()
    }

    /// Elements as i64; `None` for a float array (a float is never silently truncated).
    pub fn to_i64(&self) -> Option<Vec<i64>> {
        match &self.elements {
            Elements::Float(_) => None,
            Elements::Int(v) => Some(v.clone()),
            Elements::Bool(v) => Some(v.iter().map(|&x| i64::from(x)).collect()),
        }
    }
}

/// A decoded Python value.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// `None`.
    None,
    /// `bool`.
    Bool(bool),
    /// `int` (one that fits i64).
    Int(i64),
    /// `float`.
    Float(f64),
    /// `str`.
    Str(String),
    /// `bytes` or `bytearray`.
    Bytes(Vec<u8>),
    /// `list`.
    List(Vec<Value>),
    /// `tuple`.
    Tuple(Vec<Value>),
    /// `dict`, in insertion order (keys need not be strings).
    Dict(Vec<(Value, Value)>),
    /// A numpy array or numpy scalar (a scalar has an empty shape).
    Array(NdArray),
    /// A global reference that was never called (e.g. a class object stored as a value).
    Global {
        /// Module name.
        module: String,
        /// Attribute name.
        name: String,
    },
    /// A numpy dtype stored as a value.
    Dtype(DType),
    /// A PyTorch tensor of an archive, by reference to its storage (torch dialect only).
    Tensor(TensorRef),
}

/// Where a PyTorch tensor's elements are: the archive entry `data/<storage>`, read from element
/// `offset` with `shape` and `stride` (in elements, as `torch.Tensor.stride()`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorRef {
    /// Storage key: the archive entry's name under `data/`.
    pub storage: String,
    /// The storage class (`FloatStorage`, `HalfStorage`, ...).
    pub storage_type: String,
    /// First element, counted in elements of the storage.
    pub offset: usize,
    /// The tensor's shape.
    pub shape: Vec<usize>,
    /// Element strides per dimension.
    pub stride: Vec<usize>,
}

impl Value {
    /// A short type name for messages.
    pub fn type_name(&self) -> &'static str {
        match self {
            Self::None => "None",
            Self::Bool(_) => "bool",
            Self::Int(_) => "int",
            Self::Float(_) => "float",
            Self::Str(_) => "str",
            Self::Bytes(_) => "bytes",
            Self::List(_) => "list",
            Self::Tuple(_) => "tuple",
            Self::Dict(_) => "dict",
            Self::Array(_) => "numpy.ndarray",
            Self::Global { .. } => "global",
            Self::Dtype(_) => "numpy.dtype",
            Self::Tensor(_) => "torch.Tensor",
        }
    }

    /// Looks up a string key in a dict; `None` if this is not a dict or the key is absent.
    pub fn get(&self, key: &str) -> Option<&Value> {
        match self {
            Self::Dict(items) => items
                .iter()
                .find(|(k, _)| matches!(k, Value::Str(s) if s == key))
                .map(|(_, v)| v),
            _ => None,
        }
    }

    /// The dict's items, if this is a dict.
    pub fn as_dict(&self) -> Option<&[(Value, Value)]> {
        match self {
            Self::Dict(items) => Some(items),
            _ => None,
        }
    }

    /// The string, if this is a `str`.
    pub fn as_str(&self) -> Option<&str> {
        match self {
            Self::Str(s) => Some(s),
            _ => None,
        }
    }

    /// The array, if this is a numpy array or scalar.
    pub fn as_array(&self) -> Option<&NdArray> {
        match self {
            Self::Array(a) => Some(a),
            _ => None,
        }
    }

    /// Numeric content as an array: numpy arrays as they are, Python numbers as 0-d arrays, and
    /// (nested) lists/tuples of numbers as arrays of their nested shape. `None` otherwise.
    pub fn to_array(&self) -> Option<NdArray> {
        match self {
            Self::Array(a) => Some(a.clone()),
            Self::Int(i) => Some(NdArray {
                dtype: DType::I64,
                shape: vec![],
                elements: Elements::Int(vec![*i]),
            }),
            Self::Float(x) => NdArray::from_f64(vec![], vec![*x]),
            Self::List(items) | Self::Tuple(items) => {
                let parts: Vec<NdArray> =
                    items.iter().map(Value::to_array).collect::<Option<_>>()?;
                let inner = parts.first().map(|p| p.shape.clone()).unwrap_or_default();
                if parts.iter().any(|p| p.shape != inner) {
                    return None;
                }
                let mut shape = vec![parts.len()];
                shape.extend(inner);
                let values = parts.iter().flat_map(NdArray::to_f64).collect();
                NdArray::from_f64(shape, values)
            }
            _ => None,
        }
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.code())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dtype_codes_round_trip() {
        for d in [
            DType::Bool,
            DType::I8,
            DType::U8,
            DType::I16,
            DType::U16,
            DType::I32,
            DType::U32,
            DType::I64,
            DType::U64,
            DType::F16,
            DType::F32,
            DType::F64,
        ] {
            assert_eq!(DType::from_code(d.code()), Some(d));
        }
        assert_eq!(DType::from_code("O"), None);
    }

    #[test]
    fn nested_lists_become_arrays() {
        let v = Value::List(vec![
            Value::List(vec![Value::Int(1), Value::Float(2.5)]),
            Value::List(vec![Value::Int(3), Value::Int(4)]),
        ]);
        let a = v.to_array().unwrap();
        assert_eq!(a.shape, vec![2, 2]);
        assert_eq!(a.to_f64(), vec![1.0, 2.5, 3.0, 4.0]);
        let ragged = Value::List(vec![Value::List(vec![Value::Int(1)]), Value::Int(2)]);
        assert!(ragged.to_array().is_none());
        assert!(Value::Float(1.0).to_array().unwrap().to_i64().is_none());
    }
}
