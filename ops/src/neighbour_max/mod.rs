//! The transition-down's max over each sampled point's neighbours (design.md §7.5):
//! `out[i, ch] = max_j h[i, j, ch]` for `h` `[m, k, c]`.
//!
//! On the CPU backends it is Burn's `max_dim`. On CubeCL devices Burn's is a reduction with
//! indices forward and, backward, a zeroed `[m, k, c]` gradient and an atomic scatter of the
//! output's gradient onto it: two launches and float atomics per pass. Here ([`op`]) the forward
//! kernel writes the maximum and the neighbour it came from (the first on ties, as Burn's), and
//! the backward writes every element of `∂h` once, the output's gradient where the neighbour is
//! the maximum's and zero elsewhere: one launch each way, no zero fill, no atomics.

mod cube;
pub mod op;

use burn::tensor::Tensor;
use lifegom_render::device::runs_on_host;

/// `max_j h[i, j, ch]` as `[m, c]`, for `h` `[m, k, c]` (module docs).
pub fn max_over_neighbours(h: Tensor<3>) -> Tensor<2> {
    let [m, _, c] = h.dims();
    if runs_on_host(&h.device()) {
        return h.max_dim(1).reshape([m, c]);
    }
    Tensor::from_dispatch(
        <burn::backend::Dispatch as op::NeighbourMaxOps>::neighbour_max(h.into_dispatch()),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use lifegom_render::device::DeviceChoice;
    use lifegom_render::testing::{Rng, assert_close_to_scale, read, wgpu_test_device};

    /// The maximum and `h`'s gradient under a weighted sum of it, on `device` with autodiff;
    /// `max_over_neighbours` or Burn's `max_dim`.
    fn run(device: &Device, [m, k, c]: [usize; 3], op: bool) -> Vec<Vec<f32>> {
        let mut rng = Rng::new(17);
        let values: Vec<f32> = (0..m * k * c).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let weights: Vec<f32> = (0..m * c).map(|_| rng.range_f32(-1.0, 1.0)).collect();
        let h = Tensor::<3>::from_data(TensorData::new(values, [m, k, c]), device).require_grad();
        let w = Tensor::<2>::from_data(TensorData::new(weights, [m, c]), device);
        let out = if op {
            max_over_neighbours(h.clone())
        } else {
            h.clone().max_dim(1).reshape([m, c])
        };
        let grads = (out.clone() * w).sum().backward();
        vec![read(out), read(h.grad(&grads).expect("h's gradient"))]
    }

    /// On lavapipe the op's maximum and gradient equal Burn's `max_dim` on Flex, for
    /// neighbourhoods of 8 and 16 and more elements than one cube's threads.
    #[test]
    fn max_matches_burn_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let flex = DeviceChoice::Flex.device().autodiff();
        for shape in [[5, 8, 3], [37, 16, 24]] {
            let want = run(&flex, shape, false);
            let got = run(&device.clone().autodiff(), shape, true);
            for ((a, b), what) in got.iter().zip(&want).zip(["max", "∂h"]) {
                assert_close_to_scale(a, b, 1e-6, &format!("{shape:?}: {what}"));
            }
        }
    }
}
