//! The triangle-ID rasterizer as a Burn backend extension, so visibility runs where the mesh
//! already lives: the CPU backends call [`super::cpu`], Burn's CubeCL backend (wgpu) runs the
//! kernels of the crate-private `visibility::cube` module, and `Autodiff<B>` forwards to `B` on
//! the primal values (nothing here has a gradient).
//!
//! The op cannot return an error, so it is lenient where the checked CPU entry point
//! ([`super::rasterize_triangle_ids`]) is strict: a face with an index outside the vertex list
//! or a non-finite corner covers nothing. Shapes are checked by the tensor-level wrappers in
//! [`super`] before dispatch.

// NdArray is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend the project
// requires (design.md §1.4).
#![allow(deprecated)]

use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::fusion::custom::TensorSpec;
use burn::backend::tensor::{FloatTensor, IntTensor};
use burn::backend::{
    Autodiff, AutodiffBackend, Backend, Flex, NdArray, TensorMetadata, backend_extension,
};
use burn::tensor::{DType, TensorData};
use glam::Vec3;

use super::ViewSet;
use super::cpu::{self, TriangleIdBuffer};
use crate::camera::Camera;
use crate::readback;

/// Triangle-ID rasterization and the per-vertex visibility derived from it.
#[backend_extension(NdArray, Flex, Cube, Fusion, Autodiff)]
pub trait TriangleIdOps: Backend {
    /// Rasterizes `faces` (`[F, 3]`, vertex indices) over world-space `vertices` (`[V, 3]`).
    /// Returns the owning face per pixel (`[H, W]`, `-1` where empty) and its camera-space
    /// depth (`[H, W]`, `+inf` where empty).
    #[fusion(meta = |_vertices, _faces, camera| {
        let shape = burn::tensor::Shape::new([camera.height as usize, camera.width as usize]);
        (TensorSpec::new(shape.clone(), DType::I32), TensorSpec::new(shape, DType::F32))
    })]
    fn rasterize_triangle_ids(
        vertices: FloatTensor<Self>,
        faces: IntTensor<Self>,
        camera: Camera,
    ) -> (IntTensor<Self>, FloatTensor<Self>);

    /// `[num_vertices]`, 1 for every vertex of a face that owns a pixel of `face_ids`, else 0.
    #[fusion(meta = |_face_ids, _faces, num_vertices| {
        TensorSpec::new(burn::tensor::Shape::new([*num_vertices]), DType::I32)
    })]
    fn visible_vertices(
        face_ids: IntTensor<Self>,
        faces: IntTensor<Self>,
        num_vertices: usize,
    ) -> IntTensor<Self>;

    /// The visibility of a mesh posed once per view (`vertices` `[V, 3n]`, view `k`'s positions
    /// in columns `3k..3k + 3`), rasterized in each view's camera: `[lowres, n]` flags of the
    /// first `views.lowres` vertices and `[F, n]` flags of the faces (1.0 visible, else 0.0). A
    /// vertex is visible when it is a corner of a face that owns a pixel, a face when its three
    /// corners are (super::visibility_in_views).
    #[fusion(meta = |vertices, faces, views| {
        let n = views.cameras.len();
        let rows = vertices.shape.num_elements() / (3 * n).max(1);
        let faces = faces.shape.num_elements() / 3;
        (
            TensorSpec::new(burn::tensor::Shape::new([views.lowres.min(rows), n]), DType::F32),
            TensorSpec::new(burn::tensor::Shape::new([faces, n]), DType::F32),
        )
    })]
    fn visibility_in_views(
        vertices: FloatTensor<Self>,
        faces: IntTensor<Self>,
        views: ViewSet,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

/// Face triples from a flat index list; negative or oversized indices become `u32::MAX`, which
/// the lenient rasterizer skips as out of range.
fn face_triples(flat: &[i64]) -> Vec<[u32; 3]> {
    let to_u32 = |i: i64| u32::try_from(i).unwrap_or(u32::MAX);
    flat.chunks_exact(3)
        .map(|c| [to_u32(c[0]), to_u32(c[1]), to_u32(c[2])])
        .collect()
}

fn cpu_rasterize<B: Backend>(
    vertices: FloatTensor<B>,
    faces: IntTensor<B>,
    camera: Camera,
) -> (IntTensor<B>, FloatTensor<B>) {
    let device = vertices.device();
    let points: Vec<Vec3> = readback::cpu_float::<B>("vertices", vertices)
        .chunks_exact(3)
        .map(Vec3::from_slice)
        .collect();
    let faces = face_triples(&readback::cpu_int::<B>("faces", faces));
    let TriangleIdBuffer {
        width,
        height,
        face_ids,
        depth,
    } = cpu::rasterize_unchecked(&points, &faces, &camera);
    let shape = [height as usize, width as usize];
    let ids: Vec<i64> = face_ids.into_iter().map(i64::from).collect();
    (
        B::int_from_data(TensorData::new(ids, shape), &device),
        B::float_from_data(TensorData::new(depth, shape), &device),
    )
}

/// The vertices of the faces that own a pixel of `face_ids`, leniently: an id or a corner out
/// of range marks nothing (where [`cpu::visible_vertices`] panics).
fn marked_vertices(
    face_ids: impl IntoIterator<Item = i64>,
    faces: &[[u32; 3]],
    num_vertices: usize,
) -> Vec<bool> {
    let mut visible = vec![false; num_vertices];
    let mut face_seen = vec![false; faces.len()];
    for id in face_ids {
        let Ok(f) = usize::try_from(id) else { continue };
        if f >= faces.len() || std::mem::replace(&mut face_seen[f], true) {
            continue;
        }
        for &v in &faces[f] {
            if let Some(slot) = visible.get_mut(v as usize) {
                *slot = true;
            }
        }
    }
    visible
}

fn cpu_visible_vertices<B: Backend>(
    face_ids: IntTensor<B>,
    faces: IntTensor<B>,
    num_vertices: usize,
) -> IntTensor<B> {
    let device = faces.device();
    let faces = face_triples(&readback::cpu_int::<B>("faces", faces));
    let ids = readback::cpu_int::<B>("face_ids", face_ids);
    let visible: Vec<i64> = marked_vertices(ids, &faces, num_vertices)
        .into_iter()
        .map(i64::from)
        .collect();
    B::int_from_data(TensorData::new(visible, [num_vertices]), &device)
}

/// [`TriangleIdOps::visibility_in_views`] on the host: each view through [`cpu`]'s rasterizer.
fn cpu_visibility_in_views<B: Backend>(
    vertices: FloatTensor<B>,
    faces: IntTensor<B>,
    views: ViewSet,
) -> (FloatTensor<B>, FloatTensor<B>) {
    let device = vertices.device();
    let n = views.cameras.len();
    let coords = readback::cpu_float::<B>("vertices", vertices);
    let rows = coords.len() / (3 * n).max(1);
    let faces = face_triples(&readback::cpu_int::<B>("faces", faces));
    let lowres = views.lowres.min(rows);
    let mut vertex_flags = vec![0.0f32; lowres * n];
    let mut face_flags = vec![0.0f32; faces.len() * n];
    for (k, camera) in views.cameras.iter().enumerate() {
        let points: Vec<Vec3> = (0..rows)
            .map(|v| Vec3::from_slice(&coords[v * 3 * n + 3 * k..][..3]))
            .collect();
        let ids = cpu::rasterize_unchecked(&points, &faces, camera).face_ids;
        let visible = marked_vertices(ids.into_iter().map(i64::from), &faces, rows);
        for v in 0..lowres {
            vertex_flags[v * n + k] = f32::from(u8::from(visible[v]));
        }
        for (f, corners) in faces.iter().enumerate() {
            let all = corners
                .iter()
                .all(|&v| visible.get(v as usize).copied().unwrap_or(false));
            face_flags[f * n + k] = f32::from(u8::from(all));
        }
    }
    (
        B::float_from_data(TensorData::new(vertex_flags, [lowres, n]), &device),
        B::float_from_data(TensorData::new(face_flags, [faces.len(), n]), &device),
    )
}

macro_rules! cpu_triangle_id_backend {
    ($backend:ty) => {
        impl TriangleIdOps for $backend {
            fn rasterize_triangle_ids(
                vertices: FloatTensor<Self>,
                faces: IntTensor<Self>,
                camera: Camera,
            ) -> (IntTensor<Self>, FloatTensor<Self>) {
                cpu_rasterize::<Self>(vertices, faces, camera)
            }

            fn visible_vertices(
                face_ids: IntTensor<Self>,
                faces: IntTensor<Self>,
                num_vertices: usize,
            ) -> IntTensor<Self> {
                cpu_visible_vertices::<Self>(face_ids, faces, num_vertices)
            }

            fn visibility_in_views(
                vertices: FloatTensor<Self>,
                faces: IntTensor<Self>,
                views: ViewSet,
            ) -> (FloatTensor<Self>, FloatTensor<Self>) {
                cpu_visibility_in_views::<Self>(vertices, faces, views)
            }
        }
    };
}

cpu_triangle_id_backend!(NdArray);
cpu_triangle_id_backend!(Flex);

impl<B: TriangleIdOps, C: CheckpointStrategy> TriangleIdOps for Autodiff<B, C> {
    fn rasterize_triangle_ids(
        vertices: FloatTensor<Self>,
        faces: IntTensor<Self>,
        camera: Camera,
    ) -> (IntTensor<Self>, FloatTensor<Self>) {
        let (ids, depth) = B::rasterize_triangle_ids(Self::inner(vertices), faces, camera);
        (ids, Self::from_inner(depth))
    }

    fn visible_vertices(
        face_ids: IntTensor<Self>,
        faces: IntTensor<Self>,
        num_vertices: usize,
    ) -> IntTensor<Self> {
        B::visible_vertices(face_ids, faces, num_vertices)
    }

    fn visibility_in_views(
        vertices: FloatTensor<Self>,
        faces: IntTensor<Self>,
        views: ViewSet,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let (vertex_flags, face_flags) =
            B::visibility_in_views(Self::inner(vertices), faces, views);
        (Self::from_inner(vertex_flags), Self::from_inner(face_flags))
    }
}
