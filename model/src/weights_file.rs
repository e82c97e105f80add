//! Telling a weights file's container format from its first bytes: the one place that does it
//! (the official checkpoint importer, the encoder's torchvision import, the perceptual metrics).
//! lifegom's own `.lgck` files carry a magic of their own ([`crate::trained::is_lifegom_file`]).
//!
//! A SafeTensors file starts with its JSON header's length as a little-endian `u64`, then the
//! header itself, which opens with `{`. Anything else is handed to Burn's PyTorch reader, which
//! takes both `torch.save` containers (the zip archive and the legacy pickle) and reports its
//! own errors. The file extension is not trusted: people rename files.

use std::fmt;
use std::io::Read;
use std::path::Path;

/// Container format of a weights file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightsFormat {
    /// `torch.save` output (zip or legacy pickle).
    PyTorch,
    /// SafeTensors.
    SafeTensors,
}

impl fmt::Display for WeightsFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::PyTorch => "PyTorch",
            Self::SafeTensors => "SafeTensors",
        })
    }
}

impl WeightsFormat {
    /// The format of the file at `path`, from its content. A SafeTensors framing whose header
    /// length runs past the end of the file is not SafeTensors (a truncated download).
    pub fn sniff(path: &Path) -> std::io::Result<Self> {
        let mut head = Vec::with_capacity(9);
        std::fs::File::open(path)?.take(9).read_to_end(&mut head)?;
        let len = std::fs::metadata(path)?.len();
        Ok(match head.as_slice() {
            [h0, h1, h2, h3, h4, h5, h6, h7, b'{'] => {
                let header = u64::from_le_bytes([*h0, *h1, *h2, *h3, *h4, *h5, *h6, *h7]);
                if header.saturating_add(8) <= len {
                    Self::SafeTensors
                } else {
                    Self::PyTorch
                }
            }
            _ => Self::PyTorch,
        })
    }
}

/// Encodes `f32` tensors `(name, shape, values)` as a SafeTensors file, in the given order: the
/// header's length as a little-endian `u64`, the JSON header (padded with spaces to a multiple
/// of 8 bytes, as the reference writer does), then the little-endian payloads back to back.
pub fn encode_safetensors(tensors: &[(String, Vec<usize>, Vec<f32>)]) -> Result<Vec<u8>, String> {
    let mut header = serde_json::Map::new();
    let mut offset = 0usize;
    for (name, shape, values) in tensors {
        if values.len() != shape.iter().product::<usize>() {
            return Err(format!(
                "`{name}`: {} values for shape {shape:?}",
                values.len()
            ));
        }
        let end = offset + 4 * values.len();
        header.insert(
            name.clone(),
            serde_json::json!({"dtype": "F32", "shape": shape, "data_offsets": [offset, end]}),
        );
        offset = end;
    }
    let mut json = serde_json::to_vec(&header).map_err(|e| e.to_string())?;
    while !json.len().is_multiple_of(8) {
        json.push(b' ');
    }
    let mut out = Vec::with_capacity(8 + json.len() + offset);
    out.extend_from_slice(&(json.len() as u64).to_le_bytes());
    out.extend(json);
    for (_, _, values) in tensors {
        values
            .iter()
            .for_each(|x| out.extend_from_slice(&x.to_le_bytes()));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sniffs_safetensors_framing_and_rejects_truncation() {
        let dir = tempfile::tempdir().unwrap();
        let header = br#"{"__metadata__":{}}"#;
        let mut good = (header.len() as u64).to_le_bytes().to_vec();
        good.extend_from_slice(header);
        let cases: [(&str, Vec<u8>, WeightsFormat); 4] = [
            ("good.safetensors", good.clone(), WeightsFormat::SafeTensors),
            (
                "truncated.safetensors",
                good[..12].to_vec(),
                WeightsFormat::PyTorch,
            ),
            (
                "zip.pth",
                b"PK\x03\x04rest-of-zip".to_vec(),
                WeightsFormat::PyTorch,
            ),
            ("tiny", b"{".to_vec(), WeightsFormat::PyTorch),
        ];
        for (name, bytes, want) in cases {
            let path = dir.path().join(name);
            std::fs::write(&path, bytes).unwrap();
            assert_eq!(WeightsFormat::sniff(&path).unwrap(), want, "{name}");
        }
        assert!(WeightsFormat::sniff(&dir.path().join("missing")).is_err());
    }
}
