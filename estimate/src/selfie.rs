//! MediaPipe's selfie segmentation: the whole photo stretched onto 256 × 256 (no letterbox),
//! the person's probability per cell, resized back to the photo bilinearly (OpenCV's resize:
//! half-pixel centres, edges clamped).

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec2;
use lifegom_tflite::{Graph, TfliteError};

use crate::crop::{self, Border, Roi};

/// The model's input side.
pub const INPUT: usize = 256;

/// The person's probability per pixel of the `width × height` RGB photo, row-major.
pub fn mask(
    graph: &Graph,
    rgb: &[u8],
    width: usize,
    height: usize,
    device: &Device,
) -> lifegom_tflite::Result<Vec<f32>> {
    let roi = Roi {
        center: Vec2::new(width as f32, height as f32) / 2.0,
        size: Vec2::new(width as f32, height as f32),
        rotation: 0.0,
    };
    let pixels = crop::crop(rgb, width, height, &roi, INPUT, Border::Zero);
    let values: Vec<f32> = pixels.iter().map(|&v| f32::from(v) / 255.0).collect();
    let x = Tensor::<4>::from_data(TensorData::new(values, [1, INPUT, INPUT, 3]), device)
        .permute([0, 3, 1, 2]);
    let outputs = graph.run(vec![x])?;
    let probability = outputs
        .first()
        .ok_or_else(|| "no output".to_string())
        .and_then(|o| o.to_vec())
        .and_then(|v| {
            if v.len() == INPUT * INPUT {
                Ok(v)
            } else {
                Err(format!("{} values, expected {}", v.len(), INPUT * INPUT))
            }
        })
        .map_err(|reason| TfliteError::Input {
            graph: graph.name().to_string(),
            index: 0,
            reason,
        })?;
    Ok(resize(&probability, INPUT, INPUT, width, height))
}

/// Bilinear resize of a `w × h` map to `out_w × out_h` with half-pixel centres and clamped
/// edges (OpenCV's `INTER_LINEAR`).
fn resize(map: &[f32], w: usize, h: usize, out_w: usize, out_h: usize) -> Vec<f32> {
    let axis = |out: usize, input: usize| -> Vec<(usize, usize, f32)> {
        let scale = input as f32 / out as f32;
        (0..out)
            .map(|o| {
                let s = ((o as f32 + 0.5) * scale - 0.5).max(0.0);
                let i0 = (s.floor() as usize).min(input - 1);
                let i1 = (i0 + 1).min(input - 1);
                (i0, i1, s - i0 as f32)
            })
            .collect()
    };
    let (xs, ys) = (axis(out_w, w), axis(out_h, h));
    let mut out = Vec::with_capacity(out_w * out_h);
    for &(y0, y1, fy) in &ys {
        for &(x0, x1, fx) in &xs {
            let top = map[y0 * w + x0] * (1.0 - fx) + map[y0 * w + x1] * fx;
            let bottom = map[y1 * w + x0] * (1.0 - fx) + map[y1 * w + x1] * fx;
            out.push(top * (1.0 - fy) + bottom * fy);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resizing_keeps_centres_and_clamps_edges() {
        let up = resize(&[0.0, 1.0], 2, 1, 4, 1);
        assert_eq!(up, [0.0, 0.25, 0.75, 1.0]);
        let same = resize(&[0.5, 0.25, 1.0, 0.0], 2, 2, 2, 2);
        assert_eq!(same, [0.5, 0.25, 1.0, 0.0]);
    }
}
