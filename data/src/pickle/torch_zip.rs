//! The tensors of a PyTorch zip archive — a `torch.save` file (PyTorch ≥ 1.6) or a TorchScript
//! module (`torch.jit.save`) — read without Python and without running any of its code.
//!
//! Both are zips of one `<prefix>/data.pkl`, a pickle of the object tree whose tensors refer to
//! their bytes by storage key, and one entry `<prefix>/data/<key>` of raw little-endian elements
//! per storage. The pickle is read in [`Dialect::Torch`]; this module then walks the tree
//! (dicts, TorchScript module attributes, lists) and names every tensor by its path, joined with
//! dots as `state_dict()` would (`net.layers.conv.weight`), and gathers its elements from the
//! storage with the tensor's offset and strides.

use std::collections::HashMap;
use std::io::{Cursor, Read};
use std::path::Path;

use super::reader::{self, Dialect};
use super::value::{TensorRef, Value};
use crate::error::{DataError, Location, Result};

/// Largest storage entry read (a storage bigger than this is refused, not allocated).
pub const MAX_STORAGE_BYTES: u64 = 1 << 32;

/// One tensor of an archive, as `f32` in C order.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedTensor {
    /// Dotted path in the object tree (`net.layers.conv.weight`).
    pub name: String,
    /// The tensor's shape.
    pub shape: Vec<usize>,
    /// Its elements, row-major.
    pub values: Vec<f32>,
}

/// Reads every tensor of the archive at `path`; errors name the file and the entry or tensor.
pub fn load(path: &Path) -> Result<Vec<NamedTensor>> {
    let bytes =
        std::fs::read(path).map_err(|source| DataError::io(Location::file(path), source))?;
    from_bytes(&bytes, &Location::file(path))
}

/// Reads every tensor of an archive held in memory (`location` names it in errors).
pub fn from_bytes(bytes: &[u8], location: &Location) -> Result<Vec<NamedTensor>> {
    let bad = |field: &str, reason: String| {
        DataError::invalid(location.clone().field(field.to_string()), reason)
    };
    let mut archive = zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| {
        DataError::invalid(location.clone(), format!("not a PyTorch zip archive: {e}"))
    })?;
    let pickle_name = archive
        .file_names()
        .filter_map(|n| n.ok().map(|n| n.into_owned()))
        .find(|n| n.ends_with("data.pkl") && n.matches('/').count() <= 1)
        .ok_or_else(|| {
            DataError::invalid(
                location.clone(),
                "no `data.pkl` entry: not a torch.save or TorchScript archive",
            )
        })?;
    let prefix = pickle_name.trim_end_matches("data.pkl").to_string();
    let pickle = read_entry(&mut archive, &pickle_name).map_err(|r| bad(&pickle_name, r))?;
    let root = reader::from_slice_in(&pickle, Dialect::Torch).map_err(|e| DataError::Pickle {
        location: Box::new(location.clone().field(pickle_name.clone())),
        offset: e.offset,
        reason: e.reason,
    })?;
    let mut refs = Vec::new();
    collect(&root, String::new(), &mut refs, 0);
    let mut storages: HashMap<String, Vec<u8>> = HashMap::new();
    let mut out = Vec::with_capacity(refs.len());
    for (name, t) in refs {
        if !storages.contains_key(&t.storage) {
            let entry = format!("{prefix}data/{}", t.storage);
            let raw = read_entry(&mut archive, &entry).map_err(|r| bad(&entry, r))?;
            storages.insert(t.storage.clone(), raw);
        }
        let raw = &storages[&t.storage];
        let values = gather(&t, raw).map_err(|r| bad(&name, r))?;
        out.push(NamedTensor {
            name,
            shape: t.shape.clone(),
            values,
        });
    }
    Ok(out)
}

fn read_entry(
    archive: &mut zip::ZipArchive<Cursor<&[u8]>>,
    name: &str,
) -> std::result::Result<Vec<u8>, String> {
    let mut entry = archive
        .by_name(name)
        .map_err(|e| format!("archive entry missing or unreadable: {e}"))?;
    if entry.size() > MAX_STORAGE_BYTES {
        return Err(format!(
            "{} bytes, more than the {MAX_STORAGE_BYTES} this reader takes",
            entry.size()
        ));
    }
    let mut bytes = Vec::new();
    (&mut entry)
        .take(MAX_STORAGE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| format!("cannot decompress: {e}"))?;
    Ok(bytes)
}

/// Every tensor under `value`, with its dotted path, in the order the pickle holds them.
fn collect(value: &Value, path: String, out: &mut Vec<(String, TensorRef)>, depth: usize) {
    if depth > reader::MAX_DEPTH {
        return;
    }
    let child = |key: &str| {
        if path.is_empty() {
            key.to_string()
        } else {
            format!("{path}.{key}")
        }
    };
    match value {
        Value::Tensor(t) => out.push((path, t.clone())),
        Value::Dict(items) => {
            for (k, v) in items {
                let key = match k {
                    Value::Str(s) => s.clone(),
                    Value::Int(i) => i.to_string(),
                    _ => continue,
                };
                collect(v, child(&key), out, depth + 1);
            }
        }
        Value::List(items) | Value::Tuple(items) => {
            for (i, v) in items.iter().enumerate() {
                collect(v, child(&i.to_string()), out, depth + 1);
            }
        }
        _ => {}
    }
}

/// The tensor's elements from its storage bytes, row-major.
fn gather(t: &TensorRef, raw: &[u8]) -> std::result::Result<Vec<f32>, String> {
    let width = match t.storage_type.as_str() {
        "FloatStorage" => 4,
        "DoubleStorage" => 8,
        other => {
            return Err(format!(
                "storage type {other} is not read (only FloatStorage and DoubleStorage)"
            ));
        }
    };
    let stored = raw.len() / width;
    let numel = t
        .shape
        .iter()
        .try_fold(1usize, |n, &d| n.checked_mul(d))
        .ok_or_else(|| format!("shape {:?} overflows", t.shape))?;
    if numel == 0 {
        return Ok(Vec::new());
    }
    // The last element addressed must lie inside the storage.
    let last = t
        .shape
        .iter()
        .zip(&t.stride)
        .try_fold(t.offset, |acc, (&d, &s)| {
            (d - 1).checked_mul(s).and_then(|x| x.checked_add(acc))
        })
        .ok_or_else(|| format!("offset {} and strides {:?} overflow", t.offset, t.stride))?;
    if last >= stored {
        return Err(format!(
            "shape {:?}, stride {:?} and offset {} address element {last}, but storage {} holds {stored}",
            t.shape, t.stride, t.offset, t.storage
        ));
    }
    let element = |i: usize| -> f32 {
        let b = &raw[i * width..(i + 1) * width];
        if width == 4 {
            f32::from_le_bytes([b[0], b[1], b[2], b[3]])
        } else {
            let mut a = [0u8; 8];
            a.copy_from_slice(b);
            f64::from_le_bytes(a) as f32
        }
    };
    let mut values = Vec::with_capacity(numel);
    let mut index = vec![0usize; t.shape.len()];
    for _ in 0..numel {
        let at = t.offset
            + index
                .iter()
                .zip(&t.stride)
                .map(|(i, s)| i * s)
                .sum::<usize>();
        values.push(element(at));
        for d in (0..index.len()).rev() {
            index[d] += 1;
            if index[d] < t.shape[d] {
                break;
            }
            index[d] = 0;
        }
    }
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// A TorchScript-like archive: a module object holding a transposed 2×3 view and a
    /// parameter, its storages as entries.
    fn archive(storage_len: usize) -> Vec<u8> {
        // WrapNet().__setstate__({'w': tensor(storage '0', offset 1, size (2, 3), stride (1, 2)),
        //                          'inner': Inner().__setstate__({'b': tensor('1', 0, (2,), (1,))})})
        let mut p = vec![0x80, 2];
        let global = |p: &mut Vec<u8>, m: &str, n: &str| {
            p.push(b'c');
            p.extend(m.as_bytes());
            p.push(b'\n');
            p.extend(n.as_bytes());
            p.push(b'\n');
        };
        let text = |p: &mut Vec<u8>, s: &str| {
            p.push(b'X');
            p.extend((s.len() as u32).to_le_bytes());
            p.extend(s.as_bytes());
        };
        let tensor = |p: &mut Vec<u8>, key: &str, offset: u8, size: &[u8], stride: &[u8]| {
            global(p, "torch._utils", "_rebuild_tensor_v2");
            p.push(b'(');
            p.push(b'(');
            text(p, "storage");
            global(p, "torch", "FloatStorage");
            text(p, key);
            text(p, "cpu");
            p.extend([b'K', 7]);
            p.push(b't');
            p.push(b'Q');
            p.extend([b'K', offset]);
            p.push(b'(');
            for &d in size {
                p.extend([b'K', d]);
            }
            p.push(b't');
            p.push(b'(');
            for &d in stride {
                p.extend([b'K', d]);
            }
            p.push(b't');
            p.push(0x89);
            global(p, "collections", "OrderedDict");
            p.push(b')');
            p.push(b'R');
            p.push(b't');
            p.push(b'R');
        };
        global(&mut p, "__torch__.wrap_net", "WrapNet");
        p.push(b')');
        p.push(0x81);
        p.push(b'}');
        p.push(b'(');
        text(&mut p, "training");
        p.push(0x89);
        text(&mut p, "w");
        tensor(&mut p, "0", 1, &[2, 3], &[1, 2]);
        text(&mut p, "inner");
        global(&mut p, "__torch__.wrap_net", "Inner");
        p.push(b')');
        p.push(0x81);
        p.push(b'}');
        p.push(b'(');
        text(&mut p, "b");
        tensor(&mut p, "1", 0, &[2], &[1]);
        p.push(b'u');
        p.push(b'b');
        p.push(b'u');
        p.push(b'b');
        p.push(b'.');
        let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        zip.start_file("m/data.pkl", opts).unwrap();
        zip.write_all(&p).unwrap();
        zip.start_file("m/data/0", opts).unwrap();
        for v in 0..storage_len {
            zip.write_all(&(v as f32).to_le_bytes()).unwrap();
        }
        zip.start_file("m/data/1", opts).unwrap();
        zip.write_all(&[0.5f32, -2.0].map(f32::to_le_bytes).concat())
            .unwrap();
        zip.finish().unwrap().into_inner()
    }

    #[test]
    fn module_attributes_are_named_and_strided_views_gathered() {
        let tensors = from_bytes(&archive(7), &Location::default()).unwrap();
        let names: Vec<&str> = tensors.iter().map(|t| t.name.as_str()).collect();
        assert_eq!(names, ["w", "inner.b"]);
        // Element (i, j) is storage[1 + i + 2j].
        assert_eq!(tensors[0].shape, [2, 3]);
        assert_eq!(tensors[0].values, [1.0, 3.0, 5.0, 2.0, 4.0, 6.0]);
        assert_eq!(tensors[1].values, [0.5, -2.0]);
    }

    #[test]
    fn a_view_past_its_storage_names_the_tensor() {
        let err = from_bytes(&archive(6), &Location::file("m.pt")).unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("field `w`") && text.contains("m.pt"),
            "{text}"
        );
        assert!(text.contains("address element 6"), "{text}");
    }

    #[test]
    fn torch_globals_are_errors_in_data_files() {
        let bytes = archive(7);
        let mut zip = zip::ZipArchive::new(Cursor::new(bytes.as_slice())).unwrap();
        let pickle = read_entry(&mut zip, "m/data.pkl").unwrap();
        let err = reader::from_slice(&pickle).unwrap_err();
        assert!(
            err.reason.contains("__torch__.wrap_net.WrapNet"),
            "{}",
            err.reason
        );
        assert!(reader::from_slice_in(&pickle, Dialect::Torch).is_ok());
    }
}
