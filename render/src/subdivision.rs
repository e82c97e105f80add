//! 1→4 midpoint subdivision and the tables that rebuild high-res vertices from low-res ones
//! (design.md §5.1–§5.2).
//!
//! # Algorithm (one level)
//!
//! 1. Number the unique undirected edges of the current faces ([`MeshTopology::unique_edges`]).
//! 2. Append one vertex per edge after the existing vertices: edge `e` gets index `V_s + e`. So
//!    `V_{s+1} = V_s + E_s`, and the low-res vertices keep indices `0..V↓` at every level (the
//!    reference relies on this to read low-res visibility as a prefix of high-res visibility).
//! 3. Face `(a, b, c)` with midpoints `m_ab, m_bc, m_ca` becomes, as 4 consecutive faces,
//!    `(a, m_ab, m_ca), (m_ab, b, m_bc), (m_ca, m_bc, c), (m_ab, m_bc, m_ca)`. The vertex order
//!    inside each child is part of the contract: it fixes the Steiner frame and the order of the
//!    per-face vertex features. Child `k` of parent `p` is therefore face `4p + k` after one level,
//!    and high-res face `h` descends from low-res face `h / 4^levels`.
//!
//! # Interpolation tables
//!
//! High-res vertices are never stored: they are rebuilt from the *posed* low-res vertices as
//! `Σ_k w_k · v↓[idx_k]`, so the high-res mesh stays planar inside each posed low-res triangle.
//! Each high-res vertex keeps at most 3 `(low-res index, weight)` pairs, its barycentric
//! coordinates in a low-res triangle. A midpoint of `(p, q)` takes p's and q's pairs with all
//! weights halved, summing duplicate indices. Unused slots are `(0, 0.0)`.
//!
//! At most 3 distinct indices can ever appear, because every vertex of a face at any level lies
//! in that face's low-res ancestor, so both ends of any edge are supported on the same ≤3
//! low-res vertices. The weights are dyadic rationals (`k / 2^s`), so in `f32` they are exact
//! and sum to exactly 1 for any practical level count.

use burn::tensor::{Device, Int, Tensor, TensorData};
use glam::Vec3;

use crate::error::{RenderError, Result};
use crate::mesh::MeshTopology;

/// One high-res vertex as ≤3 `(low-res index, weight)` pairs; unused slots are `(0, 0.0)`.
pub type Barycentric = [(u32, f32); 3];

/// A mesh subdivided `levels` times, with the tables that rebuild high-res vertex positions.
#[derive(Debug, Clone, PartialEq)]
pub struct Subdivision {
    /// Number of 1→4 passes applied.
    pub levels: u32,
    /// The input mesh.
    pub lowres: MeshTopology,
    /// The subdivided mesh (`4^levels · F↓` faces; its first `V↓` vertices are the low-res ones).
    pub highres: MeshTopology,
    /// For each high-res vertex, its barycentric coordinates in low-res vertices.
    pub highres_from_lowres: Vec<Barycentric>,
}

/// Device-side copy of [`Subdivision::highres_from_lowres`], for [`SubdivisionTables::apply`].
#[derive(Debug, Clone)]
pub struct SubdivisionTables {
    /// Low-res indices, flattened `[Vh*3]` (3 slots per high-res vertex).
    pub index: Tensor<1, Int>,
    /// Weights `[Vh, 3]`, matching `index` slot for slot.
    pub weight: Tensor<2>,
    /// Number of low-res vertices the indices refer to (`apply` checks its input against it).
    pub num_lowres: usize,
}

impl Subdivision {
    /// Subdivides `lowres` `levels` times. `levels == 0` gives identity tables.
    ///
    /// Fails with [`RenderError::InvalidInput`] on an out-of-range face index (naming the face)
    /// or when the high-res mesh would not fit `u32` indices.
    pub fn new(lowres: &MeshTopology, levels: u32) -> Result<Self> {
        // Re-validate: the fields are public, so the topology may not have come from `new`.
        let lowres = MeshTopology::new(lowres.faces.clone(), lowres.num_vertices)?;
        if lowres.num_vertices > u32::MAX as usize {
            return Err(too_large(format!(
                "{} low-res vertices do not fit u32 indices",
                lowres.num_vertices
            )));
        }
        // Checked before any level is built: each level quadruples the faces, and a typo such as
        // 12 levels would otherwise allocate until the process is killed.
        let highres = 4usize
            .checked_pow(levels)
            .and_then(|f| f.checked_mul(lowres.faces.len()));
        if highres.is_none_or(|f| f > MAX_HIGHRES_FACES) {
            return Err(too_large(format!(
                "{levels} levels of {} faces would give {} faces; at most {MAX_HIGHRES_FACES} \
                 (one Gaussian each)",
                lowres.faces.len(),
                highres.map_or_else(|| "more than 2^64".to_string(), |f| f.to_string())
            )));
        }
        let mut faces = lowres.faces.clone();
        let mut table: Vec<Barycentric> = (0..lowres.num_vertices as u32)
            .map(|v| [(v, 1.0), (0, 0.0), (0, 0.0)])
            .collect();

        for level in 0..levels {
            let current = MeshTopology {
                faces,
                num_vertices: table.len(),
            };
            let (edges, face_edges) = current.edges_and_face_edges();
            let base = table.len();
            if base + edges.len() > u32::MAX as usize
                || current
                    .faces
                    .len()
                    .checked_mul(4)
                    .is_none_or(|n| n > u32::MAX as usize)
            {
                return Err(too_large(format!(
                    "level {} would have {} vertices and {} faces, past u32 indices",
                    level + 1,
                    base + edges.len(),
                    current.faces.len() as u128 * 4
                )));
            }
            table.reserve(edges.len());
            for &[p, q] in &edges {
                let merged = midpoint(&table[p as usize], &table[q as usize]);
                table.push(merged);
            }
            faces = current
                .faces
                .iter()
                .zip(&face_edges)
                .flat_map(|(&[a, b, c], &[e_ab, e_bc, e_ca])| {
                    let [m_ab, m_bc, m_ca] = [e_ab, e_bc, e_ca].map(|e| base as u32 + e);
                    [
                        [a, m_ab, m_ca],
                        [m_ab, b, m_bc],
                        [m_ca, m_bc, c],
                        [m_ab, m_bc, m_ca],
                    ]
                })
                .collect();
        }

        let highres = MeshTopology {
            faces,
            num_vertices: table.len(),
        };
        Ok(Self {
            levels,
            lowres,
            highres,
            highres_from_lowres: table,
        })
    }

    /// The low-res face a high-res face descends from (`highres_face / 4^levels`).
    pub fn parent_face(&self, highres_face: usize) -> usize {
        highres_face >> (2 * self.levels)
    }

    /// High-res vertex positions from low-res ones, on the CPU.
    ///
    /// # Panics
    ///
    /// If `lowres.len()` is not the low-res vertex count.
    pub fn highres_vertices_cpu(&self, lowres: &[Vec3]) -> Vec<Vec3> {
        assert_eq!(
            lowres.len(),
            self.lowres.num_vertices,
            "highres_vertices_cpu: `lowres` has {} vertices, the subdivision was built for {}",
            lowres.len(),
            self.lowres.num_vertices
        );
        self.highres_from_lowres
            .iter()
            .map(|slots| slots.iter().map(|&(i, w)| lowres[i as usize] * w).sum())
            .collect()
    }

    /// Uploads the interpolation tables to `device`. Build them once and reuse them: they depend
    /// on topology only.
    pub fn tables(&self, device: &Device) -> SubdivisionTables {
        let vh = self.highres_from_lowres.len();
        let index: Vec<i64> = self
            .highres_from_lowres
            .iter()
            .flatten()
            .map(|&(i, _)| i64::from(i))
            .collect();
        let weight: Vec<f32> = self
            .highres_from_lowres
            .iter()
            .flatten()
            .map(|&(_, w)| w)
            .collect();
        SubdivisionTables {
            index: Tensor::from_data(TensorData::new(index, [vh * 3]), device),
            weight: Tensor::from_data(TensorData::new(weight, [vh, 3]), device),
            num_lowres: self.lowres.num_vertices,
        }
    }
}

impl SubdivisionTables {
    /// High-res vertices `[Vh, 3]` from low-res vertices `[V↓, 3]`, as differentiable tensor ops:
    /// one gather, a weighted sum over the 3 slots. The gradient w.r.t. a low-res vertex is the
    /// weighted sum of the gradients of the high-res vertices that reference it.
    ///
    /// The tables may live on the non-autodiff twin of `lowres`'s device: they are constants.
    ///
    /// # Panics
    ///
    /// If `lowres` is not `[num_lowres, 3]`.
    pub fn apply(&self, lowres: Tensor<2>) -> Tensor<2> {
        let dims = lowres.dims();
        assert_eq!(
            dims,
            [self.num_lowres, 3],
            "SubdivisionTables::apply: `lowres` must be [{}, 3], got {dims:?}",
            self.num_lowres
        );
        self.apply_columns(lowres)
    }

    /// [`Self::apply`] for any number of columns: `[Vh, C]` from `[V↓, C]`, every column
    /// interpolated alike (several posed copies of the mesh side by side, `C = 3n`, in one
    /// gather and one weighted sum).
    ///
    /// # Panics
    ///
    /// If `lowres` does not have `num_lowres` rows.
    pub fn apply_columns(&self, lowres: Tensor<2>) -> Tensor<2> {
        let [rows, columns] = lowres.dims();
        assert_eq!(
            rows, self.num_lowres,
            "SubdivisionTables::apply_columns: `lowres` must have {} rows, got {rows}",
            self.num_lowres
        );
        let [vh, _] = self.weight.dims();
        let gathered =
            crate::select::select_rows(lowres, 0, self.index.clone()).reshape([vh, 3, columns]);
        let weighted = gathered * self.weight.clone().reshape([vh, 3, 1]);
        weighted.sum_dim(1).reshape([vh, columns])
    }
}

/// Barycentric coordinates of the midpoint of two vertices: both lists halved and merged,
/// summing duplicate indices, first-appearance order (p's slots, then q's new ones).
fn midpoint(p: &Barycentric, q: &Barycentric) -> Barycentric {
    let mut out: Barycentric = [(0, 0.0); 3];
    let mut used = 0;
    for &(i, w) in p.iter().chain(q) {
        // Empty slots carry weight 0; skipping them keeps index 0 from claiming a slot.
        if w == 0.0 {
            continue;
        }
        match out[..used].iter_mut().find(|(j, _)| *j == i) {
            Some(slot) => slot.1 += 0.5 * w,
            None => {
                // Cannot overflow: both ends of an edge lie in one low-res triangle (module docs).
                assert!(
                    used < 3,
                    "midpoint support exceeds 3 low-res vertices: {p:?} + {q:?}"
                );
                out[used] = (i, 0.5 * w);
                used += 1;
            }
        }
    }
    out
}

/// The most high-res faces a subdivision may make: 2^24, fifty times the paper's 2 levels of
/// SMPL-X (334,528), about 3 GB of Gaussian parameters and gradients in f32.
pub const MAX_HIGHRES_FACES: usize = 1 << 24;

fn too_large(reason: String) -> RenderError {
    RenderError::InvalidInput {
        what: "levels",
        reason,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::octahedron;

    /// Absurd level counts are an error naming the field before anything is allocated.
    #[test]
    fn too_many_levels_are_refused_before_allocating() {
        let (topology, _) = octahedron();
        for levels in [11, 12, 40, u32::MAX] {
            let e = Subdivision::new(&topology, levels).unwrap_err().to_string();
            assert!(
                e.contains("levels") && e.contains("at most 16777216"),
                "{e}"
            );
        }
        // Small level counts still subdivide: 8 faces · 4² = 128.
        assert_eq!(
            Subdivision::new(&topology, 2).unwrap().highres.faces.len(),
            128
        );
    }

    fn tetrahedron() -> (MeshTopology, Vec<Vec3>) {
        let faces = vec![[0, 1, 2], [0, 3, 1], [1, 3, 2], [2, 3, 0]];
        let verts = vec![
            Vec3::new(1.0, 1.0, 1.0),
            Vec3::new(1.0, -1.0, -1.0),
            Vec3::new(-1.0, 1.0, -1.0),
            Vec3::new(-1.0, -1.0, 1.0),
        ];
        (MeshTopology::new(faces, 4).unwrap(), verts)
    }

    /// Direct recursive construction: subdivide geometry level by level, placing each new vertex
    /// at the midpoint of its edge's *current* positions.
    fn recursive_midpoints(
        mesh: &MeshTopology,
        verts: &[Vec3],
        levels: u32,
    ) -> (Vec<[u32; 3]>, Vec<Vec3>) {
        let mut faces = mesh.faces.clone();
        let mut pos = verts.to_vec();
        for _ in 0..levels {
            let cur = MeshTopology::new(faces.clone(), pos.len()).unwrap();
            let base = pos.len() as u32;
            let edges = cur.unique_edges();
            for &[p, q] in &edges {
                pos.push((pos[p as usize] + pos[q as usize]) * 0.5);
            }
            let id = |p: u32, q: u32| {
                base + edges
                    .iter()
                    .position(|e| *e == [p.min(q), p.max(q)])
                    .unwrap() as u32
            };
            faces = faces
                .iter()
                .flat_map(|&[a, b, c]| {
                    let (ab, bc, ca) = (id(a, b), id(b, c), id(c, a));
                    [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
                })
                .collect();
        }
        (faces, pos)
    }

    #[test]
    fn counts_follow_the_recurrences() {
        for (mesh, _) in [tetrahedron(), octahedron()] {
            let (mut v, mut f) = (mesh.num_vertices, mesh.num_faces());
            for levels in 0..=3 {
                let sub = Subdivision::new(&mesh, levels).unwrap();
                assert_eq!(
                    sub.highres.num_faces(),
                    4usize.pow(levels) * mesh.num_faces()
                );
                assert_eq!(sub.highres.num_faces(), f);
                assert_eq!(sub.highres.num_vertices, v);
                assert_eq!(sub.highres_from_lowres.len(), v);
                // Closed meshes: Euler characteristic 2 at every level.
                let e = sub.highres.unique_edges().len();
                assert_eq!(v + f, e + 2, "levels {levels}");
                v += e;
                f *= 4;
            }
        }
    }

    #[test]
    fn child_order_and_vertex_order() {
        let (mesh, _) = tetrahedron();
        let sub = Subdivision::new(&mesh, 1).unwrap();
        // Edges in first-appearance order: (0,1)=4, (1,2)=5, (0,2)=6, then face 1 adds (0,3)=7, ...
        let (m01, m12, m02) = (4, 5, 6);
        assert_eq!(
            &sub.highres.faces[0..4],
            &[[0, m01, m02], [m01, 1, m12], [m02, m12, 2], [m01, m12, m02]]
        );
        // Face 1 = (0,3,1): m_ab = m03 (new edge 7), m_bc = m31 (new edge 8), m_ca = m10 (edge 4).
        assert_eq!(
            &sub.highres.faces[4..8],
            &[[0, 7, 4], [7, 3, 8], [4, 8, 1], [7, 8, 4]]
        );
        assert_eq!(
            sub.highres_from_lowres[m12 as usize],
            [(1, 0.5), (2, 0.5), (0, 0.0)]
        );
        for h in 0..sub.highres.num_faces() {
            assert_eq!(sub.parent_face(h), h / 4);
        }
        let sub2 = Subdivision::new(&mesh, 2).unwrap();
        assert_eq!(sub2.parent_face(31), 1);
        assert_eq!(sub2.parent_face(32), 2);
    }

    #[test]
    fn tables_reproduce_recursive_midpoints() {
        for (mesh, verts) in [tetrahedron(), octahedron()] {
            for levels in 0..=3 {
                let sub = Subdivision::new(&mesh, levels).unwrap();
                let (faces, pos) = recursive_midpoints(&mesh, &verts, levels);
                assert_eq!(sub.highres.faces, faces);
                let got = sub.highres_vertices_cpu(&verts);
                assert_eq!(got.len(), pos.len());
                for (i, (g, p)) in got.iter().zip(&pos).enumerate() {
                    assert!((*g - *p).length() < 1e-6, "vertex {i}: {g} vs {p}");
                }
                for slots in &sub.highres_from_lowres {
                    assert_eq!(slots.iter().map(|s| s.1).sum::<f32>(), 1.0, "{slots:?}");
                    assert!(slots.iter().all(|s| s.1 >= 0.0));
                }
                // Low-res vertices keep their indices and positions.
                assert_eq!(&got[..verts.len()], &verts[..]);
            }
        }
    }

    #[test]
    fn every_highres_vertex_lies_on_its_parent_triangle() {
        let (mesh, verts) = octahedron();
        let sub = Subdivision::new(&mesh, 3).unwrap();
        for (h, face) in sub.highres.faces.iter().enumerate() {
            let parent = mesh.faces[sub.parent_face(h)];
            for &v in face {
                // Support of the vertex must be a subset of the parent's corners.
                for &(i, w) in &sub.highres_from_lowres[v as usize] {
                    assert!(
                        w == 0.0 || parent.contains(&i),
                        "face {h} vertex {v}: {i} not in {parent:?}"
                    );
                }
                // Geometrically: coplanar with and inside the parent triangle.
                let [a, b, c] = parent.map(|i| verts[i as usize]);
                let p = sub.highres_vertices_cpu(&verts)[v as usize];
                let n = (b - a).cross(c - a);
                assert!(n.dot(p - a).abs() < 1e-6);
                for (x, y) in [(a, b), (b, c), (c, a)] {
                    assert!(n.dot((y - x).cross(p - x)) >= -1e-6);
                }
            }
        }
    }

    #[test]
    fn degenerate_faces_subdivide_without_panicking() {
        let mesh = MeshTopology::new(vec![[0, 0, 1], [0, 1, 2]], 3).unwrap();
        let sub = Subdivision::new(&mesh, 2).unwrap();
        assert_eq!(sub.highres.num_faces(), 32);
        for slots in &sub.highres_from_lowres {
            assert_eq!(slots.iter().map(|s| s.1).sum::<f32>(), 1.0);
        }
    }

    #[test]
    fn invalid_face_index_is_named() {
        let mesh = MeshTopology {
            faces: vec![[0, 1, 2], [0, 1, 7]],
            num_vertices: 3,
        };
        let err = Subdivision::new(&mesh, 1).unwrap_err().to_string();
        assert!(err.contains("face 1 corner 2"), "{err}");
    }

    fn apply_matches_cpu_and_backpropagates(device: Device) {
        let (mesh, verts) = octahedron();
        // Move the vertices off the unit octahedron so every coordinate matters.
        let verts: Vec<Vec3> = verts
            .iter()
            .enumerate()
            .map(|(i, v)| *v * (1.0 + 0.1 * i as f32) + Vec3::splat(0.01 * i as f32))
            .collect();
        let sub = Subdivision::new(&mesh, 2).unwrap();
        let expect = sub.highres_vertices_cpu(&verts);

        let flat: Vec<f32> = verts.iter().flat_map(|v| v.to_array()).collect();
        let tables = sub.tables(&device);
        let lowres =
            Tensor::<2>::from_data(TensorData::new(flat.clone(), [verts.len(), 3]), &device);
        let got = tables
            .apply(lowres)
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap();
        assert_eq!(got.len(), expect.len() * 3);
        for (i, e) in expect.iter().enumerate() {
            let g = Vec3::from_slice(&got[3 * i..3 * i + 3]);
            assert!((g - *e).length() < 1e-5, "vertex {i}: {g} vs {e}");
        }

        // Backward of the sum: each low-res vertex receives the total weight it contributes.
        let ad = device.autodiff();
        let lowres =
            Tensor::<2>::from_data(TensorData::new(flat, [verts.len(), 3]), &ad).require_grad();
        let loss = tables.apply(lowres.clone()).sum();
        let grads = loss.backward();
        let grad = lowres
            .grad(&grads)
            .expect("low-res vertices get a gradient");
        let grad = grad.into_data().try_into_vec_as::<f32>().unwrap();
        let mut mass = vec![0.0f32; verts.len()];
        for slots in &sub.highres_from_lowres {
            for &(i, w) in slots {
                mass[i as usize] += w;
            }
        }
        for (v, m) in mass.iter().enumerate() {
            for k in 0..3 {
                assert!(
                    (grad[3 * v + k] - m).abs() < 1e-4,
                    "vertex {v}: {} vs {m}",
                    grad[3 * v + k]
                );
            }
        }
    }

    #[test]
    #[allow(deprecated)]
    fn apply_matches_cpu_and_backpropagates_ndarray() {
        apply_matches_cpu_and_backpropagates(Device::ndarray());
    }

    #[test]
    fn apply_matches_cpu_and_backpropagates_flex() {
        apply_matches_cpu_and_backpropagates(Device::flex());
    }
}
