//! Test support shared by the workspace's test suites (not part of the API).
//!
//! - [`Rng`]: the workspace's seeded generator ([`crate::rng`]), re-exported for test suites;
//!   [`read`]: a tensor's values for assertions; [`assert_close_to_scale`]: two results equal
//!   within float summation order, relative to the expected values' largest magnitude.
//! - [`cpu_backend_tests!`](crate::cpu_backend_tests): one test body, run once per CPU backend
//!   (ndarray, which CI covers, and Flex).
//! - [`wgpu_test_device`]: the wgpu device for GPU-kernel tests, or a loud skip.
//! - [`octahedron`] and [`pixel_camera`]: the small closed mesh and the screen-aligned camera
//!   several suites build scenes from.

pub use crate::rng::Rng;

/// The values of a float tensor as `f32`, for test assertions (panics with the read-back
/// error, which a test should report as a failure).
pub fn read<const D: usize>(t: burn::tensor::Tensor<D>) -> Vec<f32> {
    crate::readback::read("test tensor", t).expect("reading a test tensor back")
}

/// Asserts that `got` equals `want` element by element within `relative` times `want`'s
/// largest magnitude (at least 1e-6): the measure for results that differ only in float
/// summation order (another backend, a split reduction). `what` names the result in the
/// failure, with the first element that is off.
pub fn assert_close_to_scale(got: &[f32], want: &[f32], relative: f32, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let scale = want.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-6);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= relative * scale,
            "{what}[{i}]: {g} against {w} (scale {scale:.2e})"
        );
    }
}

/// Runs test bodies `fn(&burn::tensor::Device)` once per CPU backend.
///
/// - `cpu_backend_tests!(a, b)` makes `ndarray_backend::{a, b}` and `flex_backend::{a, b}`;
/// - `cpu_backend_tests!(name => body)` makes `name::{ndarray, flex}` calling `body`.
#[macro_export]
macro_rules! cpu_backend_tests {
    ($test:ident => $body:ident) => {
        mod $test {
            #[test]
            #[allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it.
            fn ndarray() {
                super::$body(&burn::tensor::Device::ndarray());
            }
            #[test]
            fn flex() {
                super::$body(&burn::tensor::Device::flex());
            }
        }
    };
    ($($name:ident),+ $(,)?) => {
        mod ndarray_backend {
            $(
                #[test]
                #[allow(deprecated)] // Device::ndarray() is deprecated in Burn 0.22; CI tests it.
                fn $name() {
                    super::$name(&burn::tensor::Device::ndarray());
                }
            )+
        }
        mod flex_backend {
            $(
                #[test]
                fn $name() {
                    super::$name(&burn::tensor::Device::flex());
                }
            )+
        }
    };
}

/// The wgpu device for tests of the GPU kernels, or `None` after saying loudly that they are
/// skipped because no Vulkan adapter exists. With `LIFEGOM_REQUIRE_WGPU` set (CI sets it, and
/// installs Mesa's software lavapipe) a missing adapter is a test failure instead.
///
/// # Panics
///
/// When `LIFEGOM_REQUIRE_WGPU` is set and no adapter exists.
pub fn wgpu_test_device() -> Option<burn::tensor::Device> {
    if crate::device::wgpu_available() {
        return Some(crate::device::DeviceChoice::Wgpu.device());
    }
    assert!(
        std::env::var_os("LIFEGOM_REQUIRE_WGPU").is_none(),
        "LIFEGOM_REQUIRE_WGPU is set but no wgpu adapter exists: \
         install mesa-vulkan-drivers and libvulkan1 (lavapipe)"
    );
    eprintln!(
        "WGPU TESTS SKIPPED: no Vulkan adapter (install mesa-vulkan-drivers and libvulkan1 \
         for Mesa lavapipe)"
    );
    None
}

/// The unit octahedron (vertices `±x, ±y, ±z` in that order), faces wound outwards: the
/// smallest closed mesh whose every vertex has a different neighbourhood.
pub fn octahedron() -> (crate::mesh::MeshTopology, Vec<glam::Vec3>) {
    use glam::Vec3;
    let verts = vec![Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z];
    let faces = vec![
        [0, 2, 4],
        [2, 1, 4],
        [1, 3, 4],
        [3, 0, 4],
        [2, 0, 5],
        [1, 2, 5],
        [3, 1, 5],
        [0, 3, 5],
    ];
    let mesh = crate::mesh::MeshTopology::new(faces, 6).expect("the octahedron is a valid mesh");
    (mesh, verts)
}

/// A camera at the origin looking down `+z` with unit focal length and the principal point at
/// pixel corner `(0, 0)`: the world point `(u·z, v·z, z)` lands at pixel coordinates `(u, v)`,
/// so scenes can be written in pixels.
pub fn pixel_camera(width: u32, height: u32) -> crate::camera::Camera {
    crate::camera::Camera::new(
        crate::camera::Intrinsics {
            fx: 1.0,
            fy: 1.0,
            cx: 0.0,
            cy: 0.0,
        },
        glam::Affine3A::IDENTITY,
        width,
        height,
    )
    .expect("a valid camera")
}
