//! The operators this reader runs: their options as read from the file, and the shape each
//! produces, checked against the file's declaration before anything runs (so that a graph that
//! loads cannot fail inside a Burn op).

use crate::schema::tflite as fb;

/// TensorFlow Lite's builtin operator numbers for the operators read here.
pub(crate) mod code {
    pub const ADD: i32 = 0;
    pub const AVERAGE_POOL_2D: i32 = 1;
    pub const CONCATENATION: i32 = 2;
    pub const CONV_2D: i32 = 3;
    pub const DEPTHWISE_CONV_2D: i32 = 4;
    pub const DEPTH_TO_SPACE: i32 = 5;
    pub const DEQUANTIZE: i32 = 6;
    pub const LOGISTIC: i32 = 14;
    pub const MAX_POOL_2D: i32 = 17;
    pub const MUL: i32 = 18;
    pub const RELU: i32 = 19;
    pub const RELU_N1_TO_1: i32 = 20;
    pub const RELU6: i32 = 21;
    pub const RESHAPE: i32 = 22;
    pub const RESIZE_BILINEAR: i32 = 23;
    pub const TANH: i32 = 28;
    pub const CUSTOM: i32 = 32;
    pub const PAD: i32 = 34;
    pub const HARD_SWISH: i32 = 117;
    pub const DENSIFY: i32 = 124;
}

/// MediaPipe's custom transposed convolution with bias (the selfie model's upsampling).
pub(crate) const TRANSPOSE_CONV_BIAS: &str = "Convolution2DTransposeBias";

/// The name of a builtin operator number, for errors.
pub(crate) fn builtin_name(builtin: i32) -> String {
    let name = match builtin {
        code::ADD => "ADD",
        code::AVERAGE_POOL_2D => "AVERAGE_POOL_2D",
        code::CONCATENATION => "CONCATENATION",
        code::CONV_2D => "CONV_2D",
        code::DEPTHWISE_CONV_2D => "DEPTHWISE_CONV_2D",
        code::DEPTH_TO_SPACE => "DEPTH_TO_SPACE",
        code::DEQUANTIZE => "DEQUANTIZE",
        code::LOGISTIC => "LOGISTIC",
        code::MAX_POOL_2D => "MAX_POOL_2D",
        code::MUL => "MUL",
        code::RELU => "RELU",
        code::RELU_N1_TO_1 => "RELU_N1_TO_1",
        code::RELU6 => "RELU6",
        code::RESHAPE => "RESHAPE",
        code::RESIZE_BILINEAR => "RESIZE_BILINEAR",
        code::TANH => "TANH",
        code::CUSTOM => "CUSTOM",
        code::PAD => "PAD",
        code::HARD_SWISH => "HARD_SWISH",
        code::DENSIFY => "DENSIFY",
        9 => "FULLY_CONNECTED",
        25 => "SOFTMAX",
        _ => return format!("BUILTIN_{builtin}"),
    };
    name.to_string()
}

/// An activation fused into the operator before it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Activation {
    None,
    Relu,
    ReluMinus1To1,
    Relu6,
    Tanh,
}

impl Activation {
    fn read(a: fb::ActivationFunctionType) -> Result<Self, String> {
        Ok(match a {
            fb::ActivationFunctionType::None => Activation::None,
            fb::ActivationFunctionType::Relu => Activation::Relu,
            fb::ActivationFunctionType::ReluN1To1 => Activation::ReluMinus1To1,
            fb::ActivationFunctionType::Relu6 => Activation::Relu6,
            fb::ActivationFunctionType::Tanh => Activation::Tanh,
            fb::ActivationFunctionType::SignBit => {
                return Err("the fused activation SIGN_BIT is not run here".into());
            }
        })
    }
}

/// TensorFlow's two padding rules.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Padding {
    /// Output `ceil(in / stride)`, the zeros split with the smaller half before.
    Same,
    /// No padding.
    Valid,
}

impl Padding {
    fn read(p: fb::Padding) -> Self {
        match p {
            fb::Padding::Same => Padding::Same,
            fb::Padding::Valid => Padding::Valid,
        }
    }

    /// The output size and the `(before, after)` padding of one spatial dimension, or `None`
    /// when the window does not fit.
    pub(crate) fn window(
        self,
        input: usize,
        kernel: usize,
        stride: usize,
        dilation: usize,
    ) -> Option<(usize, (usize, usize))> {
        let extent = kernel.checked_sub(1)?.checked_mul(dilation)? + 1;
        match self {
            Padding::Same => {
                let out = input.div_ceil(stride);
                let total = ((out.checked_sub(1)?) * stride + extent).saturating_sub(input);
                Some((out, (total / 2, total - total / 2)))
            }
            Padding::Valid => Some(((input.checked_sub(extent)?) / stride + 1, (0, 0))),
        }
    }
}

/// Per spatial dimension `(before, after)` zeros, `[height, width]`.
pub(crate) type Pads = [(usize, usize); 2];

/// A 2-D window: kernel (or filter) size, stride, dilation, padding rule; `[height, width]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Window {
    pub kernel: [usize; 2],
    pub stride: [usize; 2],
    pub dilation: [usize; 2],
    pub padding: Padding,
}

impl Window {
    /// Output `[height, width]` and `[(top, bottom), (left, right)]` padding for an input of
    /// `[height, width]`.
    pub(crate) fn apply(&self, input: [usize; 2]) -> Option<([usize; 2], Pads)> {
        let (h, ph) =
            self.padding
                .window(input[0], self.kernel[0], self.stride[0], self.dilation[0])?;
        let (w, pw) =
            self.padding
                .window(input[1], self.kernel[1], self.stride[1], self.dilation[1])?;
        Some(([h, w], [ph, pw]))
    }
}

/// An operator with its options. `DEQUANTIZE` and `DENSIFY` never reach a graph: they only
/// ever convert constants, which happens at load.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Op {
    /// Inputs: x, weight `[O, kh, kw, I]`, bias `[O]`.
    Conv2d {
        window: Window,
        activation: Activation,
    },
    /// Inputs: x, weight `[1, kh, kw, C·m]`, bias `[C·m]`.
    DepthwiseConv2d {
        window: Window,
        activation: Activation,
    },
    /// Inputs: x, weight `[O, kh, kw, I]`, bias `[O]`; output `in·stride` (SAME) or
    /// `(in − 1)·stride + k` (VALID), the full result cropped by the SAME rule's padding.
    TransposeConv2dBias {
        window: Window,
        crop: [usize; 2],
    },
    MaxPool2d {
        window: Window,
        activation: Activation,
    },
    AveragePool2d {
        window: Window,
        activation: Activation,
    },
    Add {
        activation: Activation,
    },
    Mul {
        activation: Activation,
    },
    /// Along `axis` of the TensorFlow Lite shape (non-negative).
    Concatenation {
        axis: usize,
        activation: Activation,
    },
    Reshape,
    /// `(before, after)` zeros per dimension of the TensorFlow Lite shape.
    Pad {
        pads: Vec<(usize, usize)>,
    },
    /// To the output's height and width; `align_corners` as TensorFlow's, and otherwise
    /// half-pixel centres (the one non-aligned rule read here).
    ResizeBilinear {
        align_corners: bool,
    },
    DepthToSpace {
        block: usize,
    },
    Logistic,
    Relu,
    Relu6,
    Tanh,
    HardSwish,
}

/// What an operator's decoding sees of one of its inputs.
pub(crate) struct InputView<'a> {
    pub shape: &'a [usize],
    pub ints: Option<&'a [i32]>,
    pub is_constant: bool,
}

/// Decodes operator `builtin` (or the custom `custom`) and checks its inputs' shapes; returns
/// the operator and the shape it produces.
pub(crate) fn decode(
    builtin: i32,
    custom: Option<&str>,
    operator: &fb::OperatorRef<'_>,
    inputs: &[InputView<'_>],
) -> Result<(Op, Vec<usize>), String> {
    let options = operator
        .builtin_options()
        .map_err(|e| format!("options: {e}"))?;
    let wrong_options = || "its options are missing or of another operator".to_string();
    let arity = |n: usize| -> Result<(), String> {
        if inputs.len() == n {
            Ok(())
        } else {
            Err(format!("{} inputs, expected {n}", inputs.len()))
        }
    };
    let f = |e: planus::Error| format!("options: {e}");
    let positive = |v: i32, what: &str| -> Result<usize, String> {
        usize::try_from(v)
            .ok()
            .filter(|&v| (1..=1 << 16).contains(&v))
            .ok_or_else(|| format!("{what} {v} is not a positive size"))
    };
    match builtin {
        code::CONV_2D | code::DEPTHWISE_CONV_2D => {
            arity(3)?;
            let depthwise = builtin == code::DEPTHWISE_CONV_2D;
            let (padding, stride, dilation, activation, multiplier) = match (&options, depthwise) {
                (Some(fb::BuiltinOptionsRef::Conv2DOptions(o)), false) => (
                    o.padding().map_err(f)?,
                    [o.stride_h().map_err(f)?, o.stride_w().map_err(f)?],
                    [
                        o.dilation_h_factor().map_err(f)?,
                        o.dilation_w_factor().map_err(f)?,
                    ],
                    o.fused_activation_function().map_err(f)?,
                    1,
                ),
                (Some(fb::BuiltinOptionsRef::DepthwiseConv2DOptions(o)), true) => (
                    o.padding().map_err(f)?,
                    [o.stride_h().map_err(f)?, o.stride_w().map_err(f)?],
                    [
                        o.dilation_h_factor().map_err(f)?,
                        o.dilation_w_factor().map_err(f)?,
                    ],
                    o.fused_activation_function().map_err(f)?,
                    o.depth_multiplier().map_err(f)?,
                ),
                _ => return Err(wrong_options()),
            };
            let x = image(inputs[0].shape, "input")?;
            let w = image(inputs[1].shape, "weight")?;
            constant(&inputs[1], "weight")?;
            constant(&inputs[2], "bias")?;
            let out_channels = if depthwise {
                // TFLite's depth multiplier is advisory; the weight's channels decide.
                let _ = multiplier;
                if w[0] != 1 || w[3] % x[3] != 0 {
                    return Err(format!(
                        "depthwise weight {w:?} does not fit input channels {}",
                        x[3]
                    ));
                }
                w[3]
            } else {
                if w[3] != x[3] {
                    return Err(format!(
                        "weight {w:?} takes {} channels, the input has {}",
                        w[3], x[3]
                    ));
                }
                w[0]
            };
            if inputs[2].shape != [out_channels] {
                return Err(format!(
                    "bias {:?} for {out_channels} output channels",
                    inputs[2].shape
                ));
            }
            let window = Window {
                kernel: [w[1], w[2]],
                stride: [
                    positive(stride[0], "stride")?,
                    positive(stride[1], "stride")?,
                ],
                dilation: [
                    positive(dilation[0], "dilation")?,
                    positive(dilation[1], "dilation")?,
                ],
                padding: Padding::read(padding),
            };
            let (hw, _) = window
                .apply([x[1], x[2]])
                .ok_or("the kernel does not fit the input")?;
            let activation = Activation::read(activation)?;
            let op = if depthwise {
                Op::DepthwiseConv2d { window, activation }
            } else {
                Op::Conv2d { window, activation }
            };
            Ok((op, vec![x[0], hw[0], hw[1], out_channels]))
        }
        code::MAX_POOL_2D | code::AVERAGE_POOL_2D => {
            arity(1)?;
            let Some(fb::BuiltinOptionsRef::Pool2DOptions(o)) = &options else {
                return Err(wrong_options());
            };
            let window = Window {
                kernel: [
                    positive(o.filter_height().map_err(f)?, "filter")?,
                    positive(o.filter_width().map_err(f)?, "filter")?,
                ],
                stride: [
                    positive(o.stride_h().map_err(f)?, "stride")?,
                    positive(o.stride_w().map_err(f)?, "stride")?,
                ],
                dilation: [1, 1],
                padding: Padding::read(o.padding().map_err(f)?),
            };
            let activation = Activation::read(o.fused_activation_function().map_err(f)?)?;
            let x = image(inputs[0].shape, "input")?;
            let (hw, pads) = window
                .apply([x[1], x[2]])
                .ok_or("the window does not fit the input")?;
            // A window made only of padding has no average and no maximum.
            if pads
                .iter()
                .zip(window.kernel)
                .any(|(p, k)| p.0 >= k || p.1 >= k)
            {
                return Err("the padding is as wide as the window".into());
            }
            let op = if builtin == code::MAX_POOL_2D {
                Op::MaxPool2d { window, activation }
            } else {
                Op::AveragePool2d { window, activation }
            };
            Ok((op, vec![x[0], hw[0], hw[1], x[3]]))
        }
        code::ADD | code::MUL => {
            arity(2)?;
            let activation = match (&options, builtin) {
                (Some(fb::BuiltinOptionsRef::AddOptions(o)), code::ADD) => {
                    o.fused_activation_function().map_err(f)?
                }
                (Some(fb::BuiltinOptionsRef::MulOptions(o)), code::MUL) => {
                    o.fused_activation_function().map_err(f)?
                }
                (None, _) => fb::ActivationFunctionType::None,
                _ => return Err(wrong_options()),
            };
            let shape = broadcast(inputs[0].shape, inputs[1].shape)?;
            let activation = Activation::read(activation)?;
            let op = if builtin == code::ADD {
                Op::Add { activation }
            } else {
                Op::Mul { activation }
            };
            Ok((op, shape))
        }
        code::CONCATENATION => {
            if inputs.is_empty() {
                return Err("no inputs".into());
            }
            let Some(fb::BuiltinOptionsRef::ConcatenationOptions(o)) = &options else {
                return Err(wrong_options());
            };
            let rank = inputs[0].shape.len();
            let raw = o.axis().map_err(f)?;
            let axis = usize::try_from(if raw < 0 { raw + rank as i32 } else { raw })
                .ok()
                .filter(|&a| a < rank)
                .ok_or_else(|| format!("axis {raw} of a rank-{rank} tensor"))?;
            let mut shape = inputs[0].shape.to_vec();
            for other in &inputs[1..] {
                let fits = other.shape.len() == rank
                    && (0..rank).all(|d| d == axis || other.shape[d] == shape[d]);
                if !fits {
                    return Err(format!(
                        "inputs {:?} and {:?} do not concatenate along axis {axis}",
                        inputs[0].shape, other.shape
                    ));
                }
                shape[axis] += other.shape[axis];
            }
            let activation = Activation::read(o.fused_activation_function().map_err(f)?)?;
            Ok((Op::Concatenation { axis, activation }, shape))
        }
        code::RESHAPE => {
            // The target shape is the declared output's (the optional shape input and option
            // say the same); only the element count must agree, checked by the caller.
            if inputs.is_empty() || inputs.len() > 2 {
                return Err(format!("{} inputs, expected 1 or 2", inputs.len()));
            }
            Ok((Op::Reshape, Vec::new()))
        }
        code::PAD => {
            arity(2)?;
            let x = inputs[0].shape;
            let ints = inputs[1]
                .ints
                .ok_or("the paddings are not an int32 constant")?;
            if inputs[1].shape != [x.len(), 2] {
                return Err(format!(
                    "paddings {:?} for a rank-{} input",
                    inputs[1].shape,
                    x.len()
                ));
            }
            let mut pads = Vec::new();
            let mut shape = Vec::new();
            for (d, pair) in ints.chunks_exact(2).enumerate() {
                let before = usize::try_from(pair[0]).ok().filter(|&v| v <= 1 << 16);
                let after = usize::try_from(pair[1]).ok().filter(|&v| v <= 1 << 16);
                let (Some(before), Some(after)) = (before, after) else {
                    return Err(format!("padding {pair:?} of dimension {d}"));
                };
                pads.push((before, after));
                shape.push(x[d] + before + after);
            }
            Ok((Op::Pad { pads }, shape))
        }
        code::RESIZE_BILINEAR => {
            arity(2)?;
            let Some(fb::BuiltinOptionsRef::ResizeBilinearOptions(o)) = &options else {
                return Err(wrong_options());
            };
            let align_corners = o.align_corners().map_err(f)?;
            let half_pixel = o.half_pixel_centers().map_err(f)?;
            if !align_corners && !half_pixel {
                return Err(
                    "resizing without half-pixel centres or aligned corners (TensorFlow 1's \
                     rule) is not run here"
                        .into(),
                );
            }
            let x = image(inputs[0].shape, "input")?;
            let size = inputs[1]
                .ints
                .filter(|s| s.len() == 2)
                .ok_or("the size is not an int32 constant of two values")?;
            let h = positive(size[0], "height")?;
            let w = positive(size[1], "width")?;
            Ok((Op::ResizeBilinear { align_corners }, vec![x[0], h, w, x[3]]))
        }
        code::DEPTH_TO_SPACE => {
            arity(1)?;
            let Some(fb::BuiltinOptionsRef::DepthToSpaceOptions(o)) = &options else {
                return Err(wrong_options());
            };
            let block = positive(o.block_size().map_err(f)?, "block size")?;
            let x = image(inputs[0].shape, "input")?;
            if x[3] % (block * block) != 0 {
                return Err(format!("{} channels for block size {block}", x[3]));
            }
            Ok((
                Op::DepthToSpace { block },
                vec![x[0], x[1] * block, x[2] * block, x[3] / (block * block)],
            ))
        }
        code::LOGISTIC | code::RELU | code::RELU6 | code::TANH | code::HARD_SWISH => {
            arity(1)?;
            let op = match builtin {
                code::LOGISTIC => Op::Logistic,
                code::RELU => Op::Relu,
                code::RELU6 => Op::Relu6,
                code::TANH => Op::Tanh,
                _ => Op::HardSwish,
            };
            Ok((op, inputs[0].shape.to_vec()))
        }
        code::CUSTOM if custom == Some(TRANSPOSE_CONV_BIAS) => {
            arity(3)?;
            let raw = operator
                .custom_options()
                .map_err(f)?
                .ok_or("no custom options (padding, stride_w, stride_h)")?;
            // The options are a C struct of three int32: padding (1 SAME, 2 VALID), strides.
            if raw.len() < 12 {
                return Err(format!(
                    "{} bytes of custom options, expected 12",
                    raw.len()
                ));
            }
            let int = |i: usize| i32::from_le_bytes([raw[i], raw[i + 1], raw[i + 2], raw[i + 3]]);
            let padding = match int(0) {
                1 => Padding::Same,
                2 => Padding::Valid,
                p => return Err(format!("padding {p} (1 SAME, 2 VALID)")),
            };
            let stride = [positive(int(8), "stride")?, positive(int(4), "stride")?];
            let x = image(inputs[0].shape, "input")?;
            let w = image(inputs[1].shape, "weight")?;
            constant(&inputs[1], "weight")?;
            constant(&inputs[2], "bias")?;
            if w[3] != x[3] || inputs[2].shape != [w[0]] {
                return Err(format!(
                    "weight {w:?} and bias {:?} for input {x:?}",
                    inputs[2].shape
                ));
            }
            let mut out = [0; 2];
            let mut crop = [0; 2];
            for d in 0..2 {
                let (input, k, s) = (x[1 + d], w[1 + d], stride[d]);
                let full = (input - 1) * s + k;
                out[d] = match padding {
                    Padding::Same => input * s,
                    Padding::Valid => full,
                };
                let total = full
                    .checked_sub(out[d])
                    .ok_or("the kernel is smaller than the stride")?;
                crop[d] = total / 2;
            }
            let window = Window {
                kernel: [w[1], w[2]],
                stride,
                dilation: [1, 1],
                padding,
            };
            Ok((
                Op::TransposeConv2dBias { window, crop },
                vec![x[0], out[0], out[1], w[0]],
            ))
        }
        code::CUSTOM => Err("this custom operator is not run here".into()),
        _ => Err("this operator is not run here".into()),
    }
}

fn image(shape: &[usize], what: &str) -> Result<[usize; 4], String> {
    <[usize; 4]>::try_from(shape).map_err(|_| format!("{what} of shape {shape:?}, expected rank 4"))
}

fn constant(input: &InputView<'_>, what: &str) -> Result<(), String> {
    if input.is_constant {
        Ok(())
    } else {
        Err(format!("the {what} is not a constant"))
    }
}

/// NumPy's broadcasting of two shapes (trailing dimensions aligned), as TensorFlow Lite's.
fn broadcast(a: &[usize], b: &[usize]) -> Result<Vec<usize>, String> {
    let rank = a.len().max(b.len());
    if rank > 4 {
        return Err(format!("operands {a:?} and {b:?} of rank above 4"));
    }
    let at = |s: &[usize], d: usize| (d + s.len()).checked_sub(rank).map_or(1, |i| s[i]);
    (0..rank)
        .map(|d| match (at(a, d), at(b, d)) {
            (x, y) if x == y => Ok(x),
            (1, y) => Ok(y),
            (x, 1) => Ok(x),
            _ => Err(format!("operands {a:?} and {b:?} do not broadcast")),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_padding_puts_the_odd_zero_after() {
        // TensorFlow's stride-2 SAME on an even input: one zero, after.
        assert_eq!(Padding::Same.window(224, 3, 2, 1), Some((112, (0, 1))));
        assert_eq!(Padding::Same.window(225, 3, 2, 1), Some((113, (1, 1))));
        assert_eq!(Padding::Same.window(7, 5, 1, 1), Some((7, (2, 2))));
        assert_eq!(Padding::Valid.window(7, 3, 2, 1), Some((3, (0, 0))));
        assert_eq!(Padding::Valid.window(2, 3, 1, 1), None);
    }

    #[test]
    fn shapes_broadcast_from_the_right() {
        assert_eq!(broadcast(&[1, 8, 8, 4], &[4]).unwrap(), [1, 8, 8, 4]);
        assert_eq!(
            broadcast(&[1, 8, 8, 4], &[1, 1, 1, 4]).unwrap(),
            [1, 8, 8, 4]
        );
        assert!(broadcast(&[1, 8, 8, 4], &[3]).is_err());
    }
}
