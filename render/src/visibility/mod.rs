//! Discrete visibility: a triangle-ID z-buffer (which face is nearest at each pixel) and the
//! vertices of the faces that own a pixel (design.md §6.7). No gradient flows through it.
//!
//! Two entry points over one algorithm:
//!
//! - [`rasterize_triangle_ids`] on host slices: the checked CPU reference ([`cpu`], `f64` edge
//!   functions, rayon over row bands). Bad input is an error naming the face or vertex.
//! - [`rasterize_on_device`] on tensors: a Burn backend extension ([`op::TriangleIdOps`]) that
//!   runs the CPU reference on the ndarray and Flex backends and CubeCL kernels on wgpu, so the
//!   feedback loop's visibility never leaves the GPU. [`TriangleIds::visible_vertices`] turns
//!   the buffer into a per-vertex mask on the same device.
//!
//! The GPU kernels mirror the CPU's clipping, pixel convention, watertight edge functions and
//! tie rules, in `f32` (WGSL has no `f64`). Pixels whose centre is within rounding of an edge or
//! of a depth tie may therefore go to the other face; everything else agrees exactly, which the
//! backend parity tests check.
//!
//! ```
//! use burn::tensor::{Device, Int, Tensor};
//! use glam::{Affine3A, Vec3};
//! use lifegom_render::camera::{Camera, Intrinsics};
//! use lifegom_render::visibility::rasterize_on_device;
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let device = Device::flex();
//! let camera = Camera::new(Intrinsics { fx: 16.0, fy: 16.0, cx: 8.0, cy: 8.0 },
//!                          Affine3A::IDENTITY, 16, 16)?;
//! // One triangle in front of the camera, one corner behind it (clipped at the near plane).
//! let vertices = Tensor::<2>::from_floats([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, -1.0]], &device);
//! let faces = Tensor::<2, Int>::from_ints([[0, 1, 2]], &device);
//! let ids = rasterize_on_device(vertices, faces.clone(), &camera)?;
//! assert!(ids.face_ids.clone().equal_elem(0).int().sum().into_scalar::<i64>() > 10);
//! let visible = ids.visible_vertices(faces, 3);
//! assert_eq!(visible.to_data().iter::<i64>().collect::<Vec<_>>(), [1, 1, 1]);
//! # Ok(()) }
//! ```

pub mod cpu;
mod cube;
pub mod op;

use burn::tensor::{Int, Tensor};

pub use cpu::{
    BAND_ROWS, NEAR, TriangleIdBuffer, rasterize_triangle_ids, visible_faces, visible_vertices,
};

use crate::camera::Camera;
use crate::error::{RenderError, Result};

/// A triangle-ID buffer on a Burn device.
#[derive(Debug, Clone)]
pub struct TriangleIds {
    /// Face owning each pixel, `[H, W]`, `-1` where no face covers it.
    pub face_ids: Tensor<2, Int>,
    /// Camera-space depth of the owning face at each pixel centre, `[H, W]`, `+inf` where empty.
    pub depth: Tensor<2>,
}

/// Rasterizes `faces` (`[F, 3]`) over world-space `vertices` (`[V, 3]`) into a triangle-ID
/// buffer of the camera's size, on the vertices' device.
///
/// Checks the camera and the shapes. It does not read the values back (that would stall a GPU
/// pipeline): a face with an index outside `[0, V)` or a non-finite corner covers nothing. Use
/// [`rasterize_triangle_ids`] for a strict check.
pub fn rasterize_on_device(
    vertices: Tensor<2>,
    faces: Tensor<2, Int>,
    camera: &Camera,
) -> Result<TriangleIds> {
    let _span = tracing::trace_span!(
        "rasterize_on_device",
        faces = faces.dims()[0],
        width = camera.width,
        height = camera.height
    )
    .entered();
    camera.validate()?;
    check_columns("vertices", vertices.dims(), 3)?;
    let [num_faces, _] = check_columns("faces", faces.dims(), 3)?;
    if num_faces > i32::MAX as usize {
        return Err(RenderError::InvalidInput {
            what: "faces",
            reason: format!("{num_faces} faces do not fit i32 face ids"),
        });
    }
    let (face_ids, depth) = <burn::backend::Dispatch as op::TriangleIdOps>::rasterize_triangle_ids(
        vertices.into_dispatch(),
        faces.into_dispatch(),
        *camera,
    );
    Ok(TriangleIds {
        face_ids: Tensor::from_dispatch(face_ids),
        depth: Tensor::from_dispatch(depth),
    })
}

/// The cameras of a [`visibility_in_views`] call, one per view (of one image size), and how
/// many leading vertices (the low-res mesh's, of a subdivided one) have their flags returned.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewSet {
    /// One camera per view.
    pub cameras: Vec<Camera>,
    /// Vertices whose flags are returned: the first `lowres`.
    pub lowres: usize,
}

/// Per-view visibility flags of a mesh ([`visibility_in_views`]).
#[derive(Debug, Clone)]
pub struct ViewVisibility {
    /// `[lowres, n]`: 1.0 where the vertex is a corner of a face owning a pixel of the view.
    pub vertices: Tensor<2>,
    /// `[F, n]`: 1.0 where the face's three corners are visible in the view.
    pub faces: Tensor<2>,
}

/// The visibility of `faces` (`[F, 3]`) over a mesh posed once per view, `vertices` `[V, 3n]`
/// (view `k`'s positions in columns `3k..3k + 3`), in each view's camera: on a CubeCL device
/// all views in one set of launches (five, where a view at a time takes ten with the flags;
/// design.md §6.7), on the CPU backends [`cpu`]'s rasterizer view by view. The same flags as
/// [`rasterize_on_device`] and [`TriangleIds::visible_vertices`] per view. Errors name a bad
/// camera, a shape that does not match the views, or cameras of different sizes.
pub fn visibility_in_views(
    vertices: Tensor<2>,
    faces: Tensor<2, Int>,
    views: &ViewSet,
) -> Result<ViewVisibility> {
    let _span = tracing::trace_span!("visibility_in_views", views = views.cameras.len()).entered();
    let n = views.cameras.len();
    let Some(first) = views.cameras.first() else {
        return Err(RenderError::InvalidInput {
            what: "cameras",
            reason: "no view".into(),
        });
    };
    for camera in &views.cameras {
        camera.validate()?;
        if (camera.width, camera.height) != (first.width, first.height) {
            return Err(RenderError::InvalidInput {
                what: "cameras",
                reason: format!(
                    "views of one call share an image size: {}×{} and {}×{}",
                    first.width, first.height, camera.width, camera.height
                ),
            });
        }
    }
    check_columns("vertices", vertices.dims(), 3 * n)?;
    let [num_faces, _] = check_columns("faces", faces.dims(), 3)?;
    if num_faces > i32::MAX as usize {
        return Err(RenderError::InvalidInput {
            what: "faces",
            reason: format!("{num_faces} faces do not fit i32 face ids"),
        });
    }
    let (vertex_flags, face_flags) =
        <burn::backend::Dispatch as op::TriangleIdOps>::visibility_in_views(
            vertices.into_dispatch(),
            faces.into_dispatch(),
            views.clone(),
        );
    Ok(ViewVisibility {
        vertices: Tensor::from_dispatch(vertex_flags),
        faces: Tensor::from_dispatch(face_flags),
    })
}

impl TriangleIds {
    /// `[num_vertices]`: 1 for every vertex of a face (of `faces`, `[F, 3]`, the faces that were
    /// rasterized) that owns at least one pixel, else 0. For a subdivided mesh the first `V↓`
    /// entries are the low-res visibility.
    pub fn visible_vertices(&self, faces: Tensor<2, Int>, num_vertices: usize) -> Tensor<1, Int> {
        Tensor::from_dispatch(
            <burn::backend::Dispatch as op::TriangleIdOps>::visible_vertices(
                self.face_ids.clone().into_dispatch(),
                faces.into_dispatch(),
                num_vertices,
            ),
        )
    }
}

fn check_columns(what: &'static str, dims: [usize; 2], columns: usize) -> Result<[usize; 2]> {
    if dims[1] != columns {
        return Err(RenderError::InvalidInput {
            what,
            reason: format!("expected shape [_, {columns}], got {dims:?}"),
        });
    }
    Ok(dims)
}
