//! BlazePose's landmark model on the crop a detection gives: 33 body landmarks with visibility,
//! and the person's segmentation, mapped back to the photo.
//!
//! The crop is a square around the hips' centre, as wide as 2.5 times the distance to the
//! full-body circle point, turned so that the hips-to-circle direction points up. The model
//! predicts 39 points in crop pixels (the 33 landmarks and 6 it uses for tracking), their
//! visibility and presence as logits, 64 × 64 heatmaps that refine each point within a 7 × 7
//! window, and segmentation logits on the 256 × 256 crop.

use burn::tensor::{Device, Tensor, TensorData};
use glam::{Vec2, Vec3};
use lifegom_tflite::{Graph, TfliteError};

use crate::crop::{self, Border, Roi};
use crate::detector::Detection;

/// The landmark model's input side.
pub const INPUT: usize = 256;
/// The body landmarks (BlazePose's topology: nose, eyes, ears, mouth, shoulders, elbows,
/// wrists, hands, hips, knees, ankles, heels, feet).
pub const LANDMARKS: usize = 33;
/// Points the model predicts (the body's and its tracking points).
const POINTS: usize = 39;
/// The crop's side as a multiple of the detection's body diameter.
const CROP_SCALE: f32 = 1.25;
/// The heatmaps' side.
const HEATMAP: usize = 64;
/// The refinement window reaches this many heatmap cells each side of a point (a 9 × 9
/// window). MediaPipe's graph names a kernel of 7, but its pipeline (0.10.14) refines over 9 × 9:
/// with 7 × 7 the astronaut fixture's refined landmarks land up to 4.4 px from MediaPipe's, with
/// 9 × 9 within 0.001 px (measured against `tools/make_person_fixtures.py`'s output).
const HEATMAP_RADIUS: i32 = 4;
/// A heatmap refines a point only where it is at least this confident.
pub const MIN_HEATMAP_CONFIDENCE: f32 = 0.5;
/// Below this presence score the model saw no person in the crop.
pub const MIN_PRESENCE: f32 = 0.5;

/// One body landmark in the photo.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Landmark {
    /// Position in photo pixels.
    pub pixel: Vec2,
    /// Depth relative to the hips, in the same pixel units (MediaPipe's `z` times the crop
    /// width).
    pub depth: f32,
    /// How likely the point is visible (not occluded), in (0, 1).
    pub visibility: f32,
    /// How likely the point is inside the crop, in (0, 1).
    pub presence: f32,
    /// The most confident heatmap cell of the refinement window (the point was refined when
    /// it reaches [`MIN_HEATMAP_CONFIDENCE`]; 0 for a point outside the heatmap).
    pub heatmap_confidence: f32,
}

/// What the landmark model says about one person.
#[derive(Debug, Clone)]
pub struct Pose {
    /// The crop it looked at.
    pub roi: Roi,
    /// The model's confidence that a person is in the crop.
    pub presence: f32,
    /// The 33 body landmarks.
    pub landmarks: Vec<Landmark>,
    /// The person's probability per photo pixel, row-major, `width × height`.
    pub mask: Vec<f32>,
    /// Metric landmarks relative to the hips (metres; the model's world output), 33 of them.
    pub world: Vec<Vec3>,
}

/// The crop a detection gives, in photo pixels (`width × height`).
pub fn roi_from_detection(d: &Detection, width: usize, height: usize) -> Roi {
    let scale = Vec2::new(width as f32, height as f32);
    let hips = d.keypoints[0] * scale;
    let circle = d.keypoints[1] * scale;
    let to_circle = circle - hips;
    let side = 2.0 * to_circle.length() * CROP_SCALE;
    // Turn the crop so that hips → circle points up (−y on screen).
    let rotation =
        normalize_radians(std::f32::consts::FRAC_PI_2 - (-to_circle.y).atan2(to_circle.x));
    Roi {
        center: hips,
        size: Vec2::splat(side),
        rotation,
    }
}

fn normalize_radians(a: f32) -> f32 {
    use std::f32::consts::TAU;
    a - TAU * ((a + std::f32::consts::PI) / TAU).floor()
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Runs the landmark model on the crop `roi` of the `width × height` RGB photo; `None` when the
/// model sees no person there.
pub fn landmarks(
    graph: &Graph,
    rgb: &[u8],
    width: usize,
    height: usize,
    roi: &Roi,
    device: &Device,
) -> lifegom_tflite::Result<Option<Pose>> {
    let pixels = crop::crop(rgb, width, height, roi, INPUT, Border::Replicate);
    let values: Vec<f32> = pixels.iter().map(|&v| f32::from(v) / 255.0).collect();
    let x = Tensor::<4>::from_data(TensorData::new(values, [1, INPUT, INPUT, 3]), device)
        .permute([0, 3, 1, 2]);
    let outputs = graph.run(vec![x])?;
    let read = |i: usize, len: usize| -> lifegom_tflite::Result<Vec<f32>> {
        let values = outputs
            .get(i)
            .ok_or_else(|| format!("{} outputs, expected 5", outputs.len()))
            .and_then(|o| o.to_vec())
            .map_err(|reason| TfliteError::Input {
                graph: graph.name().to_string(),
                index: i,
                reason,
            })?;
        if values.len() != len {
            return Err(TfliteError::Input {
                graph: graph.name().to_string(),
                index: i,
                reason: format!("output {i} has {} values, expected {len}", values.len()),
            });
        }
        Ok(values)
    };
    let raw = read(0, POINTS * 5)?;
    let presence = read(1, 1)?[0];
    if presence < MIN_PRESENCE {
        return Ok(None);
    }
    let segmentation = read(2, INPUT * INPUT)?;
    let heatmap = read(3, HEATMAP * HEATMAP * POINTS)?;
    let world_raw = read(4, POINTS * 3)?;

    let n = INPUT as f32;
    let mut points: Vec<Vec2> = (0..POINTS)
        .map(|k| Vec2::new(raw[k * 5], raw[k * 5 + 1]) / n)
        .collect();
    let confidence = refine(&mut points, &heatmap);
    let landmarks = (0..LANDMARKS)
        .map(|k| Landmark {
            pixel: roi.to_photo(points[k] * n, n),
            depth: raw[k * 5 + 2] / n * roi.size.x,
            visibility: sigmoid(raw[k * 5 + 3]),
            presence: sigmoid(raw[k * 5 + 4]),
            heatmap_confidence: confidence[k],
        })
        .collect();
    // World points turn with the crop, about the hips, as MediaPipe's projection does.
    let (s, c) = roi.rotation.sin_cos();
    let world = (0..LANDMARKS)
        .map(|k| {
            let p = Vec3::new(world_raw[k * 3], world_raw[k * 3 + 1], world_raw[k * 3 + 2]);
            Vec3::new(c * p.x - s * p.y, s * p.x + c * p.y, p.z)
        })
        .collect();
    let probability: Vec<f32> = segmentation.iter().map(|&l| sigmoid(l)).collect();
    let mask = unproject_mask(&probability, roi, width, height);
    Ok(Some(Pose {
        roi: *roi,
        presence,
        landmarks,
        mask,
        world,
    }))
}

/// Moves each point (crop coordinates in [0, 1]) to the confidence-weighted mean of its
/// heatmap's window around it, where the window is confident enough; returns each window's
/// largest confidence.
fn refine(points: &mut [Vec2], heatmap: &[f32]) -> Vec<f32> {
    let offset = HEATMAP_RADIUS;
    let side = HEATMAP as i32;
    let mut confidence = vec![0f32; points.len()];
    for (k, p) in points.iter_mut().enumerate() {
        // Truncation towards zero, as MediaPipe's integer conversion.
        let col = (p.x * HEATMAP as f32) as i32;
        let row = (p.y * HEATMAP as f32) as i32;
        if !(0..side).contains(&col) || !(0..side).contains(&row) {
            continue;
        }
        let (mut sum, mut wc, mut wr, mut max) = (0f32, 0f32, 0f32, 0f32);
        for r in (row - offset).max(0)..(row + offset + 1).min(side) {
            for c in (col - offset).max(0)..(col + offset + 1).min(side) {
                let idx = (r as usize * HEATMAP + c as usize) * POINTS + k;
                let confidence = sigmoid(heatmap[idx]);
                sum += confidence;
                max = max.max(confidence);
                wc += c as f32 * confidence;
                wr += r as f32 * confidence;
            }
        }
        confidence[k] = max;
        if max >= MIN_HEATMAP_CONFIDENCE && sum > 0.0 {
            *p = Vec2::new(wc / sum, wr / sum) / HEATMAP as f32;
        }
    }
    confidence
}

/// The crop's `INPUT × INPUT` probabilities resampled onto the photo (bilinear, zero outside
/// the crop).
pub fn unproject_mask(probability: &[f32], roi: &Roi, width: usize, height: usize) -> Vec<f32> {
    let n = INPUT as f32;
    let at = |x: i64, y: i64| -> f32 {
        if x < 0 || y < 0 || x >= INPUT as i64 || y >= INPUT as i64 {
            0.0
        } else {
            probability[y as usize * INPUT + x as usize]
        }
    };
    let mut out = vec![0f32; width * height];
    for y in 0..height {
        for x in 0..width {
            let g = roi.to_grid(Vec2::new(x as f32, y as f32), n);
            let (x0, y0) = (g.x.floor(), g.y.floor());
            let (fx, fy) = (g.x - x0, g.y - y0);
            let (x0, y0) = (x0 as i64, y0 as i64);
            out[y * width + x] = (1.0 - fy) * ((1.0 - fx) * at(x0, y0) + fx * at(x0 + 1, y0))
                + fy * ((1.0 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1));
        }
    }
    out
}
