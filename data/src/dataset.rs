//! Splits, frame-indexing rules and per-sample loading (design.md §8.3–§8.6): what train and eval
//! iterate over.
//!
//! # Frame-indexing rules ([`Protocol`] × [`Split`])
//!
//! | protocol / split | samples per subject | inputs | target |
//! |---|---|---|---|
//! | THuman view3 and XHuman, train | 48 | `i0 ~ U{0..15}`, `i_{k+1} = (i_k + {5 or 6}) mod 16` | `16 + s` |
//! | THuman view3 and XHuman, val | N (3) | `0..N` | `N + s` |
//! | THuman view5 (train and val), AIST++ val | `frames − N` | `0..N` | `N + s` |
//! | AIST++ train | `frames` | N distinct random frames ≠ target | `s` |
//!
//! Sample `i` of a split maps to (subject, sample-in-subject `s`) by walking the subjects in
//! split order. Random choices (ring start and steps, AIST++ inputs, a random background) come
//! from the caller's [`Rng`], so a training loop controls reproducibility with its seed.
//!
//! # Backgrounds
//!
//! One colour per sample, shared by the inputs and the target: uniform in `[0, 255)³` when
//! [`Background::Random`] (THuman training), the configured colour otherwise (black for
//! THuman/XHuman test, white for AIST++).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{DataError, Location, Result};
use crate::format::{FrameCamera, FrameMeshInfo, Subject, read_split};
use crate::kinematics::KinematicTree;
use crate::preprocess::{self, FloatImage, Kernel, Resampling, ResizeMode};
use lifegom_render::rng::Rng;

/// Which experiment's frame-indexing rules apply (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Protocol {
    /// THuman2.0, 3 source views (official `datasets/thuman_view3.py`; design.md §8.4).
    ThumanView3,
    /// THuman2.0, 5 source views (official `datasets/thuman_view5.py`; design.md §8.4).
    ThumanView5,
    /// XHuman evaluation: the view3 rules on `xhuman/view3_val`.
    Xhuman,
    /// AIST++ (official `datasets/aistpp.py` for val, the default dataset for train; design.md §8.4).
    Aistpp,
}

/// Training or evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    /// Training split, random choices enabled.
    Train,
    /// Validation / test split, deterministic.
    Val,
}

/// Background colour policy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Background {
    /// A uniform random colour per sample.
    Random,
    /// A fixed colour, 0..255.
    Fixed([u8; 3]),
}

impl Background {
    /// One sample's colour in the 0..255 domain (`Random` draws three uniforms from `rng`).
    pub fn draw(self, rng: &mut Rng) -> [f32; 3] {
        match self {
            Self::Random => [0, 1, 2].map(|_| rng.range(0.0, 255.0) as f32),
            Self::Fixed(c) => c.map(f32::from),
        }
    }
}

/// The data section of an experiment config (`[data]` in `configs/*.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataConfig {
    /// Dataset root (`data/thuman2.0`); the paths below are relative to it.
    pub root: PathBuf,
    /// Frame-indexing rules.
    pub protocol: Protocol,
    /// SMPL, SMPL-X or the tree stored in the data.
    pub kinematic_tree: KinematicTree,
    /// Folder of the training subjects, relative to `root` (`view3_train`).
    pub train_dir: PathBuf,
    /// Training split file, relative to `root` (`train.json`).
    pub train_split: PathBuf,
    /// Folder of the validation subjects (`view3_val`).
    pub val_dir: PathBuf,
    /// Validation split file (`val.json`).
    pub val_split: PathBuf,
    /// Explicit validation subject list; overrides `val_split` (AIST++ lists `d16_val..d20_val`
    /// in its experiment file).
    #[serde(default)]
    pub val_subjects: Option<Vec<String>>,
    /// Output image size `[W, H]`.
    pub img_size: [u32; 2],
    /// Source views per sample, N.
    pub n_input_frames: usize,
    /// Background during training.
    pub train_background: Background,
    /// Background during evaluation.
    pub test_background: Background,
    /// How images larger than `img_size` are shrunk (design.md §8.3): `"anti_aliased"` (the
    /// default) or `"reference"` (`cv2.resize` exactly, for bit-exact comparisons with the
    /// official pipeline).
    #[serde(default)]
    pub resize: ResizeMode,
    /// Folder of a second validation set, of people the training data does not resemble
    /// (design.md §8.11; the synthetic generator's held-out family). Validated and reported
    /// beside `val_dir` wherever that is, when set together with `held_out_split`.
    #[serde(default)]
    pub held_out_dir: Option<PathBuf>,
    /// Split file of the held-out set.
    #[serde(default)]
    pub held_out_split: Option<PathBuf>,
}

impl DataConfig {
    /// The held-out validation set as a config whose validation split is it (so every reader
    /// of `Split::Val` reads it unchanged), or `None` when the config names none.
    pub fn held_out(&self) -> Option<Self> {
        let (dir, split) = (self.held_out_dir.clone()?, self.held_out_split.clone()?);
        Some(Self {
            val_dir: dir,
            val_split: split,
            val_subjects: None,
            held_out_dir: None,
            held_out_split: None,
            ..self.clone()
        })
    }

    /// The subject folder and split file of `split`.
    pub fn split_paths(&self, split: Split) -> (PathBuf, PathBuf) {
        match split {
            Split::Train => (
                self.root.join(&self.train_dir),
                self.root.join(&self.train_split),
            ),
            Split::Val => (
                self.root.join(&self.val_dir),
                self.root.join(&self.val_split),
            ),
        }
    }

    /// Checks settings that serde cannot.
    pub fn validate(&self, source: &Path) -> Result<()> {
        let bad = |field: &str, reason: String| DataError::Config {
            location: Box::new(Location::file(source).field(format!("data.{field}"))),
            reason,
        };
        if self.held_out_dir.is_some() != self.held_out_split.is_some() {
            return Err(bad(
                "held_out_dir",
                "held_out_dir and held_out_split go together: set both or neither".into(),
            ));
        }
        if self.img_size.contains(&0) {
            return Err(bad(
                "img_size",
                format!("must be positive, got {:?}", self.img_size),
            ));
        }
        if self.img_size.iter().any(|&side| side > MAX_IMAGE_SIDE) {
            return Err(bad(
                "img_size",
                format!(
                    "at most {MAX_IMAGE_SIDE} pixels a side, got {:?} (one view in f32 RGB would \
                     take {:.1} GB)",
                    self.img_size,
                    view_bytes(self.img_size) as f64 / 1e9
                ),
            ));
        }
        if self.n_input_frames == 0 {
            return Err(bad("n_input_frames", "must be at least 1".into()));
        }
        if matches!(self.protocol, Protocol::ThumanView3 | Protocol::Xhuman)
            && self.n_input_frames > 16
        {
            return Err(bad(
                "n_input_frames",
                "the ring of source views has 16 frames".into(),
            ));
        }
        Ok(())
    }
}

/// The largest image side a config may ask for: a view of 8,192² pixels is 0.8 GB as f32 RGB,
/// and a training sample holds N + 1 of them with their renders. Checked before anything is
/// allocated, so that a typo is an error naming the field rather than an aborted allocation.
pub const MAX_IMAGE_SIDE: u32 = 8192;

/// Bytes of one `[w, h]` view in f32 RGB.
fn view_bytes([w, h]: [u32; 2]) -> u64 {
    u64::from(w) * u64::from(h) * 3 * 4
}

/// One sample's frames: indices into the subject's frame list.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SampleIndex {
    /// Subject index in the split.
    pub subject: usize,
    /// Source frames, N.
    pub inputs: Vec<usize>,
    /// Target frame.
    pub target: usize,
}

/// The frame rule of a protocol and split (module docs), independent of any files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameRule {
    /// The protocol.
    pub protocol: Protocol,
    /// The split.
    pub split: Split,
    /// N.
    pub n_inputs: usize,
}

/// THuman view3 training: 16 source frames on the ring, 48 targets after them.
pub const RING_FRAMES: usize = 16;
/// THuman view3 training targets per subject.
pub const RING_TARGETS: usize = 48;

impl FrameRule {
    /// Samples a subject with `num_frames` frames contributes (0 if it has too few frames).
    pub fn samples_per_subject(&self, num_frames: usize) -> usize {
        let n = self.n_inputs;
        match (self.protocol, self.split) {
            (Protocol::ThumanView3 | Protocol::Xhuman, Split::Train) => {
                if num_frames >= RING_FRAMES + RING_TARGETS {
                    RING_TARGETS
                } else {
                    0
                }
            }
            (Protocol::ThumanView3 | Protocol::Xhuman, Split::Val) => {
                if num_frames >= 2 * n {
                    n
                } else {
                    0
                }
            }
            (Protocol::ThumanView5, _) | (Protocol::Aistpp, Split::Val) => {
                num_frames.saturating_sub(n)
            }
            (Protocol::Aistpp, Split::Train) => {
                if num_frames > n {
                    num_frames
                } else {
                    0
                }
            }
        }
    }

    /// Minimum frame count a subject needs under this rule.
    pub fn min_frames(&self) -> usize {
        let n = self.n_inputs;
        match (self.protocol, self.split) {
            (Protocol::ThumanView3 | Protocol::Xhuman, Split::Train) => RING_FRAMES + RING_TARGETS,
            (Protocol::ThumanView3 | Protocol::Xhuman, Split::Val) => 2 * n,
            _ => n + 1,
        }
    }

    /// Inputs and target of sample `s` of a subject with `num_frames` frames.
    pub fn frames(&self, s: usize, num_frames: usize, rng: &mut Rng) -> (Vec<usize>, usize) {
        let n = self.n_inputs;
        match (self.protocol, self.split) {
            (Protocol::ThumanView3 | Protocol::Xhuman, Split::Train) => {
                let mut i = rng.below(RING_FRAMES);
                let mut inputs = Vec::with_capacity(n);
                for _ in 0..n {
                    inputs.push(i);
                    i = (i + 5 + rng.below(2)) % RING_FRAMES;
                }
                (inputs, RING_FRAMES + s)
            }
            (Protocol::Aistpp, Split::Train) => {
                let pool: Vec<usize> = (0..num_frames).filter(|&f| f != s).collect();
                (rng.sample_distinct(&pool, n), s)
            }
            _ => ((0..n).collect(), n + s),
        }
    }
}

/// A preprocessed view: image, alpha and camera at the output size.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    /// Frame name.
    pub frame: String,
    /// `H×W×3` in `[0, 1]`, composited over the sample's background.
    pub rgb: Vec<f32>,
    /// `H×W` alpha in `[0, 1]`.
    pub mask: Vec<f32>,
    /// Intrinsics scaled to the output size.
    pub k: [[f32; 3]; 3],
    /// World→camera extrinsics with the body's global transform folded in:
    /// `E' = E·[R(Rh) | Th]` (design.md §3.4), so points stay in the body frame.
    pub e: [[f32; 4]; 4],
    /// The frame's axis-angle pose, flat `3J`.
    pub poses: Vec<f32>,
    /// The frame's zero-pose joints, `J×3`.
    pub tpose_joints: Vec<[f32; 3]>,
}

/// One training or evaluation sample: N source views and the target (last).
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Subject name.
    pub subject: String,
    /// `scene_<subject>_<target frame>`, the reference's output file stem.
    pub frame_name: String,
    /// The N inputs, then the target.
    pub views: Vec<View>,
    /// Background colour in `[0, 1]`.
    pub bgcolor: [f32; 3],
    /// The subject's canonical vertices (`V↓×3`).
    pub canonical_vertices: Vec<[f32; 3]>,
}

/// A split of subjects with its frame rule: what a data loader iterates over.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// The subjects, in split order.
    pub subjects: Vec<Subject>,
    /// The frame rule.
    pub rule: FrameRule,
    /// Output size `(W, H)`.
    pub img_size: (u32, u32),
    /// How larger images are shrunk to it.
    pub resize: ResizeMode,
    /// Background policy of this split.
    pub background: Background,
    /// Samples before each subject (prefix sums), plus the total at the end.
    offsets: Vec<usize>,
}

impl Dataset {
    /// Opens `split` as described by `config`: reads the split file and every
    /// subject's pickles (images are read per sample).
    pub fn open(config: &DataConfig, split: Split) -> Result<Self> {
        let (dir, split_file) = config.split_paths(split);
        let names = match (&config.val_subjects, split) {
            (Some(list), Split::Val) => list.clone(),
            _ => read_split(&split_file)?,
        };
        let rule = FrameRule {
            protocol: config.protocol,
            split,
            n_inputs: config.n_input_frames,
        };
        let mut subjects = Vec::with_capacity(names.len());
        for name in &names {
            let subject = Subject::load(&dir.join(name), config.kinematic_tree)?;
            if subject.frames.len() < rule.min_frames() {
                return Err(DataError::invalid(
                    Location::file(subject.dir.join("images")).subject(name),
                    format!(
                        "{} frames, but the {:?} {:?} rule needs at least {}",
                        subject.frames.len(),
                        rule.protocol,
                        split,
                        rule.min_frames()
                    ),
                ));
            }
            subjects.push(subject);
        }
        let background = match split {
            Split::Train => config.train_background,
            Split::Val => config.test_background,
        };
        Ok(Self::from_subjects(
            subjects,
            rule,
            (config.img_size[0], config.img_size[1]),
            background,
        )
        .with_resize(config.resize))
    }

    /// The same dataset shrinking larger images by `resize`.
    pub fn with_resize(mut self, resize: ResizeMode) -> Self {
        self.resize = resize;
        self
    }

    /// A dataset over already loaded subjects.
    pub fn from_subjects(
        subjects: Vec<Subject>,
        rule: FrameRule,
        img_size: (u32, u32),
        background: Background,
    ) -> Self {
        let mut offsets = vec![0];
        for s in &subjects {
            let last = *offsets.last().unwrap_or(&0);
            offsets.push(last + rule.samples_per_subject(s.frames.len()));
        }
        Self {
            subjects,
            rule,
            img_size,
            resize: ResizeMode::default(),
            background,
            offsets,
        }
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        *self.offsets.last().unwrap_or(&0)
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Frames of sample `i` (`None` past the end).
    pub fn index(&self, i: usize, rng: &mut Rng) -> Option<SampleIndex> {
        if i >= self.len() {
            return None;
        }
        let subject = self.offsets.partition_point(|&o| o <= i) - 1;
        let s = i - self.offsets[subject];
        let (inputs, target) = self
            .rule
            .frames(s, self.subjects[subject].frames.len(), rng);
        Some(SampleIndex {
            subject,
            inputs,
            target,
        })
    }

    /// Loads and preprocesses sample `i` (module docs); `rng` drives every random choice.
    pub fn sample(&self, i: usize, rng: &mut Rng) -> Result<Sample> {
        let idx = self.index(i, rng).ok_or_else(|| {
            DataError::invalid(
                Location::default(),
                format!("sample {i} out of range ({} samples)", self.len()),
            )
        })?;
        let bg = self.background.draw(rng);
        load_sample(
            &self.subjects[idx.subject],
            &idx.inputs,
            idx.target,
            bg,
            self.img_size,
            self.resize,
        )
    }
}

/// The sample of `subject` with frames `inputs` as sources and `target` last, composited over
/// `bg` (0..255) at `size`: what a split's [`Dataset::sample`] and a lone subject's
/// reconstruction both read.
pub fn load_sample(
    subject: &Subject,
    inputs: &[usize],
    target: usize,
    bg: [f32; 3],
    size: (u32, u32),
    resize: ResizeMode,
) -> Result<Sample> {
    let views = inputs
        .iter()
        .chain(std::iter::once(&target))
        .map(|&f| load_view(subject, f, bg, size, resize))
        .collect::<Result<Vec<_>>>()?;
    Ok(Sample {
        subject: subject.name.clone(),
        frame_name: format!("scene_{}_{}", subject.name, subject.frames[target]),
        views,
        bgcolor: bg.map(|c| c / 255.0),
        canonical_vertices: subject
            .canonical
            .vertices
            .iter()
            .map(|v| v.to_array())
            .collect(),
    })
}

/// The share of a mask's pixels above one half beyond which the mask "covers the whole image".
const FULL_COVER: f64 = 0.995;

/// How many times brighter one view's person may be than another's before
/// [`exposure_warning`] speaks: two stops.
pub const EXPOSURE_RATIO: f32 = 4.0;

/// A warning when the person's mean brightness (Rec. 709 luma over the mask) differs by more than
/// [`EXPOSURE_RATIO`] between two of `views`, naming the darkest and the brightest frame; `None`
/// otherwise. Views of one person from a few sides differ by their clothes' colours; two stops
/// apart is an exposure (or white balance, or a wrong image), which the reconstruction would
/// bake into the avatar's colours.
pub fn exposure_warning(views: &[View]) -> Option<String> {
    let brightness = |v: &View| {
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (px, &a) in v.rgb.chunks_exact(3).zip(&v.mask) {
            if a >= 0.5 {
                sum += f64::from(0.2126 * px[0] + 0.7152 * px[1] + 0.0722 * px[2]);
                n += 1;
            }
        }
        (n > 0).then(|| (sum / n as f64) as f32)
    };
    let lit: Vec<(&str, f32)> = views
        .iter()
        .filter_map(|v| brightness(v).map(|b| (v.frame.as_str(), b)))
        .collect();
    let darkest = lit.iter().min_by(|a, b| a.1.total_cmp(&b.1))?;
    let brightest = lit.iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
    (brightest.1 > EXPOSURE_RATIO * darkest.1.max(1e-3)).then(|| {
        format!(
            "frame `{}` shows the person {:.1} times brighter than frame `{}` (mean luma {:.3} \
             against {:.3}): the views look exposed differently, and the avatar's colours will \
             mix both",
            brightest.0,
            brightest.1 / darkest.1.max(1e-3),
            darkest.0,
            brightest.1,
            darkest.1
        )
    })
}

/// Reads, undistorts, composites and resizes frame `f` of `subject` (design.md §8.3).
pub fn load_view(
    subject: &Subject,
    f: usize,
    bg: [f32; 3],
    size: (u32, u32),
    resize: ResizeMode,
) -> Result<View> {
    let frame = &subject.frames[f];
    let at = |path: &Path, field: &str| {
        Location::file(path)
            .subject(&subject.name)
            .frame(frame)
            .field(field)
    };
    let img_path = subject.image_path(f);
    let mask_path = subject.mask_path(f);
    let rgb = preprocess::read_rgb(&img_path, &at(&img_path, "images"))?;
    let alpha = preprocess::read_mask(&mask_path, &at(&mask_path, "masks"))?;
    if (rgb.width, rgb.height) != (alpha.width, alpha.height) {
        return Err(DataError::Image {
            location: Box::new(at(&mask_path, "masks")),
            reason: format!(
                "image/mask size mismatch: image {}×{}, mask {}×{}",
                rgb.width, rgb.height, alpha.width, alpha.height
            ),
        });
    }
    // A mask that never reaches one half shows no person: empty, or written 0/1 instead of
    // 0/255 (which reads as 1/255, nearly transparent). Either would train or reconstruct an
    // invisible body without a word.
    let peak = alpha.data.iter().fold(0.0f32, |m, &a| m.max(a));
    if peak < 0.5 {
        return Err(DataError::Image {
            location: Box::new(at(&mask_path, "masks")),
            reason: format!(
                "the mask shows no person: its largest value is {} of 255 (masks are 0 for \
                 background and 255 for the person; a 0/1 mask must be scaled to 0/255)",
                (peak * 255.0).round()
            ),
        });
    }
    // A mask that leaves no background is inverted (255 for the background) or not a mask at
    // all; the person never fills a whole photo edge to edge.
    let covered = alpha.data.iter().filter(|&&a| a >= 0.5).count() as f64;
    let cover = covered / alpha.data.len().max(1) as f64;
    if cover > FULL_COVER {
        return Err(DataError::Image {
            location: Box::new(at(&mask_path, "masks")),
            reason: format!(
                "the mask covers the whole image ({:.1} % of its pixels): it shows no background \
                 (masks are 255 for the person and 0 for the background; is it inverted?)",
                100.0 * cover
            ),
        });
    }
    Ok(prepare_view(
        frame,
        rgb,
        alpha,
        &subject.cameras[f],
        &subject.mesh_infos[f],
        bg,
        Resampling { size, mode: resize },
    ))
}

/// Undistorts, composites over `bg` and resizes one frame's image (0..255) and alpha (0..1) of
/// equal size, and folds the body's global transform into its camera (design.md §8.3). The one
/// home of these steps for frames read from disk ([`load_view`]) and frames generated in memory
/// (`synth::stream`).
pub fn prepare_view(
    frame: &str,
    mut rgb: FloatImage,
    mut alpha: FloatImage,
    cam: &FrameCamera,
    info: &FrameMeshInfo,
    bg: [f32; 3],
    to: Resampling,
) -> View {
    let Resampling { size, mode: resize } = to;
    if let Some(d) = &cam.distortion {
        rgb = preprocess::undistort(&rgb, &cam.k, d);
        alpha = preprocess::undistort(&alpha, &cam.k, d);
    }
    preprocess::composite(&mut rgb, &alpha, bg);
    let orig = (rgb.width, rgb.height);
    let rgb = preprocess::resize(&rgb, size.0, size.1, Kernel::Lanczos4, resize);
    let alpha = preprocess::resize(&alpha, size.0, size.1, Kernel::Linear, resize);
    let k = preprocess::scale_intrinsics(cam.k, orig, size);
    let e = fold_body_transform(&cam.e, info.rh, info.th);
    View {
        frame: frame.to_owned(),
        rgb: rgb
            .data
            .iter()
            .map(|v| (v / 255.0).clamp(0.0, 1.0))
            .collect(),
        mask: alpha.data.iter().map(|v| v.clamp(0.0, 1.0)).collect(),
        k: k.map(|r| r.map(|v| v as f32)),
        e,
        poses: info.poses.clone(),
        tpose_joints: info.tpose_joints.iter().map(|j| j.to_array()).collect(),
    }
}

/// `E · [R(rh) | th]` (design.md §3.4), row-major, computed in f64.
pub fn fold_body_transform(e: &[[f64; 4]; 4], rh: glam::Vec3, th: glam::Vec3) -> [[f32; 4]; 4] {
    let r = lifegom_render::skeleton::rodrigues(rh);
    let mut body = [[0.0f64; 4]; 4];
    for (i, row) in body.iter_mut().enumerate().take(3) {
        for (j, v) in row.iter_mut().enumerate().take(3) {
            *v = r.col(j)[i] as f64;
        }
        row[3] = th[i] as f64;
    }
    body[3][3] = 1.0;
    let mut out = [[0.0f32; 4]; 4];
    for i in 0..4 {
        for j in 0..4 {
            out[i][j] = (0..4).map(|k| e[i][k] * body[k][j]).sum::<f64>() as f32;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 2×2 view whose person (the left column) has one grey level and whose background is
    /// white, so only the masked pixels may count.
    fn grey_view(frame: &str, level: f32) -> View {
        View {
            frame: frame.into(),
            rgb: [level, level, level, 1.0, 1.0, 1.0].repeat(2).to_vec(),
            mask: vec![1.0, 0.0, 1.0, 0.0],
            k: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            e: [[0.0; 4]; 4],
            poses: Vec::new(),
            tpose_joints: Vec::new(),
        }
    }

    #[test]
    fn exposure_warning_names_the_darkest_and_brightest_frames() {
        let views = [
            grey_view("front", 0.5),
            grey_view("side", 0.3),
            grey_view("back", 0.1),
        ];
        let warning = exposure_warning(&views).expect("five times brighter");
        for part in ["frame `front`", "frame `back`", "5.0 times brighter"] {
            assert!(warning.contains(part), "`{warning}` lacks `{part}`");
        }
        // Within two stops (and a white background that must not count): no warning.
        assert_eq!(exposure_warning(&views[..2]), None);
        assert_eq!(
            exposure_warning(&[grey_view("a", 0.2), grey_view("b", 0.79)]),
            None
        );
        // No view with a person: nothing to compare.
        let mut empty = grey_view("empty", 0.5);
        empty.mask = vec![0.0; 4];
        assert_eq!(exposure_warning(&[empty]), None);
    }

    fn rule(protocol: Protocol, split: Split, n: usize) -> FrameRule {
        FrameRule {
            protocol,
            split,
            n_inputs: n,
        }
    }

    #[test]
    fn thuman_view3_train_ring() {
        let r = rule(Protocol::ThumanView3, Split::Train, 3);
        assert_eq!(r.samples_per_subject(64), 48);
        assert_eq!(r.samples_per_subject(63), 0);
        let mut rng = Rng::new(3);
        let mut starts = [false; 16];
        for s in 0..48 {
            for _ in 0..20 {
                let (inputs, target) = r.frames(s, 64, &mut rng);
                assert_eq!(target, 16 + s);
                assert_eq!(inputs.len(), 3);
                starts[inputs[0]] = true;
                for w in inputs.windows(2) {
                    let step = (w[1] + 16 - w[0]) % 16;
                    assert!(step == 5 || step == 6, "{inputs:?}");
                }
                // Three distinct views (5+5+6 at most 17 > 16 wraps to a different frame).
                assert!(inputs[0] != inputs[2]);
            }
        }
        assert!(starts.iter().all(|&s| s), "every ring start is drawn");
    }

    #[test]
    fn deterministic_rules() {
        let mut rng = Rng::new(0);
        let v3 = rule(Protocol::ThumanView3, Split::Val, 3);
        assert_eq!(v3.samples_per_subject(6), 3);
        assert_eq!(v3.frames(2, 6, &mut rng), (vec![0, 1, 2], 5));
        let xh = rule(Protocol::Xhuman, Split::Val, 3);
        assert_eq!(xh.frames(0, 6, &mut rng), (vec![0, 1, 2], 3));
        for split in [Split::Train, Split::Val] {
            let v5 = rule(Protocol::ThumanView5, split, 5);
            assert_eq!(v5.samples_per_subject(64), 59);
            assert_eq!(v5.frames(0, 64, &mut rng), (vec![0, 1, 2, 3, 4], 5));
            assert_eq!(v5.frames(58, 64, &mut rng).1, 63);
        }
        let a = rule(Protocol::Aistpp, Split::Val, 5);
        assert_eq!(a.samples_per_subject(100), 95);
        assert_eq!(a.frames(3, 100, &mut rng), (vec![0, 1, 2, 3, 4], 8));
    }

    #[test]
    fn aistpp_train_draws_distinct_inputs_without_the_target() {
        let r = rule(Protocol::Aistpp, Split::Train, 5);
        assert_eq!(r.samples_per_subject(30), 30);
        let mut rng = Rng::new(9);
        for s in 0..30 {
            let (inputs, target) = r.frames(s, 30, &mut rng);
            assert_eq!(target, s);
            assert_eq!(inputs.len(), 5);
            assert!(!inputs.contains(&s));
            let mut d = inputs.clone();
            d.sort();
            d.dedup();
            assert_eq!(d.len(), 5);
        }
    }

    #[test]
    fn folding_the_body_transform() {
        let e = [
            [1.0, 0.0, 0.0, 0.5],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 2.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let f = fold_body_transform(
            &e,
            glam::Vec3::new(0.0, std::f32::consts::FRAC_PI_2, 0.0),
            glam::Vec3::new(0.0, 1.0, 0.0),
        );
        // A body point on +x goes to world -z (rotation about y by 90°), then +Th, then E.
        let p = [1.0f32, 0.0, 0.0, 1.0];
        let c: Vec<f32> = (0..3)
            .map(|i| (0..4).map(|k| f[i][k] * p[k]).sum())
            .collect();
        assert!(
            (c[0] - 0.5).abs() < 1e-4 && (c[1] - 1.0).abs() < 1e-4 && (c[2] - 1.0).abs() < 1e-4,
            "{c:?}"
        );
    }
}
