//! Retargeting: an SMPL pose sequence (capture data such as AIST++) played on the Anny rig.
//!
//! Both rigs pose their joints with axis-angle rotations about joint frames that are aligned
//! with the world axes at rest (SMPL by construction; lifegom's skeletons by design,
//! [`crate::skeleton`]), in the same canonical axes (y up, body facing +z, the body's left
//! along +x), and both rest in a T-pose. A rotation of an SMPL joint therefore means the same
//! motion of the limb below it when it is given to the Anny joint at the top of the same limb:
//! the rotation of the SMPL left hip goes to `upperleg01.L`, and the Anny joints between that
//! one and the next mapped one (`upperleg02.L`) stay at rest, so they turn with it.
//!
//! What is lost, by construction: the SMPL toes (`left_foot`, `right_foot`) and hands
//! (`left_hand`, `right_hand`) drive nothing (the Anny toes and fingers stay at rest); SMPL's
//! three spine joints drive three of Anny's five spine joints; and the joints' positions differ
//! between the two bodies (limb lengths, shoulder width), so a pose that touches (hands
//! together, a foot on the ground) may not touch after retargeting. The root translation is
//! kept as it is, in metres.

use crate::error::{RenderError, Result};
use crate::motion::{PoseSequence, SMPL_JOINT_NAMES};
use crate::skeleton::{BodyPose, Skeleton};

/// SMPL joint → the Anny joint that takes its rotation (module docs). SMPL joints not listed
/// drive nothing.
pub const SMPL_TO_ANNY: [(&str, &str); 20] = [
    ("pelvis", "root"),
    ("left_hip", "upperleg01.L"),
    ("right_hip", "upperleg01.R"),
    ("spine1", "spine05"),
    ("left_knee", "lowerleg01.L"),
    ("right_knee", "lowerleg01.R"),
    ("spine2", "spine03"),
    ("left_ankle", "foot.L"),
    ("right_ankle", "foot.R"),
    ("spine3", "spine01"),
    ("neck", "neck01"),
    ("left_collar", "clavicle.L"),
    ("right_collar", "clavicle.R"),
    ("head", "head"),
    ("left_shoulder", "upperarm01.L"),
    ("right_shoulder", "upperarm01.R"),
    ("left_elbow", "lowerarm01.L"),
    ("right_elbow", "lowerarm01.R"),
    ("left_wrist", "wrist.L"),
    ("right_wrist", "wrist.R"),
];

/// Whether `seq` is written for SMPL: 24 joints, named SMPL's way or not named.
fn is_smpl(seq: &PoseSequence) -> bool {
    seq.num_joints() == SMPL_JOINT_NAMES.len()
        && seq
            .joint_names
            .as_ref()
            .is_none_or(|names| names.iter().zip(SMPL_JOINT_NAMES).all(|(a, b)| a == b))
}

/// `Some(seq retargeted to skeleton)` when `seq` is an SMPL sequence and `skeleton` the Anny rig
/// (it has every joint of [`SMPL_TO_ANNY`]) and they differ in joint count; `None` when no
/// retargeting applies (the caller then checks the sequence against the rig as it is).
pub fn retarget_if_needed(seq: &PoseSequence, skeleton: &Skeleton) -> Result<Option<PoseSequence>> {
    if seq.num_joints() == skeleton.num_joints() || !is_smpl(seq) {
        return Ok(None);
    }
    let Some(pairs) = anny_pairs(skeleton) else {
        return Ok(None);
    };
    let poses = seq
        .poses()
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            if pose.num_joints() != SMPL_JOINT_NAMES.len() {
                return Err(RenderError::Motion {
                    path: seq.source.clone(),
                    field: format!("frames[{k}]"),
                    reason: format!(
                        "{} joints, an SMPL frame has {}",
                        pose.num_joints(),
                        SMPL_JOINT_NAMES.len()
                    ),
                });
            }
            let mut out = BodyPose::rest(skeleton.num_joints());
            for &(from, to) in &pairs {
                out.joint_rotations[to] = pose.joint_rotations[from];
            }
            Ok(out)
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Some(PoseSequence {
        source: seq.source.clone(),
        fps: seq.fps,
        joint_names: Some(skeleton.names.clone()),
        poses,
        root_translations: seq.root_translations.clone(),
    }))
}

/// `(SMPL index, Anny index)` of every pair of [`SMPL_TO_ANNY`], or `None` if `skeleton` lacks
/// one of the Anny joints.
fn anny_pairs(skeleton: &Skeleton) -> Option<Vec<(usize, usize)>> {
    SMPL_TO_ANNY
        .iter()
        .map(|(from, to)| {
            let from = SMPL_JOINT_NAMES.iter().position(|n| n == from)?;
            Some((from, skeleton.joint_index(to)?))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::template::{BodyTemplate, lowres_template_path};
    use glam::Vec3;

    /// The retargeted pose moves the Anny limbs the SMPL pose moves, the same way: the left
    /// knee bent by SMPL bends `lowerleg01.L` by the same rotation, and the joints below follow.
    #[test]
    fn smpl_rotations_land_on_the_anny_limbs_and_nothing_else() {
        let anny = BodyTemplate::load(lowres_template_path()).unwrap().skeleton;
        // The two rigs agree on which side is left (+x).
        for side in ["upperleg01.L", "upperarm01.L", "clavicle.L"] {
            assert!(
                anny.rest_joints[anny.joint_index(side).unwrap()].x > 0.0,
                "{side}"
            );
        }
        let mut pose = BodyPose::rest(24);
        let knee = SMPL_JOINT_NAMES
            .iter()
            .position(|n| *n == "left_knee")
            .unwrap();
        let hand = SMPL_JOINT_NAMES
            .iter()
            .position(|n| *n == "left_hand")
            .unwrap();
        pose.joint_rotations[knee] = Vec3::new(1.2, 0.0, 0.0);
        pose.joint_rotations[hand] = Vec3::new(0.0, 0.7, 0.0);
        let seq = PoseSequence {
            source: "capture.pkl".into(),
            fps: 60.0,
            joint_names: Some(SMPL_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect()),
            poses: vec![pose.clone(), BodyPose::rest(24)],
            root_translations: Some(vec![Vec3::ZERO, Vec3::new(0.0, 0.0, 0.1)]),
        };
        let out = retarget_if_needed(&seq, &anny).unwrap().unwrap();
        out.validate_for(&anny).unwrap();
        assert_eq!(out.len(), 2);
        assert_eq!(out.root_translations, seq.root_translations);
        let moved: Vec<&str> = out.poses()[0]
            .joint_rotations
            .iter()
            .enumerate()
            .filter(|(_, r)| **r != Vec3::ZERO)
            .map(|(j, _)| anny.names[j].as_str())
            .collect();
        assert_eq!(moved, ["lowerleg01.L"], "the SMPL hand drives nothing");
        // The ankle follows the knee: rotated about the knee's head by the same rotation.
        let m = anny.skinning_transforms(&out.poses()[0]).unwrap();
        let (k, a) = (
            anny.joint_index("lowerleg01.L").unwrap(),
            anny.joint_index("foot.L").unwrap(),
        );
        let (knee_at, ankle_at) = (anny.rest_joints[k], anny.rest_joints[a]);
        let expected =
            knee_at + glam::Quat::from_scaled_axis(Vec3::new(1.2, 0.0, 0.0)) * (ankle_at - knee_at);
        let posed = m[a].transform_point3(ankle_at);
        assert!((posed - expected).length() < 1e-4, "{posed} vs {expected}");
    }

    #[test]
    fn only_smpl_sequences_on_the_anny_rig_are_retargeted() {
        let anny = BodyTemplate::load(lowres_template_path()).unwrap().skeleton;
        let seq = |joints: usize, names: Option<Vec<String>>| PoseSequence {
            source: "m.json".into(),
            fps: 30.0,
            joint_names: names,
            poses: vec![BodyPose::rest(joints)],
            root_translations: None,
        };
        assert!(retarget_if_needed(&seq(24, None), &anny).unwrap().is_some());
        let wrong_names = Some((0..24).map(|j| format!("j{j}")).collect());
        assert!(
            retarget_if_needed(&seq(24, wrong_names), &anny)
                .unwrap()
                .is_none()
        );
        assert!(retarget_if_needed(&seq(55, None), &anny).unwrap().is_none());
        assert!(
            retarget_if_needed(&seq(104, None), &anny)
                .unwrap()
                .is_none()
        );
        let other = Skeleton::new(
            (0..30).map(|j| format!("j{j}")).collect(),
            (0..30).map(|j: usize| j.checked_sub(1)).collect(),
            vec![Vec3::ZERO; 30],
        )
        .unwrap();
        assert!(
            retarget_if_needed(&seq(24, None), &other)
                .unwrap()
                .is_none()
        );
    }
}
