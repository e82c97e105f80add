//! Gaussians-on-Mesh: one Gaussian per (high-res) face, riding on the face's Steiner frame
//! (design.md §5.4).
//!
//! For face `j` with frame `A_j` and centroid `c_j` in the current (posed) space:
//! - mean `μ = c + A·o` (offset `o` in frame units: in-plane inellipse units, normal in mm);
//! - covariance `Σ = A R S Sᵀ Rᵀ Aᵀ`, `R = exp(r̂)` (pytorch3d's so3 exponential, whose
//!   `θ = sqrt(max(|r|², 1e-4))` keeps it smooth at 0), `S = diag(s)` with raw (signed) `s`;
//! - colour: the raw 3-vector; opacity: 1 in LIFe-GoM (kept as an input so the op is general).
//!
//! Because `A` is recomputed in posed space, the per-face parameters deform with the mesh and no
//! skinning is applied to covariances. At init (`r = 0, s = 1, o = 0`) `Σ = A Aᵀ`.
//!
//! # One fused op
//!
//! The high-res mesh is never stored. [`GomMesh::new`] composes the subdivision tables
//! (design.md §5.2) with the high-res faces into a *corner table*: for each high-res face, its
//! three corners as ≤3 `(low-res index, weight)` pairs each. [`GomMesh::gaussians`] then hands
//! the posed low-res vertices, the per-face parameters and that table to one custom Burn op,
//! [`op::GomGeometryOps`] (design.md §5.6), which per face interpolates the corners, builds the
//! Steiner frame (design.md §5.3) and `exp(r̂)`, and writes mean ‖ covariance. Its backward
//! recomputes the same per face, chains the output gradient back to the face's corners and
//! parameters, and scatters the corner gradients to the low-res vertices with the table's
//! weights, so gradients reach the low-res vertices and every face parameter.
//!
//! | module | holds |
//! |---|---|
//! | [`cpu`] | the per-face math in `f64` and its backward; the NdArray / Flex implementation |
//! | [`op`] | the backend extension and its autodiff node |
//! | `cube` | the CubeCL kernels (wgpu) and their host side |
//!
//! [`gaussians_from_triangles`] (with [`so3_exp_map`] and [`crate::steiner::steiner_frames`])
//! is the same math as ~60 ordinary tensor ops. It is the specification the op is tested
//! against and what `GomMesh::gaussians_reference` runs; a mesh set to
//! [`GomGeometry::ReferenceF64`] runs it in place of the op, so whole training steps can be
//! compared too.

pub mod cpu;
pub(crate) mod cube;
pub mod op;

use burn::tensor::{DType, Device, Int, Tensor, TensorData, s};

use crate::error::Result;
use crate::mesh::{MeshTopology, face_vertices};
use crate::rasterizer::Gaussians;
use crate::steiner::steiner_frames;
use crate::subdivision::{Subdivision, SubdivisionTables};

/// Per-face Gaussian parameters.
#[derive(Debug, Clone)]
pub struct GomParams {
    /// Axis-angle rotation in the face frame, `[F, 3]`.
    pub so3: Tensor<2>,
    /// Raw scales along the rotated frame axes, `[F, 3]`.
    pub scales: Tensor<2>,
    /// Offset of the mean in the face frame, `[F, 3]`.
    pub offsets: Tensor<2>,
    /// RGB, `[F, 3]`.
    pub colors: Tensor<2>,
    /// Opacities, `[F]`.
    pub opacities: Tensor<1>,
}

impl GomParams {
    /// The parameters of consecutive blocks of faces, as one set: `blocks` itself when there
    /// is one, no faces when there is none.
    pub fn cat(mut blocks: Vec<Self>, device: &Device) -> Self {
        match blocks.len() {
            0 => Self::init(0, device),
            1 => blocks.remove(0),
            _ => {
                let field =
                    |get: fn(&Self) -> Tensor<2>| Tensor::cat(blocks.iter().map(get).collect(), 0);
                Self {
                    so3: field(|b| b.so3.clone()),
                    scales: field(|b| b.scales.clone()),
                    offsets: field(|b| b.offsets.clone()),
                    colors: field(|b| b.colors.clone()),
                    opacities: Tensor::cat(blocks.iter().map(|b| b.opacities.clone()).collect(), 0),
                }
            }
        }
    }

    /// The reference initial state: rotation 0, scale 1, offset 0, colour 0, opacity 1.
    pub fn init(num_faces: usize, device: &Device) -> Self {
        Self {
            so3: Tensor::zeros([num_faces, 3], device),
            scales: Tensor::ones([num_faces, 3], device),
            offsets: Tensor::zeros([num_faces, 3], device),
            colors: Tensor::zeros([num_faces, 3], device),
            opacities: Tensor::ones([num_faces], device),
        }
    }

    /// Number of faces.
    pub fn len(&self) -> usize {
        self.opacities.dims()[0]
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// pytorch3d's `so3_exp_map`: `R = I + sin θ/θ·K + (1 − cos θ)/θ²·K²` with `K = hat(r)` and
/// `θ = sqrt(max(|r|², 1e-4))`. `[F, 3] → [F, 3, 3]`.
pub fn so3_exp_map(r: Tensor<2>) -> Tensor<3> {
    let [f, _] = r.dims();
    let device = r.device();
    let nrm2 = (r.clone() * r.clone()).sum_dim(1); // [F, 1]
    let theta = nrm2.clone().clamp_min(cpu::SO3_THETA2_MIN).sqrt();
    let fac1 = (theta.clone().sin() / theta.clone()).reshape([f, 1, 1]);
    let fac2 = ((theta.clone().cos().neg() + 1.0) / (theta.clone() * theta)).reshape([f, 1, 1]);
    let x = r.clone().slice(s![.., 0..1]);
    let y = r.clone().slice(s![.., 1..2]);
    let z = r.clone().slice(s![.., 2..3]);
    let zero = x.zeros_like();
    let hat = Tensor::cat(
        vec![
            zero.clone(),
            z.clone().neg(),
            y.clone(),
            z,
            zero.clone(),
            x.clone().neg(),
            y.neg(),
            x,
            zero,
        ],
        1,
    )
    .reshape([f, 3, 3]);
    let eye = Tensor::<2>::eye(3, &device)
        .cast(r.dtype())
        .reshape([1, 3, 3]);
    // K² = r rᵀ − |r|² I.
    let hat2 =
        r.clone().reshape([f, 3, 1]) * r.reshape([f, 1, 3]) - eye.clone() * nrm2.reshape([f, 1, 1]);
    eye + hat * fac1 + hat2 * fac2
}

/// Builds Gaussians from triangle corners (`[F, 3]` each) and per-face parameters.
pub fn gaussians_from_triangles(
    v0: Tensor<2>,
    v1: Tensor<2>,
    v2: Tensor<2>,
    params: &GomParams,
) -> Gaussians {
    let [f, _] = v0.dims();
    let frames = steiner_frames(v0, v1, v2);
    let a = frames.frames; // [F,3,3]
    let means = frames.centroids
        + (a.clone() * params.offsets.clone().reshape([f, 1, 3]))
            .sum_dim(2)
            .reshape([f, 3]);
    // M = A·R·S; (R·S)_ij = R_ij s_j.
    let rs = so3_exp_map(params.so3.clone()) * params.scales.clone().reshape([f, 1, 3]);
    let m = a.matmul(rs);
    let row = |i: usize| m.clone().slice(s![.., i..i + 1, ..]).reshape([f, 3]);
    let (r0, r1, r2) = (row(0), row(1), row(2));
    let d = |a: &Tensor<2>, b: &Tensor<2>| (a.clone() * b.clone()).sum_dim(1);
    let covariances = Tensor::cat(
        vec![
            d(&r0, &r0),
            d(&r0, &r1),
            d(&r0, &r2),
            d(&r1, &r1),
            d(&r1, &r2),
            d(&r2, &r2),
        ],
        1,
    );
    Gaussians {
        means,
        covariances,
        colors: params.colors.clone(),
        opacities: params.opacities.clone(),
    }
}

/// Which implementation [`GomMesh::gaussians`] runs.
///
/// The model only ever calls [`GomMesh::gaussians`], so switching the mesh is how a test or a
/// benchmark runs a whole forward and backward (a training step, a reconstruction) on the
/// specification instead of the fused op, without a second code path through the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GomGeometry {
    /// The fused op [`op::GomGeometryOps`]: what training and inference use.
    #[default]
    Fused,
    /// [`GomMesh::gaussians_reference`] evaluated in `f64`, its means and covariances rounded
    /// back to the vertices' dtype. In `f32` the tensor ops are themselves off by up to ~2e-2
    /// relative on covariance entries that cancel, too coarse to check the fused op (which
    /// works in `f64` per face) at 1e-5; in `f64` the two differ by the final rounding only.
    /// Slow (about 60 tensor ops over every face) and only for backends with `f64` tensors
    /// (ndarray, Flex; not most wgpu adapters): a test and benchmark reference.
    ReferenceF64,
}

/// A low-res mesh with its subdivision, ready to turn posed low-res vertices into Gaussians.
#[derive(Debug, Clone)]
pub struct GomMesh {
    /// Topology and high-res-from-low-res tables.
    pub subdivision: Subdivision,
    tables: SubdivisionTables,
    highres_faces: Tensor<1, Int>,
    corner_index: Tensor<1, Int>,
    corner_weight: Tensor<1>,
    vertex_corner_offsets: Tensor<1, Int>,
    corner_from_vertex_order: Tensor<1, Int>,
    geometry: GomGeometry,
}

impl GomMesh {
    /// Subdivides `lowres` `levels` times and uploads the tables to `device`.
    pub fn new(lowres: &MeshTopology, levels: u32, device: &Device) -> Result<Self> {
        let subdivision = Subdivision::new(lowres, levels)?;
        let tables = subdivision.tables(device);
        let highres_faces = subdivision.highres.face_index_tensor(device);
        let (index, weight) = corner_table(&subdivision);
        let entries = index.len();
        let (offsets, order) = corner_table_by_vertex(&index, subdivision.lowres.num_vertices);
        // `i32`, the width the host and GPU kernels index with: Flex then lends the tables to
        // the op in place instead of widening a copy per call (`readback::HostLend`).
        let int_tensor = |values: Vec<i32>| {
            let n = values.len();
            Tensor::<1, Int>::from_data(TensorData::new(values, [n]), (device, DType::I32))
        };
        Ok(Self {
            subdivision,
            tables,
            highres_faces,
            corner_index: int_tensor(index),
            corner_weight: Tensor::from_data(TensorData::new(weight, [entries]), device),
            vertex_corner_offsets: int_tensor(offsets),
            corner_from_vertex_order: int_tensor(order),
            geometry: GomGeometry::default(),
        })
    }

    /// The same mesh with [`Self::gaussians`] running `geometry`.
    pub fn with_geometry(self, geometry: GomGeometry) -> Self {
        Self { geometry, ..self }
    }

    /// What [`Self::gaussians`] runs.
    pub fn geometry(&self) -> GomGeometry {
        self.geometry
    }

    /// The barycentric high-res-from-low-res tables, on the mesh's device.
    pub fn tables(&self) -> &SubdivisionTables {
        &self.tables
    }

    /// High-res face corners, flattened `[F·3]`, on the mesh's device.
    pub fn highres_faces(&self) -> &Tensor<1, Int> {
        &self.highres_faces
    }

    /// Low-res vertex indices of every high-res face corner, `[F·9]`: face `f`, corner `k`,
    /// slot `m` at `9f + 3k + m` (unused slots are index 0 with weight 0).
    pub fn corner_index(&self) -> &Tensor<1, Int> {
        &self.corner_index
    }

    /// The weights matching [`Self::corner_index`], `[F·9]`.
    pub fn corner_weight(&self) -> &Tensor<1> {
        &self.corner_weight
    }

    /// One Gaussian per high-res face.
    pub fn num_gaussians(&self) -> usize {
        self.subdivision.highres.faces.len()
    }

    /// High-res vertices interpolated from low-res ones, `[V↓, 3] → [V, 3]`.
    pub fn highres_vertices(&self, lowres_vertices: Tensor<2>) -> Tensor<2> {
        self.tables.apply(lowres_vertices)
    }

    /// The Gaussians of the mesh posed at `lowres_vertices` (`[V↓, 3]`), through the fused op
    /// [`op::GomGeometryOps`] on whichever backend the tensors live on (or the mesh's
    /// [`GomGeometry`] reference); differentiable in the vertices and in `so3`, `scales`,
    /// `offsets`, `colors` and `opacities`.
    ///
    /// # Panics
    ///
    /// If `lowres_vertices` is not `[V↓, 3]` or a parameter is not `[F, 3]` (`[F]` for the
    /// opacities), `F` the number of high-res faces.
    pub fn gaussians(&self, lowres_vertices: Tensor<2>, params: &GomParams) -> Gaussians {
        self.check_shapes(&lowres_vertices, params);
        match self.geometry {
            GomGeometry::Fused => self.gaussians_fused(lowres_vertices, params),
            GomGeometry::ReferenceF64 => self.gaussians_reference_f64(lowres_vertices, params),
        }
    }

    fn gaussians_fused(&self, lowres_vertices: Tensor<2>, params: &GomParams) -> Gaussians {
        let _span = tracing::debug_span!("gom_gaussians", faces = self.num_gaussians()).entered();
        let out: Tensor<2> = Tensor::from_dispatch(
            <burn::backend::Dispatch as op::GomGeometryOps>::gom_geometry(
                lowres_vertices.into_dispatch(),
                params.so3.clone().into_dispatch(),
                params.scales.clone().into_dispatch(),
                params.offsets.clone().into_dispatch(),
                self.corner_index.clone().into_dispatch(),
                self.corner_weight.clone().into_dispatch(),
                self.vertex_corner_offsets.clone().into_dispatch(),
                self.corner_from_vertex_order.clone().into_dispatch(),
            ),
        );
        let mut blocks = crate::split::split_columns(out, &[3, 6]).into_iter();
        let (means, covariances) = (blocks.next(), blocks.next());
        Gaussians {
            means: means.expect("a means block"),
            covariances: covariances.expect("a covariances block"),
            colors: params.colors.clone(),
            opacities: params.opacities.clone(),
        }
    }

    /// [`Self::gaussians`] as ordinary tensor ops (subdivision tables, corner gather,
    /// [`gaussians_from_triangles`]): the specification the fused op is tested and benchmarked
    /// against.
    #[doc(hidden)]
    pub fn gaussians_reference(&self, lowres_vertices: Tensor<2>, params: &GomParams) -> Gaussians {
        let _span =
            tracing::debug_span!("gom_gaussians_reference", faces = self.num_gaussians()).entered();
        // The weights are exact dyadic f32s; casting them lets the reference run in f64 too.
        let tables = SubdivisionTables {
            weight: self.tables.weight.clone().cast(lowres_vertices.dtype()),
            ..self.tables.clone()
        };
        let highres = tables.apply(lowres_vertices);
        let [v0, v1, v2] = face_vertices(highres, self.highres_faces.clone());
        gaussians_from_triangles(v0, v1, v2, params)
    }

    /// [`GomGeometry::ReferenceF64`]. The casts are differentiable, so gradients reach the
    /// caller's tensors in their own dtype.
    fn gaussians_reference_f64(&self, lowres_vertices: Tensor<2>, params: &GomParams) -> Gaussians {
        let dtype = lowres_vertices.dtype();
        let wide = GomParams {
            so3: params.so3.clone().cast(DType::F64),
            scales: params.scales.clone().cast(DType::F64),
            offsets: params.offsets.clone().cast(DType::F64),
            colors: params.colors.clone(),
            opacities: params.opacities.clone(),
        };
        let g = self.gaussians_reference(lowres_vertices.cast(DType::F64), &wide);
        Gaussians {
            means: g.means.cast(dtype),
            covariances: g.covariances.cast(dtype),
            ..g
        }
    }

    fn check_shapes(&self, lowres_vertices: &Tensor<2>, params: &GomParams) {
        let v = self.subdivision.lowres.num_vertices;
        let f = self.num_gaussians();
        let dims = lowres_vertices.dims();
        assert_eq!(
            dims,
            [v, 3],
            "GomMesh::gaussians: `lowres_vertices` must be [{v}, 3], got {dims:?}"
        );
        for (name, t) in [
            ("so3", &params.so3),
            ("scales", &params.scales),
            ("offsets", &params.offsets),
            ("colors", &params.colors),
        ] {
            let dims = t.dims();
            assert_eq!(
                dims,
                [f, 3],
                "GomMesh::gaussians: `{name}` must be [{f}, 3], got {dims:?}"
            );
        }
        let dims = params.opacities.dims();
        assert_eq!(
            dims,
            [f],
            "GomMesh::gaussians: `opacities` must be [{f}], got {dims:?}"
        );
    }
}

/// The per-high-res-face corner table (`[F·9]` indices and weights): each corner's barycentric
/// slots in the low-res mesh, i.e. the subdivision table composed with the high-res faces.
///
/// A corner that is a low-res vertex or an edge midpoint leaves slots empty; the subdivision
/// table writes those as `(0, 0.0)`, and here they get index `-1` (out of range, which the op
/// reads as weight 0). Kept as vertex 0 they would all land in vertex 0's run of the inverted
/// table: about a third of all entries, summed by the GPU backward on three threads
/// (8 ms a call on an H100 for the training mesh, most of the GoM backward at two
/// subdivisions; BENCHMARKS.md, "On a GPU").
fn corner_table(subdivision: &Subdivision) -> (Vec<i32>, Vec<f32>) {
    let slots = || {
        subdivision
            .highres
            .faces
            .iter()
            .flatten()
            .flat_map(|&v| subdivision.highres_from_lowres[v as usize])
    };
    (
        slots()
            .map(|(i, w)| match i32::try_from(i) {
                Ok(i) if w != 0.0 => i,
                _ => -1,
            })
            .collect(),
        slots().map(|(_, w)| w).collect(),
    )
}

/// The corner table inverted (a stable counting sort by low-res vertex): the `[V↓ + 1]` offsets
/// of each vertex's run, and the run itself, the table entries that read the vertex in increasing
/// entry order (entries with an out-of-range index are left out). The GPU backward sums a
/// vertex's corner gradients along its run, one thread per vertex and axis: the same additions
/// in the same order as a sequential scatter of the rows, without float atomics (design.md §5.6).
pub(crate) fn corner_table_by_vertex(index: &[i32], num_vertices: usize) -> (Vec<i32>, Vec<i32>) {
    let slot = |i: i32| usize::try_from(i).ok().filter(|&v| v < num_vertices);
    let mut offsets = vec![0i32; num_vertices + 1];
    for v in index.iter().filter_map(|&i| slot(i)) {
        offsets[v + 1] += 1;
    }
    for v in 0..num_vertices {
        offsets[v + 1] += offsets[v];
    }
    let mut cursor = offsets.clone();
    let mut order = vec![0i32; offsets[num_vertices] as usize];
    for (entry, v) in index.iter().enumerate() {
        if let Some(v) = slot(*v) {
            order[cursor[v] as usize] = entry as i32;
            cursor[v] += 1;
        }
    }
    (offsets, order)
}

#[cfg(test)]
mod tests {
    #![allow(deprecated)]
    use super::*;
    use burn::tensor::TensorData;

    use crate::template::{BodyTemplate, lowres_template_path};
    use crate::testing::read;

    fn check_so3(device: &Device) {
        let r = Tensor::<2>::from_data(
            TensorData::new(
                vec![
                    0.0,
                    0.0,
                    0.0,
                    0.3,
                    -0.2,
                    0.9,
                    0.0,
                    0.0,
                    std::f32::consts::PI,
                ],
                [3, 3],
            ),
            device,
        );
        let rot = read(so3_exp_map(r));
        // Zero → identity (up to the 1e-4 floor, which only perturbs second order).
        for (i, v) in rot[0..9].iter().enumerate() {
            let e = if i % 4 == 0 { 1.0 } else { 0.0 };
            assert!((v - e).abs() < 1e-6);
        }
        let expect = glam::Mat3::from_axis_angle(
            glam::Vec3::new(0.3, -0.2, 0.9).normalize(),
            glam::Vec3::new(0.3, -0.2, 0.9).length(),
        );
        for r in 0..3 {
            for c in 0..3 {
                assert!((rot[9 + 3 * r + c] - expect.col(c)[r]).abs() < 1e-5);
            }
        }
        // 180° about z.
        assert!(
            (rot[18] + 1.0).abs() < 1e-5
                && (rot[22] + 1.0).abs() < 1e-5
                && (rot[26] - 1.0).abs() < 1e-5
        );
    }

    crate::cpu_backend_tests!(so3 => check_so3);

    /// At init, Σ = A Aᵀ and the mean is the centroid.
    #[test]
    fn init_state_is_frame_outer_product() {
        let device = Device::flex();
        let tri =
            |p: [f32; 3]| Tensor::<2>::from_data(TensorData::new(p.to_vec(), [1, 3]), &device);
        let (a, b, c) = ([0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.1, 0.2, 0.05]);
        let g = gaussians_from_triangles(tri(a), tri(b), tri(c), &GomParams::init(1, &device));
        let frames = steiner_frames(tri(a), tri(b), tri(c));
        let am = read(frames.frames);
        let cov = read(g.covariances);
        let sigma = |i: usize, j: usize| (0..3).map(|k| am[3 * i + k] * am[3 * j + k]).sum::<f32>();
        let expect = [
            sigma(0, 0),
            sigma(0, 1),
            sigma(0, 2),
            sigma(1, 1),
            sigma(1, 2),
            sigma(2, 2),
        ];
        for (x, e) in cov.iter().zip(expect) {
            assert!((x - e).abs() < 1e-6, "{cov:?} vs {expect:?}");
        }
        let mean = read(g.means);
        let centroid = [
            (a[0] + b[0] + c[0]) / 3.0,
            (a[1] + b[1] + c[1]) / 3.0,
            (a[2] + b[2] + c[2]) / 3.0,
        ];
        for k in 0..3 {
            assert!((mean[k] - centroid[k]).abs() < 1e-6);
        }
    }

    /// The inverted corner table lists, for each vertex, exactly the entries that read it, in
    /// increasing entry order, and leaves out-of-range indices out.
    #[test]
    fn corner_table_by_vertex_is_a_stable_inverse() {
        let index = [2, 0, 2, -1, 1, 7, 0, 2, 3];
        let (offsets, order) = corner_table_by_vertex(&index, 4);
        assert_eq!(offsets, [0, 2, 3, 6, 7]);
        assert_eq!(order, [1, 6, 4, 0, 2, 7, 8]);

        // On a real table: every in-range entry once, runs ascending, each run's entries
        // pointing at its vertex.
        let body = BodyTemplate::load(lowres_template_path()).unwrap();
        let subdivision = Subdivision::new(&body.topology, 1).unwrap();
        let v = subdivision.lowres.num_vertices;
        let (index, weight) = corner_table(&subdivision);
        let (offsets, order) = corner_table_by_vertex(&index, v);
        assert_eq!(offsets.len(), v + 1);
        // Empty slots are out of range, every used slot in range with a nonzero weight.
        assert!(
            index
                .iter()
                .zip(&weight)
                .all(|(&i, &w)| (i < 0) == (w == 0.0))
        );
        assert_eq!(order.len(), index.iter().filter(|&&i| i >= 0).count());
        let mut longest = 0;
        for vertex in 0..v {
            let run = &order[offsets[vertex] as usize..offsets[vertex + 1] as usize];
            assert!(run.windows(2).all(|w| w[0] < w[1]));
            assert!(run.iter().all(|&e| index[e as usize] == vertex as i32));
            longest = longest.max(run.len());
        }
        // A vertex's run holds the slots of the faces around it: no vertex collects the padding.
        let mean = order.len() / v;
        assert!(longest < 4 * mean, "longest run {longest}, mean {mean}");
    }
}

#[cfg(test)]
mod gradient_tests {
    //! Central finite differences against `backward()` for every differentiable input of the
    //! GoM geometry: triangle corners (hence vertices), rotations, scales and offsets.
    #![allow(deprecated)]
    use super::*;
    use crate::rng::Rng;
    use burn::tensor::{DType, TensorData};

    /// Inputs as f64 host vectors: [v0, v1, v2, so3, scales, offsets], each `[F*3]`.
    type Inputs = [Vec<f64>; 6];

    fn to_tensor(v: &[f64], device: &Device) -> Tensor<2> {
        Tensor::from_data(
            TensorData::new(v.to_vec(), [v.len() / 3, 3]),
            (device, DType::F64),
        )
    }

    /// The scalar `Σ Wm·means + Σ Wc·covariances` and its tensors.
    fn loss(
        inputs: &Inputs,
        wm: &[f64],
        wc: &[f64],
        device: &Device,
    ) -> (Tensor<1>, Vec<Tensor<2>>) {
        let t: Vec<Tensor<2>> = inputs
            .iter()
            .map(|v| to_tensor(v, device).require_grad())
            .collect();
        let f = inputs[0].len() / 3;
        let params = GomParams {
            so3: t[3].clone(),
            scales: t[4].clone(),
            offsets: t[5].clone(),
            colors: Tensor::zeros([f, 3], device),
            opacities: Tensor::ones([f], device),
        };
        let g = gaussians_from_triangles(t[0].clone(), t[1].clone(), t[2].clone(), &params);
        let wm = Tensor::<2>::from_data(TensorData::new(wm.to_vec(), [f, 3]), (device, DType::F64));
        let wc = Tensor::<2>::from_data(TensorData::new(wc.to_vec(), [f, 6]), (device, DType::F64));
        ((g.means * wm).sum() + (g.covariances * wc).sum(), t)
    }

    fn scalar(t: Tensor<1>) -> f64 {
        t.into_data().try_into_vec_as::<f64>().unwrap()[0]
    }

    fn check(device: &Device) {
        let ad = device.clone().autodiff();
        let mut rng = Rng::new(42);
        let f = 6;
        let mut inputs: Inputs = Default::default();
        for (k, v) in inputs.iter_mut().enumerate() {
            *v = (0..3 * f)
                .map(|_| match k {
                    0..=2 => rng.range(-0.3, 0.3),
                    3 => rng.range(-1.5, 1.5),
                    4 => rng.range(0.5, 2.0) * if rng.uniform() < 0.2 { -1.0 } else { 1.0 },
                    _ => rng.range(-1.0, 1.0),
                })
                .collect();
        }
        let wm: Vec<f64> = (0..3 * f).map(|_| rng.range(-1.0, 1.0)).collect();
        let wc: Vec<f64> = (0..6 * f).map(|_| rng.range(-1.0, 1.0) * 50.0).collect();
        let (l, leaves) = loss(&inputs, &wm, &wc, &ad);
        let grads = l.backward();
        let names = ["v0", "v1", "v2", "so3", "scales", "offsets"];
        for (k, leaf) in leaves.iter().enumerate() {
            let analytic = leaf.grad(&grads).unwrap().into_data();
            assert_eq!(analytic.dtype(), DType::F64, "the check runs in f64");
            let analytic = analytic.try_into_vec_as::<f64>().unwrap();
            for i in 0..inputs[k].len() {
                let eps = 1e-6;
                let mut plus = inputs.clone();
                plus[k][i] += eps;
                let mut minus = inputs.clone();
                minus[k][i] -= eps;
                let numeric = (scalar(loss(&plus, &wm, &wc, &ad).0)
                    - scalar(loss(&minus, &wm, &wc, &ad).0))
                    / (2.0 * eps);
                let a = analytic[i];
                assert!(
                    (a - numeric).abs() <= 1e-5 * a.abs().max(numeric.abs()) + 1e-7,
                    "{}[{i}]: analytic {a} vs numeric {numeric}",
                    names[k]
                );
            }
        }
    }

    crate::cpu_backend_tests!(geometry_gradients => check);
}
