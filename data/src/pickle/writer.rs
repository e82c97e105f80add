//! A pickle writer for the synthetic generator: [`Value`]s (dicts, lists, tuples, numbers,
//! strings, numpy arrays) to a protocol-4 pickle that Python's `pickle.load` turns back into the
//! same objects with real `numpy.ndarray`s.
//!
//! # Format choices
//!
//! * Protocol 4 without `FRAME` opcodes (framing is optional for readers) and without the memo
//!   (nothing is shared), which keeps the writer a straight recursive walk.
//! * Arrays use numpy's classic reduction, which numpy 1.x and 2.x both load:
//!   `numpy.core.multiarray._reconstruct(numpy.ndarray, (0,), b'b')` then `BUILD` with
//!   `(1, shape, dtype, False, raw_bytes)`; numpy 2 still resolves `numpy.core.multiarray` for
//!   unpickling. Dtypes are `numpy.dtype(code, False, True)` + `BUILD (3, order, None, None,
//!   None, -1, -1, 0)`, exactly numpy's own `dtype.__reduce__`. Data is little-endian, C order.
//! * An array is written in its stored [`DType`]; float elements written as an integer dtype (or
//!   the reverse) are an error rather than a silent conversion.

use super::value::{DType, Elements, NdArray, Value};

/// Serialises `value` as a protocol-4 pickle.
pub fn to_vec(value: &Value) -> Result<Vec<u8>, String> {
    let mut w = Writer { out: vec![0x80, 4] };
    w.value(value)?;
    w.out.push(b'.');
    Ok(w.out)
}

struct Writer {
    out: Vec<u8>,
}

impl Writer {
    fn value(&mut self, value: &Value) -> Result<(), String> {
        match value {
            Value::None => self.out.push(b'N'),
            Value::Bool(true) => self.out.push(0x88),
            Value::Bool(false) => self.out.push(0x89),
            Value::Int(v) => self.int(*v),
            Value::Float(v) => {
                self.out.push(b'G');
                self.out.extend(v.to_be_bytes());
            }
            Value::Str(s) => self.str(s),
            Value::Bytes(b) => self.bytes(b),
            Value::List(items) => {
                self.out.push(b']');
                if !items.is_empty() {
                    self.out.push(b'(');
                    for item in items {
                        self.value(item)?;
                    }
                    self.out.push(b'e');
                }
            }
            Value::Tuple(items) => {
                self.out.push(b'(');
                for item in items {
                    self.value(item)?;
                }
                self.out.push(b't');
            }
            Value::Dict(items) => {
                self.out.push(b'}');
                if !items.is_empty() {
                    self.out.push(b'(');
                    for (k, v) in items {
                        self.value(k)?;
                        self.value(v)?;
                    }
                    self.out.push(b'u');
                }
            }
            Value::Array(a) => self.array(a)?,
            Value::Dtype(d) => self.dtype(*d),
            Value::Global { module, name } => self.global(module, name),
            Value::Tensor(t) => {
                return Err(format!(
                    "a torch tensor (storage {}) cannot be written: only numpy arrays are",
                    t.storage
                ));
            }
        }
        Ok(())
    }

    fn int(&mut self, v: i64) {
        if let Ok(v) = i32::try_from(v) {
            self.out.push(b'J');
            self.out.extend(v.to_le_bytes());
        } else {
            self.out.extend([0x8a, 8]);
            self.out.extend(v.to_le_bytes());
        }
    }

    fn str(&mut self, s: &str) {
        self.out.push(b'X');
        self.out.extend((s.len() as u32).to_le_bytes());
        self.out.extend(s.as_bytes());
    }

    fn bytes(&mut self, b: &[u8]) {
        if let Ok(n) = u32::try_from(b.len()) {
            self.out.push(b'B');
            self.out.extend(n.to_le_bytes());
        } else {
            self.out.push(0x8e);
            self.out.extend((b.len() as u64).to_le_bytes());
        }
        self.out.extend(b);
    }

    fn global(&mut self, module: &str, name: &str) {
        self.out.push(b'c');
        self.out.extend(module.as_bytes());
        self.out.push(b'\n');
        self.out.extend(name.as_bytes());
        self.out.push(b'\n');
    }

    fn dtype(&mut self, d: DType) {
        self.global("numpy", "dtype");
        self.out.push(b'(');
        self.str(d.code());
        self.out.extend([0x89, 0x88, b't', b'R']);
        let order = if d.has_byte_order() { "<" } else { "|" };
        self.out.push(b'(');
        self.int(3);
        self.str(order);
        self.out.extend([b'N', b'N', b'N']);
        self.int(-1);
        self.int(-1);
        self.int(0);
        self.out.extend([b't', b'b']);
    }

    fn array(&mut self, a: &NdArray) -> Result<(), String> {
        let raw = encode(a)?;
        self.global("numpy.core.multiarray", "_reconstruct");
        self.out.push(b'(');
        self.global("numpy", "ndarray");
        self.out.push(b'(');
        self.int(0);
        self.out.push(b't');
        self.out.extend([b'C', 1, b'b']);
        self.out.extend([b't', b'R']);
        // State: (1, shape, dtype, is_fortran=False, raw).
        self.out.push(b'(');
        self.int(1);
        self.out.push(b'(');
        for &d in &a.shape {
            self.int(d as i64);
        }
        self.out.push(b't');
        self.dtype(a.dtype);
        self.out.push(0x89);
        self.bytes(&raw);
        self.out.extend([b't', b'b']);
        Ok(())
    }
}

/// The array's elements as little-endian bytes of its dtype.
fn encode(a: &NdArray) -> Result<Vec<u8>, String> {
    if a.shape.iter().product::<usize>() != a.len() {
        return Err(format!(
            "array of shape {:?} has {} elements",
            a.shape,
            a.len()
        ));
    }
    let mut out = Vec::with_capacity(a.len() * a.dtype.size());
    match (&a.elements, a.dtype) {
        (Elements::Float(v), DType::F32) => {
            v.iter().for_each(|&x| out.extend((x as f32).to_le_bytes()));
        }
        (Elements::Float(v), DType::F64) => v.iter().for_each(|&x| out.extend(x.to_le_bytes())),
        (Elements::Int(v), DType::I64) => v.iter().for_each(|&x| out.extend(x.to_le_bytes())),
        (Elements::Int(v), DType::I32) => {
            for &x in v {
                let x = i32::try_from(x).map_err(|_| format!("{x} does not fit int32"))?;
                out.extend(x.to_le_bytes());
            }
        }
        (Elements::Int(v), DType::U8) => {
            for &x in v {
                let x = u8::try_from(x).map_err(|_| format!("{x} does not fit uint8"))?;
                out.push(x);
            }
        }
        (Elements::Bool(v), DType::Bool) => v.iter().for_each(|&x| out.push(u8::from(x))),
        (_, d) => {
            return Err(format!(
                "writing {d} arrays from these elements is not supported (use f4, f8, i4, i8, u1 or b1)"
            ));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::super::reader::from_slice;
    use super::*;

    #[test]
    fn round_trip_through_the_reader() {
        let arrays = [
            NdArray {
                dtype: DType::F32,
                shape: vec![2, 3],
                elements: Elements::Float(vec![0.5, -1.0, 2.0, 3.25, 0.125, 7.0]),
            },
            NdArray {
                dtype: DType::F64,
                shape: vec![3],
                elements: Elements::Float(vec![1.0 / 3.0, -2.0, 1e300]),
            },
            NdArray {
                dtype: DType::I64,
                shape: vec![2, 2],
                elements: Elements::Int(vec![-1, i64::MAX, 0, 5]),
            },
            NdArray {
                dtype: DType::I32,
                shape: vec![1],
                elements: Elements::Int(vec![-7]),
            },
            NdArray {
                dtype: DType::U8,
                shape: vec![2],
                elements: Elements::Int(vec![0, 255]),
            },
            NdArray {
                dtype: DType::Bool,
                shape: vec![],
                elements: Elements::Bool(vec![true]),
            },
        ];
        let value = Value::Dict(vec![
            (
                Value::Str("arrays".into()),
                Value::List(arrays.iter().cloned().map(Value::Array).collect()),
            ),
            (Value::Str("big".into()), Value::Int(1 << 40)),
            (
                Value::Str("t".into()),
                Value::Tuple(vec![Value::Bool(false), Value::Float(2.5), Value::None]),
            ),
            (Value::Str("empty".into()), Value::Dict(vec![])),
        ]);
        let bytes = to_vec(&value).unwrap();
        assert_eq!(from_slice(&bytes).unwrap(), value);
    }

    #[test]
    fn refuses_lossy_writes() {
        let a = NdArray {
            dtype: DType::U8,
            shape: vec![1],
            elements: Elements::Int(vec![256]),
        };
        assert!(to_vec(&Value::Array(a)).is_err());
        let b = NdArray {
            dtype: DType::I64,
            shape: vec![1],
            elements: Elements::Float(vec![1.0]),
        };
        assert!(to_vec(&Value::Array(b)).is_err());
    }
}
