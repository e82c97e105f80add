//! A small pickle virtual machine: enough of Python's unpickler to read dicts, lists and tuples
//! of numbers, strings and numpy arrays, as the official LIFe-GoM data files hold them.
//!
//! # Model
//!
//! The VM executes opcodes over a stack, as Python's `pickle.Unpickler` does, with one twist:
//! objects live in an *arena* and the stack and memo hold arena ids. Pickles memoize a container
//! *before* filling it (`EMPTY_DICT, MEMOIZE, MARK, ..., SETITEMS`), so the memo must alias the
//! object on the stack; ids make that aliasing explicit without reference counting. The root is
//! converted to an owned [`Value`] at `STOP` (with a depth limit, so a self-referencing list is
//! an error rather than a stack overflow).
//!
//! # What is supported
//!
//! Protocols 0–5 as far as data files need: all container, integer, float, string and bytes
//! opcodes of protocols 2–5, the memo (`PUT`/`GET` in all widths and `MEMOIZE`), `GLOBAL` and
//! `STACK_GLOBAL`, `REDUCE`, `NEWOBJ`, `BUILD`, `FRAME` (ignored: framing only helps buffered
//! reads), `READONLY_BUFFER` (a no-op for in-band data). Calls are *not* executed generically:
//! only a fixed table of globals is known (the private `Callable` enum) — the numpy reconstructors of numpy
//! 1.x (`numpy.core.*`) and 2.x (`numpy._core.*`), `numpy.dtype`, `_codecs.encode` (how protocol
//! 2 stores `bytes`), `collections.OrderedDict`, `builtins.bytearray/set/frozenset`. Any other
//! global is an error naming it. Out-of-band buffers (`NEXT_BUFFER`) are an error: a file cannot
//! carry them.
//!
//! # PyTorch archives ([`Dialect::Torch`])
//!
//! The `data.pkl` of a `torch.save` zip or a TorchScript archive refers to its tensors' bytes by
//! *persistent id* (`BINPERSID`): `('storage', torch.FloatStorage, key, location, numel)`, where
//! `key` names the archive entry `data/<key>`. In the torch dialect the VM also knows
//! `torch._utils._rebuild_tensor_v2` and `_rebuild_parameter`, which become
//! [`Value::Tensor`] references (storage key, type, offset, shape, stride; the bytes stay in the
//! archive, [`super::torch_zip`] reads them), and TorchScript's module classes (`__torch__.*`),
//! which become dicts of their attributes (TorchScript's typed-list wrappers,
//! `torch.jit._pickle.build_intlist` and its kin, are their argument). Nothing is executed: a TorchScript archive's code is
//! never run, only its attribute tree is read.
//!
//! # numpy arrays
//!
//! numpy pickles an array in one of two ways:
//!
//! * `_reconstruct(ndarray, (0,), b'b')` then `BUILD` with the state tuple
//!   `(version, shape, dtype, is_fortran, raw_bytes)` (protocols ≤ 4);
//! * `_frombuffer(buffer, dtype, shape, order)` with an in-band `PickleBuffer` (protocol 5).
//!
//! Dtypes are `numpy.dtype(code, align, copy)` followed by `BUILD` with
//! `(version, byteorder, subarray, names, fields, elsize, alignment, flags)`; the byte order
//! (`<`, `>`, `|`, `=`) comes from the state. Raw bytes are decoded by dtype and byte order and,
//! for Fortran order, permuted into C order. Structured and object dtypes are rejected.
//!
//! # Robustness
//!
//! Every length read from the stream is checked against the bytes left before anything is
//! allocated, so a truncated or hostile file fails with the byte offset of the opcode, never a
//! panic or a huge allocation. Converting to owned [`Value`]s copies a memoized object once per
//! reference, so that copying is bounded by the file's length (`expansion_budget`): a short file
//! of nested shared references is an error, not an endless conversion.

use std::collections::HashMap;

use super::value::{DType, Elements, NdArray, TensorRef, Value};

/// Deepest nesting converted to a [`Value`]; deeper (or cyclic) structures are an error.
pub const MAX_DEPTH: usize = 256;

/// How much a pickle of `len` bytes may expand to when converted to a [`Value`], in units of
/// one value or one payload element (character, byte, array element). Without shared
/// references every unit needs at least one byte of the file; a memo `GET` is two bytes that
/// copy a whole object, so `a = [x, x]; b = [a, a]; ...` doubles per level and a few hundred
/// bytes would describe more values than memory holds (an endless conversion, not a cycle the
/// depth limit sees). Sixteen copies of everything leave room for real sharing (dtypes, keys).
fn expansion_budget(len: usize) -> usize {
    len.saturating_mul(16).saturating_add(1 << 20)
}

/// A pickle failure: the byte offset of the opcode at fault and the reason.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PickleError {
    /// Offset of the opcode that failed (or of the end of the stream).
    pub offset: usize,
    /// What went wrong.
    pub reason: String,
}

impl std::fmt::Display for PickleError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "byte {}: {}", self.offset, self.reason)
    }
}

impl std::error::Error for PickleError {}

/// Parses one pickle from `bytes` (trailing bytes after `STOP` are ignored, as Python does).
pub fn from_slice(bytes: &[u8]) -> Result<Value, PickleError> {
    from_slice_in(bytes, Dialect::Data)
}

/// Parses one pickle of the given [`Dialect`].
pub fn from_slice_in(bytes: &[u8], dialect: Dialect) -> Result<Value, PickleError> {
    Vm::new(bytes, dialect).run()
}

/// Which globals a pickle may use beyond plain containers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dialect {
    /// Data files: numpy arrays and the builtins of the module docs; anything else is an error.
    Data,
    /// The `data.pkl` of a PyTorch archive: also persistent storage ids, tensor rebuilds and
    /// TorchScript module objects (module docs).
    Torch,
}

/// The globals the VM can call or keep as values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Callable {
    /// `numpy[._]core.multiarray._reconstruct`.
    Reconstruct,
    /// `numpy[._]core.numeric._frombuffer`.
    FromBuffer,
    /// `numpy[._]core.multiarray.scalar`.
    Scalar,
    /// `numpy.dtype`.
    Dtype,
    /// `numpy.ndarray` (only as the first argument of `_reconstruct`).
    NdarrayClass,
    /// `_codecs.encode`.
    CodecsEncode,
    /// `collections.OrderedDict`.
    OrderedDict,
    /// `builtins.bytearray` / `bytes` (protocol 2 writes `b""` as `__builtin__.bytes()`).
    ByteArray,
    /// `builtins.set`, `builtins.frozenset` (read as lists).
    Set,
    /// `torch._utils._rebuild_tensor_v2` (torch dialect).
    RebuildTensor,
    /// `torch._utils._rebuild_parameter`: a parameter is its tensor (torch dialect).
    RebuildParameter,
    /// A TorchScript module class `__torch__.*`, built from its attribute dict (torch dialect).
    TorchModule,
    /// TorchScript's typed-container wrappers (`torch.jit._pickle.build_intlist`,
    /// `restore_type_tag`, ...): the value is their first argument (torch dialect).
    FirstArgument,
}

impl Callable {
    fn lookup(module: &str, name: &str, dialect: Dialect) -> Option<Self> {
        if dialect == Dialect::Torch {
            match (module, name) {
                ("torch._utils", "_rebuild_tensor_v2") => return Some(Self::RebuildTensor),
                ("torch._utils", "_rebuild_parameter") => return Some(Self::RebuildParameter),
                (
                    "torch.jit._pickle",
                    "build_intlist" | "build_doublelist" | "build_boollist" | "build_tensorlist"
                    | "build_list" | "restore_type_tag",
                ) => return Some(Self::FirstArgument),
                (m, _) if m == "__torch__" || m.starts_with("__torch__.") => {
                    return Some(Self::TorchModule);
                }
                _ => {}
            }
        }
        let numpy_core = matches!(
            module,
            "numpy.core.multiarray" | "numpy._core.multiarray" | "numpy.core" | "numpy._core"
        );
        Some(match (module, name) {
            (_, "_reconstruct") if numpy_core => Self::Reconstruct,
            (_, "scalar") if numpy_core => Self::Scalar,
            ("numpy.core.numeric" | "numpy._core.numeric", "_frombuffer") => Self::FromBuffer,
            ("numpy", "dtype") => Self::Dtype,
            ("numpy", "ndarray") => Self::NdarrayClass,
            (_, "dtype") if numpy_core => Self::Dtype,
            (_, "ndarray") if numpy_core => Self::NdarrayClass,
            ("_codecs", "encode") => Self::CodecsEncode,
            ("collections", "OrderedDict") => Self::OrderedDict,
            ("builtins" | "__builtin__", "bytearray" | "bytes") => Self::ByteArray,
            ("builtins" | "__builtin__", "set" | "frozenset") => Self::Set,
            _ => return None,
        })
    }
}

/// An object in the arena.
#[derive(Debug, Clone)]
enum Obj {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    List(Vec<usize>),
    Tuple(Vec<usize>),
    Dict(Vec<(usize, usize)>),
    Global {
        module: String,
        name: String,
        callable: Option<Callable>,
    },
    /// A dtype before or after its `BUILD`: the type and the byte order (`<`, `>`, `|`, `=`).
    Dtype {
        dtype: DType,
        order: u8,
    },
    /// `_reconstruct`'s empty array, waiting for `BUILD`.
    EmptyArray,
    Array(NdArray),
    /// A persistent storage id of a PyTorch archive (torch dialect).
    Storage {
        key: String,
        storage_type: String,
    },
    Tensor(TensorRef),
}

struct Vm<'a> {
    bytes: &'a [u8],
    pos: usize,
    /// Offset of the opcode being executed (for errors).
    op_start: usize,
    arena: Vec<Obj>,
    stack: Vec<usize>,
    /// Stack heights at each `MARK` (Python's metastack).
    marks: Vec<usize>,
    memo: HashMap<u64, usize>,
    dialect: Dialect,
}

type R<T> = Result<T, PickleError>;

impl<'a> Vm<'a> {
    fn new(bytes: &'a [u8], dialect: Dialect) -> Self {
        Self {
            bytes,
            pos: 0,
            op_start: 0,
            arena: Vec::new(),
            stack: Vec::new(),
            marks: Vec::new(),
            memo: HashMap::new(),
            dialect,
        }
    }

    fn err<T>(&self, reason: impl Into<String>) -> R<T> {
        Err(PickleError {
            offset: self.op_start,
            reason: reason.into(),
        })
    }

    fn take(&mut self, n: usize) -> R<&'a [u8]> {
        let left = self.bytes.len() - self.pos;
        if n > left {
            return self.err(format!(
                "truncated: opcode needs {n} more bytes, {left} left"
            ));
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn u8(&mut self) -> R<u8> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> R<u16> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32(&mut self) -> R<u32> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&mut self) -> R<u64> {
        let b = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(u64::from_le_bytes(a))
    }

    /// A length-prefixed byte run with a length of `width` bytes.
    fn sized(&mut self, width: usize) -> R<&'a [u8]> {
        let n = match width {
            1 => self.u8()? as u64,
            4 => self.u32()? as u64,
            _ => self.u64()?,
        };
        let n = usize::try_from(n).or_else(|_| self.err("length does not fit in memory"))?;
        self.take(n)
    }

    /// A `\n`-terminated line (protocol 0 arguments), without the newline.
    fn line(&mut self) -> R<&'a str> {
        let rest = &self.bytes[self.pos..];
        let Some(end) = rest.iter().position(|&b| b == b'\n') else {
            return self.err("truncated: unterminated text argument");
        };
        self.pos += end + 1;
        std::str::from_utf8(&rest[..end]).or_else(|_| self.err("text argument is not UTF-8"))
    }

    fn push(&mut self, obj: Obj) {
        self.arena.push(obj);
        self.stack.push(self.arena.len() - 1);
    }

    fn pop(&mut self) -> R<usize> {
        let floor = self.marks.last().copied().unwrap_or(0);
        if self.stack.len() <= floor {
            return self.err("stack underflow");
        }
        Ok(self.stack.pop().unwrap_or_default())
    }

    fn top(&self) -> R<usize> {
        match self.stack.last() {
            Some(&id) => Ok(id),
            None => self.err("stack underflow"),
        }
    }

    /// Pops everything above the last `MARK`, and the mark.
    fn pop_mark(&mut self) -> R<Vec<usize>> {
        let Some(mark) = self.marks.pop() else {
            return self.err("no MARK on the stack");
        };
        Ok(self.stack.split_off(mark.min(self.stack.len())))
    }

    fn memo_put(&mut self, key: u64) -> R<()> {
        let id = self.top()?;
        self.memo.insert(key, id);
        Ok(())
    }

    fn memo_get(&mut self, key: u64) -> R<()> {
        match self.memo.get(&key) {
            Some(&id) => {
                self.stack.push(id);
                Ok(())
            }
            None => self.err(format!("memo key {key} was never stored")),
        }
    }

    fn run(mut self) -> R<Value> {
        loop {
            self.op_start = self.pos;
            let Some(&op) = self.bytes.get(self.pos) else {
                return self.err("truncated: no STOP opcode");
            };
            self.pos += 1;
            match op {
                0x80 => {
                    let proto = self.u8()?;
                    if proto > 5 {
                        return self.err(format!("unsupported pickle protocol {proto}"));
                    }
                }
                0x95 => {
                    self.u64()?; // FRAME: a size hint only
                }
                b'.' => {
                    let root = self.pop()?;
                    let budget = std::cell::Cell::new(expansion_budget(self.bytes.len()));
                    return self.to_value(root, 0, &budget);
                }
                b'(' => self.marks.push(self.stack.len()),
                b'}' => self.push(Obj::Dict(Vec::new())),
                b']' => self.push(Obj::List(Vec::new())),
                b')' => self.push(Obj::Tuple(Vec::new())),
                0x8f => self.push(Obj::List(Vec::new())), // EMPTY_SET
                b't' => {
                    let items = self.pop_mark()?;
                    self.push(Obj::Tuple(items));
                }
                0x91 => {
                    let items = self.pop_mark()?; // FROZENSET
                    self.push(Obj::List(items));
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    let mut items = Vec::with_capacity(n);
                    for _ in 0..n {
                        items.push(self.pop()?);
                    }
                    items.reverse();
                    self.push(Obj::Tuple(items));
                }
                b's' => {
                    let value = self.pop()?;
                    let key = self.pop()?;
                    self.set_items(&[key, value])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return self.err("SETITEMS with an odd number of items");
                    }
                    self.set_items(&items)?;
                }
                b'a' => {
                    let item = self.pop()?;
                    self.append(&[item])?;
                }
                b'e' | 0x90 => {
                    let items = self.pop_mark()?; // APPENDS, ADDITEMS
                    self.append(&items)?;
                }
                b'J' => {
                    let v = self.u32()? as i32;
                    self.push(Obj::Int(v as i64));
                }
                b'K' => {
                    let v = self.u8()?;
                    self.push(Obj::Int(v as i64));
                }
                b'M' => {
                    let v = self.u16()?;
                    self.push(Obj::Int(v as i64));
                }
                0x8a | 0x8b => {
                    let width = if op == 0x8a { 1 } else { 4 };
                    let raw = self.sized(width)?;
                    let v = self.long(raw)?;
                    self.push(Obj::Int(v));
                }
                b'I' => {
                    let line = self.line()?;
                    let obj = match line {
                        "00" => Obj::Bool(false),
                        "01" => Obj::Bool(true),
                        s => match s.parse::<i64>() {
                            Ok(v) => Obj::Int(v),
                            Err(_) => return self.err(format!("bad INT argument `{s}`")),
                        },
                    };
                    self.push(obj);
                }
                b'L' => {
                    let line = self.line()?;
                    match line.trim_end_matches('L').parse::<i64>() {
                        Ok(v) => self.push(Obj::Int(v)),
                        Err(_) => return self.err(format!("bad LONG argument `{line}`")),
                    }
                }
                b'G' => {
                    let b = self.take(8)?;
                    let mut a = [0u8; 8];
                    a.copy_from_slice(b);
                    self.push(Obj::Float(f64::from_be_bytes(a)));
                }
                b'F' => {
                    let line = self.line()?;
                    match line.parse::<f64>() {
                        Ok(v) => self.push(Obj::Float(v)),
                        Err(_) => return self.err(format!("bad FLOAT argument `{line}`")),
                    }
                }
                0x8c | b'X' | 0x8d => {
                    let width = match op {
                        0x8c => 1,
                        b'X' => 4,
                        _ => 8,
                    };
                    let raw = self.sized(width)?;
                    match std::str::from_utf8(raw) {
                        Ok(s) => self.push(Obj::Str(s.to_owned())),
                        Err(_) => return self.err("string is not valid UTF-8"),
                    }
                }
                b'C' | b'B' | 0x8e | 0x96 | b'U' | b'T' => {
                    // SHORT_BINBYTES, BINBYTES, BINBYTES8, BYTEARRAY8, and Python 2's
                    // SHORT_BINSTRING / BINSTRING (raw bytes too).
                    let width = match op {
                        b'C' | b'U' => 1,
                        b'B' | b'T' => 4,
                        _ => 8,
                    };
                    let raw = self.sized(width)?;
                    self.push(Obj::Bytes(raw.to_vec()));
                }
                b'N' => self.push(Obj::None),
                0x88 => self.push(Obj::Bool(true)),
                0x89 => self.push(Obj::Bool(false)),
                b'c' => {
                    let module = self.line()?.to_owned();
                    let name = self.line()?.to_owned();
                    self.push_global(module, name);
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    match (&self.arena[module], &self.arena[name]) {
                        (Obj::Str(m), Obj::Str(n)) => {
                            let (m, n) = (m.clone(), n.clone());
                            self.push_global(m, n);
                        }
                        _ => return self.err("STACK_GLOBAL needs two strings"),
                    }
                }
                b'R' => {
                    let args = self.pop()?;
                    let func = self.pop()?;
                    let result = self.call(func, args)?;
                    self.push(result);
                }
                0x81 => {
                    let args = self.pop()?;
                    let cls = self.pop()?;
                    let result = self.call(cls, args)?;
                    self.push(result);
                }
                b'b' => {
                    let state = self.pop()?;
                    let target = self.top()?;
                    self.build(target, state)?;
                }
                0x94 => {
                    let key = self.memo.len() as u64;
                    self.memo_put(key)?;
                }
                b'p' => {
                    let line = self.line()?;
                    let Ok(key) = line.parse::<u64>() else {
                        return self.err(format!("bad PUT argument `{line}`"));
                    };
                    self.memo_put(key)?;
                }
                b'q' => {
                    let key = self.u8()? as u64;
                    self.memo_put(key)?;
                }
                b'r' => {
                    let key = self.u32()? as u64;
                    self.memo_put(key)?;
                }
                b'g' => {
                    let line = self.line()?;
                    let Ok(key) = line.parse::<u64>() else {
                        return self.err(format!("bad GET argument `{line}`"));
                    };
                    self.memo_get(key)?;
                }
                b'h' => {
                    let key = self.u8()? as u64;
                    self.memo_get(key)?;
                }
                b'j' => {
                    let key = self.u32()? as u64;
                    self.memo_get(key)?;
                }
                b'0' => {
                    self.pop()?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let id = self.top()?;
                    self.stack.push(id);
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let storage = self.persistent_load(pid)?;
                    self.push(storage);
                }
                b'P' => {
                    return self
                        .err("PERSID: text persistent ids are not used by PyTorch archives");
                }
                0x98 => {} // READONLY_BUFFER: in-band data is already bytes
                0x97 => {
                    return self.err("NEXT_BUFFER: out-of-band buffers cannot be read from a file");
                }
                other => {
                    return self.err(format!(
                        "unsupported opcode 0x{other:02x} ({:?})",
                        other as char
                    ));
                }
            }
        }
    }

    /// Two's complement little-endian integer of LONG1/LONG4.
    fn long(&self, raw: &[u8]) -> R<i64> {
        if raw.is_empty() {
            return Ok(0);
        }
        if raw.len() > 8 {
            // Only sign-extension bytes may follow the low 8 bytes.
            let fill = if raw[7] & 0x80 != 0 { 0xff } else { 0 };
            if raw[8..].iter().any(|&b| b != fill) {
                return self.err("integer does not fit in 64 bits");
            }
        }
        let fill = if raw[raw.len() - 1] & 0x80 != 0 {
            0xff
        } else {
            0
        };
        let mut a = [fill; 8];
        let n = raw.len().min(8);
        a[..n].copy_from_slice(&raw[..n]);
        Ok(i64::from_le_bytes(a))
    }

    fn push_global(&mut self, module: String, name: String) {
        let callable = Callable::lookup(&module, &name, self.dialect);
        self.push(Obj::Global {
            module,
            name,
            callable,
        });
    }

    fn set_items(&mut self, items: &[usize]) -> R<()> {
        let target = self.top()?;
        match &mut self.arena[target] {
            Obj::Dict(entries) => {
                entries.extend(items.chunks_exact(2).map(|kv| (kv[0], kv[1])));
                Ok(())
            }
            _ => self.err("SETITEM(S) on a non-dict"),
        }
    }

    fn append(&mut self, items: &[usize]) -> R<()> {
        let target = self.top()?;
        match &mut self.arena[target] {
            Obj::List(list) => {
                list.extend_from_slice(items);
                Ok(())
            }
            _ => self.err("APPEND(S) on a non-list"),
        }
    }

    fn tuple_items(&self, id: usize, what: &str) -> R<Vec<usize>> {
        match &self.arena[id] {
            Obj::Tuple(items) => Ok(items.clone()),
            _ => self.err(format!("{what}: expected a tuple")),
        }
    }

    fn int(&self, id: usize, what: &str) -> R<i64> {
        match self.arena[id] {
            Obj::Int(v) => Ok(v),
            Obj::Bool(b) => Ok(i64::from(b)),
            _ => self.err(format!("{what}: expected an int")),
        }
    }

    fn shape(&self, id: usize, what: &str) -> R<Vec<usize>> {
        let items = match &self.arena[id] {
            Obj::Tuple(items) | Obj::List(items) => items.clone(),
            Obj::Int(_) => vec![id],
            _ => return self.err(format!("{what}: expected a shape tuple")),
        };
        items
            .iter()
            .map(|&i| {
                let v = self.int(i, what)?;
                usize::try_from(v).or_else(|_| self.err(format!("{what}: negative dimension {v}")))
            })
            .collect()
    }

    fn dtype(&self, id: usize, what: &str) -> R<(DType, u8)> {
        match self.arena[id] {
            Obj::Dtype { dtype, order } => Ok((dtype, order)),
            _ => self.err(format!("{what}: expected a numpy dtype")),
        }
    }

    /// Executes `func(*args)` for the known globals (module docs).
    fn call(&mut self, func: usize, args: usize) -> R<Obj> {
        let (module, name, callable) = match &self.arena[func] {
            Obj::Global {
                module,
                name,
                callable,
            } => (module.clone(), name.clone(), *callable),
            _ => return self.err("REDUCE/NEWOBJ on something that is not a global"),
        };
        let Some(callable) = callable else {
            return self.err(format!(
                "unknown global `{module}.{name}`: this reader only understands dicts, lists and numpy arrays"
            ));
        };
        let args = self.tuple_items(args, &format!("arguments of {module}.{name}"))?;
        match callable {
            Callable::Reconstruct => Ok(Obj::EmptyArray),
            Callable::Dtype => {
                let Some(&code) = args.first() else {
                    return self.err("numpy.dtype() without a type code");
                };
                let Obj::Str(code) = &self.arena[code] else {
                    return self.err("numpy.dtype(): type code is not a string");
                };
                // The code may carry a byte order itself ('<f4'); BUILD usually sets it later.
                let (order, bare) = match code.as_bytes().first() {
                    Some(c @ (b'<' | b'>' | b'|' | b'=')) => (*c, &code[1..]),
                    _ => (b'=', code.as_str()),
                };
                match DType::from_code(bare) {
                    Some(dtype) => Ok(Obj::Dtype { dtype, order }),
                    None => self.err(format!(
                        "unsupported numpy dtype `{code}` (only bool, int, uint and float are read)"
                    )),
                }
            }
            Callable::Scalar => {
                if args.len() != 2 {
                    return self.err("numpy scalar(): expected (dtype, bytes)");
                }
                let (dtype, order) = self.dtype(args[0], "numpy scalar dtype")?;
                let Obj::Bytes(raw) = &self.arena[args[1]] else {
                    return self.err("numpy scalar(): data is not bytes");
                };
                let elements = self.decode(raw, dtype, order, &[], false)?;
                Ok(Obj::Array(NdArray {
                    dtype,
                    shape: vec![],
                    elements,
                }))
            }
            Callable::FromBuffer => {
                if args.len() != 4 {
                    return self.err("numpy _frombuffer(): expected (buffer, dtype, shape, order)");
                }
                let (dtype, order) = self.dtype(args[1], "_frombuffer dtype")?;
                let shape = self.shape(args[2], "_frombuffer shape")?;
                let fortran = match &self.arena[args[3]] {
                    Obj::Str(s) if s == "F" => true,
                    Obj::Str(s) if s == "C" => false,
                    _ => return self.err("_frombuffer order is not 'C' or 'F'"),
                };
                let Obj::Bytes(raw) = &self.arena[args[0]] else {
                    return self.err("_frombuffer(): buffer is not bytes");
                };
                let elements = self.decode(raw, dtype, order, &shape, fortran)?;
                Ok(Obj::Array(NdArray {
                    dtype,
                    shape,
                    elements,
                }))
            }
            Callable::CodecsEncode => {
                let text = match args.first().map(|&a| &self.arena[a]) {
                    Some(Obj::Str(s)) => s.clone(),
                    _ => return self.err("_codecs.encode(): first argument is not a string"),
                };
                // Protocol 2 stores bytes as their latin-1 decoding: every char is one byte.
                let bytes: Option<Vec<u8>> =
                    text.chars().map(|c| u8::try_from(c as u32).ok()).collect();
                match bytes {
                    Some(b) => Ok(Obj::Bytes(b)),
                    None => self.err("_codecs.encode(): character outside latin-1"),
                }
            }
            Callable::OrderedDict => Ok(Obj::Dict(Vec::new())),
            Callable::ByteArray => match args.first().map(|&a| &self.arena[a]) {
                None => Ok(Obj::Bytes(Vec::new())),
                Some(Obj::Bytes(b)) => Ok(Obj::Bytes(b.clone())),
                Some(Obj::Str(s)) => {
                    let bytes: Option<Vec<u8>> =
                        s.chars().map(|c| u8::try_from(c as u32).ok()).collect();
                    bytes.map_or_else(
                        || self.err("bytearray(): not latin-1"),
                        |b| Ok(Obj::Bytes(b)),
                    )
                }
                Some(_) => self.err("bytearray(): unsupported argument"),
            },
            Callable::Set => match args.first() {
                None => Ok(Obj::List(Vec::new())),
                Some(&a) => match &self.arena[a] {
                    Obj::List(items) | Obj::Tuple(items) => Ok(Obj::List(items.clone())),
                    _ => self.err("set(): argument is not a list"),
                },
            },
            Callable::NdarrayClass => {
                self.err("numpy.ndarray called directly (only _reconstruct is supported)")
            }
            Callable::RebuildTensor => self.rebuild_tensor(&args),
            Callable::RebuildParameter => match args.first().map(|&a| &self.arena[a]) {
                Some(Obj::Tensor(t)) => Ok(Obj::Tensor(t.clone())),
                _ => self.err("_rebuild_parameter(): first argument is not a tensor"),
            },
            Callable::TorchModule => Ok(Obj::Dict(Vec::new())),
            Callable::FirstArgument => match args.first() {
                Some(&a) => Ok(self.arena[a].clone()),
                None => self.err(format!("{module}.{name}() without an argument")),
            },
        }
    }

    /// `BINPERSID` in the torch dialect: `('storage', storage_type, key, location, numel)`.
    fn persistent_load(&mut self, pid: usize) -> R<Obj> {
        if self.dialect != Dialect::Torch {
            return self.err("persistent id (BINPERSID) outside a PyTorch archive");
        }
        let items = self.tuple_items(pid, "persistent id")?;
        let text = |vm: &Self, i: usize| match items.get(i).map(|&a| &vm.arena[a]) {
            Some(Obj::Str(s)) => Some(s.clone()),
            _ => None,
        };
        if text(self, 0).as_deref() != Some("storage") || items.len() < 3 {
            return self.err("persistent id is not ('storage', type, key, ...)");
        }
        let storage_type = match items.get(1).map(|&a| &self.arena[a]) {
            Some(Obj::Global { name, .. }) => name.clone(),
            _ => return self.err("persistent id: storage type is not a global"),
        };
        let Some(key) = text(self, 2) else {
            return self.err("persistent id: storage key is not a string");
        };
        Ok(Obj::Storage { key, storage_type })
    }

    /// `_rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks[, metadata])`.
    fn rebuild_tensor(&self, args: &[usize]) -> R<Obj> {
        if args.len() < 4 {
            return self.err("_rebuild_tensor_v2(): expected (storage, offset, size, stride, ...)");
        }
        let Obj::Storage { key, storage_type } = &self.arena[args[0]] else {
            return self.err("_rebuild_tensor_v2(): first argument is not a storage");
        };
        let offset = self.int(args[1], "tensor storage offset")?;
        let offset = usize::try_from(offset)
            .or_else(|_| self.err(format!("negative tensor storage offset {offset}")))?;
        let shape = self.shape(args[2], "tensor size")?;
        let stride = self.shape(args[3], "tensor stride")?;
        if stride.len() != shape.len() {
            return self.err(format!(
                "tensor size {shape:?} and stride {stride:?} differ in rank"
            ));
        }
        Ok(Obj::Tensor(TensorRef {
            storage: key.clone(),
            storage_type: storage_type.clone(),
            offset,
            shape,
            stride,
        }))
    }

    /// `BUILD`: sets the state of a dtype or of `_reconstruct`'s empty array.
    fn build(&mut self, target: usize, state: usize) -> R<()> {
        match self.arena[target].clone() {
            Obj::Dtype { dtype, .. } => {
                let items = self.tuple_items(state, "dtype state")?;
                let order = match items.get(1).map(|&i| &self.arena[i]) {
                    Some(Obj::Str(s)) if s.len() == 1 => s.as_bytes()[0],
                    _ => return self.err("dtype state: byte order is not a 1-char string"),
                };
                if let Some(&names) = items.get(3)
                    && !matches!(self.arena[names], Obj::None)
                {
                    return self.err("structured numpy dtypes are not supported");
                }
                self.arena[target] = Obj::Dtype { dtype, order };
                Ok(())
            }
            Obj::EmptyArray => {
                let items = self.tuple_items(state, "ndarray state")?;
                if items.len() != 5 {
                    return self.err(format!(
                        "ndarray state: expected (version, shape, dtype, fortran, data), got {} items",
                        items.len()
                    ));
                }
                let shape = self.shape(items[1], "ndarray shape")?;
                let (dtype, order) = self.dtype(items[2], "ndarray dtype")?;
                let fortran = self.int(items[3], "ndarray fortran flag")? != 0;
                let elements = match &self.arena[items[4]] {
                    Obj::Bytes(raw) => self.decode(raw, dtype, order, &shape, fortran)?,
                    _ => {
                        return self
                            .err("ndarray data is not bytes (object arrays are not supported)");
                    }
                };
                self.arena[target] = Obj::Array(NdArray {
                    dtype,
                    shape,
                    elements,
                });
                Ok(())
            }
            Obj::Dict(_) => {
                // BUILD on a plain object with a dict state: merge it (harmless for OrderedDict).
                let entries = match &self.arena[state] {
                    Obj::Dict(e) => e.clone(),
                    _ => return self.err("BUILD on a dict with a non-dict state"),
                };
                if let Obj::Dict(target) = &mut self.arena[target] {
                    target.extend(entries);
                }
                Ok(())
            }
            other => self.err(format!(
                "BUILD on an unsupported object ({})",
                obj_name(&other)
            )),
        }
    }

    /// Decodes raw array bytes into C-order elements ([`decode_array`]).
    fn decode(
        &self,
        raw: &[u8],
        dtype: DType,
        order: u8,
        shape: &[usize],
        fortran: bool,
    ) -> R<Elements> {
        decode_array(raw, dtype, order, shape, fortran).or_else(|reason| self.err(reason))
    }

    /// The owned value of `id`. Each value takes one unit from `budget`, plus one per payload
    /// element (character, byte, array element), so a shared object copied out many times is
    /// paid for each time ([`expansion_budget`]).
    fn to_value(&self, id: usize, depth: usize, budget: &std::cell::Cell<usize>) -> R<Value> {
        if depth > MAX_DEPTH {
            return self.err(format!(
                "structure nested deeper than {MAX_DEPTH} levels (or self-referencing)"
            ));
        }
        let cost = 1 + match &self.arena[id] {
            Obj::Str(s) => s.len(),
            Obj::Bytes(b) => b.len(),
            Obj::Array(a) => a.elements.len(),
            _ => 0,
        };
        match budget.get().checked_sub(cost) {
            Some(left) => budget.set(left),
            None => {
                return self.err(
                    "shared references (memo GETs) expand to far more values than the file holds",
                );
            }
        }
        let list = |items: &[usize]| -> R<Vec<Value>> {
            items
                .iter()
                .map(|&i| self.to_value(i, depth + 1, budget))
                .collect()
        };
        Ok(match &self.arena[id] {
            Obj::None => Value::None,
            Obj::Bool(b) => Value::Bool(*b),
            Obj::Int(v) => Value::Int(*v),
            Obj::Float(v) => Value::Float(*v),
            Obj::Str(s) => Value::Str(s.clone()),
            Obj::Bytes(b) => Value::Bytes(b.clone()),
            Obj::List(items) => Value::List(list(items)?),
            Obj::Tuple(items) => Value::Tuple(list(items)?),
            Obj::Dict(entries) => Value::Dict(
                entries
                    .iter()
                    .map(|&(k, v)| {
                        Ok((
                            self.to_value(k, depth + 1, budget)?,
                            self.to_value(v, depth + 1, budget)?,
                        ))
                    })
                    .collect::<R<_>>()?,
            ),
            Obj::Global { module, name, .. } => Value::Global {
                module: module.clone(),
                name: name.clone(),
            },
            Obj::Dtype { dtype, .. } => Value::Dtype(*dtype),
            Obj::EmptyArray => return self.err("a numpy array was never given its state (BUILD)"),
            Obj::Array(a) => Value::Array(a.clone()),
            Obj::Storage { .. } => {
                return self.err("a tensor storage was never rebuilt into a tensor");
            }
            Obj::Tensor(t) => Value::Tensor(t.clone()),
        })
    }
}

fn obj_name(obj: &Obj) -> &'static str {
    match obj {
        Obj::None => "None",
        Obj::Bool(_) => "bool",
        Obj::Int(_) => "int",
        Obj::Float(_) => "float",
        Obj::Str(_) => "str",
        Obj::Bytes(_) => "bytes",
        Obj::List(_) => "list",
        Obj::Tuple(_) => "tuple",
        Obj::Dict(_) => "dict",
        Obj::Global { .. } => "global",
        Obj::Dtype { .. } => "dtype",
        Obj::EmptyArray => "ndarray",
        Obj::Array(_) => "ndarray",
        Obj::Storage { .. } => "torch storage",
        Obj::Tensor(_) => "torch tensor",
    }
}

/// For a Fortran-ordered array, the memory index of each C-order element (`None` when the
/// memory order already is C, or the array has at most one non-trivial axis).
fn fortran_to_c(shape: &[usize], fortran: bool) -> Option<Vec<usize>> {
    if !fortran || shape.iter().filter(|&&d| d > 1).count() <= 1 {
        return None;
    }
    let count: usize = shape.iter().product();
    // Fortran strides: the first axis is contiguous.
    let mut strides = vec![1usize; shape.len()];
    for k in 1..shape.len() {
        strides[k] = strides[k - 1] * shape[k - 1];
    }
    let mut out = Vec::with_capacity(count);
    let mut idx = vec![0usize; shape.len()];
    for _ in 0..count {
        out.push(idx.iter().zip(&strides).map(|(i, s)| i * s).sum());
        // Increment the C-order multi-index (last axis fastest).
        for k in (0..shape.len()).rev() {
            idx[k] += 1;
            if idx[k] < shape[k] {
                break;
            }
            idx[k] = 0;
        }
    }
    Some(out)
}

/// IEEE half to f64.
fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f64;
    sign * match exp {
        0 => frac * 2f64.powi(-24),
        31 if frac == 0.0 => f64::INFINITY,
        31 => f64::NAN,
        e => (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

/// Decodes raw numpy array bytes (`dtype`, byte order `order` as numpy writes it: `<`, `>`,
/// `|` or `=`, C or Fortran memory order) into C-order elements; the `.npy` reader uses it too.
pub(crate) fn decode_array(
    raw: &[u8],
    dtype: DType,
    order: u8,
    shape: &[usize],
    fortran: bool,
) -> Result<Elements, String> {
    fn fail<T>(reason: impl Into<String>) -> Result<T, String> {
        Err(reason.into())
    }
    let count = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .map_or_else(|| fail("array shape overflows"), Ok)?;
    let size = dtype.size();
    if count.checked_mul(size) != Some(raw.len()) {
        return fail(format!(
            "array data has {} bytes, but shape {shape:?} of {dtype} needs {}",
            raw.len(),
            count.saturating_mul(size)
        ));
    }
    let big = match order {
        b'>' => true,
        b'<' | b'|' => false,
        b'=' => cfg!(target_endian = "big"),
        o => return fail(format!("unknown byte order {:?}", o as char)),
    };
    let word = |i: usize| -> [u8; 8] {
        let mut a = [0u8; 8];
        let src = &raw[i * size..(i + 1) * size];
        if big && dtype.has_byte_order() {
            for (k, &b) in src.iter().rev().enumerate() {
                a[k] = b;
            }
        } else {
            a[..size].copy_from_slice(src);
        }
        a
    };
    // Memory order → C order: element at C index `c` lives at memory index `perm(c)`.
    let index = fortran_to_c(shape, fortran);
    let at = |c: usize| index.as_ref().map_or(c, |idx| idx[c]);
    let elements = match dtype {
        DType::Bool => Elements::Bool((0..count).map(|c| raw[at(c)] != 0).collect()),
        DType::F16 => Elements::Float(
            (0..count)
                .map(|c| f16_to_f64(u16::from_le_bytes([word(at(c))[0], word(at(c))[1]])))
                .collect(),
        ),
        DType::F32 => Elements::Float(
            (0..count)
                .map(|c| {
                    let w = word(at(c));
                    f32::from_le_bytes([w[0], w[1], w[2], w[3]]) as f64
                })
                .collect(),
        ),
        DType::F64 => Elements::Float(
            (0..count)
                .map(|c| f64::from_le_bytes(word(at(c))))
                .collect(),
        ),
        DType::U64 => {
            let mut out = Vec::with_capacity(count);
            for c in 0..count {
                let v = u64::from_le_bytes(word(at(c)));
                match i64::try_from(v) {
                    Ok(v) => out.push(v),
                    Err(_) => return fail(format!("uint64 value {v} exceeds i64")),
                }
            }
            Elements::Int(out)
        }
        int => {
            let signed = matches!(int, DType::I8 | DType::I16 | DType::I32 | DType::I64);
            Elements::Int(
                (0..count)
                    .map(|c| {
                        let w = word(at(c));
                        let v = i64::from_le_bytes(w);
                        if signed && size < 8 {
                            let shift = 64 - 8 * size as u32;
                            (v << shift) >> shift
                        } else {
                            v
                        }
                    })
                    .collect(),
            )
        }
    };
    Ok(elements)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_containers_and_memo() {
        // pickle.dumps({'a': [1, 2, 300, -5], 'b': (1.5, 'x'), 'c': None}, protocol=2), by hand.
        let mut p = vec![
            0x80, 2, b'}', b'q', 0, b'(', 0x8c, 1, b'a', b']', b'q', 1, b'(',
        ];
        p.extend([
            b'K', 1, b'K', 2, b'M', 44, 1, b'J', 0xfb, 0xff, 0xff, 0xff, b'e',
        ]);
        p.extend([0x8c, 1, b'b', b'G']);
        p.extend(1.5f64.to_be_bytes());
        p.extend([
            0x8c, 1, b'x', 0x86, 0x8c, 1, b'c', b'N', b'h', 1, b'u', b'.',
        ]);
        // The memo GET re-pushes the list under the name `c`... after `N`: the dict then has
        // an odd item count, which must be an error, not a panic.
        assert!(from_slice(&p).is_err());
        let n = p.len();
        p.truncate(n - 5);
        p.extend([b'N', b'u', b'.']);
        let v = from_slice(&p).unwrap();
        assert_eq!(
            v.get("a").unwrap(),
            &Value::List(vec![
                Value::Int(1),
                Value::Int(2),
                Value::Int(300),
                Value::Int(-5)
            ])
        );
        assert_eq!(
            v.get("b").unwrap(),
            &Value::Tuple(vec![Value::Float(1.5), Value::Str("x".into())])
        );
        assert_eq!(v.get("c").unwrap(), &Value::None);
    }

    #[test]
    fn long1_sign_extension() {
        let vm = Vm::new(&[], Dialect::Data);
        assert_eq!(vm.long(&[0xff]).unwrap(), -1);
        assert_eq!(vm.long(&[0x00, 0x80, 0x00]).unwrap(), 0x8000);
        assert_eq!(vm.long(&[0; 9]).unwrap(), 0);
        assert!(vm.long(&[0, 0, 0, 0, 0, 0, 0, 0, 1]).is_err());
    }

    #[test]
    fn unknown_global_is_named() {
        let p = b"\x80\x02cos\nsystem\nq\x00X\x02\x00\x00\x00lsq\x01\x85q\x02Rq\x03.";
        let e = from_slice(p).unwrap_err();
        assert!(e.reason.contains("os.system"), "{e}");
    }

    #[test]
    fn truncation_and_garbage_never_panic() {
        let p = b"\x80\x02}q\x00(X\x05\x00\x00\x00helloq\x01K\x01u.";
        assert!(from_slice(p).is_ok());
        for cut in 0..p.len() {
            assert!(from_slice(&p[..cut]).is_err());
        }
        // A huge declared length must fail without allocating.
        let huge = b"\x80\x04\x8e\xff\xff\xff\xff\xff\xff\xff\x7f";
        assert!(from_slice(huge).unwrap_err().reason.contains("truncated"));
        // A self-referencing list (l.append(l)) is an error, not a stack overflow.
        let cyclic = b"\x80\x02]q\x00h\x00a.";
        assert!(from_slice(cyclic).is_err());
        // Shared references doubling per level: [[[..., ...], ...], ...], 2^64 values once
        // copied out. Found while writing the structure-aware fuzzer (tests/tests/
        // fuzz_readers.rs): an error, where it used to run (and allocate) without end.
        let mut doubling = b"\x80\x02K\x00q\x00".to_vec();
        for level in 0..64u8 {
            doubling.extend([b'h', level, b'h', level, 0x86, b'q', level + 1]);
        }
        doubling.push(b'.');
        let e = from_slice(&doubling).unwrap_err();
        assert!(e.reason.contains("expand"), "{e}");
        let mut rng = lifegom_render::rng::Rng::new(12345);
        for _ in 0..2000 {
            let len = rng.below(40);
            let mut junk = vec![0x80, 4];
            for _ in 0..len {
                junk.push((rng.next_u64() >> 56) as u8);
            }
            let _ = from_slice(&junk);
        }
    }

    #[test]
    fn fortran_permutation() {
        // 2x3 Fortran: memory [a00 a10 a01 a11 a02 a12]; C order wants a00 a01 a02 a10 ...
        assert_eq!(fortran_to_c(&[2, 3], true).unwrap(), vec![0, 2, 4, 1, 3, 5]);
        assert!(fortran_to_c(&[1, 5], true).is_none());
    }

    #[test]
    fn half_floats() {
        assert_eq!(f16_to_f64(0x3c00), 1.0);
        assert_eq!(f16_to_f64(0xc000), -2.0);
        assert_eq!(f16_to_f64(0x7c00), f64::INFINITY);
    }
}
