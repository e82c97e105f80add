//! The official processed per-subject format (design.md §8.1–§8.2), read and validated.
//!
//! ```text
//! <subject>/images/<frame>.png     RGB
//! <subject>/masks/<frame>.png      mask (any channel count; channel 0 / 255 is the alpha)
//! <subject>/cameras.pkl            {frame: {'intrinsics': K, 'extrinsics': E, ['distortions': D]}}
//! <subject>/mesh_infos.pkl         {frame: {'poses': (3J,), 'tpose_joints': (J,3), 'Rh': 3, 'Th': 3}}
//! <subject>/canonical_joints.pkl   {'joints': (J,3), 'vertex': (V,3), 'weights': (V,J),
//!                                   'faces': (F,3), ['parents': (J,)]}
//! ```
//!
//! # Frame list
//!
//! As in the reference, the frames of a subject are the `.png` files of `images/`, sorted by
//! name; `cameras.pkl` and `mesh_infos.pkl` must have an entry for each (extra entries are
//! ignored, as the reference ignores them).
//!
//! # Validation (all at load time, so training never dies on frame 40,000)
//!
//! Every array is checked for its shape and for NaN/Inf; `E` must be 4×4 (3×4 is accepted and
//! completed with `[0,0,0,1]`), with last row `[0,0,0,1]` and an invertible rotation block; `K`
//! needs positive focal lengths; the joint count must agree across `poses`, `tpose_joints`,
//! `joints`, `weights` and the kinematic tree; face indices must be below the vertex count.
//! Every error is a [`DataError`] naming the subject, the frame and the field.

use std::path::{Path, PathBuf};

use glam::Vec3;
use lifegom_render::template::BodyTemplate;

use crate::error::{DataError, Location, Result};
use crate::kinematics::{KinematicTree, parents_as_options};
use crate::pickle::{self, NdArray, Value};

/// One frame's camera, in pixels of the stored image (`K`) and world→camera OpenCV (`E`).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameCamera {
    /// Row-major 3×3 intrinsics (only `[:3,:3]` of the stored matrix).
    pub k: [[f64; 3]; 3],
    /// Row-major 4×4 world→camera extrinsics.
    pub e: [[f64; 4]; 4],
    /// OpenCV distortion coefficients `(k1, k2, p1, p2[, k3[, ...]])`, if stored.
    pub distortion: Option<Vec<f64>>,
}

/// One frame's body pose.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMeshInfo {
    /// Axis-angle per joint, flat `3J` (entry 0 is the root rotation, applied).
    pub poses: Vec<f32>,
    /// Zero-pose joint positions of this frame's shape, `J`.
    pub tpose_joints: Vec<Vec3>,
    /// Global body rotation (axis-angle): `x_world = R(Rh)·x_body + Th`.
    pub rh: Vec3,
    /// Global body translation.
    pub th: Vec3,
}

/// The per-subject canonical body (`canonical_joints.pkl`).
#[derive(Debug, Clone, PartialEq)]
pub struct CanonicalBody {
    /// Canonical joint positions, `J`.
    pub joints: Vec<Vec3>,
    /// Zero-pose T-pose vertices with the subject's (estimated) shape, `V`.
    pub vertices: Vec<Vec3>,
    /// Dense LBS weights, row-major `V×J`.
    pub weights: Vec<f32>,
    /// Faces over `vertices`.
    pub faces: Vec<[u32; 3]>,
    /// Parent per joint (−1: root), from the kinematic tree or the stored `parents` array.
    pub parents: Vec<i32>,
}

impl CanonicalBody {
    /// A shipped template's body in some shape: its `vertices` and `joints` (from
    /// [`BodyTemplate::shaped`]) with the template's dense skinning weights, faces and parents.
    pub fn of_template(template: &BodyTemplate, vertices: Vec<Vec3>, joints: Vec<Vec3>) -> Self {
        Self {
            joints,
            vertices,
            weights: template.skin.to_dense(),
            faces: template.topology.faces.clone(),
            parents: template
                .skeleton
                .parents
                .iter()
                .map(|p| p.map_or(-1, |p| p as i32))
                .collect(),
        }
    }

    /// Number of joints.
    pub fn num_joints(&self) -> usize {
        self.joints.len()
    }
}

/// Where one frame's pictures are.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameFiles {
    /// The RGB image.
    pub image: PathBuf,
    /// The foreground mask (same size).
    pub mask: PathBuf,
}

/// One subject: its folder, frames, cameras, poses and canonical body, all validated.
#[derive(Debug, Clone)]
pub struct Subject {
    /// Folder name (the scene id in the split files).
    pub name: String,
    /// The subject folder.
    pub dir: PathBuf,
    /// Frame names (PNG stems of `images/`, sorted).
    pub frames: Vec<String>,
    /// Image and mask file of each frame, in `frames` order (`images/<frame>.png` and
    /// `masks/<frame>.png` in the official layout; anywhere in the JSON layout).
    pub files: Vec<FrameFiles>,
    /// Camera of each frame, in `frames` order.
    pub cameras: Vec<FrameCamera>,
    /// Pose of each frame, in `frames` order.
    pub mesh_infos: Vec<FrameMeshInfo>,
    /// The canonical body.
    pub canonical: CanonicalBody,
}

impl Subject {
    /// Reads and validates the subject folder `dir` against `tree` (module docs).
    pub fn load(dir: &Path, tree: KinematicTree) -> Result<Self> {
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let at = |file: &str| Location::file(dir.join(file)).subject(name.clone());
        let frames = list_frames(&dir.join("images"), &name)?;
        if frames.is_empty() {
            return Err(DataError::invalid(at("images"), "no .png frames"));
        }
        let canonical = read_canonical(&dir.join("canonical_joints.pkl"), &name, tree)?;
        let num_joints = canonical.num_joints();

        let cam_path = dir.join("cameras.pkl");
        let cams = pickle::load(&cam_path).map_err(|e| with_subject(e, &name))?;
        let info_path = dir.join("mesh_infos.pkl");
        let infos = pickle::load(&info_path).map_err(|e| with_subject(e, &name))?;
        let mut cameras = Vec::with_capacity(frames.len());
        let mut mesh_infos = Vec::with_capacity(frames.len());
        for frame in &frames {
            let loc = Location::file(&cam_path).subject(&name).frame(frame);
            let entry = cams
                .get(frame)
                .ok_or_else(|| DataError::invalid(loc.clone(), "no entry for this frame"))?;
            cameras.push(read_camera(entry, &loc)?);
            let loc = Location::file(&info_path).subject(&name).frame(frame);
            let entry = infos
                .get(frame)
                .ok_or_else(|| DataError::invalid(loc.clone(), "no entry for this frame"))?;
            mesh_infos.push(read_mesh_info(entry, &loc, num_joints)?);
        }
        let files = frames
            .iter()
            .map(|f| FrameFiles {
                image: dir.join("images").join(format!("{f}.png")),
                mask: dir.join("masks").join(format!("{f}.png")),
            })
            .collect();
        Ok(Self {
            name,
            dir: dir.to_path_buf(),
            frames,
            files,
            cameras,
            mesh_infos,
            canonical,
        })
    }

    /// Path of frame `i`'s image.
    pub fn image_path(&self, i: usize) -> PathBuf {
        self.files[i].image.clone()
    }

    /// Path of frame `i`'s mask.
    pub fn mask_path(&self, i: usize) -> PathBuf {
        self.files[i].mask.clone()
    }

    /// Checks that frame `i`'s camera sees the posed body: its root (the first joint, placed by
    /// `Rh`/`Th`) must be in front of the lens and project inside the image. A camera given as
    /// camera-to-world, facing away, or with intrinsics for another image size fails here;
    /// later stages would render the body mirrored or off-screen without noticing.
    pub fn check_camera_sees_body(&self, i: usize, source: &Path) -> Result<()> {
        let at = |field: &str| {
            Location::file(source)
                .subject(&self.name)
                .frame(&self.frames[i])
                .field(field)
        };
        let root = self.canonical.joints.first().copied().unwrap_or_default();
        let info = &self.mesh_infos[i];
        let m = crate::dataset::fold_body_transform(&self.cameras[i].e, info.rh, info.th);
        let cam: [f32; 3] = std::array::from_fn(|r| {
            m[r][0] * root.x + m[r][1] * root.y + m[r][2] * root.z + m[r][3]
        });
        if !(cam[2].is_finite() && cam[2] > 0.0) {
            return Err(DataError::invalid(
                at("extrinsics"),
                format!(
                    "the camera is behind the body (its root is at depth {:.3} m): extrinsics must \
                     map world to camera (OpenCV: +z forward)",
                    cam[2]
                ),
            ));
        }
        let k = &self.cameras[i].k;
        let u = k[0][0] * f64::from(cam[0] / cam[2]) + k[0][2];
        let v = k[1][1] * f64::from(cam[1] / cam[2]) + k[1][2];
        let path = &self.files[i].image;
        let (w, h) = image::image_dimensions(path).map_err(|e| DataError::Image {
            location: Box::new(
                Location::file(path)
                    .subject(&self.name)
                    .frame(&self.frames[i]),
            ),
            reason: format!("cannot read: {e}"),
        })?;
        if !(0.0..=f64::from(w)).contains(&u) || !(0.0..=f64::from(h)).contains(&v) {
            return Err(DataError::invalid(
                at("extrinsics"),
                format!(
                    "the body's root projects to pixel ({u:.0}, {v:.0}), outside the {w}×{h} image: \
                     extrinsics must map world to camera, and intrinsics be in this image's pixels"
                ),
            ));
        }
        Ok(())
    }
}

fn with_subject(e: DataError, subject: &str) -> DataError {
    match e {
        DataError::Io { location, source } => DataError::Io {
            location: Box::new(location.subject(subject)),
            source,
        },
        DataError::Pickle {
            location,
            offset,
            reason,
        } => DataError::Pickle {
            location: Box::new(location.subject(subject)),
            offset,
            reason,
        },
        other => other,
    }
}

/// PNG stems in `dir`, sorted by name.
pub fn list_frames(dir: &Path, subject: &str) -> Result<Vec<String>> {
    let loc = Location::file(dir).subject(subject);
    let entries = std::fs::read_dir(dir).map_err(|e| DataError::io(loc.clone(), e))?;
    let mut frames = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| DataError::io(loc.clone(), e))?.path();
        if path.extension().is_some_and(|x| x == "png")
            && let Some(stem) = path.file_stem()
        {
            frames.push(stem.to_string_lossy().into_owned());
        }
    }
    frames.sort();
    Ok(frames)
}

/// Array field `key` of dict `v`: present, numeric, finite, with `len` elements (any shape).
fn field(v: &Value, key: &str, loc: &Location) -> Result<NdArray> {
    let loc = loc.clone().field(key);
    let a = v
        .get(key)
        .ok_or_else(|| DataError::invalid(loc.clone(), "missing"))?
        .to_array()
        .ok_or_else(|| {
            DataError::invalid(
                loc.clone(),
                format!(
                    "expected a numeric array, got {}",
                    v.get(key).map_or("?", Value::type_name)
                ),
            )
        })?;
    if let Some(i) = a.to_f64().iter().position(|x| !x.is_finite()) {
        return Err(DataError::invalid(
            loc,
            format!("non-finite value at flat index {i}"),
        ));
    }
    Ok(a)
}

fn expect_len(a: &NdArray, n: usize, what: &str, loc: &Location, key: &str) -> Result<()> {
    if a.len() != n {
        return Err(DataError::invalid(
            loc.clone().field(key),
            format!("expected {what} ({n} values), got shape {:?}", a.shape),
        ));
    }
    Ok(())
}

pub(crate) fn read_camera(v: &Value, loc: &Location) -> Result<FrameCamera> {
    let k_arr = field(v, "intrinsics", loc)?;
    let kv = k_arr.to_f64();
    let kloc = loc.clone().field("intrinsics");
    // Only K[:3,:3] is read, as in the reference; a 3×4 or 4×4 K is fine.
    let cols = match k_arr.shape.as_slice() {
        [r, c] if *r >= 3 && *c >= 3 => *c,
        _ => {
            return Err(DataError::invalid(
                kloc,
                format!("expected at least 3×3, got shape {:?}", k_arr.shape),
            ));
        }
    };
    let mut k = [[0.0; 3]; 3];
    for (r, row) in k.iter_mut().enumerate() {
        for (c, x) in row.iter_mut().enumerate() {
            *x = kv[r * cols + c];
        }
    }
    if !(k[0][0] > 0.0 && k[1][1] > 0.0) {
        return Err(DataError::invalid(
            kloc,
            format!(
                "focal lengths must be > 0, got fx={} fy={}",
                k[0][0], k[1][1]
            ),
        ));
    }

    let e_arr = field(v, "extrinsics", loc)?;
    let ev = e_arr.to_f64();
    let eloc = loc.clone().field("extrinsics");
    let mut e = [
        [0.0, 0.0, 0.0, 0.0],
        [0.0; 4],
        [0.0; 4],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let rows = match e_arr.shape.as_slice() {
        [4, 4] => 4,
        [3, 4] => 3,
        _ => {
            return Err(DataError::invalid(
                eloc,
                format!("expected 4×4, got shape {:?}", e_arr.shape),
            ));
        }
    };
    for r in 0..rows {
        for c in 0..4 {
            e[r][c] = ev[r * 4 + c];
        }
    }
    if e[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(DataError::invalid(
            eloc,
            format!("last row must be [0,0,0,1], got {:?}", e[3]),
        ));
    }
    let det = e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
        - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
        + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0]);
    if det.is_nan() || det.abs() <= 1e-6 {
        return Err(DataError::invalid(
            eloc,
            format!("not invertible (rotation block determinant {det:.3e})"),
        ));
    }
    let distortion = match v.get("distortions") {
        None | Some(Value::None) => None,
        Some(_) => {
            let d = field(v, "distortions", loc)?.to_f64();
            // An all-zero vector is "no distortion": skip the resampling entirely.
            (d.iter().any(|&x| x != 0.0)).then_some(d)
        }
    };
    if let Some(d) = &distortion
        && d.len() < 4
    {
        return Err(DataError::invalid(
            loc.clone().field("distortions"),
            format!("expected at least (k1, k2, p1, p2), got {} values", d.len()),
        ));
    }
    Ok(FrameCamera { k, e, distortion })
}

fn vec3s(a: &NdArray) -> Vec<Vec3> {
    a.to_f32().chunks_exact(3).map(Vec3::from_slice).collect()
}

pub(crate) fn read_mesh_info(
    v: &Value,
    loc: &Location,
    num_joints: usize,
) -> Result<FrameMeshInfo> {
    let poses = field(v, "poses", loc)?;
    expect_len(
        &poses,
        3 * num_joints,
        &format!("{num_joints} joints × 3 axis-angle"),
        loc,
        "poses",
    )?;
    let tpose = field(v, "tpose_joints", loc)?;
    expect_len(
        &tpose,
        3 * num_joints,
        &format!("({num_joints}, 3)"),
        loc,
        "tpose_joints",
    )?;
    let rh = field(v, "Rh", loc)?;
    expect_len(&rh, 3, "3", loc, "Rh")?;
    let th = field(v, "Th", loc)?;
    expect_len(&th, 3, "3", loc, "Th")?;
    Ok(FrameMeshInfo {
        poses: poses.to_f32(),
        tpose_joints: vec3s(&tpose),
        rh: Vec3::from_slice(&rh.to_f32()),
        th: Vec3::from_slice(&th.to_f32()),
    })
}

pub(crate) fn read_canonical(
    path: &Path,
    subject: &str,
    tree: KinematicTree,
) -> Result<CanonicalBody> {
    let v = pickle::load(path).map_err(|e| with_subject(e, subject))?;
    let loc = Location::file(path).subject(subject);
    let joints = field(&v, "joints", &loc)?;
    if joints.len() % 3 != 0 {
        return Err(DataError::invalid(
            loc.field("joints"),
            format!("expected (J, 3), got shape {:?}", joints.shape),
        ));
    }
    let num_joints = joints.len() / 3;
    let fixed = tree
        .fixed_parents()
        .map_err(|r| DataError::invalid(loc.clone().field("parents"), r))?;
    let parents: Vec<i32> = match fixed {
        Some(p) => p.to_vec(),
        None => {
            if v.get("parents").is_none() {
                // The one case a user can fix by choosing another tree: say which.
                return Err(DataError::invalid(
                    loc.clone().field("parents"),
                    format!(
                        "missing, and kinematic_tree = \"stored\" reads the parent table from it \
                         ({num_joints} joints here). Use kinematic_tree = \"anny\" for Anny-rig \
                         data written by other tools (104 joints), \"smpl\" (24) or \"smplx\" (55)"
                    ),
                ));
            }
            let p = field(&v, "parents", &loc)?;
            p.to_i64()
                .ok_or_else(|| {
                    DataError::invalid(loc.clone().field("parents"), "expected integers")
                })?
                .into_iter()
                .map(|x| i32::try_from(x).unwrap_or(i32::MIN))
                .collect()
        }
    };
    if parents.len() != num_joints {
        return Err(DataError::invalid(
            loc.field("joints"),
            format!(
                "wrong joint count: {num_joints} joints, but kinematic_tree = \"{}\" has {}",
                tree.name(),
                parents.len()
            ),
        ));
    }
    parents_as_options(&parents)
        .map_err(|r| DataError::invalid(loc.clone().field("parents"), r))?;
    let vertex = field(&v, "vertex", &loc)?;
    if vertex.len() % 3 != 0 || vertex.is_empty() {
        return Err(DataError::invalid(
            loc.field("vertex"),
            format!("expected (V, 3), got shape {:?}", vertex.shape),
        ));
    }
    let num_vertices = vertex.len() / 3;
    let weights = field(&v, "weights", &loc)?;
    expect_len(
        &weights,
        num_vertices * num_joints,
        &format!("({num_vertices}, {num_joints})"),
        &loc,
        "weights",
    )?;
    let faces_arr = field(&v, "faces", &loc)?;
    let faces_i = faces_arr.to_i64().ok_or_else(|| {
        DataError::invalid(loc.clone().field("faces"), "expected integer indices")
    })?;
    if faces_i.len() % 3 != 0 {
        return Err(DataError::invalid(
            loc.field("faces"),
            format!("expected (F, 3), got shape {:?}", faces_arr.shape),
        ));
    }
    let mut faces = Vec::with_capacity(faces_i.len() / 3);
    for (f, tri) in faces_i.chunks_exact(3).enumerate() {
        let mut out = [0u32; 3];
        for (o, &i) in out.iter_mut().zip(tri) {
            if i < 0 || i as usize >= num_vertices {
                return Err(DataError::invalid(
                    loc.field("faces"),
                    format!("face {f} has vertex index {i}, but there are {num_vertices} vertices"),
                ));
            }
            *o = i as u32;
        }
        faces.push(out);
    }
    Ok(CanonicalBody {
        joints: vec3s(&joints),
        vertices: vec3s(&vertex),
        weights: weights.to_f32(),
        faces,
        parents,
    })
}

/// Reads a split file: a JSON list of subject folder names.
pub fn read_split(path: &Path) -> Result<Vec<String>> {
    let loc = Location::file(path);
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(loc.clone(), e))?;
    serde_json::from_str(&text)
        .map_err(|e| DataError::invalid(loc, format!("expected a JSON list of subject names: {e}")))
}
