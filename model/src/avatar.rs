//! The reconstructed avatar: a canonical T-pose Gaussians-on-Mesh that renders in any pose and
//! view, saves and loads, and exports to the standard 3D Gaussian splatting `.ply` (with the
//! Gaussians' rig appended) and to a rigged `.glb` ([`crate::rig_export`]).
//!
//! An avatar is the final low-res canonical vertices, the per-face Gaussian parameters of the
//! subdivided mesh, the skinning weights and the subject's skeleton. Posing is exactly the
//! training path: LBS of the low-res vertices, high-res vertices through the subdivision tables,
//! Gaussians on the posed Steiner frames — so what you see is what was supervised.
//!
//! # File format (`.lgom`)
//!
//! `LGOMAVT1`, a little-endian `u64` header length, a JSON header (skeleton, low-res faces,
//! subdivision level, tensor shapes), then the tensors as little-endian `f32` in header order.
//! Writes go to a temporary file in the same folder that is renamed over the target, so an
//! interrupted save never leaves a truncated avatar behind.

use std::io::Write;
use std::path::Path;

use burn::tensor::{Device, Tensor, TensorData};
use glam::{Mat3, Vec3};
use serde::{Deserialize, Serialize};

use lifegom_render::atomic_file::write_atomic;
use lifegom_render::camera::Camera;
use lifegom_render::gom::{GomMesh, GomParams};
use lifegom_render::mesh::MeshTopology;
use lifegom_render::rasterizer::{Gaussians, RasterSettings, Rendered, rasterize};
use lifegom_render::readback;
use lifegom_render::skeleton::{BodyPose, Skeleton};
use lifegom_render::skinning::skin_vertices;

use crate::error::{ModelError, Result};

const MAGIC: &[u8; 8] = b"LGOMAVT1";

/// A reconstructed, animatable avatar.
#[derive(Debug, Clone)]
pub struct Avatar {
    /// Canonical low-res vertices, `[V↓, 3]`.
    pub xyz: Tensor<2>,
    /// Per-face Gaussian parameters of the subdivided mesh.
    pub faces: GomParams,
    /// Dense skinning weights, `[V↓, J]`.
    pub lbs_weights: Tensor<2>,
    /// The subject's skeleton (canonical joints).
    pub skeleton: Skeleton,
    /// Low-res topology and subdivision.
    pub mesh: GomMesh,
}

#[derive(Serialize, Deserialize)]
struct Header {
    joint_names: Vec<String>,
    joint_parents: Vec<i64>,
    rest_joints: Vec<[f32; 3]>,
    faces: Vec<[u32; 3]>,
    num_vertices: usize,
    subdivision: u32,
    tensors: Vec<(String, Vec<usize>)>,
}

fn host<const D: usize>(name: &'static str, t: &Tensor<D>) -> Result<Vec<f32>> {
    Ok(readback::read(name, t.clone())?)
}

fn file_error(path: &Path, reason: impl Into<String>) -> ModelError {
    ModelError::InvalidInput {
        what: "avatar file",
        reason: format!("{}: {}", path.display(), reason.into()),
    }
}

impl Avatar {
    /// An avatar from its parts: the canonical low-res vertices `[V↓, 3]`, the per-face
    /// Gaussian parameters of `mesh`, the dense skinning weights `[V↓, J]` and the skeleton.
    pub fn new(
        xyz: Tensor<2>,
        faces: GomParams,
        lbs_weights: Tensor<2>,
        skeleton: Skeleton,
        mesh: GomMesh,
    ) -> Self {
        Self {
            xyz,
            faces,
            lbs_weights,
            skeleton,
            mesh,
        }
    }

    /// World-space Gaussians of the avatar in `pose` (axis-angles per joint, as the reference).
    pub fn gaussians(&self, pose: &BodyPose) -> Result<Gaussians> {
        let transforms = self.skeleton.skinning_transforms(pose)?;
        let posed = skin_vertices(self.xyz.clone(), self.lbs_weights.clone(), &transforms)?;
        Ok(self.mesh.gaussians(posed, &self.faces))
    }

    /// Renders the avatar in `pose` from `camera`: premultiplied RGB and alpha.
    pub fn render(&self, pose: &BodyPose, camera: &Camera) -> Result<Rendered> {
        Ok(rasterize(
            &self.gaussians(pose)?,
            &RasterSettings::new(*camera),
        )?)
    }

    /// Saves to `path` atomically (module docs).
    pub fn save(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let tensors: Vec<(&str, Vec<usize>, Vec<f32>)> = vec![
            ("xyz", self.xyz.dims().to_vec(), host("xyz", &self.xyz)?),
            (
                "lbs_weights",
                self.lbs_weights.dims().to_vec(),
                host("lbs_weights", &self.lbs_weights)?,
            ),
            (
                "so3",
                self.faces.so3.dims().to_vec(),
                host("so3", &self.faces.so3)?,
            ),
            (
                "scales",
                self.faces.scales.dims().to_vec(),
                host("scales", &self.faces.scales)?,
            ),
            (
                "offsets",
                self.faces.offsets.dims().to_vec(),
                host("offsets", &self.faces.offsets)?,
            ),
            (
                "colors",
                self.faces.colors.dims().to_vec(),
                host("colors", &self.faces.colors)?,
            ),
            (
                "opacities",
                self.faces.opacities.dims().to_vec(),
                host("opacities", &self.faces.opacities)?,
            ),
        ];
        let header = Header {
            joint_names: self.skeleton.names.clone(),
            joint_parents: self
                .skeleton
                .parents
                .iter()
                .map(|p| p.map_or(-1, |p| p as i64))
                .collect(),
            rest_joints: self
                .skeleton
                .rest_joints
                .iter()
                .map(|j| j.to_array())
                .collect(),
            faces: self.mesh.subdivision.lowres.faces.clone(),
            num_vertices: self.mesh.subdivision.lowres.num_vertices,
            subdivision: self.mesh.subdivision.levels,
            tensors: tensors
                .iter()
                .map(|(n, s, _)| (n.to_string(), s.clone()))
                .collect(),
        };
        let json = serde_json::to_vec(&header).map_err(|e| file_error(path, e.to_string()))?;
        let mut bytes = Vec::with_capacity(
            16 + json.len() + tensors.iter().map(|t| 4 * t.2.len()).sum::<usize>(),
        );
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&(json.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&json);
        for (_, _, values) in &tensors {
            for v in values {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
        write_atomic(path, &bytes).map_err(|e| file_error(path, e.to_string()))
    }

    /// Loads an avatar saved by [`Avatar::save`] onto `device`.
    pub fn load(path: impl AsRef<Path>, device: &Device) -> Result<Self> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|e| file_error(path, e.to_string()))?;
        if bytes.len() < 16 || &bytes[..8] != MAGIC {
            return Err(file_error(path, "not a lifegom avatar (bad magic)"));
        }
        let len = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")) as usize;
        let json = bytes
            .get(16..16usize.saturating_add(len))
            .ok_or_else(|| file_error(path, "truncated header"))?;
        let header: Header =
            serde_json::from_slice(json).map_err(|e| file_error(path, format!("header: {e}")))?;
        let mut at = 16 + len;
        let mut take = |name: &str, shape: &[usize]| -> Result<Vec<f32>> {
            let n: usize = shape.iter().product();
            let end = at
                .checked_add(4 * n)
                .filter(|e| *e <= bytes.len())
                .ok_or_else(|| file_error(path, format!("tensor `{name}` is truncated")))?;
            let v = bytes[at..end]
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect();
            at = end;
            Ok(v)
        };
        let mut t2 = std::collections::HashMap::new();
        for (name, shape) in &header.tensors {
            t2.insert(name.clone(), (shape.clone(), take(name, shape)?));
        }
        let get2 = |name: &str| -> Result<Tensor<2>> {
            let (shape, v) = t2
                .get(name)
                .ok_or_else(|| file_error(path, format!("missing tensor `{name}`")))?;
            if shape.len() != 2 {
                return Err(file_error(
                    path,
                    format!("tensor `{name}` has shape {shape:?}, expected 2-D"),
                ));
            }
            Ok(Tensor::from_data(
                TensorData::new(v.clone(), [shape[0], shape[1]]),
                device,
            ))
        };
        let opacities = {
            let (shape, v) = t2
                .get("opacities")
                .ok_or_else(|| file_error(path, "missing tensor `opacities`"))?;
            if shape.len() != 1 {
                return Err(file_error(
                    path,
                    format!("tensor `opacities` has shape {shape:?}, expected 1-D"),
                ));
            }
            Tensor::<1>::from_data(TensorData::new(v.clone(), [shape[0]]), device)
        };
        // The parts below check themselves; their errors get the file's name.
        let named = |e: crate::error::ModelError| file_error(path, e.to_string());
        let parents = header
            .joint_parents
            .iter()
            .map(|p| usize::try_from(*p).ok())
            .collect();
        let skeleton = Skeleton::new(
            header.joint_names,
            parents,
            header
                .rest_joints
                .iter()
                .map(|j| Vec3::from_array(*j))
                .collect(),
        )
        .map_err(|e| named(e.into()))?;
        let topology =
            MeshTopology::new(header.faces, header.num_vertices).map_err(|e| named(e.into()))?;
        let mesh =
            GomMesh::new(&topology, header.subdivision, device).map_err(|e| named(e.into()))?;
        let faces = GomParams {
            so3: get2("so3")?,
            scales: get2("scales")?,
            offsets: get2("offsets")?,
            colors: get2("colors")?,
            opacities,
        };
        if faces.len() != mesh.num_gaussians() {
            return Err(file_error(
                path,
                format!(
                    "{} face parameters for a mesh of {} faces",
                    faces.len(),
                    mesh.num_gaussians()
                ),
            ));
        }
        Ok(Self {
            xyz: get2("xyz")?,
            faces,
            lbs_weights: get2("lbs_weights")?,
            skeleton,
            mesh,
        })
    }

    /// Writes the avatar in `pose` as a standard 3D Gaussian splatting `.ply` (positions,
    /// SH DC colour, logit opacity, log scales, rotation quaternion w-x-y-z), which common splat
    /// viewers open. Each covariance is factorised `Σ = R S² Rᵀ` by a symmetric eigensolver;
    /// the flat direction of a Gaussian gets a tiny positive scale rather than `log 0`.
    ///
    /// After the standard properties every Gaussian carries its rig (the triangle it rides on,
    /// its face-frame parameters, its skinning weights), so a splat tool can animate it; the
    /// properties are listed in docs/export.md. The skinning weights act on canonical positions:
    /// export with the rest pose to animate from the `.ply` alone.
    pub fn export_ply(&self, pose: &BodyPose, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let g = self.gaussians(pose)?;
        let means = host("means", &g.means)?;
        let covs = host("covariances", &g.covariances)?;
        let colors = host("colors", &g.colors)?;
        let opacities = host("opacities", &g.opacities)?;
        let n = opacities.len();
        let rig = self.ply_rig()?;
        let mut out = Vec::new();
        let props = [
            "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0",
            "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ];
        write!(
            out,
            "ply\nformat binary_little_endian 1.0\n{}element vertex {n}\n",
            crate::rig_export::PLY_COMMENT
        )
        .expect("write to Vec");
        for p in props {
            writeln!(out, "property float {p}").expect("write to Vec");
        }
        out.extend_from_slice(rig.header.as_bytes());
        out.extend_from_slice(b"end_header\n");
        const SH_C0: f32 = 0.282_094_8;
        for i in 0..n {
            let c = &covs[6 * i..6 * i + 6];
            let sigma = Mat3::from_cols(
                Vec3::new(c[0], c[1], c[2]),
                Vec3::new(c[1], c[3], c[4]),
                Vec3::new(c[2], c[4], c[5]),
            );
            let (rot, eig) = symmetric_eigen(sigma);
            let q = glam::Quat::from_mat3(&rot).normalize();
            let o = opacities[i].clamp(1e-4, 1.0 - 1e-4);
            let mut record = vec![
                means[3 * i],
                means[3 * i + 1],
                means[3 * i + 2],
                0.0,
                0.0,
                0.0,
            ];
            record.extend((0..3).map(|k| (colors[3 * i + k] - 0.5) / SH_C0));
            record.push((o / (1.0 - o)).ln());
            record.extend(eig.to_array().map(|l| 0.5 * l.max(1e-14).ln()));
            record.extend([q.w, q.x, q.y, q.z]);
            for v in record {
                out.extend_from_slice(&v.to_le_bytes());
            }
            out.extend_from_slice(rig.record(i));
        }
        write_atomic(path, &out).map_err(|e| file_error(path, e.to_string()))
    }
}

/// Eigen-decomposition of a symmetric 3×3 matrix by cyclic Jacobi rotations (f64 inside):
/// returns a proper rotation whose columns are eigenvectors, and the eigenvalues.
#[allow(clippy::needless_range_loop)] // index form mirrors the Jacobi rotation formulas
fn symmetric_eigen(m: Mat3) -> (Mat3, Vec3) {
    let mut a = [[0.0f64; 3]; 3];
    for (r, row) in a.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = m.col(c)[r] as f64;
        }
    }
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0f64]];
    for _ in 0..32 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        if off < 1e-30 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q].abs() < 1e-300 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in &mut v {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let col = |k: usize| Vec3::new(v[0][k] as f32, v[1][k] as f32, v[2][k] as f32);
    let (c0, c1) = (col(0), col(1));
    // A rotation needs det +1: flip the last axis if the eigenvectors came out left-handed.
    let c2 = c0.cross(c1);
    (
        Mat3::from_cols(c0, c1, c2),
        Vec3::new(a[0][0] as f32, a[1][1] as f32, a[2][2] as f32),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use lifegom_render::camera::Intrinsics;
    use lifegom_render::template::{BodyTemplate, lowres_template_path};

    use lifegom_render::testing::read;

    #[test]
    fn avatar_renders_novel_poses_and_round_trips_through_files() {
        let device = Device::flex();
        let body = BodyTemplate::load(lowres_template_path()).unwrap();
        let mesh = GomMesh::new(&body.topology, 1, &device).unwrap();
        let avatar = Avatar::new(
            body.vertex_tensor(&device),
            GomParams::init(mesh.num_gaussians(), &device),
            body.skin.tensor(&device),
            body.skeleton.clone(),
            mesh,
        );
        let skel = &avatar.skeleton;
        let mut pose = BodyPose::rest(skel.names.len());
        pose.joint_rotations[skel.joint_index("upperarm01.L").unwrap()] = Vec3::new(0.0, 0.0, 1.2);
        let k = Intrinsics {
            fx: 40.0,
            fy: 40.0,
            cx: 24.0,
            cy: 24.0,
        };
        let cam =
            Camera::look_at(Vec3::new(-1.5, 0.5, 2.0), Vec3::ZERO, Vec3::Y, k, 48, 48).unwrap();
        let a = read(avatar.render(&pose, &cam).unwrap().image);
        assert!(a.iter().all(|v| v.is_finite()) && a.chunks(4).any(|p| p[3] > 0.5));

        let dir = std::env::temp_dir().join(format!("lifegom-avatar-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("a.lgom");
        avatar.save(&file).unwrap();
        let back = Avatar::load(&file, &device).unwrap();
        assert_eq!(
            a,
            read(back.render(&pose, &cam).unwrap().image),
            "a loaded avatar renders identically"
        );
        let leftovers: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| e.file_name().to_string_lossy().contains("tmp"))
            .collect();
        assert!(leftovers.is_empty(), "atomic save leaves no temporary file");

        let ply = dir.join("a.ply");
        avatar.export_ply(&pose, &ply).unwrap();
        let bytes = std::fs::read(&ply).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        let header = String::from_utf8_lossy(&bytes[..header_end]);
        let n = avatar.mesh.num_gaussians();
        assert!(
            header.contains(&format!("element vertex {n}"))
                && header.contains("property float rot_3")
        );
        // Every property, standard or rig, is 4 bytes wide.
        let props = header.lines().filter(|l| l.starts_with("property")).count();
        assert!(props > 17 && header.contains("property float lbs_weight_0"));
        assert_eq!(bytes.len() - header_end, n * props * 4);
        let body = &bytes[header_end..];
        assert!(
            body.chunks_exact(4)
                .all(|c| f32::from_le_bytes(c.try_into().unwrap()).is_finite())
        );

        std::fs::write(
            dir.join("bad.lgom"),
            b"LGOMAVT1\x05\x00\x00\x00\x00\x00\x00\x00{",
        )
        .unwrap();
        let err = Avatar::load(dir.join("bad.lgom"), &device)
            .unwrap_err()
            .to_string();
        assert!(err.contains("bad.lgom"), "{err}");
        assert!(
            Avatar::load(dir.join("missing.lgom"), &device)
                .unwrap_err()
                .to_string()
                .contains("missing.lgom")
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn eigen_reconstructs_and_is_a_rotation() {
        let r = Mat3::from_axis_angle(Vec3::new(0.3, -0.5, 0.8).normalize(), 1.1);
        let d = Mat3::from_diagonal(Vec3::new(4.0, 1e-6, 0.25));
        let sigma = r * d * r.transpose();
        let (rot, eig) = symmetric_eigen(sigma);
        assert!((rot.determinant() - 1.0).abs() < 1e-5);
        let back = rot * Mat3::from_diagonal(eig) * rot.transpose();
        for c in 0..3 {
            assert!(
                (back.col(c) - sigma.col(c)).length() < 1e-5,
                "{back} vs {sigma}"
            );
        }
    }
}
