//! LPIPS v0.1 (Zhang et al. 2018, pip `lpips` 0.1.x) with the AlexNet or VGG16 backbone.
//!
//! For images `a`, `b` in `[0, 1]`, `lpips.LPIPS(net=…, version="0.1").forward(a, b,
//! normalize=True)` computes, and [`Lpips::distance`] reproduces:
//!
//! 1. `x ← 2x − 1`, then the `ScalingLayer`: `(x − shift) / scale` with
//!    `shift = [−0.030, −0.088, −0.188]`, `scale = [0.458, 0.448, 0.450]`.
//! 2. The torchvision backbone's `features`, tapped after five ReLUs
//!    (`lpips/pretrained_networks.py`):
//!    - AlexNet: `relu1`..`relu5` (conv 11×11/4 p2 → relu, maxpool 3/2, conv 5×5 p2 → relu,
//!      maxpool 3/2, three conv 3×3 p1 → relu, each tapped); channels 64, 192, 384, 256, 256.
//!    - VGG16: `relu1_2`, `relu2_2`, `relu3_3`, `relu4_3`, `relu5_3` (3×3 p1 convs, maxpool 2/2
//!      between the stages); channels 64, 128, 256, 512, 512.
//! 3. Per tap `k`: unit-normalise each pixel's feature vector over channels,
//!    `f / (‖f‖₂ + 1e-10)` (`lpips.normalize_tensor`), square the difference of the two images'
//!    normalised features, apply the learned 1×1 conv without bias `lin{k}` (C → 1; its dropout
//!    is inactive in eval), and average over the spatial positions (`spatial_average`).
//! 4. Sum over the five taps → one distance per image pair.
//!
//! Max pools have no padding and floor their output size (torch defaults), so AlexNet needs
//! inputs of at least 31×31 and VGG16 at least 16×16 ([`LpipsNet::min_size`]).

use std::path::Path;

use burn::module::Module;
use burn::nn::PaddingConfig2d;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};

use super::{PerceptualError, load_safetensors};

/// `ScalingLayer.shift` of the `lpips` package.
pub const LPIPS_SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
/// `ScalingLayer.scale` of the `lpips` package.
pub const LPIPS_SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Epsilon of `lpips.normalize_tensor`.
const NORM_EPS: f32 = 1e-10;

/// The LPIPS backbone.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LpipsNet {
    /// torchvision AlexNet (`lpips.LPIPS(net="alex")`).
    Alex,
    /// torchvision VGG16 (`lpips.LPIPS(net="vgg")`).
    Vgg,
}

/// One backbone convolution: `[c_in, c_out]`, kernel, stride, padding, whether a max pool
/// precedes it and whether its ReLU output is an LPIPS tap.
struct ConvSpec {
    channels: [usize; 2],
    kernel: usize,
    stride: usize,
    padding: usize,
    pool_before: bool,
    tap: bool,
}

const fn spec(c_in: usize, c_out: usize, kernel: usize, pool_before: bool, tap: bool) -> ConvSpec {
    ConvSpec {
        channels: [c_in, c_out],
        kernel,
        stride: 1,
        padding: kernel / 2,
        pool_before,
        tap,
    }
}

/// torchvision `alexnet().features` up to `relu5` (indices 0, 3, 6, 8, 10).
const ALEX: [ConvSpec; 5] = [
    ConvSpec {
        channels: [3, 64],
        kernel: 11,
        stride: 4,
        padding: 2,
        pool_before: false,
        tap: true,
    },
    spec(64, 192, 5, true, true),
    spec(192, 384, 3, true, true),
    spec(384, 256, 3, false, true),
    spec(256, 256, 3, false, true),
];

/// torchvision `vgg16().features` up to `relu5_3` (indices 0, 2, 5, 7, 10, 12, 14, 17, 19, 21,
/// 24, 26, 28).
const VGG: [ConvSpec; 13] = [
    spec(3, 64, 3, false, false),
    spec(64, 64, 3, false, true),
    spec(64, 128, 3, true, false),
    spec(128, 128, 3, false, true),
    spec(128, 256, 3, true, false),
    spec(256, 256, 3, false, false),
    spec(256, 256, 3, false, true),
    spec(256, 512, 3, true, false),
    spec(512, 512, 3, false, false),
    spec(512, 512, 3, false, true),
    spec(512, 512, 3, true, false),
    spec(512, 512, 3, false, false),
    spec(512, 512, 3, false, true),
];

impl LpipsNet {
    /// The package's name of the backbone (`"alex"`, `"vgg"`).
    pub fn name(self) -> &'static str {
        match self {
            LpipsNet::Alex => "alex",
            LpipsNet::Vgg => "vgg",
        }
    }

    fn model_name(self) -> &'static str {
        match self {
            LpipsNet::Alex => "LPIPS-alex",
            LpipsNet::Vgg => "LPIPS-vgg",
        }
    }

    fn specs(self) -> &'static [ConvSpec] {
        match self {
            LpipsNet::Alex => &ALEX,
            LpipsNet::Vgg => &VGG,
        }
    }

    /// torchvision `features` indices of the backbone convolutions, in order (what
    /// `convs.{j}` of the converted file was called in the `.pth`).
    pub fn torchvision_conv_indices(self) -> &'static [usize] {
        match self {
            LpipsNet::Alex => &[0, 3, 6, 8, 10],
            LpipsNet::Vgg => &[0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28],
        }
    }

    /// Channels of the five taps (= input channels of the five linear heads).
    pub fn tap_channels(self) -> [usize; 5] {
        match self {
            LpipsNet::Alex => [64, 192, 384, 256, 256],
            LpipsNet::Vgg => [64, 128, 256, 512, 512],
        }
    }

    /// Smallest image side the backbone accepts (every pool needs a non-empty output).
    pub fn min_size(self) -> usize {
        match self {
            LpipsNet::Alex => 31,
            LpipsNet::Vgg => 16,
        }
    }

    fn pool(self) -> MaxPool2d {
        let (k, s) = match self {
            LpipsNet::Alex => (3, 2),
            LpipsNet::Vgg => (2, 2),
        };
        MaxPool2dConfig::new([k, k]).with_strides([s, s]).init()
    }
}

/// The parameters of an LPIPS network: backbone convolutions and the five linear heads.
///
/// Field paths are the keys of the converted SafeTensors file (`convs.{j}.weight`,
/// `convs.{j}.bias`, `lins.{k}.weight`).
#[derive(Module, Debug)]
pub struct LpipsModel {
    /// Backbone convolutions in forward order (with bias; each is followed by a ReLU).
    pub convs: Vec<Conv2d>,
    /// The 1×1 heads `lin0..lin4`, C_k → 1, no bias.
    pub lins: Vec<Conv2d>,
}

/// Configuration of [`LpipsModel`].
#[derive(burn::config::Config, Debug)]
pub struct LpipsConfig {
    /// Backbone: `true` for VGG16, `false` for AlexNet.
    pub vgg: bool,
}

impl LpipsConfig {
    /// The config of a backbone.
    pub fn for_net(net: LpipsNet) -> Self {
        Self::new(net == LpipsNet::Vgg)
    }

    fn net(&self) -> LpipsNet {
        if self.vgg {
            LpipsNet::Vgg
        } else {
            LpipsNet::Alex
        }
    }

    /// Builds the network with Burn's default (random) initialisation; load weights next.
    pub fn init(&self, device: &Device) -> LpipsModel {
        let net = self.net();
        let convs = net
            .specs()
            .iter()
            .map(|c| {
                let p = c.padding;
                Conv2dConfig::new(c.channels, [c.kernel, c.kernel])
                    .with_stride([c.stride, c.stride])
                    .with_padding(PaddingConfig2d::Explicit(p, p, p, p))
                    .init(device)
            })
            .collect();
        let lins = net
            .tap_channels()
            .iter()
            .map(|&c| {
                Conv2dConfig::new([c, 1], [1, 1])
                    .with_bias(false)
                    .init(device)
            })
            .collect();
        LpipsModel { convs, lins }
    }
}

impl LpipsModel {
    /// The five tapped ReLU outputs of the backbone for scaled inputs.
    fn taps(&self, net: LpipsNet, x: Tensor<4>) -> Vec<Tensor<4>> {
        let pool = net.pool();
        let mut taps = Vec::with_capacity(5);
        let mut x = x;
        for (spec, conv) in net.specs().iter().zip(&self.convs) {
            if spec.pool_before {
                x = pool.forward(x);
            }
            x = relu(conv.forward(x));
            if spec.tap {
                taps.push(x.clone());
            }
        }
        taps
    }
}

/// LPIPS v0.1 with loaded weights. See the module docs for the computation.
#[derive(Debug)]
pub struct Lpips {
    net: LpipsNet,
    model: LpipsModel,
}

/// `f / (‖f‖₂ over channels + 1e-10)` (`lpips.normalize_tensor`).
fn normalize_channels(f: Tensor<4>) -> Tensor<4> {
    let norm = f.clone().powi_scalar(2).sum_dim(1).sqrt();
    f / (norm + NORM_EPS)
}

impl Lpips {
    /// Loads converted weights (SafeTensors written by `lifegom-weights fetch` or `convert`,
    /// keys in the [`LpipsModel`] docs).
    pub fn load(net: LpipsNet, path: &Path, device: &Device) -> Result<Self, PerceptualError> {
        let model = LpipsConfig::for_net(net).init(device);
        let model = load_safetensors(model, path)?;
        Ok(Self { net, model })
    }

    /// The same network with its parameters out of every gradient: as a training loss on an
    /// autodiff device, gradients flow to the images only.
    pub fn frozen(self) -> Self {
        Self {
            net: self.net,
            model: self.model.no_grad(),
        }
    }

    /// Wraps an already built (and filled) network.
    pub fn from_model(net: LpipsNet, model: LpipsModel) -> Self {
        Self { net, model }
    }

    /// The backbone.
    pub fn net(&self) -> LpipsNet {
        self.net
    }

    /// The parameters.
    pub fn model(&self) -> &LpipsModel {
        &self.model
    }

    /// Per-image LPIPS distance; `a`, `b`: `[N, 3, H, W]` in `[0, 1]` (the `2x − 1` mapping
    /// happens inside). Returns `[N]`.
    ///
    /// # Panics
    /// If the shapes are invalid (see [`Lpips::try_distance`], which returns the error).
    pub fn distance(&self, a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
        match self.try_distance(a, b) {
            Ok(d) => d,
            Err(e) => panic!("Lpips::distance: {e}"),
        }
    }

    /// [`Lpips::distance`] with shape errors returned instead of panicking: `a` and `b` must
    /// have the same shape `[N, 3, H, W]` with `N ≥ 1` and `H, W ≥` [`LpipsNet::min_size`].
    pub fn try_distance(&self, a: Tensor<4>, b: Tensor<4>) -> Result<Tensor<1>, PerceptualError> {
        let layers = self.try_per_layer(a, b)?;
        Ok(layers
            .into_iter()
            .reduce(|x, y| x + y)
            .expect("LPIPS has five layers"))
    }

    /// The five per-tap terms (`retPerLayer=True` of the package), each `[N]`; their sum is
    /// [`Lpips::distance`].
    pub fn try_per_layer(
        &self,
        a: Tensor<4>,
        b: Tensor<4>,
    ) -> Result<Vec<Tensor<1>>, PerceptualError> {
        let model = self.net.model_name();
        let (da, db) = (a.dims(), b.dims());
        if da != db {
            return Err(PerceptualError::Input {
                model,
                field: "b",
                reason: format!("has shape {db:?} but `a` has {da:?}"),
            });
        }
        let [n, c, h, w] = da;
        let min = self.net.min_size();
        if n == 0 || c != 3 || h < min || w < min {
            return Err(PerceptualError::Input {
                model,
                field: "a",
                reason: format!("must be [N ≥ 1, 3, H ≥ {min}, W ≥ {min}], got {da:?}"),
            });
        }
        let device = a.device();
        let stat = |v: [f32; 3]| {
            Tensor::<4>::from_data(TensorData::new(v.to_vec(), [1, 3, 1, 1]), &device)
        };
        let (shift, scale) = (stat(LPIPS_SHIFT), stat(LPIPS_SCALE));
        let prep = |x: Tensor<4>| ((x * 2.0 - 1.0) - shift.clone()) / scale.clone();
        // One backbone pass over both batches: the network is per-image, and batching halves
        // the number of kernel launches.
        let both = self.model.taps(self.net, prep(Tensor::cat(vec![a, b], 0)));
        Ok(both
            .into_iter()
            .zip(&self.model.lins)
            .map(|(f, lin)| {
                let f = normalize_channels(f);
                let fa = f.clone().narrow(0, 0, n);
                let fb = f.narrow(0, n, n);
                let d = (fa - fb).powi_scalar(2);
                lin.forward(d).mean_dim(3).mean_dim(2).reshape([n])
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use lifegom_render::testing::read;

    fn images(n: usize, h: usize, w: usize, phase: f32, device: &Device) -> Tensor<4> {
        let v: Vec<f32> = (0..n * 3 * h * w)
            .map(|i| 0.5 + 0.45 * ((i as f32) * 0.031 + phase).sin())
            .collect();
        Tensor::from_data(TensorData::new(v, [n, 3, h, w]), device)
    }

    /// Tap shapes follow torch's conv/pool size formulas at the minimum sizes and above.
    fn tap_shapes(device: &Device) {
        for (net, size, expect) in [
            (LpipsNet::Alex, 64, [15, 7, 3, 3, 3]),
            (LpipsNet::Alex, 31, [7, 3, 1, 1, 1]),
            (LpipsNet::Vgg, 16, [16, 8, 4, 2, 1]),
            (LpipsNet::Vgg, 40, [40, 20, 10, 5, 2]),
        ] {
            let model = LpipsConfig::for_net(net).init(device);
            let taps = model.taps(net, images(1, size, size, 0.0, device));
            let got: Vec<[usize; 2]> = taps.iter().map(|t| [t.dims()[1], t.dims()[2]]).collect();
            let want: Vec<[usize; 2]> = net
                .tap_channels()
                .iter()
                .zip(expect)
                .map(|(&c, s)| [c, s])
                .collect();
            assert_eq!(got, want, "{net:?} at {size}");
        }
    }
    lifegom_render::cpu_backend_tests!(lpips_tap_shapes => tap_shapes);

    /// Identical images are at distance 0, distances are symmetric, non-negative with
    /// non-negative heads, and bad shapes are errors, not panics.
    fn identity_symmetry_errors(device: &Device) {
        let mut model = LpipsConfig::for_net(LpipsNet::Alex).init(device);
        for lin in &mut model.lins {
            lin.weight = lin.weight.clone().map(|w| w.abs());
        }
        let lpips = Lpips::from_model(LpipsNet::Alex, model);
        let a = images(2, 40, 36, 0.0, device);
        let b = images(2, 40, 36, 1.3, device);
        let same = read(lpips.distance(a.clone(), a.clone()));
        assert!(same.iter().all(|d| d.abs() < 1e-6), "{same:?}");
        let ab = read(lpips.distance(a.clone(), b.clone()));
        let ba = read(lpips.distance(b.clone(), a.clone()));
        assert_eq!(ab.len(), 2);
        for (x, y) in ab.iter().zip(&ba) {
            assert!(
                *x > 0.0 && (x - y).abs() <= 1e-6 * x.abs(),
                "{ab:?} vs {ba:?}"
            );
        }
        let layers = lpips.try_per_layer(a.clone(), b.clone()).unwrap();
        let sum: f32 = layers.into_iter().map(|l| read(l)[0]).sum();
        assert!((sum - ab[0]).abs() < 1e-6 * ab[0]);

        let err = lpips
            .try_distance(a.clone(), images(1, 40, 36, 0.0, device))
            .unwrap_err();
        assert!(err.to_string().contains("`b`"), "{err}");
        let err = lpips
            .try_distance(
                images(1, 30, 64, 0.0, device),
                images(1, 30, 64, 0.0, device),
            )
            .unwrap_err();
        assert!(err.to_string().contains("H ≥ 31"), "{err}");
        let gray = Tensor::<4>::zeros([1, 1, 40, 40], device);
        assert!(lpips.try_distance(gray.clone(), gray).is_err());
    }
    lifegom_render::cpu_backend_tests!(lpips_identity_symmetry_errors => identity_symmetry_errors);
}
