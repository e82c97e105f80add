//! Two folders of images scored against each other, as `python -m pytorch_fid A B` and the
//! lpips package's scripts do: images paired by file name for PSNR, SSIM and LPIPS, and the
//! two sets' FID (each image resized to 299² inside the Inception, whatever its size).
//!
//! FID over a few dozen images is strongly biased upwards and only comparable between
//! evaluations with the same image counts; the counts travel with the value.

use std::path::{Path, PathBuf};

use burn::tensor::Device;

use crate::error::EvalError;
use crate::images::Image;
use crate::metrics::{ImageRef, psnr, ssim_skimage};
use crate::perceptual::{FeatureStats, PerceptualModels, frechet_distance};
use crate::perceptual_scores::{lpips_pairs, pool3_features};

/// Image files the folders may hold (what the `image` crate is built to read).
const EXTENSIONS: [&str; 2] = ["png", "gif"];

/// The scores of one pair.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PairScores {
    /// The shared file name.
    pub name: String,
    /// PSNR in dB (`None` for identical images: infinite).
    pub psnr: Option<f64>,
    /// SSIM (skimage's).
    pub ssim: f64,
    /// LPIPS with AlexNet (`None` without its weights).
    pub lpips_alex: Option<f64>,
    /// LPIPS with VGG16 (`None` without its weights).
    pub lpips_vgg: Option<f64>,
}

/// Everything `lifegom-metrics` prints.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FolderScores {
    /// Image pairs scored.
    pub pairs: usize,
    /// Pairs with identical images (left out of the PSNR mean: their PSNR is infinite).
    pub identical_pairs: usize,
    /// Mean PSNR over the other pairs.
    pub psnr: Option<f64>,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean LPIPS-alex.
    pub lpips_alex: Option<f64>,
    /// Mean LPIPS-vgg (× 1000 is the paper's LPIPS*).
    pub lpips_vgg: Option<f64>,
    /// FID between the two folders.
    pub fid: Option<f64>,
    /// Images in the first folder that FID saw.
    pub fid_images_a: usize,
    /// Images in the second folder that FID saw.
    pub fid_images_b: usize,
    /// The weight files that were missing (their figures are `None`).
    pub missing_weights: Vec<String>,
    /// Per pair, by name.
    pub per_pair: Vec<PairScores>,
}

/// The image files of `dir`, sorted by name.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>, EvalError> {
    let err = |reason: String| EvalError::Input {
        path: dir.to_path_buf(),
        reason,
    };
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| err(format!("cannot list the folder: {e}")))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| EXTENSIONS.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(err(format!(
            "no images ({}) in the folder",
            EXTENSIONS.join(", ")
        )));
    }
    Ok(files)
}

/// Pairs the files of two folders by name; an unpaired file is an error naming it.
pub fn pair_files(a: &Path, b: &Path) -> Result<Vec<(PathBuf, PathBuf)>, EvalError> {
    let (fa, fb) = (image_files(a)?, image_files(b)?);
    let name = |p: &Path| p.file_name().map(|n| n.to_os_string());
    for (files, other, other_dir) in [(&fa, &fb, b), (&fb, &fa, a)] {
        if let Some(lone) = files
            .iter()
            .find(|p| !other.iter().any(|q| name(q) == name(p)))
        {
            return Err(EvalError::Input {
                path: lone.clone(),
                reason: format!("no image of this name in {}", other_dir.display()),
            });
        }
    }
    Ok(fa.into_iter().zip(fb).collect())
}

/// Scores folder `a` against folder `b` with whatever networks `models` holds.
pub fn score_folders(
    a: &Path,
    b: &Path,
    models: &PerceptualModels,
    device: &Device,
) -> Result<FolderScores, EvalError> {
    let files = pair_files(a, b)?;
    let mut pairs = Vec::with_capacity(files.len());
    for (fa, fb) in &files {
        let (ia, ib) = (Image::load(fa)?, Image::load(fb)?);
        if (ia.width, ia.height) != (ib.width, ib.height) {
            return Err(EvalError::Input {
                path: fb.clone(),
                reason: format!(
                    "{}×{} px, but {} is {}×{} px",
                    ib.width,
                    ib.height,
                    fa.display(),
                    ia.width,
                    ia.height
                ),
            });
        }
        pairs.push((ia, ib));
    }
    let mut per_pair = Vec::with_capacity(pairs.len());
    for ((fa, _), (ia, ib)) in files.iter().zip(&pairs) {
        let shape = [ia.height, ia.width, 3];
        let (ra, rb) = (
            ImageRef::new(&ia.data, shape)?,
            ImageRef::new(&ib.data, shape)?,
        );
        let p = psnr(ra, rb, 1.0)?;
        per_pair.push(PairScores {
            name: fa
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            psnr: p.is_finite().then_some(p),
            ssim: ssim_skimage(ra, rb)?,
            lpips_alex: None,
            lpips_vgg: None,
        });
    }
    // LPIPS batches images of one size: the pairs sorted by size, scored, put back.
    let mut order: Vec<usize> = (0..pairs.len()).collect();
    order.sort_by_key(|&i| (pairs[i].0.height, pairs[i].0.width));
    let pred: Vec<Image> = order.iter().map(|&i| pairs[i].0.clone()).collect();
    let gt: Vec<Image> = order.iter().map(|&i| pairs[i].1.clone()).collect();
    if let Some(net) = &models.lpips_alex {
        for (&k, d) in order.iter().zip(lpips_pairs(net, &pred, &gt, device)?) {
            per_pair[k].lpips_alex = Some(d);
        }
    }
    if let Some(net) = &models.lpips_vgg {
        for (&k, d) in order.iter().zip(lpips_pairs(net, &pred, &gt, device)?) {
            per_pair[k].lpips_vgg = Some(d);
        }
    }
    let fid = match &models.inception {
        Some(net) if pairs.len() >= 2 => {
            let sa = FeatureStats::from_features(&pool3_features(net, &pred, device)?, 2048)?;
            let sb = FeatureStats::from_features(&pool3_features(net, &gt, device)?, 2048)?;
            Some(frechet_distance(&sa, &sb)?)
        }
        _ => None,
    };
    let n = per_pair.len() as f64;
    let finite: Vec<f64> = per_pair.iter().filter_map(|p| p.psnr).collect();
    let mean_of = |get: fn(&PairScores) -> Option<f64>| -> Option<f64> {
        let v: Option<Vec<f64>> = per_pair.iter().map(get).collect();
        v.map(|v| v.iter().sum::<f64>() / n)
    };
    let fid_images = if fid.is_some() { pairs.len() } else { 0 };
    Ok(FolderScores {
        pairs: per_pair.len(),
        identical_pairs: per_pair.len() - finite.len(),
        psnr: (!finite.is_empty()).then(|| finite.iter().sum::<f64>() / finite.len() as f64),
        ssim: per_pair.iter().map(|p| p.ssim).sum::<f64>() / n,
        lpips_alex: mean_of(|p| p.lpips_alex),
        lpips_vgg: mean_of(|p| p.lpips_vgg),
        fid,
        fid_images_a: fid_images,
        fid_images_b: fid_images,
        missing_weights: models.missing.clone(),
        per_pair,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, w: usize, h: usize, v: f32) {
        Image::filled(w, h, [v, v * 0.5, 1.0 - v])
            .save_png(&dir.join(name))
            .unwrap();
    }

    #[test]
    fn unpaired_and_differently_sized_files_are_named() {
        let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        write(a.path(), "x.png", 8, 8, 0.2);
        write(b.path(), "x.png", 8, 8, 0.3);
        write(a.path(), "lonely.png", 8, 8, 0.2);
        let none = PerceptualModels {
            lpips_alex: None,
            lpips_vgg: None,
            inception: None,
            missing: vec!["all".into()],
        };
        let device = Device::flex();
        let e = score_folders(a.path(), b.path(), &none, &device)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("lonely.png") && e.contains("no image of this name"),
            "{e}"
        );
        write(b.path(), "lonely.png", 9, 8, 0.2);
        let e = score_folders(a.path(), b.path(), &none, &device)
            .unwrap_err()
            .to_string();
        assert!(e.contains("lonely.png") && e.contains("9×8 px"), "{e}");
        write(b.path(), "lonely.png", 8, 8, 0.2);
        let s = score_folders(a.path(), b.path(), &none, &device).unwrap();
        assert_eq!((s.pairs, s.identical_pairs), (2, 1));
        assert!(s.psnr.unwrap() > 10.0 && s.fid.is_none() && s.lpips_vgg.is_none());
    }
}
