//! Picking a Burn device by name, for binaries and tests.
//!
//! Model and render code never name a backend: they take a [`burn::tensor::Device`]. Binaries
//! take `--device` and call [`DeviceChoice::device`]. The default CPU device is Flex: measured on
//! the 2-core development machine it renders and trains faster than ndarray (BENCHMARKS.md).
//!
//! wgpu is compiled in, which makes it Burn's `Device::default()`: nothing here (or anywhere in
//! the workspace) relies on the default; every caller names its device. On a machine without a
//! GPU, wgpu runs on Mesa's software Vulkan (lavapipe) when it is installed; [`wgpu_available`]
//! tells callers whether any adapter comes up at all.
//!
//! `--device cuda` (NVIDIA cards, through CubeCL's CUDA runtime) exists in binaries built with
//! the `cuda` cargo feature (`--features lifegom-cli/cuda`); the default build and CI do not
//! need CUDA. It is the same CubeCL backend as wgpu with another runtime, so every custom op
//! (all CubeCL kernels) and Burn's kernel fusion run on it unchanged. At run time it needs the
//! NVIDIA driver (`libcuda`) and the CUDA toolkit's NVRTC (`libnvrtc`), which compiles the
//! kernels; a build needs neither (`.cargo/config.toml` names the CUDA version the bindings
//! target, so no `nvcc` is looked for).

// `Device::ndarray()` is deprecated in Burn 0.22 in favour of Flex; ndarray is the CI backend
// the project requires (design.md §1.4).
#![allow(deprecated)]

use std::sync::OnceLock;

use burn::tensor::{Device, DeviceKind, Tensor};

/// A backend the binaries can run on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceChoice {
    /// Burn's ndarray CPU backend (what CI tests).
    NdArray,
    /// Burn's Flex CPU backend (the faster CPU backend; the default).
    #[default]
    Flex,
    /// Burn's CubeCL backend on wgpu's default adapter (a GPU, or lavapipe on the CPU).
    Wgpu,
    /// Burn's CubeCL backend on CUDA's first device (module docs; the `cuda` feature).
    #[cfg(feature = "cuda")]
    Cuda,
}

impl DeviceChoice {
    /// The Burn device, without autodiff.
    pub fn device(self) -> Device {
        match self {
            DeviceChoice::NdArray => Device::ndarray(),
            DeviceChoice::Flex => Device::flex(),
            DeviceChoice::Wgpu => {
                KernelFusion::current();
                Device::wgpu(DeviceKind::DefaultDevice)
            }
            #[cfg(feature = "cuda")]
            DeviceChoice::Cuda => {
                KernelFusion::current();
                Device::cuda(0)
            }
        }
    }

    /// The name printed in benchmark JSON (`backend` field).
    pub fn name(self) -> &'static str {
        match self {
            DeviceChoice::NdArray => "ndarray",
            DeviceChoice::Flex => "flex",
            DeviceChoice::Wgpu => "wgpu",
            #[cfg(feature = "cuda")]
            DeviceChoice::Cuda => "cuda",
        }
    }

    /// Every CPU backend, for tests that run one body on each.
    pub const CPU: [DeviceChoice; 2] = [DeviceChoice::NdArray, DeviceChoice::Flex];
}

impl std::str::FromStr for DeviceChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "ndarray" => Ok(DeviceChoice::NdArray),
            "flex" => Ok(DeviceChoice::Flex),
            "wgpu" => Ok(DeviceChoice::Wgpu),
            #[cfg(feature = "cuda")]
            "cuda" => Ok(DeviceChoice::Cuda),
            #[cfg(not(feature = "cuda"))]
            "cuda" => Err(
                "this binary was built without CUDA: build with `--features lifegom-cli/cuda` \
                 (an NVIDIA driver and the CUDA toolkit's NVRTC are needed at run time), or use \
                 `--device wgpu`, which runs on NVIDIA cards through Vulkan"
                    .into(),
            ),
            other => Err(format!(
                "unknown device `{other}` (expected ndarray, flex, wgpu or cuda)"
            )),
        }
    }
}

/// A process's two-way choice from the environment variable `var`: `alternative`'s value when
/// the variable holds its name, else `default`'s (an unset variable silently, any other value
/// with a warning on stderr). The switches for benchmarks to compare against (kernel fusion,
/// the convolution kernel, where the Point Transformer plans its levels) read it once each.
pub fn env_switch<T>(var: &str, default: (&str, T), alternative: (&str, T)) -> T {
    match std::env::var(var) {
        Ok(value) if value == alternative.0 => alternative.1,
        Ok(value) if value != default.0 => {
            eprintln!(
                "warning: {var}={value} is neither `{}` nor `{}`; `{}` stays",
                default.0, alternative.0, default.0
            );
            default.1
        }
        _ => default.1,
    }
}

/// Whether Burn's kernel fusion merges ops on CubeCL devices.
///
/// Fusion is compiled in: on a CubeCL device every tensor op is recorded in a stream, and runs of
/// elementwise ops, reductions and matmul epilogues become one kernel each (design.md §1.4).
/// `LIFEGOM_FUSION=off` removes Burn's fusers instead, so that every op runs as its own kernel, as
/// without the feature: what the parity tests compare against and the benchmarks measure beside.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KernelFusion {
    /// Burn's fusers merge what they can (the default).
    On,
    /// Every op runs alone (`LIFEGOM_FUSION=off`).
    Off,
}

impl KernelFusion {
    /// This process's choice, read from `LIFEGOM_FUSION` once, before the first CubeCL device
    /// is made (Burn's fuser registry is sealed by the first op). Any value but `off` leaves
    /// fusion on; an unknown value says so on stderr.
    pub fn current() -> Self {
        static MODE: OnceLock<KernelFusion> = OnceLock::new();
        *MODE.get_or_init(|| {
            let mode = env_switch(
                "LIFEGOM_FUSION",
                ("on", KernelFusion::On),
                ("off", KernelFusion::Off),
            );
            if mode == KernelFusion::Off {
                for name in burn_cubecl::fusion::BUILTIN_NAMES {
                    if let Err(err) = burn_cubecl::fusion::remove(name) {
                        eprintln!("warning: cannot turn kernel fusion off: {err}");
                    }
                }
            }
            mode
        })
    }

    /// What `device` runs with: this process's choice on CubeCL devices, `None` on the host
    /// backends (which have no fusion).
    pub fn on_device(device: &Device) -> Option<Self> {
        (!runs_on_host(device)).then(Self::current)
    }

    /// The name printed in benchmark JSON (`kernel_fusion` field).
    pub fn name(self) -> &'static str {
        match self {
            KernelFusion::On => "on",
            KernelFusion::Off => "off",
        }
    }
}

/// Whether a wgpu adapter comes up (a GPU, or lavapipe): creates and reads back one tiny tensor
/// on [`DeviceChoice::Wgpu`], catching the panic CubeCL raises when no adapter exists. Checked
/// once per process; the first call prints the outcome to stderr so logs say what ran.
pub fn wgpu_available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(|| {
        let probe = std::panic::catch_unwind(|| {
            let device = DeviceChoice::Wgpu.device();
            let name = format!("{device:?}");
            let t = Tensor::<1>::from_floats([1.0, 2.0], &device);
            let sum: f32 = t.sum().into_scalar();
            (sum == 3.0, name)
        });
        match probe {
            Ok((true, name)) => {
                let runtime = cube_runtime_name(&DeviceChoice::Wgpu.device()).unwrap_or("?");
                eprintln!("wgpu adapter available: {name} (runtime {runtime})");
                true
            }
            Ok((false, name)) => {
                eprintln!("wgpu adapter {name} computed a wrong sum; treating wgpu as unavailable");
                false
            }
            Err(_) => {
                eprintln!("no wgpu adapter (no GPU and no Mesa lavapipe)");
                false
            }
        }
    })
}

/// The CubeCL runtime behind `device`, as CubeCL names it: `wgpu<spirv>` when wgpu runs on
/// Vulkan and kernels compile to SPIR-V (cooperative-matrix matmuls available), `wgpu<wgsl>`
/// otherwise; `None` on the host backends. Benchmarks record it beside their figures, because
/// the same card runs different kernels under the two compilers.
pub fn cube_runtime_name(device: &Device) -> Option<&'static str> {
    match device.as_dispatch().clone().inner() {
        burn::backend::DispatchDevice::Cube(cube) => Some(cube.client().name()),
        _ => None,
    }
}

/// The largest buffer `device` can allocate, in bytes; `None` on the host backends, whose
/// tensors are plain heap allocations. CubeCL puts each tensor in one buffer of at most the
/// adapter's storage-binding size: 128 MiB on lavapipe (and on wgpu's WebGPU defaults), far more
/// on a discrete card with 64-bit indexing.
pub fn max_buffer_bytes(device: &Device) -> Option<u64> {
    match device.as_dispatch().clone().inner() {
        burn::backend::DispatchDevice::Cube(cube) => {
            Some(cube.client().properties().memory.max_page_size)
        }
        _ => None,
    }
}

/// Rows per block when a stage runs block after block of `rows` rows whose largest buffer
/// holds `floats_per_row` f32 values per row: no block's buffer holds more than `cap` floats nor
/// more than `device` can allocate ([`max_buffer_bytes`]). `rows` itself (one block, the
/// unblocked stage) when they fit; at least one row.
pub fn rows_per_block(device: &Device, rows: usize, floats_per_row: usize, cap: usize) -> usize {
    let device_floats = max_buffer_bytes(device).map_or(usize::MAX, |bytes| {
        usize::try_from(bytes / size_of::<f32>() as u64).unwrap_or(usize::MAX)
    });
    (cap.min(device_floats) / floats_per_row.max(1)).clamp(1, rows.max(1))
}

/// Whether `device` (or the device an autodiff device wraps) computes on the host: ndarray or
/// Flex, where a host-side loop over a tensor's values costs no transfer. CubeCL devices (wgpu,
/// and lavapipe on a CPU) answer false.
pub fn runs_on_host(device: &Device) -> bool {
    !matches!(
        device.as_dispatch().clone().inner(),
        burn::backend::DispatchDevice::Cube(_)
    )
}

/// What work costs on a device: the one thing a model's scheduling reads about its backend,
/// for the choices above the ops (which pick their own paths) — whether to merge independent
/// passes, whether to read a result back to skip work, where to plan on the host.
///
/// The paper's layers are the same on every backend; the two kinds of backend price their
/// work differently, so the same forward is best scheduled differently:
/// - [`CostModel::Eager`] (ndarray, Flex): each op runs to completion on the host before it
///   returns. A read-back waits for nothing, so reading a no-gradient result to skip work pays
///   (tokens that repeat, faces hidden in a view) and host planning runs inline. Passes stay
///   as separate as the paper writes them, so training sums its gradients in the order it
///   always has (the ten-step metrics to the bit).
/// - [`CostModel::Queued`] (CubeCL: wgpu, lavapipe, CUDA): ops are queued and launched; a
///   launch is the unit of cost and a read-back drains the queue. So independent views and
///   branches are merged into fewer, taller launches, weights that do not change are stacked
///   once per reconstruction, and host planning runs ahead, beside the queued work.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CostModel {
    /// Ops run to completion as they are called: read-backs are free.
    Eager,
    /// Ops are queued: launches cost, read-backs wait for the queue.
    Queued,
}

impl CostModel {
    /// How `device` (or the device an autodiff device wraps) prices its work.
    pub fn of(device: &Device) -> Self {
        match runs_on_host(device) {
            true => CostModel::Eager,
            false => CostModel::Queued,
        }
    }

    /// Whether reading values back returns at once (nothing queued to wait for), so that work
    /// skipped by reading a no-gradient result back is saved.
    pub fn free_readback(self) -> bool {
        self == CostModel::Eager
    }

    /// Whether merging independent passes into fewer, taller launches saves time (the
    /// merged pass sums its gradients in another order).
    pub fn merge_passes(self) -> bool {
        self == CostModel::Queued
    }
}

/// Runs `f` on one of rayon's threads when `device` computes on the host (the calling thread if
/// it is one already, or on CubeCL devices), handing it the caller's current span so that its
/// own span can name it as parent (tracing's current span is per thread).
///
/// Nearly every op of a training step or a reconstruction runs on rayon's pool. Called from a
/// thread outside the pool, each op is handed to the pool's workers while the caller sleeps: two
/// futex wake-ups per op, hundreds of ops per step. Called from a worker, the op splits its work
/// between that worker and the others and nothing sleeps. A quickstart training step took 7–9 %
/// less time so (BENCHMARKS.md, 2026-11-25: "the step on rayon's threads with one malloc
/// arena"). That needs the binaries' allocator to keep one arena (`lifegom_cli::allocator`): with
/// glibc's per-thread arenas the workers' large blocks were unmapped and faulted in again, and
/// the cpu preset ran 10 % slower in the pool.
pub fn on_pool_thread<R: Send>(device: &Device, f: impl FnOnce(&tracing::Span) -> R + Send) -> R {
    let parent = tracing::Span::current();
    if runs_on_host(device) {
        rayon::scope(|_| f(&parent))
    } else {
        f(&parent)
    }
}

/// Waits until `t` is computed and its values are on the host; returns the element count.
///
/// For timing code. `Tensor::into_data` alone is not enough on the CubeCL backends: it returns
/// as soon as the readback is *queued*, and the bytes are fetched (waiting for every kernel
/// the tensor depends on) only when first touched. This touches them.
pub fn wait_for_values<const D: usize>(t: Tensor<D>) -> usize {
    let data = t.into_data();
    std::hint::black_box(data.as_bytes());
    data.num_elements()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blocks stay under the cap on every backend, and under the device's buffer limit where it
    /// has one (lavapipe's 128 MiB makes a block of a stage that fits a bigger card).
    #[test]
    fn blocks_fit_the_cap_and_the_device() {
        for device in [Device::ndarray(), Device::flex()] {
            assert_eq!(max_buffer_bytes(&device), None);
            assert_eq!(rows_per_block(&device, 100, 8, 1 << 20), 100);
            assert_eq!(rows_per_block(&device, 100, 8, 80), 10);
            assert_eq!(rows_per_block(&device, 100, 8, 3), 1, "at least one row");
            assert_eq!(rows_per_block(&device, 0, 8, 80), 1);
        }
        let Some(device) = crate::testing::wgpu_test_device() else {
            return;
        };
        let bytes = max_buffer_bytes(&device).expect("a CubeCL device states its limit");
        assert!(bytes >= 1 << 27, "{bytes} bytes");
        let floats = usize::try_from(bytes / 4).unwrap_or(usize::MAX);
        let width = floats / 4 + 1;
        assert_eq!(rows_per_block(&device, 10, width, usize::MAX), 3);
        assert_eq!(rows_per_block(&device, 10, 8, 80), 10);
        // A block as large as the limit allows is allocated (where that is small enough to try).
        if floats <= 1 << 26 {
            let rows = rows_per_block(&device, usize::MAX, 1024, usize::MAX);
            let t = Tensor::<2>::ones([rows, 1024], &device);
            let sum: Vec<f32> = t.sum().into_data().to_vec().unwrap();
            let expected = (rows * 1024) as f32;
            assert!(
                (sum[0] - expected).abs() <= 1e-5 * expected,
                "{sum:?} vs {expected}"
            );
        }
    }
}
