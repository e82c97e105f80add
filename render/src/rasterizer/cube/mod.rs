//! The rasterizer op on Burn's CubeCL backend (wgpu, and any other CubeCL runtime).
//!
//! This file is the host side: buffers, launches, and the state saved for the backward. The
//! kernels live one file per stage, as in Brush:
//!
//! | module | holds |
//! |---|---|
//! | `common` | tile geometry, the per-Gaussian record layouts (`splats`, `rects`, `grad2d`), alpha evaluation |
//! | `project` | 1. projection |
//! | [`sort`] | 2. and 5. exclusive scan, stable radix sort |
//! | `intersections` | 3., 4. and 6. binning: offsets, intersection map, tile ranges |
//! | `rasterize` | 7. the blend |
//! | `rasterize_backward` | the blend's backward (and the float atomic add) |
//! | `project_backward` | the projection's backward |
//!
//! Generic host helpers are in [`crate::cube::host`]; the camera record every projecting kernel
//! takes is [`crate::cube::view::ViewArgs`].
//!
//! # Forward pipeline
//!
//! 1. **Project** (`project_kernel`, one thread per Gaussian): the CPU's `project_one` —
//!    culling, EWA covariance, conic, radius, tile rectangle — writing a 32-byte splat record,
//!    the tile rectangle, the number of tiles it touches (0 when culled) and a depth sort key
//!    (the depth's bit pattern, which orders like the positive float; culled Gaussians get
//!    `0xffffffff` and sort last).
//! 2. **Depth sort**: stable GPU radix sort of `(depth key, gid)` over all 32 bits, starting
//!    from gids in index order, so ties break by index exactly as on the CPU. Gives
//!    `gid_from_depth_rank`.
//! 3. **Offsets**: tile counts gathered in depth order, exclusive scan; its last entry is the
//!    number of intersections, read back (4 bytes: the forward's only GPU→CPU sync, needed
//!    because buffer sizes depend on it).
//! 4. **Map** (`map_intersections`): each Gaussian writes `(tile id, gid)` pairs at its offset.
//! 5. **Tile sort**: stable radix sort on the tile id, only as many bits as the largest tile id
//!    needs. Stability keeps every tile's list in depth order: no 64-bit combined key.
//! 6. **Tile offsets** (`tile_offsets_kernel`): each tile's `[start, end)` in the sorted list.
//! 7. **Rasterize** (`rasterize_kernel`): one 16×16 cube per tile, shared-memory batches of
//!    256 splats, per-pixel stop at `T < 1e-4` and whole-tile early exit. Also writes the
//!    final transmittance and the last contributor per pixel for the backward.
//!
//! # Backward
//!
//! `rasterize_backward_kernel` replays each tile back to front, one thread per splat and one
//! atomic add per gradient component per batch (native float atomics where the runtime has
//! them, an atomic-exchange emulation otherwise), into dense per-Gaussian 2D gradients, each
//! tile's pixels split into groups of a cube each so that the launch fills a GPU;
//! `project_backward_kernel` then chains them to the 3D inputs, one thread per Gaussian.
//!
//! Everything the backward needs stays on the device in [`CubeSaved`]: nothing is recomputed.
//! The kernels mirror [`super::cpu`] formula by formula; `tests` compare the two.
//!
//! # Several views
//!
//! One call renders `n` views of one set of `G` Gaussians (`super::rasterize_views`; one view is
//! the case `n = 1`). Splat `k·G + g` is Gaussian `g` seen in view `k`: the projection reads
//! camera `k` from a table ([`crate::cube::view::camera_of`]) and writes the splat's record, so
//! every buffer above is per splat. View `k`'s tiles are numbered after the earlier views'
//! (`k·tiles_per_view + tile`) and its pixels follow theirs, so the depth sort (over every splat;
//! ties by splat index, which within a view is the Gaussian order), the binning, the tile sort
//! (on the global tile id) and the tile ranges run once for all views, and the blend and its
//! backward take the view from the cube's `z` (the backward's `z` counts pixel groups view after
//! view). The projection's backward writes each splat's gradients; with several views
//! `sum_views_kernel` then adds them per Gaussian, view after view.

mod common;
mod intersections;
mod project;
mod project_backward;
mod rasterize;
mod rasterize_backward;
mod sort;

use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{CubeBackend, CubeDevice};

use self::common::{GRAD_LANES, RECT_LANES, SPLAT_LANES, TILE_PIXELS, TILE_SIDE};
use self::rasterize_backward::{BWD_BATCH, BWD_PIXEL_GROUPS};
use self::sort::{bits_for, exclusive_scan, radix_sort_pairs};
use super::cpu::{AlphaCutoff, RasterConfig, TILE, ViewsConfig};
use super::op::{GaussianRasterOps, RasterKernels, SavedRaster};
use crate::camera::ViewParams;
use crate::cube::atomic::use_native_float_atomics;
use crate::cube::host::{
    ComputeClient, THREADS_1D, arg, count_1d, empty_u32, prepare, read_u32, tensor_arg, tensor_f32,
    u32_bytes, zeros_f32,
};
use crate::cube::view::{CAMERA_FLOATS, camera_table};
use crate::error::RenderError;

/// Pixel groups per tile forced by [`force_backward_pixel_groups`]; 0 for the default.
static FORCED_PIXEL_GROUPS: AtomicU32 = AtomicU32::new(0);

/// See [`super::force_backward_pixel_groups`].
pub(super) fn force_backward_pixel_groups(groups: Option<u32>) -> Result<(), RenderError> {
    let groups = groups.unwrap_or(0);
    if groups != 0 && !(groups.is_power_of_two() && groups <= BWD_PIXEL_GROUPS) {
        return Err(RenderError::InvalidInput {
            what: "pixel groups",
            reason: format!("must be a power of two up to {BWD_PIXEL_GROUPS}, not {groups}"),
        });
    }
    FORCED_PIXEL_GROUPS.store(groups, Ordering::Relaxed);
    Ok(())
}

/// What the Cube forward keeps for the backward: inputs and intermediates, all on the device.
struct CubeSaved {
    client: ComputeClient,
    device: CubeDevice,
    cfg: RasterConfig,
    /// The views rendered (`cfg.view` and more, of its size), and their camera table.
    views: usize,
    cameras: Handle,
    num_gaussians: usize,
    num_isects: usize,
    means: CubeTensor,
    covariances: CubeTensor,
    colors: CubeTensor,
    splats: Handle,
    tile_counts: Handle,
    gid_from_isect: Handle,
    tile_offsets: Handle,
    final_t: Handle,
    last_contrib: Handle,
}

/// What one call renders: one view, `[H, W, C]`, or several of one size, `[n, H, W, C]`.
enum Views<'a> {
    One(RasterConfig),
    Several(&'a ViewsConfig),
}

impl Views<'_> {
    /// The first view's configuration (channels and cutoff are every view's).
    fn first(&self) -> RasterConfig {
        match self {
            Views::One(config) => *config,
            Views::Several(config) => config.view(0),
        }
    }

    fn cameras(&self) -> &[ViewParams] {
        match self {
            Views::One(config) => std::slice::from_ref(&config.view),
            Views::Several(config) => &config.views,
        }
    }

    fn image_shape(&self) -> Vec<usize> {
        match self {
            Views::One(config) => config.image_shape().to_vec(),
            Views::Several(config) => config.image_shape().to_vec(),
        }
    }
}

/// The forward of every view of `views` (one image size): splats, tiles and pixels of view `k`
/// follow those of the views before it, so each stage is one launch for all views (module docs,
/// "Several views").
fn forward(
    means: FloatTensor<CubeBackend>,
    covariances: FloatTensor<CubeBackend>,
    colors: FloatTensor<CubeBackend>,
    opacities: FloatTensor<CubeBackend>,
    rendering: Views<'_>,
) -> (CubeTensor, CubeSaved) {
    let (cfg, views, image_shape) = (
        rendering.first(),
        rendering.cameras(),
        rendering.image_shape(),
    );
    let _span = tracing::trace_span!("cube_rasterize", views = views.len()).entered();
    let (means, covariances) = (prepare(means), prepare(covariances));
    let (colors, opacities) = (prepare(colors), prepare(opacities));
    let client = means.client.clone();
    let device = means.device.clone();
    let gaussians = opacities.shape().num_elements();
    let num_views = views.len();
    // Splat `k·gaussians + g` is Gaussian `g` in view `k`.
    let n = gaussians * num_views;
    let v = &cfg.view;
    let (width, height) = (v.width, v.height);
    let channels = cfg.channels.count();
    let tiles_x = (width as usize).div_ceil(TILE);
    let tiles_y = (height as usize).div_ceil(TILE);
    let tiles_per_view = tiles_x * tiles_y;
    let num_tiles = tiles_per_view * num_views;
    let smooth = cfg.cutoff == AlphaCutoff::Smooth;
    let cameras = camera_table(&client, views);

    let splats = client.empty(4 * (n * SPLAT_LANES).max(1));
    let tile_counts = empty_u32(&client, n);
    let mut num_isects = 0usize;
    let mut rects = None;
    let mut gid_from_depth_rank = None;
    let mut isect_offsets = None;
    if n > 0 {
        let _span = tracing::trace_span!("project_and_depth_sort").entered();
        let rect_buf = empty_u32(&client, RECT_LANES * n);
        let depth_keys = empty_u32(&client, n);
        project::project_kernel::launch(
            &client,
            count_1d(n),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&means),
            tensor_arg(&covariances),
            tensor_arg(&colors),
            tensor_arg(&opacities),
            arg(&cameras, CAMERA_FLOATS * num_views),
            arg(&splats, n * SPLAT_LANES),
            arg(&rect_buf, RECT_LANES * n),
            arg(&tile_counts, n),
            arg(&depth_keys, n),
            gaussians as u32,
            num_views as u32,
            smooth,
        );
        let ids: Vec<u32> = (0..n as u32).collect();
        let ids = client.create_from_slice(&u32_bytes(&ids));
        let (_, order) = radix_sort_pairs(&client, depth_keys, ids, n, 32);
        let offsets = empty_u32(&client, n + 1);
        intersections::gather_counts::launch(
            &client,
            count_1d(n + 1),
            CubeDim::new_1d(THREADS_1D),
            arg(&order, n),
            arg(&tile_counts, n),
            arg(&offsets, n + 1),
            n as u32,
        );
        exclusive_scan(&client, &offsets, n + 1);
        let total = empty_u32(&client, 1);
        intersections::copy_one::launch(
            &client,
            CubeCount::Static(1, 1, 1),
            CubeDim::new_1d(1),
            arg(&offsets, n + 1),
            arg(&total, 1),
            n as u32,
        );
        num_isects = read_u32(&client, total, "the intersection count") as usize;
        rects = Some(rect_buf);
        gid_from_depth_rank = Some(order);
        isect_offsets = Some(offsets);
    }

    let (gid_from_isect, tile_offsets) = match (rects, gid_from_depth_rank, isect_offsets) {
        (Some(rects), Some(order), Some(offsets)) if num_isects > 0 => {
            let _span = tracing::trace_span!("bin").entered();
            let tile_keys = empty_u32(&client, num_isects);
            let gids = empty_u32(&client, num_isects);
            intersections::map_intersections::launch(
                &client,
                count_1d(n),
                CubeDim::new_1d(THREADS_1D),
                arg(&order, n),
                arg(&rects, RECT_LANES * n),
                arg(&offsets, n + 1),
                arg(&tile_keys, num_isects),
                arg(&gids, num_isects),
                n as u32,
                gaussians as u32,
                tiles_x as u32,
                tiles_per_view as u32,
            );
            let bits = bits_for(num_tiles as u32 - 1);
            let (tile_keys, gids) = radix_sort_pairs(&client, tile_keys, gids, num_isects, bits);
            let tile_offsets = empty_u32(&client, num_tiles + 1);
            intersections::tile_offsets_kernel::launch(
                &client,
                count_1d(num_isects),
                CubeDim::new_1d(THREADS_1D),
                arg(&tile_keys, num_isects),
                arg(&tile_offsets, num_tiles + 1),
                num_isects as u32,
                num_tiles as u32,
            );
            (gids, tile_offsets)
        }
        _ => (
            empty_u32(&client, 1),
            client.create_from_slice(&u32_bytes(&vec![0; num_tiles + 1])),
        ),
    };

    let pixels = width as usize * height as usize * num_views;
    let image = client.empty(4 * (pixels * channels).max(1));
    let final_t = client.empty(4 * pixels.max(1));
    let last_contrib = empty_u32(&client, pixels);
    {
        let _span = tracing::trace_span!("blend").entered();
        // With no Gaussians the colour buffer may be empty; no kernel reads it then.
        let colors_arg = if n > 0 {
            tensor_arg(&colors)
        } else {
            arg(&splats, 1)
        };
        rasterize::rasterize_kernel::launch(
            &client,
            CubeCount::Static(tiles_x as u32, tiles_y as u32, num_views as u32),
            CubeDim::new_2d(TILE_SIDE, TILE_SIDE),
            arg(&splats, n * SPLAT_LANES),
            colors_arg,
            arg(&gid_from_isect, num_isects),
            arg(&tile_offsets, num_tiles + 1),
            arg(&image, pixels * channels),
            arg(&final_t, pixels),
            arg(&last_contrib, pixels),
            width,
            height,
            tiles_x as u32,
            gaussians.max(1) as u32,
            channels as u32,
            smooth,
        );
    }
    let image = tensor_f32(&client, &device, image, &image_shape);
    let saved = CubeSaved {
        client,
        device,
        cfg,
        views: num_views,
        cameras,
        num_gaussians: gaussians,
        num_isects,
        means,
        covariances,
        colors,
        splats,
        tile_counts,
        gid_from_isect,
        tile_offsets,
        final_t,
        last_contrib,
    };
    (image, saved)
}

fn backward(saved: &CubeSaved, grad_image: FloatTensor<CubeBackend>) -> [CubeTensor; 4] {
    let _span = tracing::trace_span!("cube_rasterize_backward").entered();
    let (client, device) = (&saved.client, &saved.device);
    let gaussians = saved.num_gaussians;
    let num_views = saved.views;
    let n = gaussians * num_views;
    let cfg = &saved.cfg;
    let (width, height) = (cfg.view.width, cfg.view.height);
    let channels = cfg.channels.count();
    let tiles_x = (width as usize).div_ceil(TILE);
    let tiles_y = (height as usize).div_ceil(TILE);
    let num_tiles = tiles_x * tiles_y * num_views;
    let pixels = width as usize * height as usize * num_views;
    let smooth = cfg.cutoff == AlphaCutoff::Smooth;

    // Per splat; with several views summed per Gaussian afterwards into the `d_*` below.
    let per_splat = |lanes: usize| client.empty(4 * (lanes * n).max(1));
    let (s_means, s_covs, s_colors, s_opacities) =
        (per_splat(3), per_splat(6), per_splat(3), per_splat(1));
    if n > 0 {
        let grad_image = prepare(grad_image);
        let grad_len = n * GRAD_LANES;
        let grad2d = zeros_f32(client, device, grad_len);
        let native = use_native_float_atomics(client);
        let groups = match FORCED_PIXEL_GROUPS.load(Ordering::Relaxed) {
            0 => BWD_PIXEL_GROUPS,
            forced => forced,
        };
        // One kernel, two slot types: see `crate::cube::atomic::AtomicAddF32`.
        macro_rules! launch_backward {
            ($slot:ty) => {
                rasterize_backward::rasterize_backward_kernel::launch::<$slot>(
                    client,
                    CubeCount::Static(tiles_x as u32, tiles_y as u32, groups * num_views as u32),
                    CubeDim::new_1d(BWD_BATCH),
                    arg(&saved.splats, n * SPLAT_LANES),
                    tensor_arg(&saved.colors),
                    arg(&saved.gid_from_isect, saved.num_isects),
                    arg(&saved.tile_offsets, num_tiles + 1),
                    arg(&saved.final_t, pixels),
                    arg(&saved.last_contrib, pixels),
                    tensor_arg(&grad_image),
                    arg(&grad2d, grad_len),
                    width,
                    height,
                    tiles_x as u32,
                    gaussians as u32,
                    channels as u32,
                    smooth,
                    TILE_PIXELS / groups,
                )
            };
        }
        if native {
            launch_backward!(f32);
        } else {
            launch_backward!(u32);
        }
        project_backward::project_backward_kernel::launch(
            client,
            count_1d(n),
            CubeDim::new_1d(THREADS_1D),
            tensor_arg(&saved.means),
            tensor_arg(&saved.covariances),
            arg(&saved.cameras, CAMERA_FLOATS * num_views),
            arg(&saved.splats, n * SPLAT_LANES),
            arg(&saved.tile_counts, n),
            arg(&grad2d, grad_len),
            arg(&s_means, 3 * n),
            arg(&s_covs, 6 * n),
            arg(&s_colors, 3 * n),
            arg(&s_opacities, n),
            gaussians as u32,
            num_views as u32,
        );
    }
    // The four per-Gaussian gradients as tensors (∂means, ∂covariances, ∂colours, ∂opacities).
    let gradients = |[m, c, col, o]: [Handle; 4]| {
        [
            tensor_f32(client, device, m, &[gaussians, 3]),
            tensor_f32(client, device, c, &[gaussians, 6]),
            tensor_f32(client, device, col, &[gaussians, 3]),
            tensor_f32(client, device, o, &[gaussians]),
        ]
    };
    if num_views == 1 || gaussians == 0 {
        return gradients([s_means, s_covs, s_colors, s_opacities]);
    }
    let total = |lanes: usize| client.empty(4 * lanes * gaussians);
    let (d_means, d_covs, d_colors, d_opacities) = (total(3), total(6), total(3), total(1));
    project_backward::sum_views_kernel::launch(
        client,
        count_1d(gaussians),
        CubeDim::new_1d(THREADS_1D),
        arg(&s_means, 3 * n),
        arg(&s_covs, 6 * n),
        arg(&s_colors, 3 * n),
        arg(&s_opacities, n),
        arg(&d_means, 3 * gaussians),
        arg(&d_covs, 6 * gaussians),
        arg(&d_colors, 3 * gaussians),
        arg(&d_opacities, gaussians),
        gaussians as u32,
        num_views as u32,
    );
    gradients([d_means, d_covs, d_colors, d_opacities])
}

impl GaussianRasterOps for CubeBackend {
    fn rasterize_gaussians(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: RasterConfig,
    ) -> FloatTensor<Self> {
        forward(means, covariances, colors, opacities, Views::One(config)).0
    }

    fn rasterize_gaussian_views(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: ViewsConfig,
    ) -> FloatTensor<Self> {
        forward(
            means,
            covariances,
            colors,
            opacities,
            Views::Several(&config),
        )
        .0
    }
}

impl RasterKernels for CubeBackend {
    fn rasterize_saving(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: RasterConfig,
    ) -> (FloatTensor<Self>, SavedRaster) {
        let (image, saved) = forward(means, covariances, colors, opacities, Views::One(config));
        (image, SavedRaster(Arc::new(saved)))
    }

    fn rasterize_views_saving(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: ViewsConfig,
    ) -> (FloatTensor<Self>, SavedRaster) {
        let rendering = Views::Several(&config);
        let (image, saved) = forward(means, covariances, colors, opacities, rendering);
        (image, SavedRaster(Arc::new(saved)))
    }

    fn rasterize_backward(
        saved: &SavedRaster,
        grad_image: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 4] {
        let saved = saved
            .0
            .downcast_ref::<CubeSaved>()
            .expect("Cube backward given a Cube forward state");
        backward(saved, grad_image)
    }
}

/// Whether the backward on `device` would use native float atomics (see
/// [`super::native_float_atomics`]); `false` for devices of other backends.
pub(crate) fn native_float_atomics(device: &burn::tensor::Device) -> bool {
    match device.as_dispatch() {
        burn::backend::DispatchDevice::Cube(cube) => use_native_float_atomics(&cube.client()),
        _ => false,
    }
}
