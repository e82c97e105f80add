//! BlazePose's person detector: the photo letterboxed to 224 × 224, the graph's 2254 anchor
//! predictions decoded, scored and merged by weighted non-maximum suppression, and the result
//! mapped back to the photo.
//!
//! Each anchor predicts a box and four keypoints relative to its centre, in input pixels:
//! keypoint 0 is the hips' centre, 1 a point on the circle around the whole body, 2 the
//! shoulders' centre, 3 a point on the circle around the upper body. The anchors are SSD's
//! (strides 8, 16 and three layers of 32, two anchors a cell, every anchor of unit size), as
//! the graph was trained with.

use burn::tensor::{Device, Tensor, TensorData};
use glam::Vec2;
use lifegom_tflite::Graph;

use crate::crop::{self, Border, Roi};

/// The detector's input side.
pub const INPUT: usize = 224;
/// Scores below this are not detections.
pub const MIN_SCORE: f32 = 0.5;
/// Detections overlapping the best one by more than this IoU are merged into it.
pub const MERGE_IOU: f32 = 0.3;

/// One person found, in the photo's coordinates normalised by its width and height.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    /// The score in (0, 1).
    pub score: f32,
    /// The box's top-left corner.
    pub min: Vec2,
    /// The box's size.
    pub size: Vec2,
    /// Hips' centre, full-body circle point, shoulders' centre, upper-body circle point.
    pub keypoints: [Vec2; 4],
}

impl Detection {
    fn iou(&self, other: &Detection) -> f32 {
        let lo = self.min.max(other.min);
        let hi = (self.min + self.size).min(other.min + other.size);
        let inter = (hi - lo).max(Vec2::ZERO);
        let inter = inter.x * inter.y;
        let union = self.size.x * self.size.y + other.size.x * other.size.y - inter;
        if union > 0.0 { inter / union } else { 0.0 }
    }
}

/// The anchors' centres, in the input's normalised coordinates, in the graph's output order.
pub fn anchors() -> Vec<Vec2> {
    // Layers sharing a stride share a grid; each layer adds two anchors a cell (its aspect
    // ratio 1 and the interpolated scale), all of unit size.
    const STRIDES: [usize; 5] = [8, 16, 32, 32, 32];
    let mut out = Vec::with_capacity(2254);
    let mut layer = 0;
    while layer < STRIDES.len() {
        let stride = STRIDES[layer];
        let same = STRIDES[layer..]
            .iter()
            .take_while(|&&s| s == stride)
            .count();
        let cells = INPUT.div_ceil(stride);
        for y in 0..cells {
            for x in 0..cells {
                let centre = Vec2::new(
                    (x as f32 + 0.5) / cells as f32,
                    (y as f32 + 0.5) / cells as f32,
                );
                out.extend(std::iter::repeat_n(centre, 2 * same));
            }
        }
        layer += same;
    }
    out
}

/// Decodes the graph's outputs (`boxes`: 2254 × 12, `scores`: 2254) into detections above
/// [`MIN_SCORE`], in the letterboxed input's normalised coordinates.
pub fn decode(boxes: &[f32], scores: &[f32], anchors: &[Vec2]) -> Vec<Detection> {
    let scale = INPUT as f32;
    let mut out = Vec::new();
    for (k, anchor) in anchors.iter().enumerate() {
        let (Some(raw), Some(&logit)) = (boxes.get(k * 12..k * 12 + 12), scores.get(k)) else {
            break;
        };
        let score = 1.0 / (1.0 + (-logit.clamp(-100.0, 100.0)).exp());
        if score < MIN_SCORE {
            continue;
        }
        let centre = Vec2::new(raw[0], raw[1]) / scale + *anchor;
        let size = Vec2::new(raw[2], raw[3]) / scale;
        let point = |i: usize| Vec2::new(raw[4 + 2 * i], raw[5 + 2 * i]) / scale + *anchor;
        out.push(Detection {
            score,
            min: centre - size / 2.0,
            size,
            keypoints: [point(0), point(1), point(2), point(3)],
        });
    }
    out
}

/// Weighted non-maximum suppression: the best-scoring detection, its box and keypoints
/// replaced by the score-weighted mean of every detection overlapping it by more than
/// [`MERGE_IOU`] (itself included), then the same on what is left.
pub fn merge(mut detections: Vec<Detection>) -> Vec<Detection> {
    detections.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut out = Vec::new();
    while let Some(best) = detections.first().copied() {
        // The best is in its own group even when its box is empty (no overlap with itself).
        let (group, rest): (Vec<_>, Vec<_>) = detections
            .into_iter()
            .enumerate()
            .partition(|(i, d)| *i == 0 || best.iou(d) > MERGE_IOU);
        let total: f32 = group.iter().map(|(_, d)| d.score).sum();
        let mut merged = best;
        if total > 0.0 {
            let mean = |f: &dyn Fn(&Detection) -> Vec2| {
                group.iter().map(|(_, d)| f(d) * d.score).sum::<Vec2>() / total
            };
            let min = mean(&|d| d.min);
            merged.size = mean(&|d| d.min + d.size) - min;
            merged.min = min;
            for i in 0..4 {
                merged.keypoints[i] = mean(&|d| d.keypoints[i]);
            }
        }
        out.push(merged);
        detections = rest.into_iter().map(|(_, d)| d).collect();
    }
    out
}

/// Maps a detection from the letterboxed input back to the photo (`pad`: the letterbox's
/// horizontal and vertical padding, each side, as a fraction of the input).
pub fn unletterbox(d: Detection, pad: [f32; 2]) -> Detection {
    let pad = Vec2::from(pad);
    let span = Vec2::ONE - 2.0 * pad;
    let map = |p: Vec2| (p - pad) / span;
    Detection {
        score: d.score,
        min: map(d.min),
        size: d.size / span,
        keypoints: d.keypoints.map(map),
    }
}

/// Every person the detector finds in the `width × height` RGB photo, best first.
pub fn detect(
    graph: &Graph,
    rgb: &[u8],
    width: usize,
    height: usize,
    device: &Device,
) -> lifegom_tflite::Result<Vec<Detection>> {
    let (roi, pad) = Roi::letterbox(width as u32, height as u32);
    let pixels = crop::crop(rgb, width, height, &roi, INPUT, Border::Zero);
    let values: Vec<f32> = pixels.iter().map(|&v| f32::from(v) / 127.5 - 1.0).collect();
    let x = Tensor::<4>::from_data(TensorData::new(values, [1, INPUT, INPUT, 3]), device)
        .permute([0, 3, 1, 2]);
    let outputs = graph.run(vec![x])?;
    let read = |i: usize| {
        outputs
            .get(i)
            .ok_or_else(|| format!("the detector has {} outputs, expected 2", outputs.len()))
            .and_then(|o| o.to_vec())
            .map_err(|reason| lifegom_tflite::TfliteError::Input {
                graph: graph.name().to_string(),
                index: i,
                reason,
            })
    };
    let (boxes, scores) = (read(0)?, read(1)?);
    let found = merge(decode(&boxes, &scores, &anchors()));
    Ok(found.into_iter().map(|d| unletterbox(d, pad)).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_anchor_grid_has_the_graphs_2254_predictions() {
        let a = anchors();
        assert_eq!(a.len(), 2254);
        // Two anchors per 28 × 28 cell first, centred on the cells.
        assert_eq!(a[0], a[1]);
        assert_eq!(a[0], Vec2::splat(0.5 / 28.0));
        assert_eq!(a[2].x, 1.5 / 28.0);
        // Six per 7 × 7 cell last.
        assert_eq!(a[2253], Vec2::splat(6.5 / 7.0));
        assert_eq!(a[2248], a[2253]);
        assert_ne!(a[2247], a[2253]);
    }

    #[test]
    fn overlapping_detections_merge_by_score() {
        let d = |x: f32, score: f32| Detection {
            score,
            min: Vec2::new(x, 0.0),
            size: Vec2::ONE,
            keypoints: [Vec2::new(x, 0.0); 4],
        };
        let out = merge(vec![d(0.0, 0.9), d(0.1, 0.6), d(5.0, 0.7)]);
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].score, 0.9);
        let x = 0.1 * 0.6 / 1.5;
        assert!((out[0].min.x - x).abs() < 1e-6 && (out[0].keypoints[2].x - x).abs() < 1e-6);
        assert_eq!(out[1].min.x, 5.0);
    }
}
