//! The synthetic generator: THuman-style (multi-view) or AIST++-style (multi-frame) subjects in
//! exactly the official processed layout (design.md §8), so the reader, training and evaluation
//! run on it unchanged. [`SynthSetting`] picks the kind; steps 1, 2 and 5 are shared.
//!
//! # Per subject (multi-view, the default)
//!
//! 1. **Shape**: PCA coefficients `c ~ N(mean, std)` of the template's shape basis (clamped to
//!    ±2.5σ), redrawn until the height is in [`HEIGHT_RANGE`] (adults, in the camera's view). **Estimated shape** for `canonical_joints.pkl` / `tpose_joints`: the true `c` plus
//!    noise (`shape_noise`·std), exactly `c`, or zero, as configured — the template in that
//!    shape, never the clothed surface ([`ShapeEstimate`]).
//! 2. **Outfit and garments** ([`body`]): per-vertex surfaces (skin, hair, top, bottom, shoes),
//!    procedural textures ([`texture`]) and offsets, so the true surface is not the template.
//! 3. **Pose**: one random plausible pose; global rotation `Rh` about the vertical axis, uniform;
//!    `Th` puts the feet on the floor (y = 0) with a small x/z jitter. One pose for all frames,
//!    as THuman scans are static.
//! 4. **Cameras** (the rig of the official THuman renders, design.md §8.7): a ring of
//!    `source_views` (16) cameras 22.5° apart from a random start azimuth, then `target_views` (48)
//!    at random azimuths in between (3 per gap), all at `camera_radius` (2 m) from the look-at
//!    point (0, 0.85, 0), pitched −8°, `fx = fy = focal_factor·W`, `cx = W/2`, `cy = H/2 +
//!    25·H/1024`. Validation subjects get the protocol's layout instead: N inputs spread over the
//!    ring, then `val_target_views` targets.
//! 5. **Ground truth**: the clothed, posed mesh through [`raster`] (a textured triangle
//!    rasterizer with a z-buffer). The default is albedo at pixel centres; Lambert shading and
//!    `supersample`×`supersample` anti-aliasing are computed only when the config asks for them.
//!    The image is the colour over black (THuman's raw background), the mask the coverage.
//!
//! # Multi-frame (AIST++-style, design.md §8.10)
//!
//! A person (steps 1–2) moves through a procedural motion ([`lifegom_render::motion`]) in front
//! of **one fixed camera** (the rig's camera at a random azimuth), as an AIST++ dancer in front of
//! camera 1. The motion is drawn per subject: walk, arm-raise or squat, a start phase, 0.75–1.5
//! cycles over the sequence, arm and leg amplitudes of 0.6–1 (legs halved under a skirt, which is
//! part of the legs' skin), and a turn about the vertical of up to ±`max_turn_deg` over the
//! sequence, so the one camera sees several sides. The joints the motion does not move keep the
//! person's own random pose (step 3). Every frame's pose, `Rh` and `Th` (feet on the floor in
//! that frame) go to `mesh_infos.pkl`.
//!
//! - Training subjects (`d01`, `d02`, ...): `sequence_frames` frames at evenly spaced times,
//!   all from the one camera. Under the AIST++ training rule every frame is a target once, with
//!   N other frames as inputs.
//! - Validation subjects (`dNN_val`): N inputs from the one camera at evenly spaced times, then
//!   `val_target_views` targets, each at a random time of the sequence (a pose the inputs do not
//!   show) and seen from a camera spread around the person (a view they do not show) — the
//!   AIST++ evaluation, which scores cameras 2–7 given frames of camera 1.
//!
//! Images are the colour over black with the coverage mask, as in the multi-view setting; the
//! AIST++ white background is the `[data]` backgrounds' job, applied when frames are read.
//!
//! Everything is a function of `(seed, subject index)` ([`Rng::fork`]), so the output is
//! identical whatever the thread count.

pub mod body;
pub mod raster;
pub mod stream;
pub mod texture;

use std::path::{Path, PathBuf};

use glam::Vec3;
use lifegom_render::atomic_file::write_png;
use lifegom_render::camera::{Camera, Intrinsics};
use lifegom_render::motion::{JointRoles, Motion};
use lifegom_render::skeleton::{BodyPose, Skeleton};
use lifegom_render::skinning::skin_points;
use lifegom_render::template::{self, BodyTemplate};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::dataset::{DataConfig, Protocol};
use crate::error::{DataError, Location, Result};
use crate::format::{CanonicalBody, FrameCamera, FrameMeshInfo};
use crate::pickle::{self, DType, Elements, NdArray, Value};
use body::{Outfit, Surface};
use lifegom_render::rng::Rng;

/// Which body template (topology) subjects are built from and `canonical_joints` uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TemplateChoice {
    /// `anny_neutral_tpose.glb`, 13,718 vertices.
    Full,
    /// `anny_closed_tpose.glb`, 13,348 vertices, no eyes/tongue.
    Closed,
    /// `anny_lowres10pc_tpose.glb`, 1,229 vertices (tests).
    Lowres,
}

impl TemplateChoice {
    /// The template file.
    pub fn path(self) -> PathBuf {
        match self {
            Self::Full => template::full_template_path(),
            Self::Closed => template::closed_template_path(),
            Self::Lowres => template::lowres_template_path(),
        }
    }
}

/// What shape `canonical_joints.pkl` (and `tpose_joints`) carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapeEstimate {
    /// True coefficients plus Gaussian noise of `shape_noise`·std per component.
    Noisy,
    /// The true coefficients (an oracle shape fit).
    Exact,
    /// The neutral template.
    Zero,
}

/// How ground-truth pixels are coloured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Shading {
    /// Albedo only (the default: simulate only the effects a scene calls for).
    Albedo,
    /// Albedo × (ambient + diffuse) with one directional light fixed to the world.
    Lambert,
    /// Lambert under a light drawn per subject (any azimuth, 25–80° above the horizon) with an
    /// ambient share of 0.3–0.6: the stream's lighting variety (design.md §8.11).
    RandomLight,
}

/// What kind of split the generator writes (design.md §8.7, §8.10).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SynthSetting {
    /// THuman-style: each person static, photographed by a ring of cameras (module docs).
    #[default]
    MultiView,
    /// AIST++-style: each person moves through a motion in front of one fixed camera; the
    /// frames are the inputs, other frames (other poses, seen from other cameras at
    /// validation) the targets (module docs, "Multi-frame").
    MultiFrame,
}

/// The `[synthetic]` section of a config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SynthConfig {
    /// Multi-view (THuman-style, the default) or multi-frame (AIST++-style).
    #[serde(default)]
    pub setting: SynthSetting,
    /// Template and topology.
    pub template: TemplateChoice,
    /// Training subjects.
    pub train_subjects: usize,
    /// Validation subjects.
    pub val_subjects: usize,
    /// Square image size, pixels.
    pub image_size: u32,
    /// Ring (source) views per training subject.
    #[serde(default = "default_source_views")]
    pub source_views: usize,
    /// Target views per training subject.
    #[serde(default = "default_target_views")]
    pub target_views: usize,
    /// Target views per validation subject (after the N inputs).
    #[serde(default = "default_val_targets")]
    pub val_target_views: usize,
    /// Camera distance to the look-at point, metres.
    #[serde(default = "default_radius")]
    pub camera_radius: f32,
    /// When set, each subject's camera distance is drawn uniformly from `[near, far]` metres
    /// instead of `camera_radius` (the stream's distance variety, design.md §8.11).
    #[serde(default)]
    pub camera_radius_range: Option<[f32; 2]>,
    /// Camera pitch, degrees (negative looks down).
    #[serde(default = "default_pitch")]
    pub camera_pitch_deg: f32,
    /// `fx = fy = focal_factor · W`.
    #[serde(default = "default_focal")]
    pub focal_factor: f32,
    /// Shape written to `canonical_joints.pkl`.
    #[serde(default = "default_estimate")]
    pub shape_estimate: ShapeEstimate,
    /// Noise of the noisy estimate, in units of each component's std.
    #[serde(default = "default_noise")]
    pub shape_noise: f32,
    /// Shading model.
    #[serde(default = "default_shading")]
    pub shading: Shading,
    /// Supersampling factor per axis (1 = one sample per pixel centre).
    #[serde(default = "default_supersample")]
    pub supersample: u32,
    /// Multi-frame: frames of each training sequence (all from the one camera).
    #[serde(default = "default_sequence_frames")]
    pub sequence_frames: usize,
    /// Multi-frame: the largest turn of the body about the vertical over one sequence, degrees
    /// (each person turns by a random angle within ±this, so the one camera sees more sides).
    #[serde(default = "default_max_turn")]
    pub max_turn_deg: f32,
    /// Multi-frame: which camera the training stream's target is seen from ([`TargetCamera`]).
    #[serde(default)]
    pub stream_target_camera: TargetCamera,
    /// Variety only the training stream draws (`[synthetic.stream_variety]`, design.md §8.11);
    /// the split written to disk ignores it, so the validation people stay the same.
    #[serde(default)]
    pub stream_variety: Option<StreamVariety>,
    /// Subjects of the held-out family written to `[data] held_out_dir` (design.md §8.11):
    /// garments, prints, hair, lighting and camera distances the training stream never draws.
    #[serde(default)]
    pub held_out_subjects: usize,
    /// The held-out subjects are written this many times larger than `image_size` (one sample
    /// per pixel), so the loader shrinks them as it shrinks anyone's photos.
    #[serde(default = "default_held_out_scale")]
    pub held_out_scale: u32,
    /// Base seed (`--seed` overrides it).
    #[serde(default)]
    pub seed: u64,
}

/// Multi-frame: which camera the training stream's target is seen from (design.md §8.10).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetCamera {
    /// The sources' camera, at another time of the sequence: the official AIST++ training
    /// (camera 1 only).
    #[default]
    Sources,
    /// One of the `val_target_views` other cameras of the validation layout, at another time:
    /// what validation and evaluation score. The sources are then that layout's N evenly
    /// spaced frames.
    Others,
}

/// How the training stream's subjects vary beyond the written split's (design.md §8.11).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StreamVariety {
    /// Each subject's camera distance, drawn uniformly from `[near, far]` metres.
    pub camera_radius: [f32; 2],
    /// The subjects' look.
    pub shading: Shading,
    /// The share of subjects drawn with this variety; the others are drawn as the split's
    /// (so the stream keeps the people its validation split shows).
    #[serde(default = "default_share")]
    pub share: f32,
    /// The garment prints the varied subjects may wear.
    #[serde(default)]
    pub prints: StreamPrints,
    /// How far the model's template of a varied subject sits inside the body, metres, drawn
    /// uniformly from `[least, most]` per subject; `[0, 0]` leaves it, a negative depth puts it
    /// outside. Inward, each vertex moves along its normal by at most half its distance to its
    /// dominant joint (design.md §8.11).
    #[serde(default)]
    pub template_inset: [f32; 2],
    /// Whose template `template_inset` moves: the varied share's only, or every subject's (the
    /// pictures of the others stay the split's either way).
    #[serde(default)]
    pub template_inset_subjects: InsetSubjects,
}

/// The stream subjects whose template [`StreamVariety::template_inset`] moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InsetSubjects {
    /// The varied share ([`StreamVariety::share`]).
    #[default]
    Varied,
    /// Every subject of the stream, varied or not.
    All,
}

/// The deepest template inset a config may ask for, metres, either way: deeper, the clamp at half
/// a vertex's distance to its joint would hold most of the limbs at half their thickness.
pub const MAX_TEMPLATE_INSET: f32 = 0.05;

/// The garment prints of the stream's varied subjects (design.md §8.11).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StreamPrints {
    /// The split's: solid, stripes, checks, noise and dots.
    #[default]
    Split,
    /// Each garment, top and legs apart, re-drawn with even odds from the extra prints
    /// (camouflage, patchwork, ring motifs: [`texture::Material::more_cloth`]), none of them
    /// the held-out family's.
    More,
}

fn default_share() -> f32 {
    1.0
}

/// Which people a subject is drawn from (design.md §8.11).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Family {
    /// The training stream's people (and the validation subjects drawn like them).
    Stream,
    /// People the stream never produces: held-out garments, prints, hair, lighting and camera
    /// distances, for a validation set the training data does not resemble.
    HeldOut,
}

fn default_source_views() -> usize {
    16
}
fn default_target_views() -> usize {
    48
}
fn default_val_targets() -> usize {
    3
}
fn default_radius() -> f32 {
    2.0
}
fn default_pitch() -> f32 {
    -8.0
}
fn default_focal() -> f32 {
    0.8
}
fn default_estimate() -> ShapeEstimate {
    ShapeEstimate::Noisy
}
fn default_noise() -> f32 {
    0.2
}
fn default_shading() -> Shading {
    Shading::Albedo
}
fn default_supersample() -> u32 {
    1
}
fn default_sequence_frames() -> usize {
    30
}
fn default_max_turn() -> f32 {
    180.0
}
fn default_held_out_scale() -> u32 {
    4
}

/// Heights (metres, T-pose) accepted when sampling shapes.
pub const HEIGHT_RANGE: std::ops::RangeInclusive<f32> = 1.55..=1.92;

/// Look-at point of the camera ring (0.85 m above the floor, as in the official THuman renders; design.md §8.7).
pub const LOOK_AT: Vec3 = Vec3::new(0.0, 0.85, 0.0);

/// The most subjects of one split a config may ask for (one folder each).
const MAX_SUBJECTS: usize = 100_000;
/// The most target views per subject a config may ask for.
const MAX_VIEWS: usize = 10_000;

impl SynthConfig {
    /// Checks settings serde cannot; `source` names the config in errors.
    pub fn validate(&self, data: &DataConfig, source: &Path) -> Result<()> {
        let bad = |field: &str, reason: String| DataError::Config {
            location: Box::new(Location::file(source).field(format!("synthetic.{field}"))),
            reason,
        };
        if self.image_size < 8 {
            return Err(bad(
                "image_size",
                format!("must be at least 8, got {}", self.image_size),
            ));
        }
        if !(1..=8).contains(&self.supersample) {
            return Err(bad(
                "supersample",
                format!("must be in 1..=8, got {}", self.supersample),
            ));
        }
        // Counts that size lists and folders, bounded before anything is allocated.
        for (field, value, limit) in [
            ("train_subjects", self.train_subjects, MAX_SUBJECTS),
            ("val_subjects", self.val_subjects, MAX_SUBJECTS),
            ("target_views", self.target_views, MAX_VIEWS),
            ("val_target_views", self.val_target_views, MAX_VIEWS),
        ] {
            if value > limit {
                return Err(bad(field, format!("must be at most {limit}, got {value}")));
            }
        }
        // The generator renders at `image_size · supersample` a side before averaging down.
        let rendered = u64::from(self.image_size) * u64::from(self.supersample);
        if rendered > u64::from(crate::dataset::MAX_IMAGE_SIDE) {
            return Err(bad(
                "image_size",
                format!(
                    "image_size × supersample must be at most {} pixels a side (the size the \
                     generator renders at), got {} × {} = {rendered}",
                    crate::dataset::MAX_IMAGE_SIDE,
                    self.image_size,
                    self.supersample
                ),
            ));
        }
        if self.held_out_subjects > MAX_SUBJECTS {
            return Err(bad(
                "held_out_subjects",
                format!(
                    "must be at most {MAX_SUBJECTS}, got {}",
                    self.held_out_subjects
                ),
            ));
        }
        if self.held_out_subjects > 0 {
            if data.held_out().is_none() {
                return Err(bad(
                    "held_out_subjects",
                    "held-out subjects need a folder and a split file: set [data] held_out_dir and held_out_split".into(),
                ));
            }
            let side = u64::from(self.image_size) * u64::from(self.held_out_scale);
            if self.held_out_scale == 0 || side > u64::from(crate::dataset::MAX_IMAGE_SIDE) {
                return Err(bad(
                    "held_out_scale",
                    format!(
                        "image_size × held_out_scale must be in 1..={} pixels a side, got {} × {}",
                        crate::dataset::MAX_IMAGE_SIDE,
                        self.image_size,
                        self.held_out_scale
                    ),
                ));
            }
        }
        if self.setting == SynthSetting::MultiFrame {
            return self.validate_multi_frame(data, source);
        }
        if self.source_views < data.n_input_frames.max(1) || self.source_views > 360 {
            return Err(bad(
                "source_views",
                format!("must be in N..=360, got {}", self.source_views),
            ));
        }
        if matches!(data.protocol, Protocol::ThumanView3 | Protocol::Xhuman)
            && (self.source_views, self.target_views) != (16, 48)
            && self.train_subjects > 0
        {
            return Err(bad(
                "source_views",
                "the THuman view3 training rule needs 16 source + 48 target views".into(),
            ));
        }
        self.validate_shared(data, source)
    }

    /// The settings only the multi-frame split reads, and the ones it shares.
    fn validate_multi_frame(&self, data: &DataConfig, source: &Path) -> Result<()> {
        let bad = |field: &str, reason: String| DataError::Config {
            location: Box::new(Location::file(source).field(format!("synthetic.{field}"))),
            reason,
        };
        if data.protocol != Protocol::Aistpp {
            return Err(bad(
                "setting",
                format!(
                    "a multi-frame split follows the AIST++ frame rules: set [data] protocol = \"aistpp\" (got {:?})",
                    data.protocol
                ),
            ));
        }
        let n = data.n_input_frames;
        if self.sequence_frames <= n || self.sequence_frames > 10_000 {
            return Err(bad(
                "sequence_frames",
                format!(
                    "must be in {}..=10000 (more than the {n} inputs), got {}",
                    n + 1,
                    self.sequence_frames
                ),
            ));
        }
        if self.val_subjects > 0 && self.val_target_views == 0 {
            return Err(bad(
                "val_target_views",
                "a validation sequence needs at least one target frame".into(),
            ));
        }
        if !(self.max_turn_deg.is_finite() && (0.0..=360.0).contains(&self.max_turn_deg)) {
            return Err(bad(
                "max_turn_deg",
                format!("must be in 0..=360, got {}", self.max_turn_deg),
            ));
        }
        self.validate_shared(data, source)
    }

    /// The settings both splits read: camera, shape noise and the split files.
    fn validate_shared(&self, data: &DataConfig, source: &Path) -> Result<()> {
        let bad = |field: &str, reason: String| DataError::Config {
            location: Box::new(Location::file(source).field(format!("synthetic.{field}"))),
            reason,
        };
        if !(self.camera_radius > 0.3 && self.camera_radius.is_finite()) {
            return Err(bad(
                "camera_radius",
                format!("must be > 0.3 m, got {}", self.camera_radius),
            ));
        }
        for (field, range) in [
            ("camera_radius_range", self.camera_radius_range),
            (
                "stream_variety.camera_radius",
                self.stream_variety.map(|v| v.camera_radius),
            ),
        ] {
            if let Some([near, far]) = range
                && !(near > 0.3 && near.is_finite() && far.is_finite() && near <= far)
            {
                return Err(bad(
                    field,
                    format!("must be [near, far] with 0.3 < near <= far, got [{near}, {far}]"),
                ));
            }
        }
        if let Some(v) = self.stream_variety
            && !(0.0..=1.0).contains(&v.share)
        {
            return Err(bad(
                "stream_variety.share",
                format!("must be in 0..=1, got {}", v.share),
            ));
        }
        if let Some(StreamVariety {
            template_inset: [least, most],
            ..
        }) = self.stream_variety
            && !(-MAX_TEMPLATE_INSET <= least && least <= most && most <= MAX_TEMPLATE_INSET)
        {
            return Err(bad(
                "stream_variety.template_inset",
                format!(
                    "must be [least, most] metres with -{MAX_TEMPLATE_INSET} <= least <= most <= {MAX_TEMPLATE_INSET}, got [{least}, {most}]"
                ),
            ));
        }
        if self.stream_target_camera == TargetCamera::Others
            && (self.setting != SynthSetting::MultiFrame || self.val_target_views == 0)
        {
            return Err(bad(
                "stream_target_camera",
                "\"others\" needs setting = \"multi_frame\" and val_target_views >= 1 (the cameras the targets are drawn from)".into(),
            ));
        }
        if !(self.focal_factor > 0.0 && self.focal_factor.is_finite()) {
            return Err(bad(
                "focal_factor",
                format!("must be > 0, got {}", self.focal_factor),
            ));
        }
        if !(self.shape_noise >= 0.0 && self.shape_noise.is_finite()) {
            return Err(bad(
                "shape_noise",
                format!("must be >= 0, got {}", self.shape_noise),
            ));
        }
        self.validate_split_files(data, source)
    }

    /// The split files the generator writes must not clash, and an explicit validation list
    /// must name the subjects it writes.
    fn validate_split_files(&self, data: &DataConfig, source: &Path) -> Result<()> {
        let bad = |field: &str, reason: String| DataError::Config {
            location: Box::new(Location::file(source).field(format!("data.{field}"))),
            reason,
        };
        let (_, val) = self.subject_names();
        match &data.val_subjects {
            Some(list) if *list != val => Err(bad(
                "val_subjects",
                format!("lists {list:?}, but the generator writes the validation subjects {val:?}"),
            )),
            None if data.val_split == data.train_split && !val.is_empty() => Err(bad(
                "val_split",
                "is the training split file: the generator would overwrite one list with the other (list the validation subjects in data.val_subjects, or use another file)".into(),
            )),
            _ => Ok(()),
        }
    }

    /// Folder names of the training and validation subjects: `0000`, `0001`, ... in the
    /// multi-view setting; AIST++'s style in the multi-frame one (`d01`, `d02`, ... then
    /// `d03_val`, ...), numbered on through both.
    pub fn subject_names(&self) -> (Vec<String>, Vec<String>) {
        let total = self.train_subjects + self.val_subjects;
        let names: Vec<String> = match self.setting {
            SynthSetting::MultiView => (0..total).map(|i| format!("{i:04}")).collect(),
            SynthSetting::MultiFrame => (0..total)
                .map(|i| {
                    let suffix = if i < self.train_subjects { "" } else { "_val" };
                    format!("d{:02}{suffix}", i + 1)
                })
                .collect(),
        };
        let (train, val) = names.split_at(self.train_subjects);
        (train.to_vec(), val.to_vec())
    }

    /// Folder names of the held-out subjects: `held_000`, `held_001`, ...
    pub fn held_out_names(&self) -> Vec<String> {
        (0..self.held_out_subjects)
            .map(|i| format!("held_{i:03}"))
            .collect()
    }

    /// The settings a held-out subject is rendered with: `held_out_scale` times the size, one
    /// sample per pixel (the loader's anti-aliased shrink is the supersampling), shaded.
    fn held_out_render(&self) -> Self {
        Self {
            image_size: self.image_size * self.held_out_scale,
            supersample: 1,
            shading: Shading::Lambert,
            ..self.clone()
        }
    }

    /// Frames of one training subject: the camera ring and its targets (multi-view), or the
    /// sequence (multi-frame).
    pub fn train_frames(&self) -> usize {
        match self.setting {
            SynthSetting::MultiView => self.source_views + self.target_views,
            SynthSetting::MultiFrame => self.sequence_frames,
        }
    }
}

/// Where the body is in one frame, as `mesh_infos.pkl` stores it (the shape is the subject's).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameBody {
    /// Flat axis-angle pose, `3J`.
    pub poses: Vec<f32>,
    /// Global rotation (axis-angle, about y).
    pub rh: Vec3,
    /// Global translation (feet on the floor).
    pub th: Vec3,
}

/// One rendered frame: name, camera, RGB (over black) and mask, at the configured size, and
/// the body's pose in it.
pub struct RenderedFrame {
    /// `frame_%06d`.
    pub name: String,
    /// The camera (world → camera; the body's `Rh`/`Th` are part of the world).
    pub camera: Camera,
    /// `H×W×3` RGB8.
    pub rgb: Vec<u8>,
    /// `H×W` mask, 0..255.
    pub mask: Vec<u8>,
    /// The body's pose (one for every frame of a static multi-view subject).
    pub body: FrameBody,
}

/// A generated subject, before it is written.
pub struct SyntheticSubject {
    /// Folder name.
    pub name: String,
    /// Frames.
    pub frames: Vec<RenderedFrame>,
    /// Estimated-shape joints.
    pub est_joints: Vec<Vec3>,
    /// Estimated-shape template vertices.
    pub est_vertices: Vec<Vec3>,
}

impl RenderedFrame {
    /// The frame's camera as `cameras.pkl` stores it: `K` and `E` (world → camera), each entry
    /// an `f32` widened to `f64`, exactly what reading the written file gives back.
    pub fn frame_camera(&self) -> FrameCamera {
        let k = self.camera.intrinsics.matrix();
        let r = self.camera.rotation();
        let t = self.camera.cam_from_world.translation;
        let e = [
            [r.x_axis.x, r.y_axis.x, r.z_axis.x, t.x],
            [r.x_axis.y, r.y_axis.y, r.z_axis.y, t.y],
            [r.x_axis.z, r.y_axis.z, r.z_axis.z, t.z],
            [0.0, 0.0, 0.0, 1.0],
        ];
        FrameCamera {
            k: k.map(|row| row.map(f64::from)),
            e: e.map(|row| row.map(f64::from)),
            distortion: None,
        }
    }
}

impl SyntheticSubject {
    /// Frame `frame`'s body as `mesh_infos.pkl` stores it: its pose, global transform and the
    /// subject's estimated zero-pose joints.
    pub fn mesh_info(&self, frame: &RenderedFrame) -> FrameMeshInfo {
        FrameMeshInfo {
            poses: frame.body.poses.clone(),
            tpose_joints: self.est_joints.clone(),
            rh: frame.body.rh,
            th: frame.body.th,
        }
    }

    /// The canonical body as `canonical_joints.pkl` stores it: the estimated shape's joints and
    /// template vertices, the template's dense skinning weights, faces and parents.
    pub fn canonical_body(&self, template: &BodyTemplate) -> CanonicalBody {
        CanonicalBody::of_template(template, self.est_vertices.clone(), self.est_joints.clone())
    }
}

/// Camera azimuths (radians) of a training subject: the ring, then targets in the gaps.
fn train_azimuths(cfg: &SynthConfig, rng: &mut Rng) -> Vec<f32> {
    let n = cfg.source_views;
    let step = std::f32::consts::TAU / n as f32;
    let start = rng.uniform() as f32 * std::f32::consts::TAU;
    let mut az: Vec<f32> = (0..n).map(|k| start + k as f32 * step).collect();
    for t in 0..cfg.target_views {
        // Gaps in turn (3 per gap for 16 + 48), at a random position inside the gap.
        let gap = t % n;
        az.push(start + (gap as f32 + rng.range(0.1, 0.9) as f32) * step);
    }
    az
}

/// Camera azimuths of a validation subject: N inputs spread over the ring, then targets.
fn val_azimuths(cfg: &SynthConfig, n_inputs: usize, rng: &mut Rng) -> Vec<f32> {
    let ring = cfg.source_views as f32;
    let step = std::f32::consts::TAU / ring;
    let start = rng.uniform() as f32 * std::f32::consts::TAU;
    let mut az: Vec<f32> = (0..n_inputs)
        .map(|k| start + (k as f32 * ring / n_inputs as f32).round() * step)
        .collect();
    for _ in 0..cfg.val_target_views {
        az.push(start + rng.uniform() as f32 * std::f32::consts::TAU);
    }
    az
}

/// The THuman-rig camera (design.md §8.7) at azimuth `az`.
pub fn ring_camera(cfg: &SynthConfig, az: f32) -> Result<Camera> {
    let size = cfg.image_size;
    let pitch = cfg.camera_pitch_deg.to_radians();
    // Negative pitch looks down: the camera sits above the look-at point.
    let dir = Vec3::new(az.sin() * pitch.cos(), -pitch.sin(), az.cos() * pitch.cos());
    let f = cfg.focal_factor * size as f32;
    let intr = Intrinsics {
        fx: f,
        fy: f,
        cx: size as f32 / 2.0,
        cy: size as f32 / 2.0 + 25.0 * size as f32 / 1024.0,
    };
    Camera::look_at(
        LOOK_AT + dir * cfg.camera_radius,
        LOOK_AT,
        Vec3::Y,
        intr,
        size,
        size,
    )
    .map_err(|e| DataError::render(Location::default().field("camera"), e))
}

/// The subject's surface, ready to shade.
struct Scene<'a> {
    world: Vec<Vec3>,
    canonical: Vec<Vec3>,
    normals: Vec<Vec3>,
    surfaces: Vec<Surface>,
    faces: &'a [[u32; 3]],
    outfit: Outfit,
    /// Direction towards the light, world space, and the ambient share (shaded looks only).
    light: Vec3,
    ambient: f32,
}

impl Scene<'_> {
    /// Renders one view (module docs, step 5).
    fn render(&self, camera: &Camera, shading: Shading, ss: u32) -> Result<(Vec<u8>, Vec<u8>)> {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut hi = *camera;
        hi.width *= ss;
        hi.height *= ss;
        let s = ss as f32;
        hi.intrinsics = Intrinsics {
            fx: camera.intrinsics.fx * s,
            fy: camera.intrinsics.fy * s,
            cx: camera.intrinsics.cx * s,
            cy: camera.intrinsics.cy * s,
        };
        let frags = raster::rasterize(&self.world, self.faces, &hi);
        let light = self.light;
        let mut acc = vec![[0f32; 4]; w * h];
        let hw = hi.width as usize;
        for (p, frag) in frags.iter().enumerate() {
            let Some(frag) = frag else { continue };
            let face = self.faces[frag.face as usize];
            let b = frag.bary;
            let interp =
                |attr: &[Vec3]| -> Vec3 { (0..3).map(|c| attr[face[c] as usize] * b[c]).sum() };
            // The material of the corner nearest the sample, so textures do not blend across
            // garment borders.
            let corner = (0..3).max_by(|&x, &y| b[x].total_cmp(&b[y])).unwrap_or(0);
            let surface = self.surfaces[face[corner] as usize];
            let mut c = self.outfit.materials[surface as usize].albedo(interp(&self.canonical));
            if shading != Shading::Albedo {
                let n = interp(&self.normals).normalize_or_zero();
                let lit = self.ambient + (1.0 - self.ambient) * n.dot(light).max(0.0);
                c = c.map(|v| v * lit);
            }
            let (x, y) = ((p % hw) / ss as usize, (p / hw) / ss as usize);
            let a = &mut acc[y * w + x];
            a[0] += c[0];
            a[1] += c[1];
            a[2] += c[2];
            a[3] += 1.0;
        }
        let n = (ss * ss) as f32;
        let to_u8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        let rgb = acc
            .iter()
            .flat_map(|a| [to_u8(a[0] / n), to_u8(a[1] / n), to_u8(a[2] / n)])
            .collect();
        let mask = acc.iter().map(|a| to_u8(a[3] / n)).collect();
        Ok((rgb, mask))
    }
}

/// Generates subject `index` (global over train then val) with `n_inputs`-input validation
/// layout when `val` is true.
pub fn generate_subject(
    template: &BodyTemplate,
    cfg: &SynthConfig,
    seed: u64,
    index: usize,
    name: &str,
    val_inputs: Option<usize>,
) -> Result<SyntheticSubject> {
    generate_subject_frames(template, cfg, seed, index, name, val_inputs, None)
}

/// A shaped, clothed person in the canonical pose: steps 1–2 of the module docs.
struct Person {
    skeleton: Skeleton,
    clothed: Vec<Vec3>,
    surfaces: Vec<Surface>,
    outfit: Outfit,
    est_joints: Vec<Vec3>,
    est_vertices: Vec<Vec3>,
    /// Direction towards the light (world space) and the ambient share, when shaded.
    light: Vec3,
    ambient: f32,
}

/// The stream's light: fixed to the world, from above, front and side.
const STREAM_LIGHT: Vec3 = Vec3::new(0.3, 1.0, 0.5);
/// The ambient share of Lambert shading under a fixed light.
const STREAM_AMBIENT: f32 = 0.35;

/// A light direction at any azimuth and an elevation drawn from `elevation` (degrees).
fn random_light(rng: &mut Rng, elevation: (f64, f64)) -> Vec3 {
    let az = rng.uniform() as f32 * std::f32::consts::TAU;
    let el = (rng.range(elevation.0, elevation.1) as f32).to_radians();
    Vec3::new(az.sin() * el.cos(), el.sin(), az.cos() * el.cos())
}

impl Person {
    /// Draws the person from `rng` (shape, estimated shape, outfit, in that order; the
    /// held-out family then its light).
    fn sample(
        template: &BodyTemplate,
        cfg: &SynthConfig,
        family: Family,
        name: &str,
        rng: &mut Rng,
    ) -> Result<Self> {
        let at = |field: &str| Location::default().subject(name).field(field.to_owned());
        let basis = &template.shape_basis;
        let k = basis.num_components();
        // Rejection-sample adult heights (the official THuman renders rescale the scans to 1.80 ± 0.05 m; the PCA's tails
        // reach child-like and >2 m bodies that leave the 2 m camera ring's field of view).
        let mut coeffs = vec![0.0; k];
        for attempt in 0..64 {
            let spread = if attempt < 48 { 1.0 } else { 0.5 };
            coeffs = (0..k)
                .map(|i| {
                    basis.coeff_mean[i]
                        + spread * basis.coeff_std[i] * (rng.normal() as f32).clamp(-2.5, 2.5)
                })
                .collect();
            let (v, _) = template
                .shaped(&coeffs)
                .map_err(|e| DataError::render(at("shape"), e))?;
            let (lo, hi) = v
                .iter()
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), p| {
                    (lo.min(p.y), hi.max(p.y))
                });
            if HEIGHT_RANGE.contains(&(hi - lo)) {
                break;
            }
        }
        let est: Vec<f32> = match cfg.shape_estimate {
            ShapeEstimate::Exact => coeffs.clone(),
            ShapeEstimate::Zero => vec![0.0; k],
            ShapeEstimate::Noisy => coeffs
                .iter()
                .zip(&basis.coeff_std)
                .map(|(c, s)| c + cfg.shape_noise * s * rng.normal() as f32)
                .collect(),
        };
        let (vertices, joints) = template
            .shaped(&coeffs)
            .map_err(|e| DataError::render(at("shape"), e))?;
        let (est_vertices, est_joints) = template
            .shaped(&est)
            .map_err(|e| DataError::render(at("shape"), e))?;
        let skeleton = template
            .skeleton
            .with_rest_joints(joints.clone())
            .map_err(|e| DataError::render(at("skeleton"), e))?;

        let (outfit, light) = match family {
            Family::Stream => (Outfit::sample(rng), STREAM_LIGHT.normalize()),
            Family::HeldOut => {
                let outfit = Outfit::held_out(rng);
                // Any azimuth, 15–70° above the horizon.
                (outfit, random_light(rng, (15.0, 70.0)))
            }
        };
        let dominant = dominant_joints(template);
        let faces = &template.topology.faces;
        let normals = body::vertex_normals(&vertices, faces);
        let surfaces = body::surfaces(&skeleton, &joints, &vertices, &dominant, &outfit);
        let clothed = body::clothe(&skeleton, &joints, &vertices, &normals, &surfaces, &outfit);
        Ok(Self {
            skeleton,
            clothed,
            surfaces,
            outfit,
            est_joints,
            est_vertices,
            light,
            ambient: STREAM_AMBIENT,
        })
    }

    /// The person in `pose`, turned by `rh` about the vertical and standing on the floor
    /// (y = 0) at `(x, z)`: the scene to render and the body's global transform.
    fn posed<'a>(
        &self,
        template: &'a BodyTemplate,
        pose: &BodyPose,
        rh: Vec3,
        (x, z): (f32, f32),
        name: &str,
    ) -> Result<(Scene<'a>, FrameBody)> {
        let at = |field: &str| Location::default().subject(name).field(field.to_owned());
        let faces = &template.topology.faces;
        let transforms = self
            .skeleton
            .skinning_transforms(pose)
            .map_err(|e| DataError::render(at("pose"), e))?;
        let posed = skin_points(&self.clothed, &template.skin, &transforms)
            .map_err(|e| DataError::render(at("skinning"), e))?;
        let posed_normals = body::vertex_normals(&posed, faces);
        let rot = lifegom_render::skeleton::rodrigues(rh);
        let min_y = posed
            .iter()
            .map(|p| (rot * *p).y)
            .fold(f32::INFINITY, f32::min);
        let th = Vec3::new(x, -min_y, z);
        let scene = Scene {
            world: posed.iter().map(|p| rot * *p + th).collect(),
            canonical: self.clothed.clone(),
            normals: posed_normals.iter().map(|n| rot * *n).collect(),
            surfaces: self.surfaces.clone(),
            faces,
            outfit: self.outfit.clone(),
            light: self.light,
            ambient: self.ambient,
        };
        let body = FrameBody {
            poses: pose.to_flat(),
            rh,
            th,
        };
        Ok((scene, body))
    }
}

/// [`generate_subject`], rendering only the frames in `only` (indices into the full camera
/// layout; `None`: all). The subject (shape, outfit, pose or motion, every camera) is the same
/// whatever frames are rendered: a training stream that needs four of the 64 views pays for four.
pub fn generate_subject_frames(
    template: &BodyTemplate,
    cfg: &SynthConfig,
    seed: u64,
    index: usize,
    name: &str,
    val_inputs: Option<usize>,
    only: Option<&[usize]>,
) -> Result<SyntheticSubject> {
    let rng = Rng::new(seed).fork(index as u64);
    // The variety draws come from a fork of their own, so a config without variety draws the
    // same people as before it existed.
    let mut variety = rng.fork(STREAM_VARIETY);
    // The stream's variety, for its share of the subjects (the written split has none).
    let (range, shading, prints, inset) = match cfg.stream_variety {
        Some(v) if variety.uniform() < f64::from(v.share) => {
            (Some(v.camera_radius), v.shading, v.prints, v.template_inset)
        }
        v => (
            cfg.camera_radius_range,
            cfg.shading,
            StreamPrints::Split,
            match v {
                Some(v) if v.template_inset_subjects == InsetSubjects::All => v.template_inset,
                _ => [0.0; 2],
            },
        ),
    };
    let cfg = SynthConfig {
        camera_radius: match range {
            Some([near, far]) => variety.range(f64::from(near), f64::from(far)) as f32,
            None => cfg.camera_radius,
        },
        shading,
        stream_variety: None,
        ..cfg.clone()
    };
    let mut rng = rng;
    let mut person = Person::sample(template, &cfg, Family::Stream, name, &mut rng)?;
    if cfg.shading == Shading::RandomLight {
        person.light = random_light(&mut variety, (25.0, 80.0));
        person.ambient = variety.range(0.3, 0.6) as f32;
    }
    // After the light's draws, so that adding prints leaves a varied person's camera and light.
    if prints == StreamPrints::More {
        for garment in [Surface::Top, Surface::Bottom] {
            if variety.uniform() < 0.5 {
                person.outfit.materials[garment as usize] =
                    texture::Material::more_cloth(&mut variety);
            }
        }
    }
    // Last of all, so that the inset changes the template only, never the pictures.
    if inset != [0.0; 2] {
        let depth = variety.range(f64::from(inset[0]), f64::from(inset[1])) as f32;
        inset_template(template, &mut person, depth);
    }
    subject_from(template, &cfg, person, rng, name, val_inputs, only)
}

/// Moves the model's template of `person` (`est_vertices`, what `canonical_joints.pkl` stores)
/// `depth` metres inward along its vertex normals (outward where `depth` is negative), so that
/// the gap between the template and the pictured outline varies by more than the stream's
/// garments alone make it (design.md §8.11). Inward, a vertex moves at most half its distance to
/// its dominant joint, so that fingers, toes and the nose thin out instead of turning inside out.
fn inset_template(template: &BodyTemplate, person: &mut Person, depth: f32) {
    let normals = body::vertex_normals(&person.est_vertices, &template.topology.faces);
    for ((v, n), joint) in person
        .est_vertices
        .iter_mut()
        .zip(normals)
        .zip(dominant_joints(template))
    {
        let radius = person.est_joints.get(joint).map_or(0.0, |j| j.distance(*v));
        *v -= n * depth.min(0.5 * radius);
    }
}

/// Each template vertex's joint of largest skinning weight.
fn dominant_joints(template: &BodyTemplate) -> Vec<usize> {
    template
        .skin
        .joints
        .iter()
        .zip(&template.skin.weights)
        .map(|(j, w)| {
            let best = (0..4).max_by(|&a, &b| w[a].total_cmp(&w[b])).unwrap_or(0);
            j[best] as usize
        })
        .collect()
}

/// Fork key of a stream subject's drawn camera distance and light (design.md §8.11).
const STREAM_VARIETY: u64 = 0x5641_5249_4554_5900;

/// Fork key of the held-out family's subjects (design.md §8.11), kept apart from the split's.
const HELD_OUT_SUBJECTS: u64 = 0x4845_4c44_4f55_5400;

/// Held-out subject `index` (design.md §8.11) in the validation layout with `n_inputs` inputs:
/// a person of [`Family::HeldOut`], rendered at `held_out_scale` times `image_size`, Lambert
/// shaded under its own light, the cameras at 0.85–1.35 times `camera_radius` (1.7–2.7 m for
/// the THuman ring).
pub fn generate_held_out_subject(
    template: &BodyTemplate,
    cfg: &SynthConfig,
    seed: u64,
    index: usize,
    name: &str,
    n_inputs: usize,
) -> Result<SyntheticSubject> {
    let mut rng = Rng::new(seed).fork(HELD_OUT_SUBJECTS).fork(index as u64);
    let render = SynthConfig {
        // 0.85–1.35 times the split's distance: 1.7–2.7 m for the THuman ring's 2 m.
        camera_radius: (f64::from(cfg.camera_radius) * rng.range(0.85, 1.35)) as f32,
        ..cfg.held_out_render()
    };
    let person = Person::sample(template, &render, Family::HeldOut, name, &mut rng)?;
    subject_from(template, &render, person, rng, name, Some(n_inputs), None)
}

/// The frames of `person`, with the pose, cameras and so on drawn from `rng`.
fn subject_from(
    template: &BodyTemplate,
    cfg: &SynthConfig,
    person: Person,
    mut rng: Rng,
    name: &str,
    val_inputs: Option<usize>,
    only: Option<&[usize]>,
) -> Result<SyntheticSubject> {
    let frames = match cfg.setting {
        SynthSetting::MultiView => {
            multi_view_frames(template, cfg, &person, name, val_inputs, only, &mut rng)?
        }
        SynthSetting::MultiFrame => {
            multi_frame_frames(template, cfg, &person, name, val_inputs, only, &mut rng)?
        }
    };
    Ok(SyntheticSubject {
        name: name.to_owned(),
        frames,
        est_joints: person.est_joints,
        est_vertices: person.est_vertices,
    })
}

fn wanted(only: Option<&[usize]>, f: usize) -> bool {
    only.is_none_or(|o| o.contains(&f))
}

/// Multi-view: one random pose, the ring's cameras (module docs, steps 3–5).
fn multi_view_frames(
    template: &BodyTemplate,
    cfg: &SynthConfig,
    person: &Person,
    name: &str,
    val_inputs: Option<usize>,
    only: Option<&[usize]>,
    rng: &mut Rng,
) -> Result<Vec<RenderedFrame>> {
    let pose = body::random_pose(&person.skeleton, &person.outfit, rng);
    let rh = Vec3::new(0.0, rng.uniform() as f32 * std::f32::consts::TAU, 0.0);
    let x = rng.range(-0.05, 0.05) as f32;
    let z = rng.range(-0.05, 0.05) as f32;
    let (scene, body) = person.posed(template, &pose, rh, (x, z), name)?;
    let azimuths = match val_inputs {
        None => train_azimuths(cfg, rng),
        Some(n) => val_azimuths(cfg, n, rng),
    };
    azimuths
        .iter()
        .enumerate()
        .filter(|(f, _)| wanted(only, *f))
        .map(|(f, &az)| {
            let camera = ring_camera(cfg, az)?;
            let (rgb, mask) = scene.render(&camera, cfg.shading, cfg.supersample)?;
            Ok(RenderedFrame {
                name: format!("frame_{f:06}"),
                camera,
                rgb,
                mask,
                body: body.clone(),
            })
        })
        .collect()
}

/// Fork key of a sequence's motion parameters (kept apart from the person's draws).
const MOTION_CHOICES: u64 = 0x4d4f_5449_4f4e;

/// How one person moves through a multi-frame sequence (module docs, "Multi-frame").
struct SequenceMotion {
    motion: Motion,
    roles: JointRoles,
    /// Phase at the first frame, cycles.
    phase: f32,
    /// Cycles over the sequence.
    cycles: f32,
    /// Scale of the motion's arm and leg rotations.
    arms: f32,
    legs: f32,
    /// Heading at the first frame, and the turn over the sequence (radians about y).
    heading: f32,
    turn: f32,
}

impl SequenceMotion {
    fn sample(cfg: &SynthConfig, person: &Person, rng: &Rng, name: &str) -> Result<Self> {
        let mut rng = rng.fork(MOTION_CHOICES);
        let roles = JointRoles::for_skeleton(&person.skeleton).ok_or_else(|| {
            DataError::invalid(
                Location::default().subject(name).field("skeleton"),
                "no hips/knees/shoulders/elbows to move: not an Anny, SMPL or SMPL-X rig",
            )
        })?;
        let motion = Motion::ALL[rng.below(Motion::ALL.len())];
        // A skirt is part of the legs' skin: wide leg swings would tear it.
        let skirt = if person.outfit.bottom.is_skirt() {
            0.5
        } else {
            1.0
        };
        Ok(Self {
            motion,
            roles,
            phase: rng.uniform() as f32,
            cycles: rng.range(0.75, 1.5) as f32,
            arms: rng.range(0.6, 1.0) as f32,
            legs: skirt * rng.range(0.6, 1.0) as f32,
            heading: rng.uniform() as f32 * std::f32::consts::TAU,
            turn: rng.range(-1.0, 1.0) as f32 * cfg.max_turn_deg.to_radians(),
        })
    }

    /// The pose and heading at time `u ∈ [0, 1)` of the sequence: `base` (the person's own
    /// random pose) with the joints the motion moves replaced by the scaled motion.
    fn at(&self, base: &BodyPose, u: f32) -> (BodyPose, Vec3) {
        let j = base.num_joints();
        let m = self
            .motion
            .pose(&self.roles, j, self.phase + self.cycles * u);
        // The joints this motion moves at some point of its cycle.
        let moved = |joint: usize| {
            (0..4).any(|q| {
                self.motion
                    .pose(&self.roles, j, q as f32 / 4.0)
                    .joint_rotations[joint]
                    != Vec3::ZERO
            })
        };
        let mut pose = base.clone();
        let r = &self.roles;
        for (joints, scale) in [
            (r.hips, self.legs),
            (r.knees, self.legs),
            (r.shoulders, self.arms),
            (r.elbows, self.arms),
        ] {
            for joint in joints {
                if joint < j && moved(joint) {
                    pose.joint_rotations[joint] = m.joint_rotations[joint] * scale;
                }
            }
        }
        let rh = Vec3::new(0.0, self.heading + self.turn * u, 0.0);
        (pose, rh)
    }
}

/// Multi-frame: the person moves through a procedural motion (module docs, "Multi-frame").
/// Training subjects: `sequence_frames` frames, all from one camera. Validation subjects: the N
/// inputs from that camera, spread over the sequence, then `val_target_views` targets at other
/// times (other poses) from cameras spread around the person (other views), as AIST++ scores
/// cameras 2–7 given frames of camera 1.
fn multi_frame_frames(
    template: &BodyTemplate,
    cfg: &SynthConfig,
    person: &Person,
    name: &str,
    val_inputs: Option<usize>,
    only: Option<&[usize]>,
    rng: &mut Rng,
) -> Result<Vec<RenderedFrame>> {
    let base = body::random_pose(&person.skeleton, &person.outfit, rng);
    let x = rng.range(-0.05, 0.05) as f32;
    let z = rng.range(-0.05, 0.05) as f32;
    let motion = SequenceMotion::sample(cfg, person, rng, name)?;
    let camera_az = rng.uniform() as f32 * std::f32::consts::TAU;
    // (time in the sequence, camera azimuth) of every frame.
    let layout: Vec<(f32, f32)> = match val_inputs {
        None => {
            let f = cfg.sequence_frames;
            (0..f).map(|k| (k as f32 / f as f32, camera_az)).collect()
        }
        Some(n) => {
            let targets = cfg.val_target_views;
            let gap = std::f32::consts::TAU / (targets + 1) as f32;
            let inputs = (0..n).map(|k| (k as f32 / n as f32, camera_az));
            let others: Vec<(f32, f32)> = (0..targets)
                .map(|t| {
                    let u = rng.uniform() as f32;
                    let az = camera_az + gap * (t as f32 + 1.0 + rng.range(-0.3, 0.3) as f32);
                    (u, az)
                })
                .collect();
            inputs.chain(others).collect()
        }
    };
    layout
        .iter()
        .enumerate()
        .filter(|(f, _)| wanted(only, *f))
        .map(|(f, &(u, az))| {
            let _span = tracing::trace_span!("sequence_frame", f).entered();
            let (pose, rh) = motion.at(&base, u);
            let (scene, body) = person.posed(template, &pose, rh, (x, z), name)?;
            let camera = ring_camera(cfg, az)?;
            let (rgb, mask) = scene.render(&camera, cfg.shading, cfg.supersample)?;
            Ok(RenderedFrame {
                name: format!("frame_{f:06}"),
                camera,
                rgb,
                mask,
                body,
            })
        })
        .collect()
}

fn f32_array(shape: Vec<usize>, values: impl IntoIterator<Item = f32>) -> Value {
    Value::Array(NdArray {
        dtype: DType::F32,
        shape,
        elements: Elements::Float(values.into_iter().map(f64::from).collect()),
    })
}

fn i64_array(shape: Vec<usize>, values: impl IntoIterator<Item = i64>) -> Value {
    Value::Array(NdArray {
        dtype: DType::I64,
        shape,
        elements: Elements::Int(values.into_iter().collect()),
    })
}

fn key(s: &str) -> Value {
    Value::Str(s.to_owned())
}

fn vec3_array(v: &[Vec3]) -> Value {
    f32_array(vec![v.len(), 3], v.iter().flat_map(|p| p.to_array()))
}

/// Writes `subject` into `dir/<name>/` in the official layout.
pub fn write_subject(
    template: &BodyTemplate,
    subject: &SyntheticSubject,
    dir: &Path,
) -> Result<()> {
    let root = dir.join(&subject.name);
    let io = |path: &Path, e: std::io::Error| {
        DataError::io(Location::file(path).subject(&subject.name), e)
    };
    for sub in ["images", "masks"] {
        let p = root.join(sub);
        std::fs::create_dir_all(&p).map_err(|e| io(&p, e))?;
    }
    let mut cameras = Vec::new();
    let mut infos = Vec::new();
    let body = subject.canonical_body(template);
    let j = body.num_joints();
    for frame in &subject.frames {
        let (w, h) = (frame.camera.width, frame.camera.height);
        let img_path = root.join("images").join(format!("{}.png", frame.name));
        let save_err = |path: &Path, e: image::ImageError| DataError::Image {
            location: Box::new(
                Location::file(path)
                    .subject(&subject.name)
                    .frame(&frame.name),
            ),
            reason: format!("cannot write PNG: {e}"),
        };
        // By rename: regenerating a split on a full disk leaves each old picture whole.
        write_png(&img_path, &frame.rgb, w, h, image::ExtendedColorType::Rgb8)
            .map_err(|e| save_err(&img_path, e))?;
        let mask_path = root.join("masks").join(format!("{}.png", frame.name));
        write_png(&mask_path, &frame.mask, w, h, image::ExtendedColorType::L8)
            .map_err(|e| save_err(&mask_path, e))?;
        let camera = frame.frame_camera();
        let info = subject.mesh_info(frame);
        // Exact: the entries are f32 values widened to f64.
        let k: Vec<f32> = camera.k.iter().flatten().map(|&v| v as f32).collect();
        let e: Vec<f32> = camera.e.iter().flatten().map(|&v| v as f32).collect();
        cameras.push((
            key(&frame.name),
            Value::Dict(vec![
                (key("intrinsics"), f32_array(vec![3, 3], k)),
                (key("extrinsics"), f32_array(vec![4, 4], e)),
            ]),
        ));
        infos.push((
            key(&frame.name),
            Value::Dict(vec![
                (
                    key("poses"),
                    f32_array(vec![3 * j], info.poses.iter().copied()),
                ),
                (key("tpose_joints"), vec3_array(&info.tpose_joints)),
                (key("Rh"), f32_array(vec![3], info.rh.to_array())),
                (key("Th"), f32_array(vec![3], info.th.to_array())),
            ]),
        ));
    }
    pickle::save(&root.join("cameras.pkl"), &Value::Dict(cameras))?;
    pickle::save(&root.join("mesh_infos.pkl"), &Value::Dict(infos))?;
    let canonical = Value::Dict(vec![
        (key("joints"), vec3_array(&body.joints)),
        (key("vertex"), vec3_array(&body.vertices)),
        (
            key("weights"),
            f32_array(vec![body.vertices.len(), j], body.weights.iter().copied()),
        ),
        (
            key("faces"),
            i64_array(
                vec![body.faces.len(), 3],
                body.faces.iter().flatten().map(|&i| i64::from(i)),
            ),
        ),
        (
            key("parents"),
            i64_array(vec![j], body.parents.iter().map(|&p| i64::from(p))),
        ),
        (
            key("joint_names"),
            Value::List(template.skeleton.names.iter().map(|n| key(n)).collect()),
        ),
    ]);
    pickle::save(&root.join("canonical_joints.pkl"), &canonical)
}

/// Summary of a generated split.
#[derive(Debug, Clone, PartialEq)]
pub struct SplitSummary {
    /// Training subject names.
    pub train: Vec<String>,
    /// Validation subject names.
    pub val: Vec<String>,
    /// Held-out subject names (design.md §8.11).
    pub held_out: Vec<String>,
    /// Frames written.
    pub frames: usize,
}

/// Generates the whole split under `out` (the dataset root): `data.train_dir`, `data.val_dir`,
/// the split JSONs and `<val_dir>_meta.json`. `progress` is called once per finished subject.
pub fn generate_split(
    cfg: &SynthConfig,
    data: &DataConfig,
    out: &Path,
    seed: u64,
    progress: &(dyn Fn() + Sync),
) -> Result<SplitSummary> {
    let template = BodyTemplate::load(cfg.template.path())
        .map_err(|e| DataError::render(Location::file(cfg.template.path()), e))?;
    // The stream's variety is the stream's: the split on disk is drawn without it.
    let cfg = &SynthConfig {
        stream_variety: None,
        ..cfg.clone()
    };
    let (train_names, val_names) = cfg.subject_names();
    let names: Vec<String> = train_names.iter().chain(&val_names).cloned().collect();
    let n = data.n_input_frames;
    let frames: usize = names
        .par_iter()
        .enumerate()
        .map(|(i, name)| {
            let (val, dir) = if i < cfg.train_subjects {
                (None, out.join(&data.train_dir))
            } else {
                (Some(n), out.join(&data.val_dir))
            };
            let subject = generate_subject(&template, cfg, seed, i, name, val)?;
            write_subject(&template, &subject, &dir)?;
            progress();
            Ok(subject.frames.len())
        })
        .collect::<Result<Vec<_>>>()?
        .iter()
        .sum();
    let (train, val) = names.split_at(cfg.train_subjects);
    let frames = frames + generate_held_out_split(&template, cfg, data, out, seed, progress)?;
    write_json(out.join(&data.train_split), serde_json::json!(train))?;
    // A config whose validation subjects are listed in `[data] val_subjects` may share one
    // split file with training (as the AIST++ experiment does): it holds the training list.
    if data.val_split != data.train_split {
        write_json(out.join(&data.val_split), serde_json::json!(val))?;
    }
    let meta_name = format!("{}_meta.json", data.val_dir.display());
    write_json(out.join(meta_name), split_meta(val, n))?;
    Ok(SplitSummary {
        train: train.to_vec(),
        val: val.to_vec(),
        held_out: if data.held_out().is_some() {
            cfg.held_out_names()
        } else {
            Vec::new()
        },
        frames,
    })
}

/// Writes the held-out subjects (design.md §8.11) into `data.held_out_dir` with their split
/// file; returns the frames written (none when the config asks for none).
fn generate_held_out_split(
    template: &BodyTemplate,
    cfg: &SynthConfig,
    data: &DataConfig,
    out: &Path,
    seed: u64,
    progress: &(dyn Fn() + Sync),
) -> Result<usize> {
    let Some(held) = data.held_out().filter(|_| cfg.held_out_subjects > 0) else {
        return Ok(0);
    };
    let names = cfg.held_out_names();
    let dir = out.join(&held.val_dir);
    let n = data.n_input_frames;
    let frames: usize = names
        .par_iter()
        .enumerate()
        .map(|(i, name)| {
            let subject = generate_held_out_subject(template, cfg, seed, i, name, n)?;
            write_subject(template, &subject, &dir)?;
            progress();
            Ok(subject.frames.len())
        })
        .collect::<Result<Vec<_>>>()?
        .iter()
        .sum();
    write_json(out.join(&held.val_split), serde_json::json!(names))?;
    let meta_name = format!("{}_meta.json", held.val_dir.display());
    write_json(out.join(meta_name), split_meta(&names, n))?;
    Ok(frames)
}

/// Writes `value` as pretty JSON to `path` by rename, creating its folder.
fn write_json(path: PathBuf, value: serde_json::Value) -> Result<()> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|e| DataError::io(Location::file(parent), e))?;
    }
    let text = serde_json::to_string_pretty(&value).unwrap_or_default();
    lifegom_render::atomic_file::write_atomic(&path, text.as_bytes())
        .map_err(|e| DataError::write(Location::file(&path), e))
}

/// The `<split>_meta.json` list of validation subjects: each one's N inputs and its first target.
fn split_meta(subjects: &[String], n_inputs: usize) -> serde_json::Value {
    subjects
        .iter()
        .map(|s| serde_json::json!({"scene": s, "input_frames": (0..n_inputs).collect::<Vec<_>>(), "output_frame": n_inputs}))
        .collect()
}

/// A contact sheet of generated subjects: per subject, `views` images then their masks, in one
/// row; `dir` is a split folder. Returns `(width, height, rgb8)`.
pub fn contact_sheet(
    dir: &Path,
    subjects: &[String],
    views: &[usize],
) -> Result<(u32, u32, Vec<u8>)> {
    let mut tiles: Vec<Vec<image::RgbImage>> = Vec::new();
    for s in subjects {
        let mut row = Vec::new();
        for sub in ["images", "masks"] {
            for &v in views {
                let path = dir.join(s).join(sub).join(format!("frame_{v:06}.png"));
                let loc = Location::file(&path).subject(s);
                let img = image::open(&path).map_err(|e| DataError::Image {
                    location: Box::new(loc),
                    reason: e.to_string(),
                })?;
                row.push(img.to_rgb8());
            }
        }
        tiles.push(row);
    }
    let (tw, th) = tiles
        .first()
        .and_then(|r| r.first())
        .map_or((0, 0), |t| (t.width(), t.height()));
    let cols = tiles.first().map_or(0, Vec::len) as u32;
    let (w, h) = (cols * tw, tiles.len() as u32 * th);
    let mut sheet = image::RgbImage::new(w, h);
    for (r, row) in tiles.iter().enumerate() {
        for (c, t) in row.iter().enumerate() {
            image::imageops::replace(
                &mut sheet,
                t,
                (c as u32 * tw) as i64,
                (r as u32 * th) as i64,
            );
        }
    }
    Ok((w, h, sheet.into_raw()))
}
