//! The image encoder (design.md §7.1): a torchvision ResNet-18 cut into a feature pyramid, plus a
//! 1×1 "rgb embedding" of the normalised image.
//!
//! For an image batch `[N, 3, H, W]` in `[0, 1]`:
//!
//! | # | source | channels (width 1) | stride |
//! |---|---|---|---|
//! | 0 | `relu(bn1(conv1(x)))` | 64 | /2 |
//! | 1 | `layer1(maxpool(·))` | 64 | /4 |
//! | 2 | `layer2` | 128 | /8 |
//! | 3 | `layer3` | 256 | /16 |
//! | 4 | `layer4` | 512 | /32 |
//! | 5 | `rgb_embed(x)`, Conv2d 3→128, 1×1, bias | 128 | /1 |
//!
//! where `x` is the image normalised with the ImageNet mean/std (done inside
//! [`ImageEncoder::forward`]). 1152 channels in all at width 1.
//!
//! # Batch norm: frozen statistics, trainable affine
//!
//! The reference keeps every BatchNorm in eval mode during training (overridden `train()`), so
//! the running mean/variance are never updated and never replaced by batch statistics, while
//! γ/β still learn. Here every BatchNorm is applied with its running statistics, whatever the
//! device (autodiff or not) and whatever the layer's `training` flag (which is also set to
//! false at init, so Burn's own `BatchNorm::forward` would agree): the output of an image
//! never depends on the other images in the batch, and gradients still reach γ, β and the
//! convolutions. Each BN is applied as its per-channel `x·scale + shift`, folded once per
//! reconstruction and kept for the encoder's other passes ([`crate::norm_folds`]).
//!
//! # Width
//!
//! [`ImageEncoderConfig::width`] scales every ResNet channel count (rounded, at least 8) so that
//! tests and CPU smoke runs can use a small network. Only width 1 matches the torchvision
//! architecture and can load pretrained weights.
//!
//! # Sampling without the full-resolution embedding
//!
//! [`ImageEncoder::encode`] returns [`EncodedViews`], which samples exactly what
//! [`lifegom_ops::sampling::sample_maps`] would sample from `forward`'s six maps, but applies the
//! 1×1 `rgb_embed` after sampling (it is affine per pixel), so the 128-channel full-resolution
//! map never exists. Use it for the reconstructor; `forward` is the literal pyramid.
//!
//! # Weights
//!
//! [`ImageEncoder::load_torchvision`] reads a torchvision ResNet-18 state dict (`.pth` zip or
//! legacy pickle, or `.safetensors`) or an official LIFe-GoM checkpoint (keys
//! `img_encoder.encoder.{0,1,4,5,6,7}.*` and `img_encoder.rgb_embed.*`, possibly nested under a
//! wrapper key), remaps the names onto this module and reports what was loaded. Without a
//! weights file the encoder keeps its random initialisation ([`Weights::RandomInit`]); callers
//! must say so plainly, because an ImageNet-free encoder is far from the paper's setting.

use std::fmt;
use std::path::{Path, PathBuf};

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, Initializer, PaddingConfig2d};
use burn::store::{ApplyResult, KeyRemapper, ModuleSnapshot, PytorchStore, SafetensorsStore};
use burn::tensor::{Device, Tensor, TensorData, s};
use lifegom_ops::activation::relu;

use crate::norm_folds::NormFolds;
use crate::weights_file::WeightsFormat;
use lifegom_ops::activation::Activation::{self, Identity, Relu};
use lifegom_ops::channel_norm::ChannelNorm;
use lifegom_ops::conv_norm::ConvNorm;
use lifegom_ops::gemm_conv::gemm_patches;
use lifegom_ops::sampling::{PreparedMaps, SamplingError};

/// ImageNet normalisation used by torchvision's ResNet weights.
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// ImageNet standard deviation.
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// ResNet-18 channel counts at width 1: stem, layer1..layer4.
const RESNET18_CHANNELS: [usize; 5] = [64, 64, 128, 256, 512];

/// Errors of the image encoder (weight loading).
#[derive(Debug, thiserror::Error)]
pub enum EncoderError {
    /// The weights file cannot be opened or read.
    #[error("image encoder weights {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The file is not a readable PyTorch or SafeTensors checkpoint.
    #[error("image encoder weights {path}: not a readable {format} file: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// The format it was read as (`PyTorch`, `SafeTensors`).
        format: &'static str,
        /// The reader's message.
        reason: String,
    },
    /// No tensor in the file has a ResNet-18 or LIFe-GoM encoder name.
    #[error(
        "image encoder weights {path}: no tensor named like a ResNet-18 (`conv1.weight`, \
         `layer1.0.conv1.weight`, `img_encoder.encoder.0.weight`, ...); the file has {count} \
         tensors, e.g. {examples:?}"
    )]
    NoMatch {
        /// The file.
        path: PathBuf,
        /// How many tensors the file has.
        count: usize,
        /// A few of their names.
        examples: Vec<String>,
    },
    /// Some ResNet-18 tensors are absent: a partial backbone would be silently wrong.
    #[error("image encoder weights {path}: incomplete ResNet-18, missing {missing:?}")]
    Incomplete {
        /// The file.
        path: PathBuf,
        /// The encoder fields that were not found.
        missing: Vec<String>,
    },
    /// Tensors exist under the right names but with the wrong shape or type.
    #[error("image encoder weights {path}: {errors:?}")]
    Mismatch {
        /// The file.
        path: PathBuf,
        /// One line per offending tensor (field, expected and found shape or dtype).
        errors: Vec<String>,
    },
    /// Pretrained weights only fit the width-1 network.
    #[error(
        "image encoder: pretrained weights need width 1 (ResNet channels {RESNET18_CHANNELS:?}), \
         this encoder has {channels:?}"
    )]
    Width {
        /// This encoder's ResNet channel counts.
        channels: Vec<usize>,
    },
}

/// Where the encoder's parameters came from.
#[derive(Debug, Clone, PartialEq)]
pub enum Weights {
    /// Loaded from a file.
    Pretrained {
        /// The file.
        path: PathBuf,
        /// Number of tensors applied.
        applied: usize,
        /// Encoder fields the file did not have and which keep their random init (only
        /// `rgb_embed.*`, absent from torchvision files, can be here).
        missing: Vec<String>,
    },
    /// No weights file: random initialisation.
    RandomInit,
}

impl fmt::Display for Weights {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Weights::Pretrained {
                path,
                applied,
                missing,
            } => {
                write!(f, "{applied} tensors loaded from {}", path.display())?;
                if !missing.is_empty() {
                    write!(f, "; randomly initialised: {}", missing.join(", "))?;
                }
                Ok(())
            }
            Weights::RandomInit => write!(
                f,
                "RANDOM initialisation (no ResNet-18 weights file given): features are not \
                 ImageNet-pretrained as in the paper"
            ),
        }
    }
}

/// Configuration of [`ImageEncoder`].
#[derive(Config, Debug)]
pub struct ImageEncoderConfig {
    /// Scale of every ResNet channel count (rounded, at least 8). 1 is ResNet-18.
    #[config(default = 1.0)]
    pub width: f32,
    /// Channels of the 1×1 rgb embedding (level 5). Not scaled by `width`.
    #[config(default = 128)]
    pub rgb_embed_channels: usize,
    /// Batch-norm epsilon (torchvision: 1e-5).
    #[config(default = 1e-5)]
    pub bn_epsilon: f64,
}

/// A ResNet basic block: `relu(bn2(conv2(relu(bn1(conv1(x))))) + shortcut(x))`.
#[derive(Module, Debug)]
pub struct BasicBlock {
    /// 3×3 conv, carries the block's stride.
    pub conv1: Conv2d,
    /// BN after `conv1`.
    pub bn1: BatchNorm,
    /// 3×3 conv.
    pub conv2: Conv2d,
    /// BN after `conv2`.
    pub bn2: BatchNorm,
    /// 1×1 strided conv + BN when the block changes resolution or width.
    pub downsample: Option<Downsample>,
}

/// The projection shortcut of a [`BasicBlock`] (torchvision's `downsample.{0,1}`).
#[derive(Module, Debug)]
pub struct Downsample {
    /// 1×1 strided conv (torchvision `downsample.0`).
    pub conv: Conv2d,
    /// Its BN (torchvision `downsample.1`).
    pub bn: BatchNorm,
}

/// The ResNet-18 feature pyramid with an rgb embedding. See the module docs.
///
/// Field names follow torchvision (`layerK` are the block lists), so a state dict maps onto
/// them with only `downsample.{0,1}` renamed.
#[derive(Module, Debug)]
pub struct ImageEncoder {
    /// 7×7 stride-2 stem conv.
    pub conv1: Conv2d,
    /// Stem BN.
    pub bn1: BatchNorm,
    /// 3×3 stride-2 max pool before `layer1`.
    pub maxpool: MaxPool2d,
    /// Two blocks, stride 1.
    pub layer1: Vec<BasicBlock>,
    /// Two blocks, stride 2.
    pub layer2: Vec<BasicBlock>,
    /// Two blocks, stride 2.
    pub layer3: Vec<BasicBlock>,
    /// Two blocks, stride 2.
    pub layer4: Vec<BasicBlock>,
    /// 1×1 conv with bias on the normalised image (level 5).
    pub rgb_embed: Conv2d,
}

/// torchvision's ResNet init: `kaiming_normal_(mode="fan_out", nonlinearity="relu")`.
fn resnet_init() -> Initializer {
    Initializer::KaimingNormal {
        gain: std::f64::consts::SQRT_2,
        fan_out_only: true,
    }
}

fn conv(c_in: usize, c_out: usize, kernel: usize, stride: usize, device: &Device) -> Conv2d {
    let pad = kernel / 2;
    Conv2dConfig::new([c_in, c_out], [kernel, kernel])
        .with_stride([stride, stride])
        .with_padding(PaddingConfig2d::Explicit(pad, pad, pad, pad))
        .with_bias(false)
        .with_initializer(resnet_init())
        .init(device)
}

fn batch_norm(channels: usize, epsilon: f64, device: &Device) -> BatchNorm {
    let mut bn = BatchNormConfig::new(channels)
        .with_epsilon(epsilon)
        .init(device);
    // Statistics are frozen (module docs); `frozen_bn` ignores the flag, this keeps Burn's own
    // `BatchNorm::forward` consistent with it.
    bn.training = bn.training.with_value(false);
    bn
}

/// BatchNorm with running statistics, whatever the device or the layer's flag: `x·scale + shift`
/// per channel, then `activation`, as a [`ChannelNorm`] kept in `folds` for the
/// reconstruction's other encoder passes ([`crate::norm_folds`]): two tensor ops on the CPU
/// backends instead of Burn's six-op inference `batch_norm`, one launch per pass on CubeCL
/// devices with one gradient of `[γ; β]` for every pass.
fn frozen_bn<'a>(
    folds: &NormFolds<'a>,
    bn: &'a BatchNorm,
    x: Tensor<4>,
    activation: Activation,
) -> Tensor<4> {
    let device = x.device();
    folds
        .keep(bn, "channel norm", || ChannelNorm::new(bn, &device))
        .apply(x, activation)
}

/// What follows a convolution's BatchNorm: an activation, or a residual block's
/// `relu(· + shortcut)`.
#[expect(
    clippy::large_enum_variant,
    reason = "made and taken apart within one call, never stored"
)]
enum Ending {
    Activation(Activation),
    ResidualRelu(Tensor<4>),
}

/// `ending(BN(conv(x)))`, the BatchNorm as [`frozen_bn`]. On CubeCL devices whose convolutions
/// are products ([`lifegom_ops::gemm_conv::ConvKernel`]) the convolution, the norm and the ending are
/// one shared product per pass ([`lifegom_ops::conv_norm`], kept in `folds` for the other passes);
/// elsewhere the convolution, then [`frozen_bn`].
fn conv_bn<'a>(
    folds: &NormFolds<'a>,
    conv: &'a Conv2d,
    bn: &'a BatchNorm,
    x: Tensor<4>,
    ending: Ending,
) -> Tensor<4> {
    if let Some(patches) = gemm_patches(conv, &x) {
        let device = x.device();
        let layer = folds.keep(conv, "conv norm", || {
            ConvNorm::new(conv, bn, patches, &device)
        });
        return match ending {
            Ending::Activation(activation) => layer.apply(x, activation),
            Ending::ResidualRelu(shortcut) => layer.apply_residual_relu(x, shortcut),
        };
    }
    match ending {
        Ending::Activation(activation) => frozen_bn(folds, bn, conv.forward(x), activation),
        Ending::ResidualRelu(shortcut) => {
            relu(frozen_bn(folds, bn, conv.forward(x), Identity) + shortcut)
        }
    }
}

impl BasicBlock {
    fn new(c_in: usize, c_out: usize, stride: usize, eps: f64, device: &Device) -> Self {
        let downsample = (stride != 1 || c_in != c_out).then(|| Downsample {
            conv: conv(c_in, c_out, 1, stride, device),
            bn: batch_norm(c_out, eps, device),
        });
        Self {
            conv1: conv(c_in, c_out, 3, stride, device),
            bn1: batch_norm(c_out, eps, device),
            conv2: conv(c_out, c_out, 3, 1, device),
            bn2: batch_norm(c_out, eps, device),
            downsample,
        }
    }

    fn forward<'a>(&'a self, folds: &NormFolds<'a>, x: Tensor<4>) -> Tensor<4> {
        let shortcut = match &self.downsample {
            Some(d) => conv_bn(
                folds,
                &d.conv,
                &d.bn,
                x.clone(),
                Ending::Activation(Identity),
            ),
            None => x.clone(),
        };
        let y = conv_bn(folds, &self.conv1, &self.bn1, x, Ending::Activation(Relu));
        conv_bn(
            folds,
            &self.conv2,
            &self.bn2,
            y,
            Ending::ResidualRelu(shortcut),
        )
    }

    #[cfg(test)]
    fn bns_mut(&mut self) -> Vec<&mut BatchNorm> {
        let mut v = vec![&mut self.bn1, &mut self.bn2];
        if let Some(d) = &mut self.downsample {
            v.push(&mut d.bn);
        }
        v
    }
}

fn layer(c_in: usize, c_out: usize, stride: usize, eps: f64, device: &Device) -> Vec<BasicBlock> {
    vec![
        BasicBlock::new(c_in, c_out, stride, eps, device),
        BasicBlock::new(c_out, c_out, 1, eps, device),
    ]
}

impl ImageEncoderConfig {
    /// ResNet channel counts (stem, layer1..layer4) at this width.
    pub fn resnet_channels(&self) -> [usize; 5] {
        RESNET18_CHANNELS.map(|c| ((c as f32 * self.width).round() as usize).max(8))
    }

    /// Channels of the six output maps, in output order (what [`ImageEncoder::channels`] of
    /// the built encoder returns).
    pub fn channels(&self) -> [usize; 6] {
        let [c0, c1, c2, c3, c4] = self.resnet_channels();
        [c0, c1, c2, c3, c4, self.rgb_embed_channels]
    }

    /// Total channels of the pyramid (1152 at the defaults).
    pub fn feature_dim(&self) -> usize {
        self.channels().iter().sum()
    }

    /// Builds the encoder with torchvision's random initialisation.
    ///
    /// # Panics
    /// If `width` is not finite and positive or `rgb_embed_channels` is zero.
    pub fn init(&self, device: &Device) -> ImageEncoder {
        assert!(
            self.width.is_finite() && self.width > 0.0,
            "ImageEncoderConfig.width must be finite and > 0, got {}",
            self.width
        );
        assert!(
            self.rgb_embed_channels > 0,
            "ImageEncoderConfig.rgb_embed_channels must be > 0"
        );
        let [c0, c1, c2, c3, c4] = self.resnet_channels();
        let eps = self.bn_epsilon;
        ImageEncoder {
            conv1: conv(3, c0, 7, 2, device),
            bn1: batch_norm(c0, eps, device),
            // Padding value does not matter: the input is post-ReLU (≥ 0) and every window
            // holds at least one real element, so zero padding equals torch's −∞ padding.
            maxpool: MaxPool2dConfig::new([3, 3])
                .with_strides([2, 2])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(),
            layer1: layer(c0, c1, 1, eps, device),
            layer2: layer(c1, c2, 2, eps, device),
            layer3: layer(c2, c3, 2, eps, device),
            layer4: layer(c3, c4, 2, eps, device),
            // PyTorch's default Conv2d init, which is Burn's default too.
            rgb_embed: Conv2dConfig::new([3, self.rgb_embed_channels], [1, 1]).init(device),
        }
    }
}

impl ImageEncoder {
    /// Channels of the six output maps, in output order.
    pub fn channels(&self) -> [usize; 6] {
        let out = |blocks: &[BasicBlock]| blocks[blocks.len() - 1].conv2.weight.dims()[0];
        [
            self.conv1.weight.dims()[0],
            out(&self.layer1),
            out(&self.layer2),
            out(&self.layer3),
            out(&self.layer4),
            self.rgb_embed.weight.dims()[0],
        ]
    }

    /// Total channels of the concatenated pyramid (`img_feat_dim`; 1152 at width 1).
    pub fn feature_dim(&self) -> usize {
        self.channels().iter().sum()
    }

    /// Stride of each output map relative to the input image.
    pub const STRIDES: [usize; 6] = [2, 4, 8, 16, 32, 1];

    /// Normalises `images` `[N, 3, H, W]` (in `[0, 1]`) with the ImageNet mean/std.
    pub fn normalize(images: Tensor<4>) -> Tensor<4> {
        let device = images.device();
        let dtype = images.dtype();
        let stat = |v: [f32; 3]| {
            Tensor::<4>::from_data(TensorData::new(v.to_vec(), [1, 3, 1, 1]), (&device, dtype))
        };
        (images - stat(IMAGENET_MEAN)) / stat(IMAGENET_STD)
    }

    /// The six feature maps of `images` `[N, 3, H, W]` in `[0, 1]`, in the order of the module
    /// docs.
    ///
    /// # Panics
    /// If `images` does not have 3 channels.
    pub fn forward(&self, images: Tensor<4>) -> Vec<Tensor<4>> {
        let folds = NormFolds::new();
        let dims = images.dims();
        assert_eq!(
            dims[1], 3,
            "ImageEncoder::forward: images must be [N, 3, H, W], got {dims:?}"
        );
        let x = Self::normalize(images);
        let rgb = self.rgb_embed.forward(x.clone());
        let f0 = conv_bn(&folds, &self.conv1, &self.bn1, x, Ending::Activation(Relu));
        let run = |blocks: &[BasicBlock], x: Tensor<4>| {
            blocks.iter().fold(x, |x, b| b.forward(&folds, x))
        };
        let f1 = run(&self.layer1, self.maxpool.forward(f0.clone()));
        let f2 = run(&self.layer2, f1.clone());
        let f3 = run(&self.layer3, f2.clone());
        let f4 = run(&self.layer4, f3.clone());
        vec![f0, f1, f2, f3, f4, rgb]
    }

    /// The backbone maps plus what is needed to sample the rgb embedding without building it
    /// at full resolution; see [`EncodedViews`]. The BN folds are those of `folds`, made on first
    /// use and kept there for the next call ([`crate::norm_folds`]).
    pub fn encode<'a>(
        &'a self,
        folds: &NormFolds<'a>,
        images: Tensor<4>,
    ) -> Result<EncodedViews, SamplingError> {
        let dims = images.dims();
        assert_eq!(
            dims[1], 3,
            "ImageEncoder::encode: images must be [N, 3, H, W], got {dims:?}"
        );
        let x = Self::normalize(images);
        let f0 = conv_bn(
            folds,
            &self.conv1,
            &self.bn1,
            x.clone(),
            Ending::Activation(Relu),
        );
        let run =
            |blocks: &[BasicBlock], x: Tensor<4>| blocks.iter().fold(x, |x, b| b.forward(folds, x));
        let f1 = run(&self.layer1, self.maxpool.forward(f0.clone()));
        let f2 = run(&self.layer2, f1.clone());
        let f3 = run(&self.layer3, f2.clone());
        let f4 = run(&self.layer4, f3.clone());
        // [x̂ | 1]: bilinear weights are linear, so sampling x̂ and the in-image weight sum
        // recovers Σw·(W x̂ + b) = W·Σw x̂ + b·Σw exactly, zero padding included.
        let ones = x.clone().slice(s![.., 0..1, .., ..]).ones_like();
        let affine = Tensor::cat(vec![x, ones], 1);
        let [c_rgb, _, _, _] = self.rgb_embed.weight.dims();
        let w = self.rgb_embed.weight.val().reshape([c_rgb, 3]).transpose(); // [3, C]
        let b = match &self.rgb_embed.bias {
            Some(b) => b.val().reshape([1, c_rgb]),
            None => w.clone().slice(s![0..1, ..]).zeros_like(),
        };
        let rgb_projection = Tensor::cat(vec![w, b], 0);
        Ok(EncodedViews {
            maps: PreparedMaps::with_tail(&[f0, f1, f2, f3, f4, affine], rgb_projection)?,
        })
    }

    /// Every batch norm (tests set their statistics).
    #[cfg(test)]
    fn bns_mut(&mut self) -> Vec<&mut BatchNorm> {
        let mut v = vec![&mut self.bn1];
        for layer in [
            &mut self.layer1,
            &mut self.layer2,
            &mut self.layer3,
            &mut self.layer4,
        ] {
            for block in layer.iter_mut() {
                v.extend(block.bns_mut());
            }
        }
        v
    }

    /// Loads `path` if given, else keeps the random initialisation and says so.
    pub fn load_optional(self, path: Option<&Path>) -> Result<(Self, Weights), EncoderError> {
        match path {
            Some(p) => self.load_torchvision(p),
            None => Ok((self, Weights::RandomInit)),
        }
    }

    /// Loads a torchvision ResNet-18 state dict or an official LIFe-GoM checkpoint.
    ///
    /// The format is detected from the content (SafeTensors header, else PyTorch zip/pickle).
    /// Accepted names, after stripping wrapper prefixes such as `module.` or `state_dict.`:
    /// torchvision's `conv1`, `bn1`, `layerK.I.{conv1,bn1,conv2,bn2,downsample.0,downsample.1}`
    /// (`fc.*` ignored), or LIFe-GoM's `img_encoder.encoder.{0,1,4,5,6,7}` (= conv1, bn1,
    /// layer1..4) and `img_encoder.rgb_embed` at any nesting depth. Every backbone tensor must be
    /// present with the right shape; `rgb_embed` may be absent (it is new in LIFe-GoM and is
    /// trained from scratch) and is then listed in [`Weights::Pretrained::missing`].
    pub fn load_torchvision(mut self, path: &Path) -> Result<(Self, Weights), EncoderError> {
        let resnet = self.channels()[..5].to_vec();
        if resnet != RESNET18_CHANNELS {
            return Err(EncoderError::Width { channels: resnet });
        }
        let io = |source| EncoderError::Io {
            path: path.to_path_buf(),
            source,
        };
        let safetensors = WeightsFormat::sniff(path).map_err(io)? == WeightsFormat::SafeTensors;
        let remapper = key_remapper();
        let (result, keys) = if safetensors {
            let mut store = SafetensorsStore::from_file(path)
                .remap(remapper)
                .with_from_adapter(burn::store::PyTorchToBurnAdapter)
                .skip_enum_variants(true)
                .map_indices_contiguous(false)
                .allow_partial(true)
                .validate(false);
            apply(&mut self, &mut store, path, "SafeTensors")?
        } else {
            let mut store = PytorchStore::from_file(path)
                .remap(remapper)
                .map_indices_contiguous(false)
                .allow_partial(true)
                .validate(false);
            apply(&mut self, &mut store, path, "PyTorch")?
        };
        if !result.errors.is_empty() {
            return Err(EncoderError::Mismatch {
                path: path.to_path_buf(),
                errors: result.errors.iter().map(|e| e.to_string()).collect(),
            });
        }
        if result.applied.is_empty() {
            return Err(EncoderError::NoMatch {
                path: path.to_path_buf(),
                count: keys.len(),
                examples: keys.into_iter().take(5).collect(),
            });
        }
        let missing: Vec<String> = result.missing.iter().map(|(p, _)| p.clone()).collect();
        let backbone_missing: Vec<String> = missing
            .iter()
            .filter(|p| !p.starts_with("rgb_embed."))
            .cloned()
            .collect();
        if !backbone_missing.is_empty() {
            return Err(EncoderError::Incomplete {
                path: path.to_path_buf(),
                missing: backbone_missing,
            });
        }
        let weights = Weights::Pretrained {
            path: path.to_path_buf(),
            applied: result.applied.len(),
            missing,
        };
        tracing::info!(%weights, "image encoder weights");
        Ok((self, weights))
    }
}

/// The encoded source views, ready to be sampled at any pixel positions many times.
///
/// Equivalent to [`lifegom_ops::sampling::sample_maps`] on [`ImageEncoder::forward`]'s six maps, but
/// the full-resolution rgb embedding (128 channels at `H × W`, 1.5 GB for three 1024² views) is
/// never built: its 1×1 convolution is affine per pixel, so it is applied after sampling the
/// 3-channel normalised image (and a ones channel that carries the zero-padding weight).
#[derive(Debug, Clone)]
pub struct EncodedViews {
    /// Levels 0–4 and `[x̂ | 1]` (4 channels), channel-last, with `[Wᵀ; bᵀ]` of `rgb_embed`
    /// (`[4, C_rgb]`) as the last level's tail.
    maps: PreparedMaps,
}

impl EncodedViews {
    /// Samples the pyramid at `uv` `[N, V, 2]` (pixels of the `width × height` image the views
    /// were encoded from): `[V, N, feature_dim]`, the same as sampling `forward`'s maps.
    pub fn sample(
        &self,
        uv: Tensor<3>,
        width: u32,
        height: u32,
    ) -> Result<Tensor<3>, SamplingError> {
        self.maps.sample(uv, width, height)
    }

    /// Channels of one sample (1152 at width 1).
    pub fn feature_dim(&self) -> usize {
        self.maps.out_channels()
    }

    /// The same views detached from the autodiff graph (the feedback branch, design.md §7.3).
    pub fn detach(self) -> Self {
        Self {
            maps: self.maps.detach(),
        }
    }
}

/// Applies a store to the encoder; returns the result and the (remapped) keys of the file.
fn apply<S: burn::store::ModuleStore>(
    encoder: &mut ImageEncoder,
    store: &mut S,
    path: &Path,
    format: &'static str,
) -> Result<(ApplyResult, Vec<String>), EncoderError> {
    let err = |e: S::Error| EncoderError::Format {
        path: path.to_path_buf(),
        format,
        reason: e.to_string(),
    };
    let keys = store.keys().map_err(err)?;
    let result = encoder.load_from(store).map_err(err)?;
    Ok((result, keys))
}

/// File names → this module's field paths (patterns applied in order).
fn key_remapper() -> KeyRemapper {
    const ANY_PREFIX: &str = r"^(?:.*\.)?img_encoder\.";
    let mut patterns: Vec<(String, String)> = [
        ("encoder\\.0\\.", "conv1."),
        ("encoder\\.1\\.", "bn1."),
        ("encoder\\.4\\.", "layer1."),
        ("encoder\\.5\\.", "layer2."),
        ("encoder\\.6\\.", "layer3."),
        ("encoder\\.7\\.", "layer4."),
        ("rgb_embed\\.", "rgb_embed."),
    ]
    .into_iter()
    .map(|(from, to)| (format!("{ANY_PREFIX}{from}"), to.to_string()))
    .collect();
    patterns.extend(
        [
            // Wrapper prefixes of torchvision-style state dicts (DataParallel, checkpoints).
            (
                r"^(?:(?:module|state_dict|model)\.)+(conv1|bn1|layer[1-4]|fc)\.",
                "$1.",
            ),
            (
                r"^(layer[1-4]\.[0-9]+)\.downsample\.0\.",
                "$1.downsample.conv.",
            ),
            (
                r"^(layer[1-4]\.[0-9]+)\.downsample\.1\.",
                "$1.downsample.bn.",
            ),
        ]
        .map(|(a, b)| (a.to_string(), b.to_string())),
    );
    KeyRemapper::from_patterns(patterns).expect("the encoder's key patterns are valid regexes")
}

#[cfg(test)]
mod tests {
    // `Device::ndarray()` is deprecated in Burn 0.22; ndarray is the CI backend the project
    // requires (design.md §1.4).
    #![allow(deprecated)]
    use super::*;
    use burn::module::RunningState;
    use burn::store::{BurnToPyTorchAdapter, bridge};
    use burn::tensor::Distribution;

    fn small() -> ImageEncoderConfig {
        ImageEncoderConfig::new()
            .with_width(0.125)
            .with_rgb_embed_channels(16)
    }

    /// A smooth deterministic image batch in [0, 1].
    fn images(n: usize, h: usize, w: usize, device: &Device) -> Tensor<4> {
        let v: Vec<f32> = (0..n * 3 * h * w)
            .map(|i| 0.5 + 0.45 * ((i as f32) * 0.013).sin() * ((i / w) as f32 * 0.07).cos())
            .collect();
        Tensor::from_data(TensorData::new(v, [n, 3, h, w]), device)
    }

    use lifegom_render::testing::read;

    fn max_abs_diff<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
        (a - b).abs().max().into_scalar::<f32>()
    }

    #[test]
    fn default_width_is_resnet18_with_1152_channels() {
        let cfg = ImageEncoderConfig::new();
        assert_eq!(cfg.resnet_channels(), RESNET18_CHANNELS);
        assert_eq!(cfg.feature_dim(), 1152);
        assert_eq!(small().channels(), small().init(&Device::flex()).channels());
        assert_eq!(small().resnet_channels(), [8, 8, 16, 32, 64]);
        assert_eq!(
            ImageEncoderConfig::new().with_width(0.01).resnet_channels(),
            [8; 5]
        );
    }

    /// Output order, channels and strides (torch's conv/pool size formulas, odd sizes too).
    fn shapes(device: &Device) {
        let enc = small().init(device);
        assert_eq!(enc.channels(), [8, 8, 16, 32, 64, 16]);
        assert_eq!(enc.feature_dim(), 144);
        let maps = enc.forward(images(2, 64, 48, device));
        let dims: Vec<[usize; 4]> = maps.iter().map(|m| m.dims()).collect();
        assert_eq!(
            dims,
            [
                [2, 8, 32, 24],
                [2, 8, 16, 12],
                [2, 16, 8, 6],
                [2, 32, 4, 3],
                [2, 64, 2, 2],
                [2, 16, 64, 48]
            ]
        );
        let maps = enc.forward(images(1, 33, 17, device));
        let hw: Vec<[usize; 2]> = maps.iter().map(|m| [m.dims()[2], m.dims()[3]]).collect();
        // torchvision: 33×17 → conv1 17×9 → pool 9×5 → 5×3 → 3×2 → 2×1.
        assert_eq!(hw, [[17, 9], [9, 5], [5, 3], [3, 2], [2, 1], [33, 17]]);
        for m in maps {
            assert!(read(m).iter().all(|v| v.is_finite()));
        }
    }
    lifegom_render::cpu_backend_tests!(pyramid_shapes_and_order => shapes);

    /// The rgb embedding sees the ImageNet-normalised image: W·((x − μ)/σ) + b per pixel.
    fn normalisation(device: &Device) {
        let enc = small().init(device);
        let img = images(1, 4, 5, device);
        let rgb = read(enc.forward(img.clone()).pop().unwrap()); // [1, 16, 4, 5]
        let w = read(enc.rgb_embed.weight.val()); // [16, 3, 1, 1]
        let b = read(enc.rgb_embed.bias.as_ref().unwrap().val());
        let x = read(img);
        for (pix, c_out) in [(0usize, 0usize), (7, 3), (19, 15)] {
            let mut expect = b[c_out];
            for c in 0..3 {
                expect += w[c_out * 3 + c] * (x[c * 20 + pix] - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
            }
            let got = rgb[c_out * 20 + pix];
            assert!(
                (got - expect).abs() < 1e-5,
                "pixel {pix} channel {c_out}: {got} vs {expect}"
            );
        }
    }
    lifegom_render::cpu_backend_tests!(rgb_embed_sees_normalised_image => normalisation);

    /// Gives every batch norm random statistics and affine parameters.
    fn randomise_bn(enc: &mut ImageEncoder, device: &Device) {
        for bn in enc.bns_mut() {
            let [c] = bn.gamma.dims();
            let rand =
                |lo: f64, hi: f64| Tensor::<1>::random([c], Distribution::Uniform(lo, hi), device);
            bn.running_mean = RunningState::new(rand(-0.3, 0.3));
            bn.running_var = RunningState::new(rand(0.5, 2.0));
            bn.gamma = burn::module::Param::from_tensor(rand(0.5, 1.5));
            bn.beta = burn::module::Param::from_tensor(rand(-0.2, 0.2));
        }
    }

    /// Batch norm uses the running statistics on an autodiff device (the output of one image
    /// does not depend on the batch and matches the plain device), never updates them, and
    /// γ, β and the convolutions still get gradients.
    fn frozen_batch_norm(device: &Device) {
        let mut enc = small().init(device);
        randomise_bn(&mut enc, device);
        let plain: Vec<Tensor<4>> = enc.forward(images(1, 32, 32, device));
        let ad = device.clone().autodiff();
        // `fork` keeps the (plain) autodiff state; `train` turns gradient tracking on.
        let enc_ad = enc.clone().fork(&ad).train();
        let before = read(enc_ad.bn1.running_mean.value());
        let batch = Tensor::cat(
            vec![images(1, 32, 32, &ad), images(1, 32, 32, &ad).flip([3])],
            0,
        );
        let maps = enc_ad.forward(batch);
        for (l, (m, p)) in maps.iter().zip(&plain).enumerate() {
            let first = m.clone().narrow(0, 0, 1).inner();
            let d = max_abs_diff(first, p.clone());
            assert!(
                d < 1e-4,
                "level {l}: autodiff batch output differs from plain by {d}"
            );
        }
        let loss = maps
            .into_iter()
            .map(|m| m.sum())
            .reduce(|a, b| a + b)
            .unwrap();
        let grads = loss.backward();
        assert_eq!(
            read(enc_ad.bn1.running_mean.value()),
            before,
            "running mean was updated"
        );
        let block = &enc_ad.layer2[0];
        for (name, g) in [
            ("bn1.gamma", enc_ad.bn1.gamma.grad(&grads).map(read)),
            ("bn1.beta", enc_ad.bn1.beta.grad(&grads).map(read)),
            ("layer2.0.bn2.gamma", block.bn2.gamma.grad(&grads).map(read)),
            (
                "layer2.0.conv1.weight",
                block.conv1.weight.grad(&grads).map(read),
            ),
            (
                "rgb_embed.weight",
                enc_ad.rgb_embed.weight.grad(&grads).map(read),
            ),
        ] {
            let g = g.unwrap_or_else(|| panic!("{name} has no gradient"));
            assert!(
                g.iter().any(|v| *v != 0.0) && g.iter().all(|v| v.is_finite()),
                "{name}"
            );
        }
    }
    lifegom_render::cpu_backend_tests!(batch_norm_is_frozen_but_affine_trains => frozen_batch_norm);

    /// `encode(..).sample(..)` equals sampling `forward`'s six maps (out-of-image points too),
    /// and gradients reach the rgb embedding's weight and bias through the affine path.
    fn encoded_views(device: &Device) {
        let enc = small().init(device);
        let (w, h) = (24u32, 32u32);
        let img = images(2, h as usize, w as usize, device);
        let pts: Vec<f32> = (0..2 * 9)
            .flat_map(|i| [(i as f32 * 2.9) % 27.0 - 1.5, (i as f32 * 3.7) % 35.0 - 1.5])
            .collect();
        let uv = Tensor::<3>::from_data(TensorData::new(pts, [2, 9, 2]), device);
        let direct =
            lifegom_ops::sampling::sample_maps(&enc.forward(img.clone()), uv.clone(), w, h)
                .unwrap();
        let views = enc.encode(&NormFolds::new(), img.clone()).unwrap();
        assert_eq!(views.feature_dim(), enc.feature_dim());
        let via = views.sample(uv.clone(), w, h).unwrap();
        assert_eq!(via.dims(), [9, 2, 144]);
        let d = max_abs_diff(direct, via);
        assert!(
            d < 1e-4,
            "encode().sample() differs from sampling forward() by {d}"
        );

        let ad = device.clone().autodiff();
        let enc = enc.fork(&ad).train();
        let sampled = enc
            .encode(&NormFolds::new(), img.clone().to_device(&ad))
            .unwrap()
            .sample(uv.to_device(&ad), w, h)
            .unwrap();
        let grads = sampled.sum().backward();
        assert!(enc.rgb_embed.weight.grad(&grads).is_some());
        let gb = read(enc.rgb_embed.bias.as_ref().unwrap().grad(&grads).unwrap());
        assert!(
            gb.iter().all(|g| *g > 0.0),
            "bias gradient is the sum of in-image weights: {gb:?}"
        );
        assert!(enc.conv1.weight.grad(&grads).is_some());
    }
    lifegom_render::cpu_backend_tests!(encoded_views_match_sampled_forward => encoded_views);

    /// A second `encode` with the first one's folds gives the same maps bit for bit and
    /// folds nothing new: one fold per BatchNorm (20 in ResNet-18).
    fn kept_folds(device: &Device) {
        let enc = small().init(device);
        let (w, h) = (24usize, 32usize);
        let img = images(2, h, w, device);
        let uv = Tensor::<3>::from_data(
            TensorData::new(
                vec![3.5f32, 7.25, 11.0, 2.0, 20.5, 30.0, 0.5, 0.5],
                [2, 2, 2],
            ),
            device,
        );
        let sample =
            |views: EncodedViews| read(views.sample(uv.clone(), w as u32, h as u32).unwrap());
        let fresh = sample(enc.encode(&NormFolds::new(), img.clone()).unwrap());
        let folds = NormFolds::new();
        let first = sample(enc.encode(&folds, img.clone()).unwrap());
        assert_eq!(folds.kept(), (20, 0));
        let second = sample(enc.encode(&folds, img).unwrap());
        assert_eq!(folds.kept(), (20, 0), "the second pass folded again");
        assert_eq!(first, fresh);
        assert_eq!(second, fresh);
    }
    lifegom_render::cpu_backend_tests!(kept_folds_are_reused => kept_folds);

    /// A scratch directory removed on drop.
    struct TempDir(PathBuf);
    impl TempDir {
        fn new(name: &str) -> Self {
            let dir = std::env::temp_dir().join(format!(
                "lifegom-encoder-{name}-{}-{:?}",
                std::process::id(),
                std::thread::current().id()
            ));
            std::fs::create_dir_all(&dir).unwrap();
            Self(dir)
        }
        fn path(&self, file: &str) -> PathBuf {
            self.0.join(file)
        }
    }
    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    /// Saves `enc` as a PyTorch-convention SafeTensors file (weight/bias for BN, `downsample.0/1`)
    /// with `prefix_patterns` renaming Burn paths, and only the tensors matching `keep`.
    fn save_torch_style(enc: &ImageEncoder, path: &Path, keep: &str, renames: &[(&str, &str)]) {
        let mut store = SafetensorsStore::from_file(path)
            .with_to_adapter(BurnToPyTorchAdapter)
            .with_regex(keep)
            .with_key_remapping(r"\.downsample\.conv\.", ".downsample.0.")
            .with_key_remapping(r"\.downsample\.bn\.", ".downsample.1.");
        for (from, to) in renames {
            store = store.with_key_remapping(*from, *to);
        }
        enc.save_into(&mut store).unwrap();
    }

    /// Every tensor of the module by Burn path.
    fn snapshot(enc: &ImageEncoder) -> std::collections::BTreeMap<String, Vec<f32>> {
        enc.collect(None, None, false)
            .into_iter()
            .map(|t| {
                let name = t.name.clone();
                (
                    name,
                    bridge::into_data(t)
                        .unwrap()
                        .convert::<f32>()
                        .to_vec::<f32>()
                        .unwrap(),
                )
            })
            .collect()
    }

    /// torchvision names (no rgb_embed, as in an ImageNet file) load into every backbone field,
    /// running statistics included; rgb_embed keeps its init and is reported.
    fn torchvision_round_trip(device: &Device) {
        let dir = TempDir::new("torchvision");
        let mut source = ImageEncoderConfig::new().init(device);
        randomise_bn(&mut source, device);
        let file = dir.path("resnet18.safetensors");
        save_torch_style(&source, &file, r"^(conv1|bn1|layer)", &[]);
        let target = ImageEncoderConfig::new().init(device);
        let rgb_before = read(target.rgb_embed.weight.val());
        let (loaded, weights) = target.load_torchvision(&file).unwrap();
        let Weights::Pretrained {
            applied,
            missing,
            path,
        } = &weights
        else {
            panic!("{weights:?}")
        };
        assert_eq!(path, &file);
        // 20 convs + 20 BNs × 4 tensors (num_batches_tracked is not saved by Burn).
        assert_eq!(*applied, 20 + 20 * 4);
        let mut missing = missing.clone();
        missing.sort();
        assert_eq!(missing, ["rgb_embed.bias", "rgb_embed.weight"]);
        assert!(
            weights.to_string().contains("rgb_embed.weight"),
            "{weights}"
        );
        let (a, b) = (snapshot(&source), snapshot(&loaded));
        assert_eq!(a.len(), b.len());
        for (name, va) in &a {
            if name.starts_with("rgb_embed") {
                continue;
            }
            assert_eq!(va, &b[name], "{name} differs after loading");
        }
        assert!(a.contains_key("layer2.0.downsample.bn.running_var"));
        assert_eq!(read(loaded.rgb_embed.weight.val()), rgb_before);
    }
    lifegom_render::cpu_backend_tests!(torchvision_names_round_trip => torchvision_round_trip);

    /// The official checkpoint's names (nested under a wrapper key) load every field,
    /// rgb_embed included; the forward pass then equals the source encoder's.
    #[test]
    fn lifegom_names_round_trip_and_forward_flex() {
        let device = Device::flex();
        let dir = TempDir::new("lifegom");
        let mut source = ImageEncoderConfig::new().init(&device);
        randomise_bn(&mut source, &device);
        let file = dir.path("checkpoint.safetensors");
        save_torch_style(
            &source,
            &file,
            ".*",
            &[
                (r"^conv1\.", "network.img_encoder.encoder.0."),
                (r"^bn1\.", "network.img_encoder.encoder.1."),
                (r"^layer1\.", "network.img_encoder.encoder.4."),
                (r"^layer2\.", "network.img_encoder.encoder.5."),
                (r"^layer3\.", "network.img_encoder.encoder.6."),
                (r"^layer4\.", "network.img_encoder.encoder.7."),
                (r"^rgb_embed\.", "network.img_encoder.rgb_embed."),
            ],
        );
        let (loaded, weights) = ImageEncoderConfig::new()
            .init(&device)
            .load_torchvision(&file)
            .unwrap();
        let Weights::Pretrained {
            applied, missing, ..
        } = &weights
        else {
            panic!("{weights:?}")
        };
        assert_eq!((*applied, missing.len()), (102, 0), "{weights}");
        assert_eq!(snapshot(&source), snapshot(&loaded));
        let img = images(1, 128, 128, &device);
        for (l, (a, b)) in source
            .forward(img.clone())
            .into_iter()
            .zip(loaded.forward(img))
            .enumerate()
        {
            assert_eq!(max_abs_diff(a, b), 0.0, "level {l}");
        }
    }

    #[test]
    fn loading_errors_name_the_file() {
        let device = Device::flex();
        let dir = TempDir::new("errors");
        let enc = || ImageEncoderConfig::new().init(&device);

        let missing = dir.path("absent.pth");
        let err = enc().load_torchvision(&missing).unwrap_err();
        assert!(matches!(err, EncoderError::Io { .. }), "{err}");
        assert!(err.to_string().contains("absent.pth"), "{err}");

        let corrupt = dir.path("corrupt.pth");
        std::fs::write(&corrupt, b"this is not a checkpoint at all").unwrap();
        let err = enc().load_torchvision(&corrupt).unwrap_err();
        assert!(matches!(err, EncoderError::Format { .. }), "{err}");
        assert!(err.to_string().contains("corrupt.pth"), "{err}");

        let truncated = dir.path("truncated.safetensors");
        std::fs::write(&truncated, b"\x40\0\0\0\0\0\0\0{\"a\":").unwrap();
        let err = enc().load_torchvision(&truncated).unwrap_err();
        assert!(err.to_string().contains("truncated.safetensors"), "{err}");

        let unrelated = dir.path("unrelated.safetensors");
        save_torch_style(&enc(), &unrelated, ".*", &[(r"^", "something.else.")]);
        let err = enc().load_torchvision(&unrelated).unwrap_err();
        assert!(matches!(err, EncoderError::NoMatch { .. }), "{err}");
        assert!(err.to_string().contains("something.else."), "{err}");

        let partial = dir.path("partial.safetensors");
        save_torch_style(&enc(), &partial, r"^(conv1|bn1|layer[1-3])\.", &[]);
        let err = enc().load_torchvision(&partial).unwrap_err();
        assert!(matches!(err, EncoderError::Incomplete { .. }), "{err}");
        assert!(err.to_string().contains("layer4.0.conv1.weight"), "{err}");

        let err = small()
            .init(&device)
            .load_torchvision(&partial)
            .unwrap_err();
        assert!(matches!(err, EncoderError::Width { .. }), "{err}");

        let (_, weights) = small().init(&device).load_optional(None).unwrap();
        assert_eq!(weights, Weights::RandomInit);
        assert!(weights.to_string().contains("RANDOM"));
    }

    /// Forward time of the width-1 encoder on 3 images of 256², per CPU backend, plus one
    /// forward+backward on Flex autodiff. Run with
    /// `cargo test --workspace encoder_forward_timing -- --ignored --nocapture`.
    #[test]
    #[ignore = "timing report, not a check"]
    fn encoder_forward_timing() {
        use std::time::Instant;
        let median = |mut t: Vec<f64>| {
            t.sort_by(f64::total_cmp);
            t[t.len() / 2]
        };
        let sync = |maps: Vec<Tensor<4>>| -> f32 {
            maps.into_iter().map(|m| m.sum().into_scalar::<f32>()).sum()
        };
        for (name, device) in [("flex", Device::flex()), ("ndarray", Device::ndarray())] {
            let enc = ImageEncoderConfig::new().init(&device);
            let img = images(3, 256, 256, &device);
            sync(enc.forward(img.clone())); // warm-up
            let times: Vec<f64> = (0..3)
                .map(|_| {
                    let t = Instant::now();
                    sync(enc.forward(img.clone()));
                    t.elapsed().as_secs_f64()
                })
                .collect();
            eprintln!(
                "encoder forward, width 1, 3x3x256x256, {name}: median {:.3} s of {times:.3?}",
                median(times.clone())
            );
        }
        let ad = Device::flex().autodiff();
        let enc = ImageEncoderConfig::new().init(&ad);
        let img = images(3, 256, 256, &ad);
        let times: Vec<f64> = (0..3)
            .map(|_| {
                let t = Instant::now();
                let loss = enc
                    .forward(img.clone())
                    .into_iter()
                    .map(|m| m.mean())
                    .reduce(|a, b| a + b)
                    .unwrap();
                let grads = loss.backward();
                assert!(enc.conv1.weight.grad(&grads).is_some());
                t.elapsed().as_secs_f64()
            })
            .collect();
        eprintln!(
            "encoder forward+backward, width 1, 3x3x256x256, flex autodiff: median {:.3} s of {times:.3?}",
            median(times.clone())
        );
    }
}
