//! The skinning and its backward on Burn's CubeCL backend (see [`super`]): one thread per
//! vertex, looping over the joints. Forward it sums `w_j (R_j x + t_j)` over the joints with a
//! weight; backward it writes each joint's `∂w = g · (R_j x + t_j)` and sums
//! `∂x = Σ_j w_j R_jᵀ g`.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::op::{SkinningKernels, SkinningOps};
use crate::cube::host::{THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32};

/// Row `i` of joint `b / 12`'s `[R | t]` applied to `[x, 1]`.
#[cube]
fn transformed(m: &[f32], b: usize, i: usize, x0: f32, x1: f32, x2: f32) -> f32 {
    let r = b + 4 * i;
    m[r] * x0 + m[r + 1] * x1 + m[r + 2] * x2 + m[r + 3]
}

#[cube(launch)]
fn skin_kernel(x: &[f32], w: &[f32], m: &[f32], out: &mut [f32], vertices: usize, joints: usize) {
    let v = ABSOLUTE_POS;
    if v < vertices {
        let (x0, x1, x2) = (x[3 * v], x[3 * v + 1], x[3 * v + 2]);
        let mut o0 = 0.0f32;
        let mut o1 = 0.0f32;
        let mut o2 = 0.0f32;
        for j in 0..joints {
            let wj = w[v * joints + j];
            if wj != 0.0 {
                let b = 12 * j;
                o0 += wj * transformed(m, b, 0, x0, x1, x2);
                o1 += wj * transformed(m, b, 1, x0, x1, x2);
                o2 += wj * transformed(m, b, 2, x0, x1, x2);
            }
        }
        out[3 * v] = o0;
        out[3 * v + 1] = o1;
        out[3 * v + 2] = o2;
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn skin_backward_kernel(
    x: &[f32],
    w: &[f32],
    m: &[f32],
    g: &[f32],
    dx: &mut [f32],
    dw: &mut [f32],
    vertices: usize,
    joints: usize,
) {
    let v = ABSOLUTE_POS;
    if v < vertices {
        let (x0, x1, x2) = (x[3 * v], x[3 * v + 1], x[3 * v + 2]);
        let (g0, g1, g2) = (g[3 * v], g[3 * v + 1], g[3 * v + 2]);
        let mut d0 = 0.0f32;
        let mut d1 = 0.0f32;
        let mut d2 = 0.0f32;
        for j in 0..joints {
            let b = 12 * j;
            dw[v * joints + j] = g0 * transformed(m, b, 0, x0, x1, x2)
                + g1 * transformed(m, b, 1, x0, x1, x2)
                + g2 * transformed(m, b, 2, x0, x1, x2);
            let wj = w[v * joints + j];
            d0 += wj * (m[b] * g0 + m[b + 4] * g1 + m[b + 8] * g2);
            d1 += wj * (m[b + 1] * g0 + m[b + 5] * g1 + m[b + 9] * g2);
            d2 += wj * (m[b + 2] * g0 + m[b + 6] * g1 + m[b + 10] * g2);
        }
        dx[3 * v] = d0;
        dx[3 * v + 1] = d1;
        dx[3 * v + 2] = d2;
    }
}

impl SkinningOps for CubeBackend {
    fn skin(
        vertices: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        transforms: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let dtype = vertices.dtype();
        let [v, j] = [vertices.shape()[0], weights.shape()[1]];
        let (client, device) = (vertices.client.clone(), vertices.device.clone());
        let [x, w, m] = [vertices, weights, transforms].map(prepare);
        let out = client.empty(4 * (3 * v).max(1));
        if v > 0 {
            skin_kernel::launch(
                &client,
                count_1d(v),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&x),
                tensor_arg(&w),
                tensor_arg(&m),
                arg(&out, 3 * v),
                v,
                j,
            );
        }
        cast_to(tensor_f32(&client, &device, out, &[v, 3]), dtype)
    }
}

impl SkinningKernels for CubeBackend {
    fn skin_backward(
        vertices: FloatTensor<Self>,
        weights: FloatTensor<Self>,
        transforms: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let dtype = vertices.dtype();
        let [v, j] = [vertices.shape()[0], weights.shape()[1]];
        let (client, device) = (vertices.client.clone(), vertices.device.clone());
        let [x, w, m, g] = [vertices, weights, transforms, grad].map(prepare);
        let dx = client.empty(4 * (3 * v).max(1));
        let dw = client.empty(4 * (v * j).max(1));
        if v > 0 {
            skin_backward_kernel::launch(
                &client,
                count_1d(v),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&x),
                tensor_arg(&w),
                tensor_arg(&m),
                tensor_arg(&g),
                arg(&dx, 3 * v),
                arg(&dw, (v * j).max(1)),
                v,
                j,
            );
        }
        (
            cast_to(tensor_f32(&client, &device, dx, &[v, 3]), dtype),
            cast_to(tensor_f32(&client, &device, dw, &[v, j]), dtype),
        )
    }
}
