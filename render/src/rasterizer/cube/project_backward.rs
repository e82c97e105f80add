//! Backward of stage 1, **project backward** (`cpu::project_backward`): the dense 2D gradients
//! of [`super::rasterize_backward`] chained back through the conic, the EWA Jacobian and the
//! view transform to the 3D inputs, one thread per Gaussian.

use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;

use super::common::{
    GRAD_COLOR, GRAD_CONIC_A, GRAD_CONIC_B, GRAD_CONIC_C, GRAD_DEPTH, GRAD_LANES, GRAD_OPACITY,
    GRAD_X, GRAD_Y, SPLAT_CONIC_A, SPLAT_CONIC_B, SPLAT_CONIC_C, SPLAT_LANES,
};
use super::project::{COV_LANES, ewa, sym_row};
use crate::cube::view::camera_of;
use crate::rasterizer::cpu::FOV_CLAMP;

/// One thread per Gaussian: chains the 2D gradients back through the conic, the EWA Jacobian
/// and the view transform to the mean and the 6 covariance entries (`cpu::project_backward`),
/// and copies out the colour and opacity gradients. Culled Gaussians get zeros.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn project_backward_kernel(
    means: &[f32],
    covs: &[f32],
    cameras: &[f32],
    splats: &[f32],
    tile_counts: &[u32],
    grad2d: &[f32],
    d_means: &mut [f32],
    d_covs: &mut [f32],
    d_colors: &mut [f32],
    d_opacities: &mut [f32],
    num_gaussians: u32,
    views: u32,
) {
    // One thread per splat (Gaussian `g` in view `k` at `i = k·num_gaussians + g`), its
    // gradients at `i`: per view, summed over the views afterwards (`sum_views_kernel`).
    let splat = ABSOLUTE_POS as u32;
    if splat < num_gaussians * views {
        let i = splat as usize;
        let g = (splat % num_gaussians) as usize;
        let view = camera_of(cameras, splat / num_gaussians);
        if tile_counts[i] == 0u32 {
            for c in 0..3u32 {
                d_means[3 * i + c as usize] = 0.0;
                d_colors[3 * i + c as usize] = 0.0;
            }
            for c in 0..COV_LANES {
                d_covs[COV_LANES * i + c] = 0.0;
            }
            d_opacities[i] = 0.0;
        } else {
            let gb = GRAD_LANES * i;
            d_colors[3 * i] = grad2d[gb + GRAD_COLOR];
            d_colors[3 * i + 1] = grad2d[gb + GRAD_COLOR + 1];
            d_colors[3 * i + 2] = grad2d[gb + GRAD_COLOR + 2];
            d_opacities[i] = grad2d[gb + GRAD_OPACITY];
            let dxy0 = grad2d[gb + GRAD_X];
            let dxy1 = grad2d[gb + GRAD_Y];
            let dq0 = grad2d[gb + GRAD_CONIC_A];
            let dq1 = grad2d[gb + GRAD_CONIC_B];
            let dq2 = grad2d[gb + GRAD_CONIC_C];
            let d_depth = grad2d[gb + GRAD_DEPTH];

            let mx = means[3 * g];
            let my = means[3 * g + 1];
            let mz = means[3 * g + 2];
            let x = view.camera_x(mx, my, mz);
            let y = view.camera_y(mx, my, mz);
            let z = view.camera_z(mx, my, mz);
            let fx = view.fx;
            let fy = view.fy;
            let e = ewa(&view, x, y, z);

            // Conic → 2D covariance: dL/dM = −Q·G·Q, G the symmetric gradient of Q.
            let s = SPLAT_LANES * i;
            let qa = splats[s + SPLAT_CONIC_A];
            let qb = splats[s + SPLAT_CONIC_B];
            let qc = splats[s + SPLAT_CONIC_C];
            let h = 0.5 * dq1;
            let qg00 = qa * dq0 + qb * h;
            let qg01 = qa * h + qb * dq2;
            let qg10 = qb * dq0 + qc * h;
            let qg11 = qb * h + qc * dq2;
            let gm00 = -(qg00 * qa + qg01 * qb);
            let gm01 = -(qg00 * qb + qg01 * qc);
            let gm10 = -(qg10 * qa + qg11 * qb);
            let gm11 = -(qg10 * qb + qg11 * qc);

            // dL/dΣ = Tᵀ·dL/dM·T, entry (a, b) with u = T row 0, v = T row 1.
            let mut u = Array::<f32>::new(3usize);
            let mut v = Array::<f32>::new(3usize);
            u[0] = e.t0x;
            u[1] = e.t0y;
            u[2] = e.t0z;
            v[0] = e.t1x;
            v[1] = e.t1y;
            v[2] = e.t1z;
            let mut ds = Array::<f32>::new(9usize);
            for a in 0..3u32 {
                for b in 0..3u32 {
                    let ua = u[a as usize];
                    let va = v[a as usize];
                    let ub = u[b as usize];
                    let vb = v[b as usize];
                    ds[(3 * a + b) as usize] =
                        ua * gm00 * ub + ua * gm01 * vb + va * gm10 * ub + va * gm11 * vb;
                }
            }
            let cb = COV_LANES * i;
            d_covs[cb] = ds[0];
            d_covs[cb + 1] = ds[1] + ds[3];
            d_covs[cb + 2] = ds[2] + ds[6];
            d_covs[cb + 3] = ds[4];
            d_covs[cb + 4] = ds[5] + ds[7];
            d_covs[cb + 5] = ds[8];

            // dL/dT = 2·dL/dM·T·Σ.
            let mut ts0 = Array::<f32>::new(3usize);
            let mut ts1 = Array::<f32>::new(3usize);
            let input_cov = COV_LANES * g;
            for a in 0..3u32 {
                ts0[a as usize] = sym_row(covs, input_cov, a, e.t0x, e.t0y, e.t0z);
                ts1[a as usize] = sym_row(covs, input_cov, a, e.t1x, e.t1y, e.t1z);
            }
            let mut d_j00 = 0.0f32;
            let mut d_j02 = 0.0f32;
            let mut d_j11 = 0.0f32;
            let mut d_j12 = 0.0f32;
            for a in 0..3u32 {
                let au = a as usize;
                let dt0 = 2.0 * (gm00 * ts0[au] + gm01 * ts1[au]);
                let dt1 = 2.0 * (gm10 * ts0[au] + gm11 * ts1[au]);
                d_j00 += dt0 * view.rotation(0u32, a);
                d_j02 += dt0 * view.rotation(2u32, a);
                d_j11 += dt1 * view.rotation(1u32, a);
                d_j12 += dt1 * view.rotation(2u32, a);
            }

            let z2 = z * z;
            let z3 = z * z * z;
            let mut dvx = 0.0f32;
            let mut dvy = 0.0f32;
            let mut dvz = -fx / z2 * d_j00 - fy / z2 * d_j11;
            if e.clamped_x {
                // J02 = −fx·(±lim)/z: only z moves it.
                let lim =
                    select(x / z >= 0.0, 1.0f32, -1.0f32) * FOV_CLAMP * f32::cast_from(view.width)
                        / (2.0 * fx);
                dvz += fx * lim / z2 * d_j02;
            } else {
                dvx += -fx / z2 * d_j02;
                dvz += 2.0 * fx * x / z3 * d_j02;
            }
            if e.clamped_y {
                let lim =
                    select(y / z >= 0.0, 1.0f32, -1.0f32) * FOV_CLAMP * f32::cast_from(view.height)
                        / (2.0 * fy);
                dvz += fy * lim / z2 * d_j12;
            } else {
                dvy += -fy / z2 * d_j12;
                dvz += 2.0 * fy * y / z3 * d_j12;
            }
            dvx += fx / z * dxy0;
            dvy += fy / z * dxy1;
            dvz += -fx * x / z2 * dxy0 - fy * y / z2 * dxy1 + d_depth;
            // dL/dmean = Rᵀ·dL/dt.
            d_means[3 * i] = view.r00 * dvx + view.r10 * dvy + view.r20 * dvz;
            d_means[3 * i + 1] = view.r01 * dvx + view.r11 * dvy + view.r21 * dvz;
            d_means[3 * i + 2] = view.r02 * dvx + view.r12 * dvy + view.r22 * dvz;
        }
    }
}

/// `out[i] = Σ_k per_view[k·len + i]` for `i < len`, the views in order.
#[cube]
fn sum_over_views(per_view: &[f32], out: &mut [f32], i: u32, len: u32, views: u32) {
    let mut sum = per_view[i as usize];
    for k in 1..views {
        sum += per_view[(k * len + i) as usize];
    }
    out[i as usize] = sum;
}

/// One thread per Gaussian: its four gradients summed over the views in order (the splats' of
/// [`project_backward_kernel`], view after view).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn sum_views_kernel(
    s_means: &[f32],
    s_covs: &[f32],
    s_colors: &[f32],
    s_opacities: &[f32],
    d_means: &mut [f32],
    d_covs: &mut [f32],
    d_colors: &mut [f32],
    d_opacities: &mut [f32],
    num_gaussians: u32,
    views: u32,
) {
    let g = ABSOLUTE_POS as u32;
    if g < num_gaussians {
        for c in 0..3u32 {
            sum_over_views(s_means, d_means, 3 * g + c, 3 * num_gaussians, views);
            sum_over_views(s_colors, d_colors, 3 * g + c, 3 * num_gaussians, views);
        }
        for c in 0..6u32 {
            sum_over_views(s_covs, d_covs, 6 * g + c, 6 * num_gaussians, views);
        }
        sum_over_views(s_opacities, d_opacities, g, num_gaussians, views);
    }
}
