//! The projection's kernels on Burn's CubeCL backend (see [`super::projection_op`]): one thread
//! per view and point each way, in the order of the tensor ops (`c_j = Σ_i p_i·Rᵀ_ij + t_j`,
//! then `c_x / max(c_z, MIN_DEPTH)·fx + cx`). The backward follows Burn's rules: the division's
//! `∂c_x = ∂u·fx / z'` and `∂z' = −(∂u·fx·c_x + ∂v·fy·c_y) / z'²`, which reaches `c_z` where
//! `c_z ≥ MIN_DEPTH` (the clamp's pass-through), plus `∂Z`; then `∂p_i = Σ_j ∂c_j·Rᵀ_ij`.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::projection_op::{CAMERA_FLOATS, ProjectionKernels, ProjectionOps};

/// Point `(view, point)`'s camera-space coordinate `j`.
#[cube]
fn camera_space(points: &[f32], cameras: &[f32], at: usize, cam: usize, j: usize) -> f32 {
    points[at] * cameras[cam + j]
        + points[at + 1] * cameras[cam + 3 + j]
        + points[at + 2] * cameras[cam + 6 + j]
        + cameras[cam + 9 + j]
}

/// One thread's point in its camera's frame.
#[derive(CubeType)]
struct Seen {
    /// The point's first float in the `[N, V, 3]` buffers.
    at: usize,
    /// Its camera's first float in the cameras table.
    cam: usize,
    x: f32,
    y: f32,
    z: f32,
    /// `max(z, MIN_DEPTH)`.
    z_safe: f32,
}

/// Thread `unit`'s point (view `unit / per_view`) in its camera's frame.
#[cube]
fn seen(points: &[f32], cameras: &[f32], unit: usize, per_view: usize, min_depth: f32) -> Seen {
    let at = unit * 3;
    let cam = (unit / per_view) * CAMERA_FLOATS;
    let x = camera_space(points, cameras, at, cam, 0);
    let y = camera_space(points, cameras, at, cam, 1);
    let z = camera_space(points, cameras, at, cam, 2);
    Seen {
        at,
        cam,
        x,
        y,
        z,
        z_safe: f32::max(z, min_depth),
    }
}

#[cube(launch)]
fn project_kernel(
    points: &[f32],
    cameras: &[f32],
    out: &mut [f32],
    units: usize,
    per_view: usize,
    min_depth: f32,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let p = seen(points, cameras, unit, per_view, min_depth);
        out[p.at] = p.x / p.z_safe * cameras[p.cam + 12] + cameras[p.cam + 14];
        out[p.at + 1] = p.y / p.z_safe * cameras[p.cam + 13] + cameras[p.cam + 15];
        out[p.at + 2] = p.z;
    }
}

#[cube(launch)]
fn project_backward_kernel(
    points: &[f32],
    cameras: &[f32],
    grad: &[f32],
    dp: &mut [f32],
    units: usize,
    per_view: usize,
    min_depth: f32,
) {
    let unit = ABSOLUTE_POS;
    if unit < units {
        let p = seen(points, cameras, unit, per_view, min_depth);
        let (at, cam, zs) = (p.at, p.cam, p.z_safe);
        let gu = grad[at] * cameras[cam + 12];
        let gv = grad[at + 1] * cameras[cam + 13];
        let dx = gu / zs;
        let dy = gv / zs;
        let mut dz = grad[at + 2];
        if p.z >= min_depth {
            dz += -(gu * p.x) / (zs * zs) - (gv * p.y) / (zs * zs);
        }
        for i in 0..3usize {
            dp[at + i] = dx * cameras[cam + 3 * i]
                + dy * cameras[cam + 3 * i + 1]
                + dz * cameras[cam + 3 * i + 2];
        }
    }
}

impl ProjectionOps for CubeBackend {
    fn project(points: FloatTensor<Self>, cameras: FloatTensor<Self>) -> FloatTensor<Self> {
        let dtype = points.dtype();
        let shape = points.shape();
        let (client, device) = (points.client.clone(), points.device.clone());
        let (points, cameras) = (prepare(points), prepare(cameras));
        let units = shape[0] * shape[1];
        let out = client.empty(4 * (3 * units).max(1));
        if units > 0 {
            project_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&points),
                tensor_arg(&cameras),
                arg(&out, 3 * units),
                units,
                shape[1],
                super::MIN_DEPTH as f32,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &shape), dtype)
    }
}

impl ProjectionKernels for CubeBackend {
    fn project_backward(
        points: FloatTensor<Self>,
        cameras: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let dtype = points.dtype();
        let shape = points.shape();
        let (client, device) = (points.client.clone(), points.device.clone());
        let [points, cameras, grad] = [points, cameras, grad].map(prepare);
        let units = shape[0] * shape[1];
        let dp = client.empty(4 * (3 * units).max(1));
        if units > 0 {
            project_backward_kernel::launch(
                &client,
                count_1d(units),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&points),
                tensor_arg(&cameras),
                tensor_arg(&grad),
                arg(&dp, 3 * units),
                units,
                shape[1],
                super::MIN_DEPTH as f32,
            );
        }
        cast_to(tensor_f32(&client, &device, dp, &shape), dtype)
    }
}
