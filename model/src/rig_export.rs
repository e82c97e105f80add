//! The avatar's rig for other tools (design.md §4.7, docs/export.md): a rigged binary glTF
//! (`.glb`) of the canonical subdivided surface, and the per-Gaussian rig that
//! [`Avatar::export_ply`] appends to the 3D Gaussian splatting `.ply`.
//!
//! # The rigged surface
//!
//! [`Avatar::canonical_rig`] gathers, on the host, everything a skinned mesh needs:
//!
//! * **vertices**: the high-res canonical vertices, rebuilt from the low-res ones through the
//!   subdivision tables (design.md §5.2). Their first `V↓` are the low-res vertices, in order;
//! * **triangles**: the high-res faces; triangle `f` carries Gaussian `f`;
//! * **colours**: each vertex takes the mean colour of the Gaussians on its triangles. A
//!   Gaussian's colour reproduces image pixel values, which are sRGB-encoded, so the mean is
//!   clamped to `[0, 1]` and decoded to the linear values glTF's `COLOR_0` holds;
//! * **normals**: area-weighted triangle normals, unit length (a vertex on no triangle of
//!   non-zero area gets +Y, since glTF requires unit normals);
//! * **skinning**: a high-res vertex with barycentric slots `(i_k, b_k)` takes the weights
//!   `Σ_k b_k · W↓[i_k]` of the avatar's dense low-res weights `W↓` (`[V↓, J]`). A vertex can so
//!   have more than 4 influences (up to 3 low-res vertices' worth); every non-zero weight is
//!   kept. Weights are sorted by decreasing value (ties by joint index) and divided by their
//!   sum, which glTF requires to be 1 (lifegom's own LBS does not normalise, design.md §4.3;
//!   [`CanonicalRig::max_weight_sum_error`] says by how much the two can differ).
//!
//! # The `.glb`
//!
//! One node per joint, in the skeleton's joint order, so glTF joint index `j` is lifegom joint
//! `j`. A joint's node is a child of its parent's and holds only a translation: the joint head
//! minus the parent's head (a root: the head itself). Joint frames are world-aligned at the rest
//! heads (render/src/skeleton.rs), so the rest pose has no rotation anywhere, and a pose's
//! axis-angle `θ_j` is the node's rotation as it is. The inverse bind matrix of joint `j` is
//! `Trans(−J_j)`, so joint world matrix × inverse bind matrix is lifegom's skinning transform
//! `M_j = G_j · Trans(−J_j)` (design.md §4.2). A skeleton with several roots gets one extra,
//! identity node above them (glTF wants the joints of a skin to share a root).
//!
//! The mesh node is a root of the scene with no transform, as glTF asks of skinned meshes. Its
//! one primitive has `POSITION` (with the min/max glTF requires), `NORMAL`, `COLOR_0`, the
//! triangles as `u32` indices, and `JOINTS_n`/`WEIGHTS_n` for `n = 0..S`, `S = ⌈k/4⌉` for the
//! most influences `k` of any vertex. Set 0 holds every vertex's 4 largest weights, so a viewer
//! that reads only `JOINTS_0`/`WEIGHTS_0` still gets the dominant ones; unused slots are joint 0
//! with weight 0. Joint indices are `u16`. The primitive's material is a rough, non-metallic
//! white that the vertex colours multiply. The mesh's `extras` record the low-res vertex count
//! and the subdivision level.
//!
//! # Animations
//!
//! [`Avatar::export_glb_animated`] adds one glTF animation per [`RigAnimation`] (a motion the
//! avatar plays): keyframe `k` at time `k / fps`, `LINEAR` interpolation, and for every joint a
//! `rotation` channel on its node holding the quaternion of the pose's axis-angle (rotations are
//! local to the world-aligned joint frames, so the quaternion is the node's rotation as it is,
//! as above). A motion with root translations (capture data) also gets a `translation` channel
//! on each root joint: its rest translation plus the frame's offset. All channels of an
//! animation share one time accessor, whose `min`/`max` glTF requires.
//!
//! # The `.ply` rig
//!
//! [`GaussianRig`] is the per-Gaussian part: the triangle the Gaussian sits on (its index and
//! corners in the `.glb`'s numbering), the low-res triangle that one lies in with the
//! barycentric coordinates of its corners there, and the skinning weights at the triangle's
//! centroid, the mean of its three corners' weights, normalised and sorted as above. With the
//! Gaussian's face-frame parameters (which [`Avatar::export_ply`] adds) the first two give the
//! avatar's own posing exactly: skin the low-res corners, interpolate, rebuild the Gaussian on
//! its posed triangle (design.md §5.3–§5.4). The weights give the usual approximation, LBS of
//! the Gaussian's centre. docs/export.md lists the exact `.ply` properties.

use std::collections::BTreeMap;
use std::path::Path;

use glam::Vec3;
use gltf::json;
use json::validation::{Checked::Valid, USize64};

use lifegom_render::atomic_file::write_atomic;
use lifegom_render::readback;
use lifegom_render::skeleton::BodyPose;

use crate::avatar::Avatar;
use crate::error::{ModelError, Result};

/// The largest joint count a rig can have: joint indices are written as `u16`.
pub const MAX_JOINTS: usize = u16::MAX as usize + 1;

/// One vertex's skinning: `(joint, weight)` pairs with positive weights, sorted by decreasing
/// weight (ties by joint index), summing to 1 up to `f32` rounding.
pub type Influences = Vec<(u16, f32)>;

/// The canonical (zero-pose) rigged surface of an avatar, on the host: what
/// [`Avatar::export_glb`] writes (module docs).
#[derive(Debug, Clone)]
pub struct CanonicalRig {
    /// High-res canonical vertices; the first `V↓` are the low-res vertices.
    pub positions: Vec<Vec3>,
    /// High-res triangles; triangle `f` carries Gaussian `f`.
    pub triangles: Vec<[u32; 3]>,
    /// Unit, area-weighted vertex normals.
    pub normals: Vec<Vec3>,
    /// Linear RGB in `[0, 1]` per vertex.
    pub colors: Vec<[f32; 3]>,
    /// Skinning per vertex (module docs).
    pub influences: Vec<Influences>,
    /// The largest `|Σ_j w_j − 1|` of a vertex's interpolated weights before they were
    /// normalised: how far the normalised glTF weights can be from the weights lifegom's own LBS
    /// uses (a posed vertex moves by at most this times its distance from the joints' origin of
    /// motion).
    pub max_weight_sum_error: f64,
}

impl CanonicalRig {
    /// The most influences any vertex has.
    pub fn max_influences(&self) -> usize {
        self.influences.iter().map(Vec::len).max().unwrap_or(0)
    }
}

/// The per-Gaussian rig (module docs): for Gaussian `f`, high-res triangle `f`.
#[derive(Debug, Clone)]
pub struct GaussianRig {
    /// The triangle's corners, in the `.glb`'s (high-res) vertex numbering.
    pub corners: Vec<[u32; 3]>,
    /// The corners of the low-res triangle the Gaussian's triangle lies in (its ancestor,
    /// design.md §5.1): low-res vertex indices, which are also the `.glb`'s first vertices.
    pub lowres_corners: Vec<[u32; 3]>,
    /// `barycentric[f][c][k]`: corner `c` of triangle `f` is `Σ_k b_ck · lowres_corners[f][k]`,
    /// in any pose (the subdivision tables, design.md §5.2, restricted to the ancestor).
    pub barycentric: Vec<[[f32; 3]; 3]>,
    /// Skinning weights at the triangle's centroid.
    pub influences: Vec<Influences>,
}

impl GaussianRig {
    /// The most influences any Gaussian has.
    pub fn max_influences(&self) -> usize {
        self.influences.iter().map(Vec::len).max().unwrap_or(0)
    }
}

fn invalid(what: &'static str, reason: impl Into<String>) -> ModelError {
    ModelError::InvalidInput {
        what,
        reason: reason.into(),
    }
}

/// The sRGB decoding of one channel value in `[0, 1]` (IEC 61966-2-1).
fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// A motion to write into the `.glb` as a glTF animation (module docs, "Animations").
#[derive(Debug, Clone, Copy)]
pub struct RigAnimation<'a> {
    /// The animation's name (`walk`, a motion file's stem).
    pub name: &'a str,
    /// Keyframes per second.
    pub fps: f32,
    /// One pose per keyframe, for the avatar's skeleton.
    pub poses: &'a [BodyPose],
    /// Per keyframe, the offset of the root joint(s) from their rest position, in metres, when
    /// the motion moves the body (capture data); `None` keeps the body in place.
    pub root_translations: Option<&'a [Vec3]>,
}

impl RigAnimation<'_> {
    /// Checks the animation against a skeleton of `num_joints` joints before anything is
    /// written: an error names the animation, and the frame and joint where it applies.
    fn check(&self, num_joints: usize) -> Result<()> {
        let bad = |reason: String| invalid("glb animation", format!("`{}`: {reason}", self.name));
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(bad(format!("fps must be > 0, got {}", self.fps)));
        }
        if self.poses.is_empty() {
            return Err(bad("no frames".into()));
        }
        for (k, pose) in self.poses.iter().enumerate() {
            if pose.num_joints() != num_joints {
                return Err(bad(format!(
                    "frame {k} has {} joints, the skeleton {num_joints}",
                    pose.num_joints()
                )));
            }
            if let Some(j) = pose.joint_rotations.iter().position(|r| !r.is_finite()) {
                return Err(bad(format!("frame {k}, joint {j}: non-finite rotation")));
            }
        }
        if let Some(t) = self.root_translations {
            if t.len() != self.poses.len() {
                return Err(bad(format!(
                    "{} root translations for {} frames",
                    t.len(),
                    self.poses.len()
                )));
            }
            if let Some(k) = t.iter().position(|v| !v.is_finite()) {
                return Err(bad(format!("frame {k}: non-finite root translation")));
            }
        }
        Ok(())
    }
}

/// Sorts, normalises and rounds accumulated weights; `None` when they sum to zero.
///
/// The rounding residual goes to the largest weight so that the `f32` weights sum to 1 as
/// closely as `f32` allows (glTF validators check the sum).
fn normalised(weights: BTreeMap<u16, f64>) -> Option<(Influences, f64)> {
    let sum: f64 = weights.values().sum();
    if sum <= 0.0 || !sum.is_finite() {
        return None;
    }
    let mut pairs: Vec<(u16, f64)> = weights.into_iter().filter(|&(_, w)| w > 0.0).collect();
    pairs.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut out: Influences = pairs.iter().map(|&(j, w)| (j, (w / sum) as f32)).collect();
    let rounded: f64 = out.iter().map(|&(_, w)| f64::from(w)).sum();
    out[0].1 = (f64::from(out[0].1) + (1.0 - rounded)) as f32;
    Some((out, (sum - 1.0).abs()))
}

/// Host copies of the avatar's canonical low-res state, checked against each other.
struct HostAvatar {
    lowres: Vec<Vec3>,
    /// Non-zero dense weights per low-res vertex.
    weights: Vec<Vec<(u16, f64)>>,
}

impl Avatar {
    fn host_state(&self) -> Result<HostAvatar> {
        let sub = &self.mesh.subdivision;
        let v_low = sub.lowres.num_vertices;
        let joints = self.skeleton.num_joints();
        if self.xyz.dims() != [v_low, 3] {
            return Err(invalid(
                "avatar.xyz",
                format!(
                    "shape {:?}, the mesh has {v_low} low-res vertices",
                    self.xyz.dims()
                ),
            ));
        }
        if self.lbs_weights.dims() != [v_low, joints] {
            return Err(invalid(
                "avatar.lbs_weights",
                format!(
                    "shape {:?}, expected [{v_low}, {joints}] (low-res vertices, joints)",
                    self.lbs_weights.dims()
                ),
            ));
        }
        if joints == 0 || joints > MAX_JOINTS {
            return Err(invalid(
                "avatar.skeleton",
                format!("{joints} joints; a rig needs 1 to {MAX_JOINTS}"),
            ));
        }
        let xyz: Vec<f32> = readback::read("xyz", self.xyz.clone())?;
        let lowres: Vec<Vec3> = xyz.chunks_exact(3).map(Vec3::from_slice).collect();
        if let Some(v) = lowres.iter().position(|p| !p.is_finite()) {
            return Err(invalid(
                "avatar.xyz",
                format!("low-res vertex {v} is not finite"),
            ));
        }
        let dense: Vec<f32> = readback::read("lbs_weights", self.lbs_weights.clone())?;
        let mut weights = Vec::with_capacity(v_low);
        for (v, row) in dense.chunks_exact(joints).enumerate() {
            if let Some(j) = row.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
                return Err(invalid(
                    "avatar.lbs_weights",
                    format!(
                        "low-res vertex {v} has weight {} for joint {j} `{}`; a rig needs finite, \
                         non-negative weights",
                        row[j], self.skeleton.names[j]
                    ),
                ));
            }
            weights.push(
                row.iter()
                    .enumerate()
                    .filter(|&(_, &w)| w > 0.0)
                    .map(|(j, &w)| (j as u16, f64::from(w)))
                    .collect(),
            );
        }
        Ok(HostAvatar { lowres, weights })
    }

    /// The canonical rigged surface (module docs) that [`Avatar::export_glb`] writes.
    ///
    /// Fails when the avatar's parts disagree on vertex, joint or face counts, when a weight is
    /// negative or not finite, or when a vertex ends up with no weight at all (glTF has no way
    /// to say "not skinned").
    pub fn canonical_rig(&self) -> Result<CanonicalRig> {
        let host = self.host_state()?;
        let sub = &self.mesh.subdivision;
        let triangles = sub.highres.faces.clone();
        let positions = sub.highres_vertices_cpu(&host.lowres);

        let mut influences = Vec::with_capacity(positions.len());
        let mut max_weight_sum_error = 0.0f64;
        for (v, slots) in sub.highres_from_lowres.iter().enumerate() {
            let mut acc = BTreeMap::new();
            for &(i, b) in slots.iter().filter(|(_, b)| *b > 0.0) {
                for &(j, w) in &host.weights[i as usize] {
                    *acc.entry(j).or_insert(0.0) += f64::from(b) * w;
                }
            }
            let (inf, err) = normalised(acc).ok_or_else(|| {
                invalid(
                    "avatar.lbs_weights",
                    format!(
                        "vertex {v} of the subdivided mesh (from low-res vertices {:?}) has no \
                         skinning weight",
                        slots
                            .iter()
                            .filter(|(_, b)| *b > 0.0)
                            .map(|(i, _)| *i)
                            .collect::<Vec<_>>()
                    ),
                )
            })?;
            max_weight_sum_error = max_weight_sum_error.max(err);
            influences.push(inf);
        }

        let face_colors = self.face_colors()?;
        let mut color_sum = vec![[0.0f64; 3]; positions.len()];
        let mut color_count = vec![0u32; positions.len()];
        let mut normal_sum = vec![glam::DVec3::ZERO; positions.len()];
        for (tri, rgb) in triangles.iter().zip(&face_colors) {
            let [a, b, c] = tri.map(|v| positions[v as usize].as_dvec3());
            // The cross product's length is twice the area: area-weighted for free.
            let n = (b - a).cross(c - a);
            for &v in tri {
                let v = v as usize;
                normal_sum[v] += n;
                color_count[v] += 1;
                for k in 0..3 {
                    color_sum[v][k] += f64::from(rgb[k]);
                }
            }
        }
        let normals = normal_sum
            .iter()
            .map(|n| {
                if n.length() > 1e-30 {
                    n.normalize().as_vec3()
                } else {
                    Vec3::Y
                }
            })
            .collect();
        let colors = color_sum
            .iter()
            .zip(&color_count)
            .map(|(sum, &count)| {
                sum.map(|s| {
                    let mean = if count == 0 {
                        0.0
                    } else {
                        s / f64::from(count)
                    };
                    srgb_to_linear((mean as f32).clamp(0.0, 1.0))
                })
            })
            .collect();
        Ok(CanonicalRig {
            positions,
            triangles,
            normals,
            colors,
            influences,
            max_weight_sum_error,
        })
    }

    /// Per-face RGB of the Gaussians, checked against the mesh.
    fn face_colors(&self) -> Result<Vec<[f32; 3]>> {
        let faces = self.mesh.num_gaussians();
        if self.faces.colors.dims() != [faces, 3] {
            return Err(invalid(
                "avatar.faces.colors",
                format!(
                    "shape {:?}, the mesh has {faces} faces",
                    self.faces.colors.dims()
                ),
            ));
        }
        let rgb: Vec<f32> = readback::read("colors", self.faces.colors.clone())?;
        Ok(rgb.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }

    /// The per-Gaussian rig (module docs) that [`Avatar::export_ply`] appends.
    pub fn gaussian_rig(&self) -> Result<GaussianRig> {
        let host = self.host_state()?;
        let sub = &self.mesh.subdivision;
        let faces = sub.highres.faces.len();
        let mut influences = Vec::with_capacity(faces);
        let mut lowres_corners = Vec::with_capacity(faces);
        let mut barycentric = Vec::with_capacity(faces);
        for (f, tri) in sub.highres.faces.iter().enumerate() {
            let ancestor = sub.lowres.faces[sub.parent_face(f)];
            let mut bary = [[0.0f32; 3]; 3];
            for (c, &v) in tri.iter().enumerate() {
                for &(i, b) in sub.highres_from_lowres[v as usize]
                    .iter()
                    .filter(|(_, b)| *b > 0.0)
                {
                    // Every vertex of a face lies in its low-res ancestor (render's
                    // subdivision.rs), so `i` is one of the ancestor's corners.
                    let k = ancestor.iter().position(|&a| a == i).ok_or_else(|| {
                        invalid(
                            "avatar.mesh",
                            format!(
                                "high-res vertex {v} of face {f} leans on low-res vertex {i}, \
                                 outside its ancestor face {ancestor:?}"
                            ),
                        )
                    })?;
                    bary[c][k] += b;
                }
            }
            lowres_corners.push(ancestor);
            barycentric.push(bary);
            let mut acc = BTreeMap::new();
            for &v in tri {
                for &(i, b) in sub.highres_from_lowres[v as usize]
                    .iter()
                    .filter(|(_, b)| *b > 0.0)
                {
                    for &(j, w) in &host.weights[i as usize] {
                        *acc.entry(j).or_insert(0.0) += f64::from(b) * w / 3.0;
                    }
                }
            }
            let (inf, _) = normalised(acc).ok_or_else(|| {
                invalid(
                    "avatar.lbs_weights",
                    format!("the corners of Gaussian {f} (face {tri:?}) have no skinning weight"),
                )
            })?;
            influences.push(inf);
        }
        Ok(GaussianRig {
            corners: sub.highres.faces.clone(),
            lowres_corners,
            barycentric,
            influences,
        })
    }

    /// Writes the canonical avatar as a rigged binary glTF (module docs) to `path`, atomically.
    pub fn export_glb(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let bytes = self.glb_bytes()?;
        write_atomic(path, &bytes)
            .map_err(|e| invalid("glb export", format!("{}: {e}", path.display())))
    }

    /// The rigged `.glb` of [`Avatar::export_glb`] as bytes.
    pub fn glb_bytes(&self) -> Result<Vec<u8>> {
        self.glb_bytes_animated(&[])
    }

    /// Writes the rigged `.glb` with `animations` (module docs, "Animations"), atomically.
    pub fn export_glb_animated(
        &self,
        path: impl AsRef<Path>,
        animations: &[RigAnimation<'_>],
    ) -> Result<()> {
        let path = path.as_ref();
        let bytes = self.glb_bytes_animated(animations)?;
        write_atomic(path, &bytes)
            .map_err(|e| invalid("glb export", format!("{}: {e}", path.display())))
    }

    /// The rigged `.glb` with `animations`, as bytes.
    pub fn glb_bytes_animated(&self, animations: &[RigAnimation<'_>]) -> Result<Vec<u8>> {
        for animation in animations {
            animation.check(self.skeleton.num_joints())?;
        }
        let rig = self.canonical_rig()?;
        GlbWriter::default().write(self, &rig, animations)
    }
}

/// The binary chunk and JSON document of a `.glb` under construction.
#[derive(Default)]
struct GlbWriter {
    root: json::Root,
    bin: Vec<u8>,
}

/// What an accessor's elements are.
#[derive(Clone, Copy)]
enum Element {
    Vec3F32,
    Vec4F32,
    Vec4U16,
    ScalarU32,
    ScalarF32,
    Mat4F32,
}

impl GlbWriter {
    /// Appends `bytes` as a buffer view (4-byte aligned, as every accessor here needs) and an
    /// accessor of `count` elements over it.
    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        element: Element,
        target: Option<json::buffer::Target>,
        min_max: Option<(Vec<f32>, Vec<f32>)>,
    ) -> json::Index<json::Accessor> {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        let view = self.root.push(json::buffer::View {
            buffer: json::Index::new(0),
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            name: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        });
        use json::accessor::{ComponentType as C, Type as T};
        let (component, kind) = match element {
            Element::Vec3F32 => (C::F32, T::Vec3),
            Element::Vec4F32 => (C::F32, T::Vec4),
            Element::Vec4U16 => (C::U16, T::Vec4),
            Element::ScalarU32 => (C::U32, T::Scalar),
            Element::ScalarF32 => (C::F32, T::Scalar),
            Element::Mat4F32 => (C::F32, T::Mat4),
        };
        let bound = |v: Vec<f32>| Some(json::Value::from(v));
        self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(count),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(kind),
            min: min_max.clone().and_then(|(lo, _)| bound(lo)),
            max: min_max.and_then(|(_, hi)| bound(hi)),
            name: None,
            normalized: false,
            sparse: None,
        })
    }

    /// Appends one animation (module docs); `animation` was checked against the skeleton.
    fn animation(&mut self, avatar: &Avatar, animation: &RigAnimation<'_>) {
        use json::animation::{Channel, Interpolation, Property, Sampler, Target};
        let skeleton = &avatar.skeleton;
        let frames = animation.poses.len();
        let times: Vec<f32> = (0..frames).map(|k| k as f32 / animation.fps).collect();
        let last = times.last().copied().unwrap_or(0.0);
        let input = self.accessor(
            &Self::f32_bytes(times),
            frames,
            Element::ScalarF32,
            None,
            Some((vec![0.0], vec![last])),
        );
        let mut channels = Vec::new();
        let mut samplers = Vec::new();
        let mut channel =
            |this: &mut Self, node: usize, path: Property, bytes: Vec<u8>, element| {
                let output = this.accessor(&bytes, frames, element, None, None);
                channels.push(Channel {
                    sampler: json::Index::new(samplers.len() as u32),
                    target: Target {
                        node: json::Index::new(node as u32),
                        path: Valid(path),
                        extensions: None,
                        extras: Default::default(),
                    },
                    extensions: None,
                    extras: Default::default(),
                });
                samplers.push(Sampler {
                    input,
                    interpolation: Valid(Interpolation::Linear),
                    output,
                    extensions: None,
                    extras: Default::default(),
                });
            };
        for j in 0..skeleton.num_joints() {
            let quats = Self::f32_bytes(animation.poses.iter().flat_map(|pose| {
                glam::Quat::from_scaled_axis(pose.joint_rotations[j])
                    .normalize()
                    .to_array()
            }));
            channel(self, j, Property::Rotation, quats, Element::Vec4F32);
        }
        if let Some(offsets) = animation.root_translations {
            for (j, parent) in skeleton.parents.iter().enumerate() {
                if parent.is_none() {
                    let rest = skeleton.rest_joints[j];
                    let bytes =
                        Self::f32_bytes(offsets.iter().flat_map(|t| (rest + *t).to_array()));
                    channel(self, j, Property::Translation, bytes, Element::Vec3F32);
                }
            }
        }
        self.root.push(json::Animation {
            name: Some(animation.name.to_string()),
            channels,
            samplers,
            extensions: None,
            extras: Default::default(),
        });
    }

    fn f32_bytes(values: impl IntoIterator<Item = f32>) -> Vec<u8> {
        values.into_iter().flat_map(f32::to_le_bytes).collect()
    }

    fn write(
        mut self,
        avatar: &Avatar,
        rig: &CanonicalRig,
        animations: &[RigAnimation<'_>],
    ) -> Result<Vec<u8>> {
        use json::buffer::Target::{ArrayBuffer, ElementArrayBuffer};
        let skeleton = &avatar.skeleton;
        let num_joints = skeleton.num_joints();
        let v = rig.positions.len();

        // Joint nodes first, so node `j` is joint `j`.
        let mut children: Vec<Vec<json::Index<json::Node>>> = vec![Vec::new(); num_joints];
        for (j, parent) in skeleton.parents.iter().enumerate() {
            if let Some(p) = parent {
                children[*p].push(json::Index::new(j as u32));
            }
        }
        for (j, kids) in children.into_iter().enumerate() {
            let head = skeleton.rest_joints[j];
            let local = match skeleton.parents[j] {
                Some(p) => head - skeleton.rest_joints[p],
                None => head,
            };
            self.root.push(json::Node {
                name: Some(skeleton.names[j].clone()),
                translation: Some(local.to_array()),
                children: (!kids.is_empty()).then_some(kids),
                ..Default::default()
            });
        }
        let unique = |base: &str| {
            let mut name = base.to_string();
            while skeleton.names.contains(&name) {
                name.push('_');
            }
            name
        };
        let roots: Vec<json::Index<json::Node>> = (0..num_joints)
            .filter(|&j| skeleton.parents[j].is_none())
            .map(|j| json::Index::new(j as u32))
            .collect();
        let skeleton_root = if roots.len() == 1 {
            roots[0]
        } else {
            self.root.push(json::Node {
                name: Some(unique("skeleton")),
                children: Some(roots),
                ..Default::default()
            })
        };

        let (lo, hi) = rig.positions.iter().fold(
            (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
            |(lo, hi), p| (lo.min(*p), hi.max(*p)),
        );
        let position = self.accessor(
            &Self::f32_bytes(rig.positions.iter().flat_map(|p| p.to_array())),
            v,
            Element::Vec3F32,
            Some(ArrayBuffer),
            Some((lo.to_array().to_vec(), hi.to_array().to_vec())),
        );
        let normal = self.accessor(
            &Self::f32_bytes(rig.normals.iter().flat_map(|n| n.to_array())),
            v,
            Element::Vec3F32,
            Some(ArrayBuffer),
            None,
        );
        let color = self.accessor(
            &Self::f32_bytes(rig.colors.iter().flatten().copied()),
            v,
            Element::Vec3F32,
            Some(ArrayBuffer),
            None,
        );
        let indices = self.accessor(
            &rig.triangles
                .iter()
                .flatten()
                .flat_map(|i| i.to_le_bytes())
                .collect::<Vec<u8>>(),
            3 * rig.triangles.len(),
            Element::ScalarU32,
            Some(ElementArrayBuffer),
            None,
        );
        let mut attributes = BTreeMap::new();
        attributes.insert(Valid(json::mesh::Semantic::Positions), position);
        attributes.insert(Valid(json::mesh::Semantic::Normals), normal);
        attributes.insert(Valid(json::mesh::Semantic::Colors(0)), color);
        let sets = rig.max_influences().div_ceil(4).max(1);
        for set in 0..sets {
            let slot =
                |inf: &Influences, k: usize| inf.get(4 * set + k).copied().unwrap_or((0, 0.0));
            let joints: Vec<u8> = rig
                .influences
                .iter()
                .flat_map(|inf| (0..4).flat_map(move |k| slot(inf, k).0.to_le_bytes()))
                .collect();
            let weights = Self::f32_bytes(
                rig.influences
                    .iter()
                    .flat_map(|inf| (0..4).map(move |k| slot(inf, k).1)),
            );
            let joints = self.accessor(&joints, v, Element::Vec4U16, Some(ArrayBuffer), None);
            let weights = self.accessor(&weights, v, Element::Vec4F32, Some(ArrayBuffer), None);
            attributes.insert(Valid(json::mesh::Semantic::Joints(set as u32)), joints);
            attributes.insert(Valid(json::mesh::Semantic::Weights(set as u32)), weights);
        }
        // Inverse bind matrices Trans(−J_j), column-major.
        let ibm = Self::f32_bytes(
            skeleton
                .rest_joints
                .iter()
                .flat_map(|j| glam::Mat4::from_translation(-*j).to_cols_array()),
        );
        let ibm = self.accessor(&ibm, num_joints, Element::Mat4F32, None, None);

        let material = self.root.push(json::Material {
            name: Some("gaussian_colours".into()),
            pbr_metallic_roughness: json::material::PbrMetallicRoughness {
                metallic_factor: json::material::StrengthFactor(0.0),
                roughness_factor: json::material::StrengthFactor(1.0),
                ..Default::default()
            },
            ..Default::default()
        });
        let extras = serde_json::value::to_raw_value(&serde_json::json!({
            "lowres_vertices": avatar.mesh.subdivision.lowres.num_vertices,
            "subdivision_levels": avatar.mesh.subdivision.levels,
        }))
        .map_err(|e| invalid("glb export", e.to_string()))?;
        let mesh = self.root.push(json::Mesh {
            name: Some("avatar".into()),
            primitives: vec![json::mesh::Primitive {
                attributes,
                indices: Some(indices),
                material: Some(material),
                mode: Valid(json::mesh::Mode::Triangles),
                targets: None,
                extensions: None,
                extras: Default::default(),
            }],
            weights: None,
            extensions: None,
            extras: Some(extras),
        });
        let skin = self.root.push(json::Skin {
            name: Some("skeleton".into()),
            joints: (0..num_joints as u32).map(json::Index::new).collect(),
            inverse_bind_matrices: Some(ibm),
            skeleton: Some(skeleton_root),
            extensions: None,
            extras: Default::default(),
        });
        let mesh_node = self.root.push(json::Node {
            name: Some(unique("avatar")),
            mesh: Some(mesh),
            skin: Some(skin),
            ..Default::default()
        });
        let scene = self.root.push(json::Scene {
            name: Some("lifegom avatar".into()),
            nodes: vec![mesh_node, skeleton_root],
            extensions: None,
            extras: Default::default(),
        });
        self.root.scene = Some(scene);
        for animation in animations {
            self.animation(avatar, animation);
        }
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        if self.bin.len() > u32::MAX as usize - (1 << 20) {
            return Err(invalid(
                "glb export",
                format!(
                    "{} bytes of mesh data do not fit a .glb (4 GiB at most)",
                    self.bin.len()
                ),
            ));
        }
        self.root.push(json::Buffer {
            byte_length: USize64::from(self.bin.len()),
            name: None,
            uri: None,
            extensions: None,
            extras: Default::default(),
        });
        self.root.asset = json::Asset {
            generator: Some(format!("lifegom {}", env!("CARGO_PKG_VERSION"))),
            version: "2.0".into(),
            copyright: None,
            extensions: None,
            extras: Default::default(),
            min_version: None,
        };
        let json_bytes = self
            .root
            .to_vec()
            .map_err(|e| invalid("glb export", e.to_string()))?;
        let glb = gltf::binary::Glb {
            header: gltf::binary::Header {
                magic: *b"glTF",
                version: 2,
                // `to_vec` computes the real length.
                length: 0,
            },
            json: json_bytes.into(),
            bin: Some(self.bin.into()),
        };
        glb.to_vec()
            .map_err(|e| invalid("glb export", e.to_string()))
    }
}

/// The `.ply` header comment that points a reader at the rig properties' description.
pub(crate) const PLY_COMMENT: &str = "comment lifegom rig: face_id, face_v*, lowres_v*, bary_*, \
    gom_* and lbs_* are described in lifegom's docs/export.md\n";

/// The rig properties [`Avatar::export_ply`] appends to every Gaussian's record (docs/export.md):
/// the header lines and one fixed-size little-endian record per Gaussian.
pub(crate) struct PlyRig {
    /// `property ...` lines, each ending in a newline.
    pub header: String,
    record_len: usize,
    data: Vec<u8>,
}

impl PlyRig {
    /// The rig bytes of Gaussian `i`.
    pub fn record(&self, i: usize) -> &[u8] {
        &self.data[i * self.record_len..(i + 1) * self.record_len]
    }
}

impl Avatar {
    /// The per-Gaussian rig as `.ply` properties (docs/export.md).
    pub(crate) fn ply_rig(&self) -> Result<PlyRig> {
        let rig = self.gaussian_rig()?;
        let faces = self.mesh.num_gaussians();
        let mut params = Vec::new();
        for (name, t) in [
            ("so3", &self.faces.so3),
            ("scales", &self.faces.scales),
            ("offsets", &self.faces.offsets),
        ] {
            if t.dims() != [faces, 3] {
                return Err(invalid(
                    "avatar.faces",
                    format!(
                        "`{name}` has shape {:?}, the mesh has {faces} faces",
                        t.dims()
                    ),
                ));
            }
            params.push(readback::read::<f32, 2, _>(name, t.clone())?);
        }
        let k = rig.max_influences();
        let mut header = String::new();
        let mut props: Vec<(String, &str)> = vec![("face_id".into(), "uint")];
        props.extend((0..3).map(|c| (format!("face_v{c}"), "uint")));
        props.extend((0..3).map(|k| (format!("lowres_v{k}"), "uint")));
        for c in 0..3 {
            props.extend((0..3).map(|k| (format!("bary_{c}_{k}"), "float")));
        }
        for name in ["so3", "scale", "offset"] {
            props.extend((0..3).map(|c| (format!("gom_{name}_{c}"), "float")));
        }
        props.extend((0..k).map(|s| (format!("lbs_joint_{s}"), "uint")));
        props.extend((0..k).map(|s| (format!("lbs_weight_{s}"), "float")));
        for (name, ty) in &props {
            header.push_str(&format!("property {ty} {name}\n"));
        }
        let record_len = 4 * props.len();
        let mut data = Vec::with_capacity(record_len * faces);
        for f in 0..faces {
            data.extend_from_slice(&(f as u32).to_le_bytes());
            for c in rig.corners[f].iter().chain(&rig.lowres_corners[f]) {
                data.extend_from_slice(&c.to_le_bytes());
            }
            for b in rig.barycentric[f].iter().flatten() {
                data.extend_from_slice(&b.to_le_bytes());
            }
            for p in &params {
                for v in &p[3 * f..3 * f + 3] {
                    data.extend_from_slice(&v.to_le_bytes());
                }
            }
            let inf = &rig.influences[f];
            let slot = |s: usize| inf.get(s).copied().unwrap_or((0, 0.0));
            for s in 0..k {
                data.extend_from_slice(&u32::from(slot(s).0).to_le_bytes());
            }
            for s in 0..k {
                data.extend_from_slice(&slot(s).1.to_le_bytes());
            }
        }
        Ok(PlyRig {
            header,
            record_len,
            data,
        })
    }
}
