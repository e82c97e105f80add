//! The image encoder's BatchNorms on CubeCL devices: frozen statistics, trainable `γ`, `β`, one
//! launch per pass each way, and one for `γ`'s and `β`'s gradient over all passes (design.md
//! §7.1).
//!
//! A reconstruction runs the encoder on the source views and on every feedback step's renders
//! with the same weights. Each BatchNorm there is the per-channel affine map
//! `y = x·s + t`, `s = γ/√(σ²+ε)`, `t = β − μ·s`, on its running statistics, often followed by
//! a ReLU. As tensor ops that is, per pass, a product and a sum forward, and backward the
//! input's gradient, two reductions for `s` and `t` and the ReLU's mask; then per step the
//! fold's own backward and Burn's additions of every pass's `∂s`, `∂t`. [`ChannelNorm`] is one
//! parameter node per BatchNorm and reconstruction (no launch), and per pass one op: forward one
//! launch (the map and the ReLU), backward one launch writing `∂x` and the pass's partial sums
//! of `g·x` and `g` per channel; the parameter node adds every pass's sums up in one launch and
//! turns them into `∂γ`, `∂β` (the `op` module, the same scheme as the Point Transformer's
//! shared weights).
//!
//! On the CPU backends [`ChannelNorm`] keeps the tensor ops, whose float order is the network's.

mod cube;
pub mod op;

use burn::backend::Dispatch;
use burn::nn::BatchNorm;
use burn::tensor::{Device, Tensor};

use crate::activation::Activation;
use op::{ChannelNormOps, NormLedger};

/// One BatchNorm's `γ`, `β` and statistics, kept for every pass of a reconstruction (module
/// docs).
#[derive(Debug, Clone)]
pub struct ChannelNorm {
    path: NormPath,
}

/// How a [`ChannelNorm`] runs on its device.
#[derive(Debug, Clone)]
enum NormPath {
    /// The CPU backends: the per-channel `(s, t)` as tensors, applied with tensor ops, whose
    /// float order is the network's.
    Host(Box<(Tensor<1>, Tensor<1>)>),
    /// CubeCL devices: the op, one launch per pass each way.
    Device(Box<DeviceNorm>),
}

/// A [`ChannelNorm`]'s op inputs on a CubeCL device.
#[derive(Debug, Clone)]
struct DeviceNorm {
    /// `γ` as the parameter node hands it on (the `op` module).
    params: Tensor<1>,
    beta: Tensor<1>,
    mean: Tensor<1>,
    var: Tensor<1>,
    epsilon: f32,
    ledger: NormLedger,
}

impl ChannelNorm {
    /// The BatchNorm `bn` on `device` (no launch on a CubeCL device; its fold
    /// [`crate::frozen_affine::frozen_affine`] on the CPU backends).
    pub fn new(bn: &BatchNorm, device: &Device) -> Self {
        if lifegom_render::device::runs_on_host(device) {
            let (scale, shift) = crate::frozen_affine::frozen_affine(bn, device);
            return Self {
                path: NormPath::Host(Box::new((scale, shift))),
            };
        }
        let mean = bn.running_mean.value().to_device(device);
        let var = bn.running_var.value().to_device(device);
        let epsilon = bn.epsilon as f32;
        let ledger = NormLedger::default();
        let params = Tensor::from_dispatch(<Dispatch as ChannelNormOps>::channel_norm_parameters(
            bn.gamma.val().into_dispatch(),
            bn.beta.val().into_dispatch(),
            mean.clone().into_dispatch(),
            var.clone().into_dispatch(),
            epsilon,
            ledger.clone(),
        ));
        Self {
            path: NormPath::Device(Box::new(DeviceNorm {
                params,
                beta: bn.beta.val(),
                mean,
                var,
                epsilon,
                ledger,
            })),
        }
    }

    /// `activation(x·s + t)` per channel of `x` `[N, C, H, W]`.
    ///
    /// # Panics
    ///
    /// If `x`'s channels are not the BatchNorm's.
    pub fn apply(&self, x: Tensor<4>, activation: Activation) -> Tensor<4> {
        let c = x.dims()[1];
        match &self.path {
            NormPath::Host(fold) => {
                let (scale, shift) = fold.as_ref();
                assert_eq!(
                    c,
                    scale.dims()[0],
                    "one BatchNorm channel per image channel"
                );
                let y =
                    x * scale.clone().reshape([1, c, 1, 1]) + shift.clone().reshape([1, c, 1, 1]);
                match activation {
                    Activation::Identity => y,
                    Activation::Relu => crate::activation::relu(y),
                }
            }
            NormPath::Device(norm) => {
                let DeviceNorm {
                    params,
                    beta,
                    mean,
                    var,
                    epsilon,
                    ledger,
                } = norm.as_ref();
                assert_eq!(
                    c,
                    params.dims()[0],
                    "one BatchNorm channel per image channel"
                );
                Tensor::from_dispatch(<Dispatch as ChannelNormOps>::channel_norm(
                    x.into_dispatch(),
                    params.clone().into_dispatch(),
                    beta.clone().into_dispatch(),
                    mean.clone().into_dispatch(),
                    var.clone().into_dispatch(),
                    *epsilon,
                    activation,
                    ledger.clone(),
                ))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::module::{Param, RunningState};
    use burn::nn::BatchNormConfig;
    use burn::tensor::TensorData;
    use lifegom_render::testing::{Rng, assert_close_to_scale, read, wgpu_test_device};

    /// `passes` passes of one BatchNorm over different `[2, 5, 9, 31]` images (more pixels than
    /// one partial sum covers; row-major and channels-last), each pass's loss weighing its output differently, on `device`:
    /// the outputs and the gradients of the images, `γ` and `β`. `composed` runs the tensor ops
    /// the CPU backends run.
    fn run(
        device: &Device,
        passes: usize,
        activation: Activation,
        composed: bool,
    ) -> Vec<Vec<f32>> {
        let device = device.clone().autodiff();
        let (n, c, h, w) = (2, 5, 9, 31);
        let mut rng = Rng::new(41);
        let mut draw = |len: usize, lo: f32, hi: f32| -> Vec<f32> {
            (0..len).map(|_| rng.range_f32(lo, hi)).collect()
        };
        let vector = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v, [c]), &device);
        let mut bn = BatchNormConfig::new(c).init(&device);
        bn.gamma = Param::from_tensor(vector(draw(c, -1.5, 1.5)));
        bn.beta = Param::from_tensor(vector(draw(c, -0.5, 0.5)));
        bn.running_mean = RunningState::new(vector(draw(c, -0.5, 0.5)));
        bn.running_var = RunningState::new(vector(draw(c, 0.2, 2.0)));
        // Every other pass's images are channels-last in memory, as convolutions hand them back.
        let images: Vec<Tensor<4>> = (0..passes)
            .map(|pass| {
                let values = draw(n * c * h * w, -1.0, 1.0);
                let x = if pass % 2 == 0 {
                    Tensor::from_data(TensorData::new(values, [n, c, h, w]), &device)
                } else {
                    Tensor::<4>::from_data(TensorData::new(values, [n, h, w, c]), &device)
                        .permute([0, 3, 1, 2])
                };
                x.require_grad()
            })
            .collect();
        let norm = (!composed).then(|| ChannelNorm::new(&bn, &device));
        let mut loss = Tensor::<1>::zeros([1], &device);
        let mut outputs = Vec::new();
        for (pass, x) in images.iter().enumerate() {
            let y = match &norm {
                Some(norm) => norm.apply(x.clone(), activation),
                None => {
                    let scale = bn.gamma.val() / (bn.running_var.value() + bn.epsilon).sqrt();
                    let shift = bn.beta.val() - bn.running_mean.value() * scale.clone();
                    let y = x.clone() * scale.reshape([1, c, 1, 1]) + shift.reshape([1, c, 1, 1]);
                    match activation {
                        Activation::Identity => y,
                        Activation::Relu => crate::activation::relu(y),
                    }
                }
            };
            loss = loss + (y.clone() * (1.0 + pass as f32)).sin().sum();
            outputs.push(read(y));
        }
        let grads = loss.backward();
        outputs.extend(
            images
                .iter()
                .map(|x| read(x.grad(&grads).expect("an image gradient"))),
        );
        outputs.push(read(bn.gamma.val().grad(&grads).expect("γ's gradient")));
        outputs.push(read(bn.beta.val().grad(&grads).expect("β's gradient")));
        outputs
    }

    /// On lavapipe the op equals the tensor ops on Flex for one pass, three (one launch for the
    /// sums) and six (two), with and without the ReLU: outputs, the images' gradients, `γ`'s and
    /// `β`'s.
    #[test]
    fn channel_norm_matches_tensor_ops_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        for activation in [Activation::Identity, Activation::Relu] {
            for passes in [1, 3, 6] {
                let want = run(&Device::flex(), passes, activation, true);
                let got = run(&device, passes, activation, false);
                assert_eq!(want.len(), got.len());
                for (i, (a, b)) in got.iter().zip(&want).enumerate() {
                    let what = format!("{activation:?}, {passes} passes, part {i}");
                    assert_close_to_scale(a, b, 1e-5, &what);
                }
            }
        }
    }
}
