//! pytorch-fid's InceptionV3 up to the pool3 features (2048-d), with the FID Inception
//! architecture (`pytorch_fid.inception.fid_inception_v3`).
//!
//! [`InceptionPool3::features`] matches `InceptionV3([3], resize_input=True,
//! normalize_input=True, use_fid_inception=True)`, which `python -m pytorch_fid` uses:
//!
//! 1. `F.interpolate(x, size=(299, 299), mode="bilinear", align_corners=False)` (half-pixel
//!    centres, source coordinates clamped at 0, no antialiasing when shrinking);
//! 2. `x ← 2x − 1`;
//! 3. block 0: `Conv2d_1a_3x3` (3→32, 3×3/2), `Conv2d_2a_3x3` (32→32, 3×3), `Conv2d_2b_3x3`
//!    (32→64, 3×3 p1), max pool 3/2;
//! 4. block 1: `Conv2d_3b_1x1` (64→80), `Conv2d_4a_3x3` (80→192, 3×3), max pool 3/2;
//! 5. block 2: `Mixed_5b/5c/5d` (FID InceptionA, pool features 32/64/64), `Mixed_6a`
//!    (torchvision InceptionB), `Mixed_6b/6c/6d/6e` (FID InceptionC, 7×7 channels
//!    128/160/160/192);
//! 6. block 3: `Mixed_7a` (torchvision InceptionD), `Mixed_7b` (FID InceptionE_1), `Mixed_7c`
//!    (FID InceptionE_2), adaptive average pool to 1×1.
//!
//! Every `BasicConv2d` is conv (no bias) → BatchNorm (eps 0.001, running statistics) → ReLU.
//! The FID blocks differ from torchvision's in their pooling branch, which this module
//! follows: the 3×3/1 average pools of A, C and E_1 use `count_include_pad=False` (padding is
//! not counted in the divisor), and E_2 (`Mixed_7c`) uses a 3×3/1 **max** pool, padding 1.
//! That max pool's input is a concatenation of ReLU outputs (≥ 0) and every window contains
//! its centre, so the value of the padding cannot change the result.

use std::path::Path;

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::interpolate::{Interpolate2dConfig, InterpolateMode};
use burn::nn::pool::{AvgPool2dConfig, MaxPool2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

use super::{PerceptualError, load_safetensors};

/// Input side of the network (pytorch-fid resizes every image to it).
pub const INCEPTION_SIZE: usize = 299;
/// Dimension of the pool3 features.
pub const POOL3_DIM: usize = 2048;
/// BatchNorm epsilon of torchvision's `BasicConv2d`.
const BN_EPS: f64 = 0.001;

/// torchvision's `BasicConv2d`: conv without bias → BatchNorm (running stats) → ReLU.
#[derive(Module, Debug)]
pub struct BasicConv2d {
    /// The convolution.
    pub conv: Conv2d,
    /// Its batch norm.
    pub bn: BatchNorm,
}

/// Kernel `[kh, kw]`, stride and padding `[ph, pw]` of a [`BasicConv2d`].
#[derive(Config, Debug)]
pub struct BasicConv2dConfig {
    /// `[c_in, c_out]`.
    pub channels: [usize; 2],
    /// `[kh, kw]`.
    #[config(default = "[1, 1]")]
    pub kernel: [usize; 2],
    /// Stride (both axes).
    #[config(default = 1)]
    pub stride: usize,
    /// `[ph, pw]`.
    #[config(default = "[0, 0]")]
    pub padding: [usize; 2],
}

impl BasicConv2dConfig {
    /// Builds the layer (random conv, identity batch norm; load weights next).
    pub fn init(&self, device: &Device) -> BasicConv2d {
        let [ph, pw] = self.padding;
        let mut bn = BatchNormConfig::new(self.channels[1])
            .with_epsilon(BN_EPS)
            .init(device);
        bn.training = bn.training.with_value(false);
        BasicConv2d {
            conv: Conv2dConfig::new(self.channels, self.kernel)
                .with_stride([self.stride, self.stride])
                .with_padding(PaddingConfig2d::Explicit(ph, pw, ph, pw))
                .with_bias(false)
                .init(device),
            bn,
        }
    }
}

fn basic(c_in: usize, c_out: usize, device: &Device) -> BasicConv2d {
    BasicConv2dConfig::new([c_in, c_out]).init(device)
}

fn basic_k(
    c_in: usize,
    c_out: usize,
    kernel: [usize; 2],
    stride: usize,
    padding: [usize; 2],
    device: &Device,
) -> BasicConv2d {
    BasicConv2dConfig::new([c_in, c_out])
        .with_kernel(kernel)
        .with_stride(stride)
        .with_padding(padding)
        .init(device)
}

impl BasicConv2d {
    /// `relu(bn(conv(x)))` with the running statistics (inference only).
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let x = self.conv.forward(x);
        let device = x.device();
        relu(burn::tensor::module::batch_norm(
            x,
            self.bn.gamma.val(),
            self.bn.beta.val(),
            self.bn.running_mean.value().to_device(&device),
            self.bn.running_var.value().to_device(&device),
            self.bn.epsilon,
        ))
    }
}

/// 3×3/1 average pool with padding 1 not counted (`count_include_pad=False`).
fn avg_pool_3x3(x: Tensor<4>) -> Tensor<4> {
    AvgPool2dConfig::new([3, 3])
        .with_strides([1, 1])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .with_count_include_pad(false)
        .init()
        .forward(x)
}

/// 3×3/2 max pool without padding (`nn.MaxPool2d(3, 2)`, `F.max_pool2d(x, 3, 2)`).
fn max_pool_3x3_s2(x: Tensor<4>) -> Tensor<4> {
    MaxPool2dConfig::new([3, 3])
        .with_strides([2, 2])
        .init()
        .forward(x)
}

/// FID InceptionA (`Mixed_5b/5c/5d`).
#[derive(Module, Debug)]
pub struct InceptionA {
    /// 1×1 → 64.
    pub branch1x1: BasicConv2d,
    /// 1×1 → 48.
    pub branch5x5_1: BasicConv2d,
    /// 5×5 p2, 48 → 64.
    pub branch5x5_2: BasicConv2d,
    /// 1×1 → 64.
    pub branch3x3dbl_1: BasicConv2d,
    /// 3×3 p1, 64 → 96.
    pub branch3x3dbl_2: BasicConv2d,
    /// 3×3 p1, 96 → 96.
    pub branch3x3dbl_3: BasicConv2d,
    /// 1×1 after the average pool → pool features.
    pub branch_pool: BasicConv2d,
}

impl InceptionA {
    fn new(c_in: usize, pool_features: usize, device: &Device) -> Self {
        Self {
            branch1x1: basic(c_in, 64, device),
            branch5x5_1: basic(c_in, 48, device),
            branch5x5_2: basic_k(48, 64, [5, 5], 1, [2, 2], device),
            branch3x3dbl_1: basic(c_in, 64, device),
            branch3x3dbl_2: basic_k(64, 96, [3, 3], 1, [1, 1], device),
            branch3x3dbl_3: basic_k(96, 96, [3, 3], 1, [1, 1], device),
            branch_pool: basic(c_in, pool_features, device),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let b1 = self.branch1x1.forward(x.clone());
        let b5 = self
            .branch5x5_2
            .forward(self.branch5x5_1.forward(x.clone()));
        let b3 = self.branch3x3dbl_3.forward(
            self.branch3x3dbl_2
                .forward(self.branch3x3dbl_1.forward(x.clone())),
        );
        let bp = self.branch_pool.forward(avg_pool_3x3(x));
        Tensor::cat(vec![b1, b5, b3, bp], 1)
    }
}

/// torchvision InceptionB (`Mixed_6a`), a stride-2 reduction.
#[derive(Module, Debug)]
pub struct InceptionB {
    /// 3×3/2 → 384.
    pub branch3x3: BasicConv2d,
    /// 1×1 → 64.
    pub branch3x3dbl_1: BasicConv2d,
    /// 3×3 p1, 64 → 96.
    pub branch3x3dbl_2: BasicConv2d,
    /// 3×3/2, 96 → 96.
    pub branch3x3dbl_3: BasicConv2d,
}

impl InceptionB {
    fn new(c_in: usize, device: &Device) -> Self {
        Self {
            branch3x3: basic_k(c_in, 384, [3, 3], 2, [0, 0], device),
            branch3x3dbl_1: basic(c_in, 64, device),
            branch3x3dbl_2: basic_k(64, 96, [3, 3], 1, [1, 1], device),
            branch3x3dbl_3: basic_k(96, 96, [3, 3], 2, [0, 0], device),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let b3 = self.branch3x3.forward(x.clone());
        let bd = self.branch3x3dbl_3.forward(
            self.branch3x3dbl_2
                .forward(self.branch3x3dbl_1.forward(x.clone())),
        );
        Tensor::cat(vec![b3, bd, max_pool_3x3_s2(x)], 1)
    }
}

/// FID InceptionC (`Mixed_6b..6e`) with factorised 7×7 convolutions.
#[derive(Module, Debug)]
pub struct InceptionC {
    /// 1×1 → 192.
    pub branch1x1: BasicConv2d,
    /// 1×1 → c7.
    pub branch7x7_1: BasicConv2d,
    /// 1×7 p(0,3), c7 → c7.
    pub branch7x7_2: BasicConv2d,
    /// 7×1 p(3,0), c7 → 192.
    pub branch7x7_3: BasicConv2d,
    /// 1×1 → c7.
    pub branch7x7dbl_1: BasicConv2d,
    /// 7×1, c7 → c7.
    pub branch7x7dbl_2: BasicConv2d,
    /// 1×7, c7 → c7.
    pub branch7x7dbl_3: BasicConv2d,
    /// 7×1, c7 → c7.
    pub branch7x7dbl_4: BasicConv2d,
    /// 1×7, c7 → 192.
    pub branch7x7dbl_5: BasicConv2d,
    /// 1×1 after the average pool → 192.
    pub branch_pool: BasicConv2d,
}

impl InceptionC {
    fn new(c_in: usize, c7: usize, device: &Device) -> Self {
        let row = |a, b| basic_k(a, b, [1, 7], 1, [0, 3], device);
        let col = |a, b| basic_k(a, b, [7, 1], 1, [3, 0], device);
        Self {
            branch1x1: basic(c_in, 192, device),
            branch7x7_1: basic(c_in, c7, device),
            branch7x7_2: row(c7, c7),
            branch7x7_3: col(c7, 192),
            branch7x7dbl_1: basic(c_in, c7, device),
            branch7x7dbl_2: col(c7, c7),
            branch7x7dbl_3: row(c7, c7),
            branch7x7dbl_4: col(c7, c7),
            branch7x7dbl_5: row(c7, 192),
            branch_pool: basic(c_in, 192, device),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let b1 = self.branch1x1.forward(x.clone());
        let b7 = [&self.branch7x7_1, &self.branch7x7_2, &self.branch7x7_3]
            .iter()
            .fold(x.clone(), |y, l| l.forward(y));
        let bd = [
            &self.branch7x7dbl_1,
            &self.branch7x7dbl_2,
            &self.branch7x7dbl_3,
            &self.branch7x7dbl_4,
            &self.branch7x7dbl_5,
        ]
        .iter()
        .fold(x.clone(), |y, l| l.forward(y));
        let bp = self.branch_pool.forward(avg_pool_3x3(x));
        Tensor::cat(vec![b1, b7, bd, bp], 1)
    }
}

/// torchvision InceptionD (`Mixed_7a`), a stride-2 reduction.
#[derive(Module, Debug)]
pub struct InceptionD {
    /// 1×1 → 192.
    pub branch3x3_1: BasicConv2d,
    /// 3×3/2, 192 → 320.
    pub branch3x3_2: BasicConv2d,
    /// 1×1 → 192.
    pub branch7x7x3_1: BasicConv2d,
    /// 1×7 p(0,3).
    pub branch7x7x3_2: BasicConv2d,
    /// 7×1 p(3,0).
    pub branch7x7x3_3: BasicConv2d,
    /// 3×3/2, 192 → 192.
    pub branch7x7x3_4: BasicConv2d,
}

impl InceptionD {
    fn new(c_in: usize, device: &Device) -> Self {
        Self {
            branch3x3_1: basic(c_in, 192, device),
            branch3x3_2: basic_k(192, 320, [3, 3], 2, [0, 0], device),
            branch7x7x3_1: basic(c_in, 192, device),
            branch7x7x3_2: basic_k(192, 192, [1, 7], 1, [0, 3], device),
            branch7x7x3_3: basic_k(192, 192, [7, 1], 1, [3, 0], device),
            branch7x7x3_4: basic_k(192, 192, [3, 3], 2, [0, 0], device),
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let b3 = self
            .branch3x3_2
            .forward(self.branch3x3_1.forward(x.clone()));
        let b7 = [
            &self.branch7x7x3_1,
            &self.branch7x7x3_2,
            &self.branch7x7x3_3,
            &self.branch7x7x3_4,
        ]
        .iter()
        .fold(x.clone(), |y, l| l.forward(y));
        Tensor::cat(vec![b3, b7, max_pool_3x3_s2(x)], 1)
    }
}

/// FID InceptionE_1 (`Mixed_7b`, average pool) or E_2 (`Mixed_7c`, max pool).
#[derive(Module, Debug)]
pub struct InceptionE {
    /// 1×1 → 320.
    pub branch1x1: BasicConv2d,
    /// 1×1 → 384.
    pub branch3x3_1: BasicConv2d,
    /// 1×3 p(0,1), 384 → 384.
    pub branch3x3_2a: BasicConv2d,
    /// 3×1 p(1,0), 384 → 384.
    pub branch3x3_2b: BasicConv2d,
    /// 1×1 → 448.
    pub branch3x3dbl_1: BasicConv2d,
    /// 3×3 p1, 448 → 384.
    pub branch3x3dbl_2: BasicConv2d,
    /// 1×3 p(0,1), 384 → 384.
    pub branch3x3dbl_3a: BasicConv2d,
    /// 3×1 p(1,0), 384 → 384.
    pub branch3x3dbl_3b: BasicConv2d,
    /// 1×1 after the pool → 192.
    pub branch_pool: BasicConv2d,
    /// `true` for FIDInceptionE_2 (3×3/1 max pool), `false` for E_1 (average pool without
    /// counting padding). Not a tensor: not in the weights file.
    pub max_pool: bool,
}

impl InceptionE {
    fn new(c_in: usize, max_pool: bool, device: &Device) -> Self {
        Self {
            branch1x1: basic(c_in, 320, device),
            branch3x3_1: basic(c_in, 384, device),
            branch3x3_2a: basic_k(384, 384, [1, 3], 1, [0, 1], device),
            branch3x3_2b: basic_k(384, 384, [3, 1], 1, [1, 0], device),
            branch3x3dbl_1: basic(c_in, 448, device),
            branch3x3dbl_2: basic_k(448, 384, [3, 3], 1, [1, 1], device),
            branch3x3dbl_3a: basic_k(384, 384, [1, 3], 1, [0, 1], device),
            branch3x3dbl_3b: basic_k(384, 384, [3, 1], 1, [1, 0], device),
            branch_pool: basic(c_in, 192, device),
            max_pool,
        }
    }

    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let b1 = self.branch1x1.forward(x.clone());
        let b3 = self.branch3x3_1.forward(x.clone());
        let b3 = Tensor::cat(
            vec![
                self.branch3x3_2a.forward(b3.clone()),
                self.branch3x3_2b.forward(b3),
            ],
            1,
        );
        let bd = self
            .branch3x3dbl_2
            .forward(self.branch3x3dbl_1.forward(x.clone()));
        let bd = Tensor::cat(
            vec![
                self.branch3x3dbl_3a.forward(bd.clone()),
                self.branch3x3dbl_3b.forward(bd),
            ],
            1,
        );
        let pooled = if self.max_pool {
            MaxPool2dConfig::new([3, 3])
                .with_strides([1, 1])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init()
                .forward(x)
        } else {
            avg_pool_3x3(x)
        };
        let bp = self.branch_pool.forward(pooled);
        Tensor::cat(vec![b1, b3, bd, bp], 1)
    }
}

/// The FID InceptionV3 trunk. Field paths are the converted file's keys (pytorch-fid's
/// `Conv2d_*` / `Mixed_*` names lower-cased).
#[derive(Module, Debug)]
pub struct InceptionV3Fid {
    /// 3×3/2, 3 → 32.
    pub conv2d_1a_3x3: BasicConv2d,
    /// 3×3, 32 → 32.
    pub conv2d_2a_3x3: BasicConv2d,
    /// 3×3 p1, 32 → 64.
    pub conv2d_2b_3x3: BasicConv2d,
    /// 1×1, 64 → 80.
    pub conv2d_3b_1x1: BasicConv2d,
    /// 3×3, 80 → 192.
    pub conv2d_4a_3x3: BasicConv2d,
    /// A(192, 32) → 256.
    pub mixed_5b: InceptionA,
    /// A(256, 64) → 288.
    pub mixed_5c: InceptionA,
    /// A(288, 64) → 288.
    pub mixed_5d: InceptionA,
    /// B(288) → 768.
    pub mixed_6a: InceptionB,
    /// C(768, 128).
    pub mixed_6b: InceptionC,
    /// C(768, 160).
    pub mixed_6c: InceptionC,
    /// C(768, 160).
    pub mixed_6d: InceptionC,
    /// C(768, 192).
    pub mixed_6e: InceptionC,
    /// D(768) → 1280.
    pub mixed_7a: InceptionD,
    /// E_1(1280) → 2048.
    pub mixed_7b: InceptionE,
    /// E_2(2048) → 2048.
    pub mixed_7c: InceptionE,
}

/// Configuration of [`InceptionV3Fid`] (the architecture is fixed).
#[derive(Config, Debug)]
pub struct InceptionV3FidConfig {}

impl InceptionV3FidConfig {
    /// Builds the network with random convolutions and identity batch norms; load weights
    /// next.
    pub fn init(&self, device: &Device) -> InceptionV3Fid {
        let d = device;
        InceptionV3Fid {
            conv2d_1a_3x3: basic_k(3, 32, [3, 3], 2, [0, 0], d),
            conv2d_2a_3x3: basic_k(32, 32, [3, 3], 1, [0, 0], d),
            conv2d_2b_3x3: basic_k(32, 64, [3, 3], 1, [1, 1], d),
            conv2d_3b_1x1: basic(64, 80, d),
            conv2d_4a_3x3: basic_k(80, 192, [3, 3], 1, [0, 0], d),
            mixed_5b: InceptionA::new(192, 32, d),
            mixed_5c: InceptionA::new(256, 64, d),
            mixed_5d: InceptionA::new(288, 64, d),
            mixed_6a: InceptionB::new(288, d),
            mixed_6b: InceptionC::new(768, 128, d),
            mixed_6c: InceptionC::new(768, 160, d),
            mixed_6d: InceptionC::new(768, 160, d),
            mixed_6e: InceptionC::new(768, 192, d),
            mixed_7a: InceptionD::new(768, d),
            mixed_7b: InceptionE::new(1280, false, d),
            mixed_7c: InceptionE::new(2048, true, d),
        }
    }
}

impl InceptionV3Fid {
    /// Blocks 0–3 on an already resized and normalised batch `[N, 3, H, W]` → `[N, 2048]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        let x = self.conv2d_1a_3x3.forward(x);
        let x = self.conv2d_2a_3x3.forward(x);
        let x = self.conv2d_2b_3x3.forward(x);
        let x = max_pool_3x3_s2(x);
        let x = self.conv2d_3b_1x1.forward(x);
        let x = self.conv2d_4a_3x3.forward(x);
        let x = max_pool_3x3_s2(x);
        let x = self.mixed_5b.forward(x);
        let x = self.mixed_5c.forward(x);
        let x = self.mixed_5d.forward(x);
        let x = self.mixed_6a.forward(x);
        let x = self.mixed_6b.forward(x);
        let x = self.mixed_6c.forward(x);
        let x = self.mixed_6d.forward(x);
        let x = self.mixed_6e.forward(x);
        let x = self.mixed_7a.forward(x);
        let x = self.mixed_7b.forward(x);
        let x = self.mixed_7c.forward(x);
        let [n, c, _, _] = x.dims();
        // AdaptiveAvgPool2d((1, 1)) = mean over the spatial positions.
        x.mean_dim(3).mean_dim(2).reshape([n, c])
    }
}

/// pytorch-fid's pool3 feature extractor with loaded weights. See the module docs.
#[derive(Debug)]
pub struct InceptionPool3 {
    model: InceptionV3Fid,
}

impl InceptionPool3 {
    /// Loads converted weights (`pt_inception.safetensors` from
    /// `lifegom-weights fetch` or `convert`).
    pub fn load(path: &Path, device: &Device) -> Result<Self, PerceptualError> {
        let model = InceptionV3FidConfig::new().init(device);
        Ok(Self {
            model: load_safetensors(model, path)?,
        })
    }

    /// Wraps an already built (and filled) network.
    pub fn from_model(model: InceptionV3Fid) -> Self {
        Self { model }
    }

    /// The network.
    pub fn model(&self) -> &InceptionV3Fid {
        &self.model
    }

    /// pytorch-fid features: images `[N, 3, H, W]` in `[0, 1]` → `[N, 2048]` (resize to 299
    /// bilinear `align_corners=False`, normalise to `[−1, 1]`, FID-Inception blocks, global
    /// average pool).
    ///
    /// # Panics
    /// If the shape is invalid (see [`InceptionPool3::try_features`]).
    pub fn features(&self, images: Tensor<4>) -> Tensor<2> {
        match self.try_features(images) {
            Ok(f) => f,
            Err(e) => panic!("InceptionPool3::features: {e}"),
        }
    }

    /// [`InceptionPool3::features`] returning an error for a batch that is not
    /// `[N ≥ 1, 3, H ≥ 1, W ≥ 1]`.
    pub fn try_features(&self, images: Tensor<4>) -> Result<Tensor<2>, PerceptualError> {
        let dims = images.dims();
        let [n, c, h, w] = dims;
        if n == 0 || c != 3 || h == 0 || w == 0 {
            return Err(PerceptualError::Input {
                model: "InceptionPool3",
                field: "images",
                reason: format!("must be [N ≥ 1, 3, H ≥ 1, W ≥ 1], got {dims:?}"),
            });
        }
        let x = if [h, w] == [INCEPTION_SIZE; 2] {
            // torch's bilinear resize to the same size is the identity.
            images
        } else {
            Interpolate2dConfig::new()
                .with_output_size(Some([INCEPTION_SIZE, INCEPTION_SIZE]))
                .with_mode(InterpolateMode::Linear)
                .with_align_corners(false)
                .init()
                .forward(images)
        };
        Ok(self.model.forward(x * 2.0 - 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Stage shapes of torchvision's Inception at 299² (pool3 is 8×8×2048 before the mean),
    /// with the default random weights: only shapes and finiteness are checked here, the
    /// numbers are checked against pytorch-fid in `tests/perceptual_parity.rs`.
    #[test]
    fn shapes_and_input_errors() {
        let device = Device::flex();
        let model = InceptionV3FidConfig::new().init(&device);
        let x = Tensor::<4>::ones([1, 3, 299, 299], &device);
        let x = model.conv2d_1a_3x3.forward(x);
        assert_eq!(x.dims(), [1, 32, 149, 149]);
        let x = model.conv2d_2b_3x3.forward(model.conv2d_2a_3x3.forward(x));
        let x = max_pool_3x3_s2(x);
        assert_eq!(x.dims(), [1, 64, 73, 73]);
        let x = max_pool_3x3_s2(model.conv2d_4a_3x3.forward(model.conv2d_3b_1x1.forward(x)));
        assert_eq!(x.dims(), [1, 192, 35, 35]);
        let x = model.mixed_5b.forward(x);
        assert_eq!(x.dims(), [1, 256, 35, 35]);
        let x = model
            .mixed_6a
            .forward(model.mixed_5d.forward(model.mixed_5c.forward(x)));
        assert_eq!(x.dims(), [1, 768, 17, 17]);
        let x = model.mixed_7a.forward(model.mixed_6b.forward(x));
        assert_eq!(x.dims(), [1, 1280, 8, 8]);
        let x = model.mixed_7c.forward(model.mixed_7b.forward(x));
        assert_eq!(x.dims(), [1, 2048, 8, 8]);

        let net = InceptionPool3::from_model(model);
        for bad in [[0, 3, 8, 8], [1, 1, 8, 8], [1, 3, 0, 8]] {
            let err = net
                .try_features(Tensor::<4>::zeros(bad, &device))
                .unwrap_err();
            assert!(err.to_string().contains("`images`"), "{err}");
        }
    }

    /// `count_include_pad=False`: a constant map stays constant under the 3×3 average pool,
    /// borders included (with padding counted, corners would be 4/9 of the value).
    fn avg_pool_excludes_padding(device: &Device) {
        let x = Tensor::<4>::ones([1, 2, 5, 4], device) * 3.0;
        let y = avg_pool_3x3(x);
        assert_eq!(y.dims(), [1, 2, 5, 4]);
        let v = y.into_data().try_to_vec::<f32>().unwrap();
        assert!(v.iter().all(|p| (p - 3.0).abs() < 1e-6), "{v:?}");
    }
    lifegom_render::cpu_backend_tests!(avg_pool_count_include_pad_false => avg_pool_excludes_padding);
}
