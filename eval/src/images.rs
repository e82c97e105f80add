//! Images on the host: tensors to HWC floats, PNG/GIF writing, comparison sheets, error maps.
//!
//! Float images here are row-major `H × W × 3` in `[0, 1]`. PNGs are written the way the
//! reference dumps predictions (design.md §10.1): `uint8(255 · clip(x, 0, 1))`, truncating, so a
//! metric computed on our PNGs matches one computed on the reference's.

use lifegom_render::atomic_file::write_atomic;
use std::path::Path;

use burn::tensor::Tensor;

/// An `H × W × 3` float image.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width.
    pub width: usize,
    /// Height.
    pub height: usize,
    /// Row-major RGB in `[0, 1]` (values outside are clipped when written).
    pub data: Vec<f32>,
}

/// Errors writing images; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// Encoding or filesystem error.
    #[error("{path}: {source}")]
    Write {
        /// The file.
        path: std::path::PathBuf,
        /// The cause.
        source: image::ImageError,
    },
    /// Images that should have one size do not.
    #[error("image sizes differ: {0}")]
    Size(String),
    /// The tensor's values could not be read back.
    #[error(transparent)]
    Readback(#[from] lifegom_render::readback::ReadbackError),
}

impl Image {
    /// A solid image.
    pub fn filled(width: usize, height: usize, rgb: [f32; 3]) -> Self {
        Self {
            width,
            height,
            data: rgb.repeat(width * height),
        }
    }

    /// From a `[3, H, W]` tensor (reads it back to the host).
    pub fn from_chw(t: Tensor<3>) -> Result<Self, ImageError> {
        let [_, h, w] = t.dims();
        Self::from_hwc(t.permute([1, 2, 0]), h, w)
    }

    /// From a `[H, W, 3]` tensor.
    pub fn from_hwc(t: Tensor<3>, h: usize, w: usize) -> Result<Self, ImageError> {
        let data = lifegom_render::readback::read("image", t)?;
        Ok(Self {
            width: w,
            height: h,
            data,
        })
    }

    /// The reference's uint8 conversion (truncation after clipping).
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.data
            .iter()
            .map(|x| {
                if x.is_finite() {
                    (x.clamp(0.0, 1.0) * 255.0) as u8
                } else {
                    0
                }
            })
            .collect()
    }

    /// The image after a PNG round trip (what a metric on saved files sees).
    pub fn quantized(&self) -> Self {
        Self {
            data: self
                .to_rgb8()
                .iter()
                .map(|v| f32::from(*v) / 255.0)
                .collect(),
            ..self.clone()
        }
    }

    /// Writes a PNG.
    pub fn save_png(&self, path: &Path) -> Result<(), ImageError> {
        let err = |source| ImageError::Write {
            path: path.to_path_buf(),
            source,
        };
        lifegom_render::atomic_file::write_png(
            path,
            &self.to_rgb8(),
            self.width as u32,
            self.height as u32,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(err)
    }

    /// The image as a `[1, 3, H, W]` batch (what the perceptual networks take).
    pub fn to_batch(&self, device: &burn::tensor::Device) -> Tensor<4> {
        Tensor::<3>::from_data(
            burn::tensor::TensorData::new(self.data.clone(), [self.height, self.width, 3]),
            device,
        )
        .permute([2, 0, 1])
        .unsqueeze_dim(0)
    }

    /// Reads a PNG (or any format the `image` crate was built with) as RGB.
    pub fn load(path: &Path) -> Result<Self, ImageError> {
        let img = image::open(path)
            .map_err(|source| ImageError::Write {
                path: path.to_path_buf(),
                source,
            })?
            .to_rgb8();
        Ok(Self {
            width: img.width() as usize,
            height: img.height() as usize,
            data: img.as_raw().iter().map(|v| f32::from(*v) / 255.0).collect(),
        })
    }

    /// Nearest-neighbour resize (for contact sheets only, never for metrics).
    pub fn resize_nearest(&self, width: usize, height: usize) -> Self {
        let mut data = Vec::with_capacity(width * height * 3);
        for y in 0..height {
            let sy = (y * self.height / height.max(1)).min(self.height.saturating_sub(1));
            for x in 0..width {
                let sx = (x * self.width / width.max(1)).min(self.width.saturating_sub(1));
                let i = (sy * self.width + sx) * 3;
                data.extend_from_slice(&self.data[i..i + 3]);
            }
        }
        Self {
            width,
            height,
            data,
        }
    }
}

/// Per-pixel absolute error, mean over channels, ×`gain`, through a black→red→yellow→white
/// ramp: dark where the prediction is right.
pub fn error_map(pred: &Image, gt: &Image, gain: f32) -> Result<Image, ImageError> {
    if (pred.width, pred.height) != (gt.width, gt.height) {
        return Err(ImageError::Size(format!(
            "prediction {}x{}, ground truth {}x{}",
            pred.width, pred.height, gt.width, gt.height
        )));
    }
    let data = pred
        .data
        .chunks_exact(3)
        .zip(gt.data.chunks_exact(3))
        .flat_map(|(p, g)| {
            let e = (p.iter().zip(g).map(|(a, b)| (a - b).abs()).sum::<f32>() / 3.0 * gain)
                .clamp(0.0, 1.0);
            let e = if e.is_finite() { e } else { 1.0 };
            [
                (3.0 * e).min(1.0),
                (3.0 * e - 1.0).clamp(0.0, 1.0),
                (3.0 * e - 2.0).clamp(0.0, 1.0),
            ]
        })
        .collect();
    Ok(Image {
        width: pred.width,
        height: pred.height,
        data,
    })
}

/// Tiles images into a grid (rows × columns), `pad` pixels of `background` between cells; every
/// cell is resized (nearest) to the first image's size.
pub fn grid(rows: &[Vec<Image>], pad: usize, background: [f32; 3]) -> Image {
    let Some(first) = rows.iter().flatten().next() else {
        return Image::filled(1, 1, background);
    };
    let (cw, ch) = (first.width, first.height);
    let cols = rows.iter().map(Vec::len).max().unwrap_or(0);
    let width = cols * cw + (cols + 1) * pad;
    let height = rows.len() * ch + (rows.len() + 1) * pad;
    let mut out = Image::filled(width, height, background);
    for (r, row) in rows.iter().enumerate() {
        for (c, img) in row.iter().enumerate() {
            let img = if (img.width, img.height) == (cw, ch) {
                img.clone()
            } else {
                img.resize_nearest(cw, ch)
            };
            let (x0, y0) = (pad + c * (cw + pad), pad + r * (ch + pad));
            for y in 0..ch {
                let dst = ((y0 + y) * width + x0) * 3;
                let src = y * cw * 3;
                out.data[dst..dst + cw * 3].copy_from_slice(&img.data[src..src + cw * 3]);
            }
        }
    }
    out
}

/// Writes frames as an endlessly looping animated GIF.
pub fn save_gif(path: &Path, frames: &[Image], delay_ms: u32) -> Result<(), ImageError> {
    use image::codecs::gif::{GifEncoder, Repeat};
    let err = |source| ImageError::Write {
        path: path.to_path_buf(),
        source,
    };
    let mut gif = Vec::new();
    let mut encoder = GifEncoder::new_with_speed(&mut gif, 10);
    encoder.set_repeat(Repeat::Infinite).map_err(err)?;
    for f in frames {
        let rgba: Vec<u8> = f
            .to_rgb8()
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect();
        let buffer = image::RgbaImage::from_raw(f.width as u32, f.height as u32, rgba)
            .ok_or_else(|| ImageError::Size("GIF frame buffer".into()))?;
        let frame =
            image::Frame::from_parts(buffer, 0, 0, image::Delay::from_numer_denom_ms(delay_ms, 1));
        encoder.encode_frame(frame).map_err(err)?;
    }
    drop(encoder);
    write_atomic(path, &gif).map_err(|e| err(image::ImageError::IoError(e)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uint8_conversion_truncates_like_the_reference() {
        let img = Image {
            width: 4,
            height: 1,
            data: vec![
                0.0,
                1.0,
                0.999,
                1.5,
                -0.2,
                0.5,
                f32::NAN,
                0.1,
                0.2,
                0.3,
                0.4,
                0.5,
            ],
        };
        assert_eq!(&img.to_rgb8()[..6], &[0, 255, 254, 255, 0, 127]);
        assert_eq!(img.to_rgb8()[6], 0, "NaN writes black");
    }

    #[test]
    fn png_round_trip_and_error_map() {
        let dir = std::env::temp_dir().join(format!("lifegom-images-{}", std::process::id()));
        let a = Image {
            width: 2,
            height: 2,
            data: (0..12).map(|i| i as f32 / 11.0).collect(),
        };
        let path = dir.join("a.png");
        a.save_png(&path).unwrap();
        assert_eq!(Image::load(&path).unwrap(), a.quantized());
        let e = error_map(&a, &a, 4.0).unwrap();
        assert!(e.data.iter().all(|v| *v == 0.0), "no error is black");
        let white = Image::filled(2, 2, [1.0; 3]);
        let black = Image::filled(2, 2, [0.0; 3]);
        assert!(
            error_map(&white, &black, 1.0)
                .unwrap()
                .data
                .iter()
                .all(|v| *v == 1.0)
        );
        assert!(error_map(&white, &Image::filled(3, 2, [0.0; 3]), 1.0).is_err());
        let g = grid(&[vec![a.clone(), white], vec![black]], 1, [0.5; 3]);
        assert_eq!((g.width, g.height), (2 * 2 + 3, 2 * 2 + 3));
        save_gif(&dir.join("a.gif"), &[a.clone(), a], 100).unwrap();
        assert!(std::fs::metadata(dir.join("a.gif")).unwrap().len() > 0);
        let err = Image::load(&dir.join("missing.png"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing.png"), "{err}");
    }
}
