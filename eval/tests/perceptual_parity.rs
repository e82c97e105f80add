//! Parity of `lifegom_eval::perceptual` with the reference Python packages (pip `lpips` 0.1.x,
//! `pytorch-fid`), and the weight-file error paths.
//!
//! The fixture `fixtures/perceptual/reference.json` comes from `tools/make_perceptual_fixtures.py`:
//! every network tensor is listed under its converted name with the seed/offset/scale of a
//! splitmix64 hash formula, and the reference outputs were computed by the Python packages with
//! those exact values. Here the tensors are regenerated bit-exactly, written to a SafeTensors
//! file in the converter's format, and loaded through the real `load` functions.

use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor, TensorData};
use lifegom_eval::perceptual::{
    FeatureStats, InceptionPool3, Lpips, LpipsNet, PerceptualError, PerceptualModels,
    frechet_distance,
};
use serde_json::Value;

fn fixture() -> &'static Value {
    static FIXTURE: std::sync::OnceLock<Value> = std::sync::OnceLock::new();
    FIXTURE.get_or_init(|| {
        let path =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/perceptual/reference.json");
        let text = std::fs::read_to_string(&path).unwrap();
        serde_json::from_str(&text).unwrap()
    })
}

/// The fixture generator's hash: u in [0, 1) from splitmix64's finaliser, then
/// `offset + scale·(2u − 1)` in f64, rounded to f32.
fn hash_values(n: usize, seed: u64, offset: f64, scale: f64) -> Vec<f32> {
    let base = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    (0..n as u64)
        .map(|i| {
            let mut h = i.wrapping_add(base);
            h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            h ^= h >> 31;
            let u = (h >> 40) as f64 / (1u64 << 24) as f64;
            (offset + scale * (2.0 * u - 1.0)) as f32
        })
        .collect()
}

/// `(shape, values)` of a `{shape, seed, offset, scale}` spec.
fn generate(spec: &Value) -> (Vec<usize>, Vec<f32>) {
    let shape: Vec<usize> = spec["shape"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d.as_u64().unwrap() as usize)
        .collect();
    let n = shape.iter().product();
    let values = hash_values(
        n,
        spec["seed"].as_u64().unwrap(),
        spec["offset"].as_f64().unwrap(),
        spec["scale"].as_f64().unwrap(),
    );
    (shape, values)
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

type Named = Vec<(String, Vec<usize>, Vec<f32>)>;

/// The manifest's tensors, generated.
fn manifest_tensors(case: &Value) -> Named {
    case["tensors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            let (shape, values) = generate(t);
            (t["key"].as_str().unwrap().to_string(), shape, values)
        })
        .collect()
}

/// A minimal SafeTensors writer (what `safetensors.torch.save_file` produces for f32 tensors):
/// u64 LE header length, JSON header padded with spaces to 8 bytes, raw LE data.
fn write_safetensors(path: &Path, tensors: &Named) {
    let mut header = serde_json::Map::new();
    let mut offset = 0usize;
    for (key, shape, values) in tensors {
        let end = offset + 4 * values.len();
        header.insert(
            key.clone(),
            serde_json::json!({"dtype": "F32", "shape": shape, "data_offsets": [offset, end]}),
        );
        offset = end;
    }
    let mut json = serde_json::to_vec(&header).unwrap();
    while !json.len().is_multiple_of(8) {
        json.push(b' ');
    }
    let mut bytes = Vec::with_capacity(8 + json.len() + offset);
    bytes.extend_from_slice(&(json.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&json);
    for (_, _, values) in tensors {
        for v in values {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// A scratch directory removed on drop.
struct TempDir(PathBuf);
impl TempDir {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!(
            "lifegom-perceptual-{name}-{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }
    fn path(&self, file: &str) -> PathBuf {
        self.0.join(file)
    }
}
impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn image_tensor(spec: &Value, device: &Device) -> Tensor<4> {
    let (shape, values) = generate(spec);
    let shape: [usize; 4] = shape.try_into().unwrap();
    Tensor::from_data(TensorData::new(values, shape), device)
}

use lifegom_render::testing::read;

/// Largest |got − want| / max(|want|, floor).
fn max_rel_err(got: &[f32], want: &[f64], floor: f64) -> f64 {
    assert_eq!(got.len(), want.len());
    got.iter()
        .zip(want)
        .map(|(g, w)| (f64::from(*g) - w).abs() / w.abs().max(floor))
        .fold(0.0, f64::max)
}

fn lpips_parity(net: LpipsNet, device: &Device) {
    let name = format!("lpips_{}", net.name());
    let case = &fixture()[&name];
    let dir = TempDir::new(&name);
    let file = dir.path(&format!("{name}.safetensors"));
    write_safetensors(&file, &manifest_tensors(case));
    let lpips = Lpips::load(net, &file, device).unwrap();
    let (a, b) = (
        image_tensor(&case["a"], device),
        image_tensor(&case["b"], device),
    );
    let t = std::time::Instant::now();
    let got = read(lpips.distance(a.clone(), b.clone()));
    let secs = t.elapsed().as_secs_f64();
    let want = floats(&case["distance"]);
    let err = max_rel_err(&got, &want, 1e-6);
    eprintln!("{name}: distance {got:?} vs {want:?}, max rel err {err:.2e}, {secs:.2} s");
    assert!(
        err < 1e-4,
        "{name}: {got:?} vs {want:?} (rel err {err:.2e})"
    );
    let layers = lpips.try_per_layer(a, b).unwrap();
    for (k, (layer, want)) in layers
        .into_iter()
        .zip(case["per_layer"].as_array().unwrap())
        .enumerate()
    {
        let want = floats(want);
        let got = read(layer);
        let err = max_rel_err(&got, &want, 1e-6);
        assert!(err < 1e-4, "{name} layer {k}: {got:?} vs {want:?}");
    }
}

fn lpips_alex(device: &Device) {
    lpips_parity(LpipsNet::Alex, device);
}
fn lpips_vgg(device: &Device) {
    lpips_parity(LpipsNet::Vgg, device);
}
lifegom_render::cpu_backend_tests!(lpips_alex_matches_lpips_package => lpips_alex);
lifegom_render::cpu_backend_tests!(lpips_vgg_matches_lpips_package => lpips_vgg);

/// pool3 features of pytorch-fid's InceptionV3 on one upsampled (40×52) and one downsampled
/// (320×310) image. ndarray takes ~14 s per 299² forward on two cores, so it checks only the
/// downsampled case (the real one: THuman crops are 1000×500); Flex checks both.
fn inception(device: &Device, cases: std::ops::Range<usize>) {
    let case = &fixture()["inception"];
    let dir = TempDir::new("inception");
    let file = dir.path("pt_inception.safetensors");
    write_safetensors(&file, &manifest_tensors(case));
    let net = InceptionPool3::load(&file, device).unwrap();
    for c in &case["cases"].as_array().unwrap()[cases] {
        let images = image_tensor(&c["images"], device);
        let shape = images.dims();
        let t = std::time::Instant::now();
        let got = read(net.features(images));
        let secs = t.elapsed().as_secs_f64();
        let want = floats(&c["features"]);
        assert_eq!(got.len(), 2048);
        let max_abs = got
            .iter()
            .zip(&want)
            .map(|(g, w)| (f64::from(*g) - w).abs())
            .fold(0.0, f64::max);
        let scale = want.iter().fold(0.0f64, |m, w| m.max(w.abs()));
        eprintln!(
            "inception {shape:?}: max abs err {max_abs:.2e} (features up to {scale:.2}), {secs:.2} s"
        );
        assert!(
            max_abs < 1e-3,
            "inception {shape:?}: max abs err {max_abs:.2e}"
        );
    }
}
mod inception_pool3_matches_pytorch_fid {
    #[test]
    #[allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it.
    fn ndarray() {
        super::inception(&burn::tensor::Device::ndarray(), 1..2);
    }
    #[test]
    fn flex() {
        super::inception(&burn::tensor::Device::flex(), 0..2);
    }
}

/// Fréchet distance of two small feature sets vs `calculate_frechet_distance` (the second case
/// has fewer rows than dimensions: singular covariances).
#[test]
fn frechet_distance_matches_pytorch_fid() {
    for case in fixture()["fid"].as_array().unwrap() {
        let dim = case["dim"].as_u64().unwrap() as usize;
        let rows = |k: &str| -> Vec<f32> { floats(&case[k]).iter().map(|v| *v as f32).collect() };
        let a = FeatureStats::from_features(&rows("a"), dim).unwrap();
        let b = FeatureStats::from_features(&rows("b"), dim).unwrap();
        let got = frechet_distance(&a, &b).unwrap();
        let want = case["fid"].as_f64().unwrap();
        let rel = (got - want).abs() / want.abs();
        eprintln!(
            "FID dim {dim} ({} vs {} rows): {got} vs {want}, rel err {rel:.2e}",
            a.count, b.count
        );
        // pytorch-fid keeps the mean in float32 (np.mean of float32 activations): ~1e-7.
        assert!(rel < 1e-5, "FID {got} vs pytorch-fid {want}");
    }
}

/// The LPIPS-alex manifest with `edit` applied, written to `file`.
fn alex_file(file: &Path, edit: impl FnOnce(&mut Named)) {
    let mut tensors = manifest_tensors(&fixture()["lpips_alex"]);
    edit(&mut tensors);
    write_safetensors(file, &tensors);
}

#[test]
fn discover_records_missing_files_and_loads_present_ones() {
    let device = Device::flex();
    let dir = TempDir::new("discover");
    let models = PerceptualModels::discover(&dir.0, &device).unwrap();
    assert!(
        models.lpips_alex.is_none() && models.lpips_vgg.is_none() && models.inception.is_none()
    );
    assert_eq!(models.missing.len(), 3, "{:?}", models.missing);
    for file in [
        "lpips_alex.safetensors",
        "lpips_vgg.safetensors",
        "pt_inception.safetensors",
    ] {
        let expected = dir.path(file).display().to_string();
        assert!(
            models.missing.iter().any(|m| m.contains(&expected)),
            "{file} not in {:?}",
            models.missing
        );
    }

    alex_file(&dir.path("lpips_alex.safetensors"), |_| {});
    let models = PerceptualModels::discover(&dir.0, &device).unwrap();
    assert_eq!(
        models.lpips_alex.as_ref().map(Lpips::net),
        Some(LpipsNet::Alex)
    );
    assert_eq!(models.missing.len(), 2, "{:?}", models.missing);
    assert!(models.missing.iter().all(|m| !m.contains("lpips_alex")));

    // A corrupt file is an error naming it, not a missing entry.
    std::fs::write(dir.path("lpips_vgg.safetensors"), b"not a safetensors file").unwrap();
    let err = PerceptualModels::discover(&dir.0, &device).unwrap_err();
    assert!(matches!(err, PerceptualError::Format { .. }), "{err}");
    assert!(err.to_string().contains("lpips_vgg.safetensors"), "{err}");
}

#[test]
fn default_dir_is_weights_unless_overridden() {
    // Only this test touches the variable.
    // SAFETY: no other test in this binary reads or writes LIFEGOM_WEIGHTS.
    unsafe { std::env::remove_var("LIFEGOM_WEIGHTS") };
    assert_eq!(PerceptualModels::default_dir(), PathBuf::from("weights"));
    // SAFETY: as above.
    unsafe { std::env::set_var("LIFEGOM_WEIGHTS", "/opt/w") };
    assert_eq!(PerceptualModels::default_dir(), PathBuf::from("/opt/w"));
    // SAFETY: as above.
    unsafe { std::env::remove_var("LIFEGOM_WEIGHTS") };
}

#[test]
fn bad_files_are_errors_naming_file_and_key() {
    let device = Device::flex();
    let dir = TempDir::new("errors");

    let absent = dir.path("absent.safetensors");
    let err = Lpips::load(LpipsNet::Alex, &absent, &device).unwrap_err();
    assert!(matches!(err, PerceptualError::Io { .. }), "{err}");
    assert!(err.to_string().contains("absent.safetensors"), "{err}");

    let garbage = dir.path("garbage.safetensors");
    std::fs::write(&garbage, b"\x40\0\0\0\0\0\0\0{\"a\":").unwrap();
    let err = InceptionPool3::load(&garbage, &device).unwrap_err();
    assert!(err.to_string().contains("garbage.safetensors"), "{err}");

    // Valid header, data cut short.
    let truncated = dir.path("truncated.safetensors");
    alex_file(&truncated, |_| {});
    let bytes = std::fs::read(&truncated).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let err = Lpips::load(LpipsNet::Alex, &truncated, &device).unwrap_err();
    assert!(err.to_string().contains("truncated.safetensors"), "{err}");

    let wrong_shape = dir.path("wrong_shape.safetensors");
    alex_file(&wrong_shape, |t| {
        let entry = t
            .iter_mut()
            .find(|(k, _, _)| k == "convs.1.weight")
            .unwrap();
        entry.1 = vec![192, 64, 3, 3];
        entry.2.truncate(192 * 64 * 9);
    });
    let err = Lpips::load(LpipsNet::Alex, &wrong_shape, &device).unwrap_err();
    assert!(matches!(err, PerceptualError::Tensor { .. }), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("convs.1.weight") && msg.contains("wrong_shape.safetensors"),
        "{msg}"
    );

    let partial = dir.path("partial.safetensors");
    alex_file(&partial, |t| t.retain(|(k, _, _)| k != "lins.4.weight"));
    let err = Lpips::load(LpipsNet::Alex, &partial, &device).unwrap_err();
    assert!(
        matches!(err, PerceptualError::MissingTensors { .. }),
        "{err}"
    );
    assert!(err.to_string().contains("lins.4.weight"), "{err}");

    // The AlexNet file is not a VGG file: shapes differ from the first conv on.
    let alex = dir.path("alex.safetensors");
    alex_file(&alex, |_| {});
    let err = Lpips::load(LpipsNet::Vgg, &alex, &device).unwrap_err();
    assert!(err.to_string().contains("alex.safetensors"), "{err}");
}
