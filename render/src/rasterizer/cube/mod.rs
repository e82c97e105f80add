//! The rasterizer op on Burn's CubeCL backend (wgpu, and any other CubeCL runtime).
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
//! them, an atomic-exchange emulation otherwise), into dense per-Gaussian 2D gradients;
//! `project_backward_kernel` then chains them to the 3D inputs, one thread per Gaussian.
//!
//! Everything the backward needs stays on the device in [`CubeSaved`]: nothing is recomputed.
//! The kernels mirror [`super::cpu`] formula by formula; `tests` compare the two.

mod kernels;
pub(crate) mod sort;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::TensorMetadata;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{DType, FloatDType, Shape};
use burn_cubecl::cubecl::features::AtomicUsage;
use burn_cubecl::cubecl::ir::{ElemType, FloatKind};
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::tensor::CubeTensor;
use burn_cubecl::{CubeBackend, CubeDevice};

use self::kernels::{BWD_BATCH, GRAD_LANES, SPLAT_LANES, TILE_SIDE};
use self::sort::{ComputeClient, arg, bits_for, count_1d, empty_u32, exclusive_scan};
use super::cpu::{AlphaCutoff, RasterConfig, TILE};
use super::op::{GaussianRasterOps, RasterKernels, SavedRaster};

/// What the Cube forward keeps for the backward: inputs and intermediates, all on the device.
struct CubeSaved {
    client: ComputeClient,
    device: CubeDevice,
    cfg: RasterConfig,
    num_gaussians: usize,
    num_isects: usize,
    means: CubeTensor,
    covariances: CubeTensor,
    colors: CubeTensor,
    view: Handle,
    splats: Handle,
    tile_counts: Handle,
    gid_from_isect: Handle,
    tile_offsets: Handle,
    final_t: Handle,
    last_contrib: Handle,
}

/// f32 and contiguous, the layout every kernel indexes.
pub(crate) fn prepare(t: FloatTensor<CubeBackend>) -> CubeTensor {
    let t = if t.dtype() == DType::F32 {
        t
    } else {
        CubeBackend::float_cast(t, FloatDType::F32)
    };
    into_contiguous(t)
}

pub(crate) fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn u32_bytes(values: &[u32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// An f32 tensor over a kernel's output buffer.
fn tensor(
    client: &ComputeClient,
    device: &CubeDevice,
    handle: Handle,
    shape: &[usize],
) -> CubeTensor {
    tensor_of(client, device, handle, shape, DType::F32)
}

/// A contiguous tensor of `dtype` over a kernel's output buffer.
pub(crate) fn tensor_of(
    client: &ComputeClient,
    device: &CubeDevice,
    handle: Handle,
    shape: &[usize],
    dtype: DType,
) -> CubeTensor {
    CubeTensor::new_contiguous(
        client.clone(),
        device.clone(),
        Shape::from(shape.to_vec()),
        handle,
        dtype,
    )
}

fn tensor_arg(t: &CubeTensor) -> BufferArg {
    t.clone().into_buffer_arg()
}

/// A zero-filled f32 buffer of `len` elements.
fn zeros_f32(client: &ComputeClient, device: &CubeDevice, len: usize) -> Handle {
    burn_cubecl::ops::numeric::zeros_client(
        client.clone(),
        device.clone(),
        Shape::from(vec![len.max(1)]),
        DType::F32,
    )
    .handle
}

fn read_u32(client: &ComputeClient, handle: Handle) -> u32 {
    let bytes = client
        .read_one(handle)
        .expect("reading the intersection count back from the device");
    u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])
}

fn forward(
    means: FloatTensor<CubeBackend>,
    covariances: FloatTensor<CubeBackend>,
    colors: FloatTensor<CubeBackend>,
    opacities: FloatTensor<CubeBackend>,
    cfg: RasterConfig,
) -> (CubeTensor, CubeSaved) {
    let _span = tracing::trace_span!("cube_rasterize").entered();
    let (means, covariances) = (prepare(means), prepare(covariances));
    let (colors, opacities) = (prepare(colors), prepare(opacities));
    let client = means.client.clone();
    let device = means.device.clone();
    let n = opacities.shape().num_elements();
    let v = &cfg.view;
    let (width, height) = (v.width, v.height);
    let channels = cfg.channels.count();
    let tiles_x = (width as usize).div_ceil(TILE);
    let tiles_y = (height as usize).div_ceil(TILE);
    let num_tiles = tiles_x * tiles_y;
    let smooth = cfg.cutoff == AlphaCutoff::Smooth;

    let mut params = v.view.to_vec();
    params.extend([v.fx, v.fy, v.cx, v.cy]);
    let view = client.create_from_slice(&f32_bytes(&params));

    let splats = client.empty(4 * (n * SPLAT_LANES as usize).max(1));
    let tile_counts = empty_u32(&client, n);
    let mut num_isects = 0usize;
    let mut rects = None;
    let mut gid_from_depth_rank = None;
    let mut isect_offsets = None;
    if n > 0 {
        let _span = tracing::trace_span!("project_and_depth_sort").entered();
        let rect_buf = empty_u32(&client, 4 * n);
        let depth_keys = empty_u32(&client, n);
        kernels::project_kernel::launch(
            &client,
            count_1d(n),
            CubeDim::new_1d(sort::THREADS_1D),
            tensor_arg(&means),
            tensor_arg(&covariances),
            tensor_arg(&colors),
            tensor_arg(&opacities),
            arg(&view, 16),
            arg(&splats, n * SPLAT_LANES as usize),
            arg(&rect_buf, 4 * n),
            arg(&tile_counts, n),
            arg(&depth_keys, n),
            n as u32,
            width,
            height,
            smooth,
        );
        let ids: Vec<u32> = (0..n as u32).collect();
        let ids = client.create_from_slice(&u32_bytes(&ids));
        let (_, order) = sort::radix_sort_pairs(&client, depth_keys, ids, n, 32);
        let offsets = empty_u32(&client, n + 1);
        kernels::gather_counts::launch(
            &client,
            count_1d(n + 1),
            CubeDim::new_1d(sort::THREADS_1D),
            arg(&order, n),
            arg(&tile_counts, n),
            arg(&offsets, n + 1),
            n as u32,
        );
        exclusive_scan(&client, &offsets, n + 1);
        let total = empty_u32(&client, 1);
        kernels::copy_one::launch(
            &client,
            CubeCount::Static(1, 1, 1),
            CubeDim::new_1d(1),
            arg(&offsets, n + 1),
            arg(&total, 1),
            n as u32,
        );
        num_isects = read_u32(&client, total) as usize;
        rects = Some(rect_buf);
        gid_from_depth_rank = Some(order);
        isect_offsets = Some(offsets);
    }

    let (gid_from_isect, tile_offsets) = match (rects, gid_from_depth_rank, isect_offsets) {
        (Some(rects), Some(order), Some(offsets)) if num_isects > 0 => {
            let _span = tracing::trace_span!("bin").entered();
            let tile_keys = empty_u32(&client, num_isects);
            let gids = empty_u32(&client, num_isects);
            kernels::map_intersections::launch(
                &client,
                count_1d(n),
                CubeDim::new_1d(sort::THREADS_1D),
                arg(&order, n),
                arg(&rects, 4 * n),
                arg(&offsets, n + 1),
                arg(&tile_keys, num_isects),
                arg(&gids, num_isects),
                n as u32,
                tiles_x as u32,
            );
            let bits = bits_for(num_tiles as u32 - 1);
            let (tile_keys, gids) =
                sort::radix_sort_pairs(&client, tile_keys, gids, num_isects, bits);
            let tile_offsets = empty_u32(&client, num_tiles + 1);
            kernels::tile_offsets_kernel::launch(
                &client,
                count_1d(num_isects),
                CubeDim::new_1d(sort::THREADS_1D),
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

    let pixels = width as usize * height as usize;
    let image = client.empty(4 * pixels * channels);
    let final_t = client.empty(4 * pixels);
    let last_contrib = empty_u32(&client, pixels);
    {
        let _span = tracing::trace_span!("blend").entered();
        // With no Gaussians the colour buffer may be empty; no kernel reads it then.
        let colors_arg = if n > 0 {
            tensor_arg(&colors)
        } else {
            arg(&splats, 1)
        };
        kernels::rasterize_kernel::launch(
            &client,
            CubeCount::Static(tiles_x as u32, tiles_y as u32, 1),
            CubeDim::new_2d(TILE_SIDE, TILE_SIDE),
            arg(&splats, n * SPLAT_LANES as usize),
            colors_arg,
            arg(&gid_from_isect, num_isects),
            arg(&tile_offsets, num_tiles + 1),
            arg(&image, pixels * channels),
            arg(&final_t, pixels),
            arg(&last_contrib, pixels),
            width,
            height,
            tiles_x as u32,
            channels as u32,
            smooth,
        );
    }
    let image = tensor(
        &client,
        &device,
        image,
        &[height as usize, width as usize, channels],
    );
    let saved = CubeSaved {
        client,
        device,
        cfg,
        num_gaussians: n,
        num_isects,
        means,
        covariances,
        colors,
        view,
        splats,
        tile_counts,
        gid_from_isect,
        tile_offsets,
        final_t,
        last_contrib,
    };
    (image, saved)
}

/// Set by [`super::force_emulated_float_atomics`]: use the exchange emulation even where
/// native float atomics exist, so tests cover both paths on one machine.
pub(crate) static FORCE_EMULATED: AtomicBool = AtomicBool::new(false);

/// Whether the backward adds `f32` atomically in hardware: the runtime supports it (WGSL has no
/// float atomics; some Vulkan devices do) and the emulation is not forced.
fn use_native_float_atomics(client: &ComputeClient) -> bool {
    !FORCE_EMULATED.load(Ordering::Relaxed)
        && client
            .properties()
            .atomic_type_usage(Type::atomic(ElemType::Float(FloatKind::F32)))
            .contains(AtomicUsage::Add)
}

fn backward(saved: &CubeSaved, grad_image: FloatTensor<CubeBackend>) -> [CubeTensor; 4] {
    let _span = tracing::trace_span!("cube_rasterize_backward").entered();
    let (client, device) = (&saved.client, &saved.device);
    let n = saved.num_gaussians;
    let cfg = &saved.cfg;
    let (width, height) = (cfg.view.width, cfg.view.height);
    let channels = cfg.channels.count();
    let tiles_x = (width as usize).div_ceil(TILE);
    let tiles_y = (height as usize).div_ceil(TILE);
    let num_tiles = tiles_x * tiles_y;
    let pixels = width as usize * height as usize;
    let smooth = cfg.cutoff == AlphaCutoff::Smooth;

    let d_means = client.empty(4 * (3 * n).max(1));
    let d_covs = client.empty(4 * (6 * n).max(1));
    let d_colors = client.empty(4 * (3 * n).max(1));
    let d_opacities = client.empty(4 * n.max(1));
    if n > 0 {
        let grad_image = prepare(grad_image);
        let grad2d = zeros_f32(client, device, n * GRAD_LANES as usize);
        let native = use_native_float_atomics(client);
        let grad_len = n * GRAD_LANES as usize;
        // One kernel, two slot types: see `kernels::AtomicAddF32`.
        macro_rules! launch_backward {
            ($slot:ty) => {
                kernels::rasterize_backward_kernel::launch::<$slot>(
                    client,
                    CubeCount::Static(tiles_x as u32, tiles_y as u32, 1),
                    CubeDim::new_1d(BWD_BATCH),
                    arg(&saved.splats, n * SPLAT_LANES as usize),
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
                    channels as u32,
                    smooth,
                )
            };
        }
        if native {
            launch_backward!(f32);
        } else {
            launch_backward!(u32);
        }
        kernels::project_backward_kernel::launch(
            client,
            count_1d(n),
            CubeDim::new_1d(sort::THREADS_1D),
            tensor_arg(&saved.means),
            tensor_arg(&saved.covariances),
            arg(&saved.view, 16),
            arg(&saved.splats, n * SPLAT_LANES as usize),
            arg(&saved.tile_counts, n),
            arg(&grad2d, grad_len),
            arg(&d_means, 3 * n),
            arg(&d_covs, 6 * n),
            arg(&d_colors, 3 * n),
            arg(&d_opacities, n),
            n as u32,
            width,
            height,
        );
    }
    [
        tensor(client, device, d_means, &[n, 3]),
        tensor(client, device, d_covs, &[n, 6]),
        tensor(client, device, d_colors, &[n, 3]),
        tensor(client, device, d_opacities, &[n]),
    ]
}

impl GaussianRasterOps for CubeBackend {
    fn rasterize_gaussians(
        means: FloatTensor<Self>,
        covariances: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        opacities: FloatTensor<Self>,
        config: RasterConfig,
    ) -> FloatTensor<Self> {
        forward(means, covariances, colors, opacities, config).0
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
        let (image, saved) = forward(means, covariances, colors, opacities, config);
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
