//! Kinematic trees of the body models the datasets use (design.md §4.5).
//!
//! The official data carries no parent table: the loader knows it from `use_smplx` (SMPL, 24
//! joints, for AIST++; SMPL-X, 55 joints, for THuman2.0 and XHuman). Data on the Anny rig takes
//! its table from one of two places: our synthetic generator stores it as an extra `parents`
//! array in `canonical_joints.pkl` (−1 for the root; the official Python loader ignores unknown
//! keys), while data written by other tools for Anny has no such entry and takes the table of
//! the shipped template (`anny`).

use std::sync::OnceLock;

use lifegom_render::template::{BodyTemplate, lowres_template_path};
use serde::{Deserialize, Serialize};

/// Parent of each SMPL joint (−1: root).
pub const SMPL_PARENTS: [i32; 24] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
];

/// SMPL joint names, in order (one home: the motion files name their joints with them).
pub use lifegom_render::motion::SMPL_JOINT_NAMES;

/// Parent of each SMPL-X joint (−1: root): the 22 body joints as SMPL, jaw and eyes under the
/// head (15), five 3-joint fingers under each wrist (20 left, 21 right) in the order index,
/// middle, pinky, ring, thumb.
pub const SMPLX_PARENTS: [i32; 55] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, // body
    15, 15, 15, // jaw, left eye, right eye
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38, // left hand
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53, // right hand
];

/// Which kinematic tree the poses and joints of a dataset follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum KinematicTree {
    /// SMPL, 24 joints (AIST++).
    Smpl,
    /// SMPL-X, 55 joints (THuman2.0, XHuman).
    Smplx,
    /// The Anny rig's 104 joints, parent table from the shipped template (data on the Anny
    /// body written by other tools, which carries no `parents` entry).
    Anny,
    /// The parent table stored in `canonical_joints.pkl['parents']` (our synthetic Anny data).
    Stored,
}

impl KinematicTree {
    /// The fixed parent table, `Ok(None)` for [`KinematicTree::Stored`]. Only `anny` can fail:
    /// its table is read from the shipped template, and the error says what was missing.
    pub fn fixed_parents(self) -> Result<Option<&'static [i32]>, String> {
        match self {
            Self::Smpl => Ok(Some(&SMPL_PARENTS)),
            Self::Smplx => Ok(Some(&SMPLX_PARENTS)),
            Self::Anny => anny_parents().map(Some),
            Self::Stored => Ok(None),
        }
    }

    /// Number of joints of the fixed trees (`None` for `stored`, or when the Anny template
    /// cannot be read).
    pub fn num_joints(self) -> Option<usize> {
        self.fixed_parents().ok().flatten().map(<[i32]>::len)
    }

    /// The config spelling (`kinematic_tree = "..."`), for error messages.
    pub fn name(self) -> &'static str {
        match self {
            Self::Smpl => "smpl",
            Self::Smplx => "smplx",
            Self::Anny => "anny",
            Self::Stored => "stored",
        }
    }
}

/// The shipped Anny template's parent table, read once. All three templates share the rig, so
/// the smallest one is read.
fn anny_parents() -> Result<&'static [i32], String> {
    static PARENTS: OnceLock<Result<Vec<i32>, String>> = OnceLock::new();
    PARENTS
        .get_or_init(|| {
            let path = lowres_template_path();
            let template = BodyTemplate::load(&path).map_err(|e| {
                format!(
                    "kinematic_tree = \"anny\" needs the shipped template {}: {e}",
                    path.display()
                )
            })?;
            Ok(template
                .skeleton
                .parents
                .iter()
                .map(|p| p.map_or(-1, |p| p as i32))
                .collect())
        })
        .as_deref()
        .map_err(Clone::clone)
}

/// Checks a parent table: one root at least, every parent a valid earlier-or-later joint, no
/// cycle. Returns the parents as `Option<usize>` (the render crate's [`Skeleton`] form).
///
/// [`Skeleton`]: lifegom_render::skeleton::Skeleton
pub fn parents_as_options(parents: &[i32]) -> Result<Vec<Option<usize>>, String> {
    let n = parents.len();
    let out: Vec<Option<usize>> = parents
        .iter()
        .enumerate()
        .map(|(i, &p)| match p {
            -1 => Ok(None),
            p if p >= 0 && (p as usize) < n && p as usize != i => Ok(Some(p as usize)),
            p => Err(format!("joint {i} has invalid parent {p} ({n} joints)")),
        })
        .collect::<Result<_, _>>()?;
    if n > 0 && out.iter().all(Option::is_some) {
        return Err("no root joint (parent −1)".into());
    }
    for start in 0..n {
        let (mut j, mut steps) = (start, 0);
        while let Some(p) = out[j] {
            steps += 1;
            if steps > n {
                return Err(format!("joint {start} is on a parent cycle"));
            }
            j = p;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fixed_trees_are_valid_forests_with_one_root() {
        for tree in [KinematicTree::Smpl, KinematicTree::Smplx] {
            let parents = tree.fixed_parents().unwrap().unwrap();
            let opts = parents_as_options(parents).unwrap();
            assert_eq!(opts.iter().filter(|p| p.is_none()).count(), 1);
            // Parents precede children in both standard orders.
            assert!(parents.iter().enumerate().all(|(i, &p)| p < i as i32));
        }
        assert_eq!(KinematicTree::Smpl.num_joints(), Some(24));
        assert_eq!(KinematicTree::Smplx.num_joints(), Some(55));
        // SMPL-X body joints are SMPL's first 22.
        assert_eq!(SMPLX_PARENTS[..22], SMPL_PARENTS[..22]);
        // Jaw and eyes hang off the head; fingers off the wrists.
        assert_eq!(SMPLX_PARENTS[22..25], [15, 15, 15]);
        assert_eq!(SMPLX_PARENTS[25], 20);
        assert_eq!(SMPLX_PARENTS[40], 21);
    }

    #[test]
    fn anny_tree_is_the_shipped_templates_rig() {
        let parents = KinematicTree::Anny.fixed_parents().unwrap().unwrap();
        let template = BodyTemplate::load(lowres_template_path()).unwrap();
        assert_eq!(parents.len(), 104);
        assert_eq!(
            parents_as_options(parents).unwrap(),
            template.skeleton.parents
        );
        assert_eq!(KinematicTree::Anny.num_joints(), Some(104));
        assert_eq!(KinematicTree::Stored.fixed_parents(), Ok(None));
    }

    #[test]
    fn bad_tables_are_rejected() {
        assert!(parents_as_options(&[0, 0]).is_err()); // self parent
        assert!(parents_as_options(&[-1, 5]).is_err()); // out of range
        assert!(parents_as_options(&[-1, 2, 1]).is_err()); // cycle
        assert!(parents_as_options(&[1, 0]).is_err()); // no root
    }
}
