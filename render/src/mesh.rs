//! Triangle-mesh topology: the face list, its unique edges, and the differentiable gather of
//! per-face corner positions.
//!
//! # Invariants
//!
//! A [`MeshTopology`] only guarantees that every face index is `< num_vertices`. Degenerate faces
//! (a repeated index, such as `(a, a, b)`) are allowed on purpose: body templates can contain
//! them, and every consumer (subdivision, the Steiner frame, the triangle-ID rasterizer) must
//! treat them as zero-area faces rather than reject the whole mesh.
//!
//! # Edge numbering
//!
//! [`MeshTopology::unique_edges`] numbers undirected edges in order of first appearance while
//! scanning faces in order and, inside face `(a, b, c)`, its edges `(a,b), (b,c), (c,a)`. Each edge
//! is stored sorted `(min, max)`. The reference deduplicates with a sort-based routine instead, so
//! the numbering differs from it, but any deterministic numbering is fine (design.md §5.1):
//! no learned tensor is indexed by edge or high-res vertex id.

use std::collections::HashMap;

use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::error::{RenderError, Result};

/// Faces of a triangle mesh plus its vertex count. Vertex positions live elsewhere (a tensor, or
/// a CPU slice), because one topology serves canonical and every posed copy of the mesh.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MeshTopology {
    /// Faces as vertex-index triples, in the winding the source mesh uses.
    pub faces: Vec<[u32; 3]>,
    /// Number of vertices the face indices refer to.
    pub num_vertices: usize,
}

impl MeshTopology {
    /// Validates that every face index is `< num_vertices`. Degenerate faces are kept (see the
    /// module docs).
    pub fn new(faces: Vec<[u32; 3]>, num_vertices: usize) -> Result<Self> {
        for (f, face) in faces.iter().enumerate() {
            for (corner, &v) in face.iter().enumerate() {
                if v as usize >= num_vertices {
                    return Err(RenderError::InvalidInput {
                        what: "faces",
                        reason: format!(
                            "face {f} corner {corner} has vertex index {v}, but the mesh has {num_vertices} vertices"
                        ),
                    });
                }
            }
        }
        Ok(Self {
            faces,
            num_vertices,
        })
    }

    /// Number of faces.
    pub fn num_faces(&self) -> usize {
        self.faces.len()
    }

    /// Undirected edges, each sorted `(min, max)`, in order of first appearance (see the module
    /// docs). A degenerate face contributes its self-edge `(a, a)` like any other edge, so that
    /// subdivision counts stay `V + E` exactly as in the reference.
    pub fn unique_edges(&self) -> Vec<[u32; 2]> {
        self.edges_and_face_edges().0
    }

    /// The unique edges, plus for each face the ids of its edges `(a,b), (b,c), (c,a)` into that
    /// list. Subdivision needs both, computed in one pass so they cannot disagree.
    pub(crate) fn edges_and_face_edges(&self) -> (Vec<[u32; 2]>, Vec<[u32; 3]>) {
        let mut ids: HashMap<[u32; 2], u32> = HashMap::with_capacity(self.faces.len() * 3 / 2 + 3);
        let mut edges = Vec::with_capacity(self.faces.len() * 3 / 2 + 3);
        let face_edges = self
            .faces
            .iter()
            .map(|&[a, b, c]| {
                [[a, b], [b, c], [c, a]].map(|[p, q]| {
                    let key = [p.min(q), p.max(q)];
                    *ids.entry(key).or_insert_with(|| {
                        edges.push(key);
                        (edges.len() - 1) as u32
                    })
                })
            })
            .collect();
        (edges, face_edges)
    }

    /// The face indices flattened to `[F*3]` (`a0, b0, c0, a1, ...`), for [`face_vertices`].
    pub fn face_index_tensor(&self, device: &Device) -> Tensor<1, Int> {
        let flat: Vec<i64> = self.faces.iter().flatten().map(|&v| i64::from(v)).collect();
        let n = flat.len();
        Tensor::from_data(TensorData::new(flat, [n]), device)
    }
}

/// The three corner positions of every face, each `[F, 3]`, from `vertices` `[V, 3]` and the
/// flattened face indices `[F*3]` of [`MeshTopology::face_index_tensor`].
///
/// One `select` gathers all corners, so the backward pass is a single scatter-add into the
/// vertex gradient (a vertex shared by many faces accumulates all their contributions).
pub fn face_vertices(vertices: Tensor<2>, faces_flat: Tensor<1, Int>) -> [Tensor<2>; 3] {
    let [n] = faces_flat.dims();
    let f = n / 3;
    let corners = crate::select::select_rows(vertices, 0, faces_flat).reshape([f, 9]);
    [0, 1, 2].map(|k| corners.clone().narrow(1, 3 * k, 3))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_range_index_names_face_and_corner() {
        let err = MeshTopology::new(vec![[0, 1, 2], [2, 1, 3]], 3)
            .unwrap_err()
            .to_string();
        assert!(err.contains("face 1 corner 2"), "{err}");
        assert!(err.contains("vertex index 3"), "{err}");
        // Degenerate faces are accepted.
        assert!(MeshTopology::new(vec![[0, 0, 1]], 2).is_ok());
    }

    #[test]
    fn unique_edges_in_first_appearance_order() {
        let mesh = MeshTopology::new(vec![[0, 1, 2], [2, 1, 3]], 4).unwrap();
        assert_eq!(
            mesh.unique_edges(),
            vec![[0, 1], [1, 2], [0, 2], [1, 3], [2, 3]]
        );
        let (_, face_edges) = mesh.edges_and_face_edges();
        assert_eq!(face_edges, vec![[0, 1, 2], [1, 3, 4]]);
    }

    #[test]
    fn face_vertices_gathers_corners() {
        let device = Device::flex();
        let mesh = MeshTopology::new(vec![[0, 1, 2], [3, 2, 1]], 4).unwrap();
        let verts: Vec<f32> = (0..12).map(|v| v as f32).collect();
        let vertices = Tensor::<2>::from_data(TensorData::new(verts, [4, 3]), &device);
        let [a, b, c] = face_vertices(vertices, mesh.face_index_tensor(&device));
        let read = |t: Tensor<2>| t.into_data().try_into_vec_as::<f32>().unwrap();
        assert_eq!(read(a), vec![0.0, 1.0, 2.0, 9.0, 10.0, 11.0]);
        assert_eq!(read(b), vec![3.0, 4.0, 5.0, 6.0, 7.0, 8.0]);
        assert_eq!(read(c), vec![6.0, 7.0, 8.0, 3.0, 4.0, 5.0]);
    }
}
