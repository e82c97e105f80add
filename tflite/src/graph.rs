//! A read graph on a Burn device, and running it.
//!
//! Layout: TensorFlow Lite is NHWC, Burn's convolutions NCHW. Every rank-4 tensor is held NCHW
//! on the device (inputs, activations and constants alike: converted once, constants at load),
//! so a `[O, kh, kw, I]` kernel is held `[O, I, kh, kw]`, Burn's own. Tensors of other ranks
//! are held in TensorFlow Lite's element order, as a rank-4 Burn tensor with leading ones; a
//! `RESHAPE` or a broadcast between the two converts.

use std::path::Path;

use burn::tensor::activation;
use burn::tensor::module::{avg_pool2d, conv_transpose2d, conv2d, max_pool2d};
use burn::tensor::ops::{AvgPoolOptions, ConvOptions, ConvTransposeOptions, MaxPoolOptions};
use burn::tensor::{Device, Tensor, TensorData};

use crate::error::{Result, TfliteError};
use crate::file::{self, Constant, Node, Program};
use crate::op::{Activation, Op};

/// A graph input or output as declared: its name and its TensorFlow Lite (NHWC) shape.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorSpec {
    /// The tensor's name in the file.
    pub name: String,
    /// Its shape, TensorFlow Lite's order (`[N, H, W, C]` for an image).
    pub shape: Vec<usize>,
}

/// One output of [`Graph::run`].
#[derive(Debug, Clone)]
pub struct Output {
    /// Name and TensorFlow Lite shape.
    pub spec: TensorSpec,
    /// The values in Burn's layout: `[N, C, H, W]` for a rank-4 output, otherwise the
    /// TensorFlow Lite shape with leading ones up to rank 4.
    pub tensor: Tensor<4>,
}

impl Output {
    /// The values in TensorFlow Lite's element order (NHWC), read back to the host.
    pub fn to_vec(&self) -> std::result::Result<Vec<f32>, String> {
        to_file_order(self.tensor.clone(), self.spec.shape.len())
            .try_into_vec_as::<f32>()
            .map_err(|e| format!("reading `{}` back: {e}", self.spec.name))
    }
}

/// A TensorFlow Lite graph, read and uploaded to one device.
#[derive(Debug, Clone)]
pub struct Graph {
    name: String,
    device: Device,
    shapes: Vec<Vec<usize>>,
    /// Constants on the device, in the layout above (`None`: computed at run time).
    constants: Vec<Option<Tensor<4>>>,
    steps: Vec<Step>,
    inputs: Vec<usize>,
    outputs: Vec<usize>,
    names: Vec<String>,
}

#[derive(Debug, Clone)]
struct Step {
    node: Node,
    /// The kernel in the form the Burn op takes (convolutions), and the bias.
    kernel: Option<(Tensor<4>, Tensor<1>)>,
    /// A bilinear resize as two products: rows `[out_h, in_h]`, columns transposed
    /// `[in_w, out_w]`.
    resize: Option<(Tensor<2>, Tensor<2>)>,
    /// Tensors that are not needed after this step.
    release: Vec<usize>,
}

impl Graph {
    /// Reads the `.tflite` file at `path` onto `device`.
    pub fn read(path: &Path, device: &Device) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|source| TfliteError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_bytes(&path.display().to_string(), &bytes, device)
    }

    /// Reads a model held in memory; `name` names it in errors.
    pub fn from_bytes(name: &str, bytes: &[u8], device: &Device) -> Result<Self> {
        Ok(Self::upload(file::read(name, bytes)?, device))
    }

    fn upload(program: Program, device: &Device) -> Self {
        let Program {
            name,
            tensors,
            inputs,
            outputs,
            nodes,
        } = program;
        let shapes: Vec<Vec<usize>> = tensors.iter().map(|t| t.shape.clone()).collect();
        let names: Vec<String> = tensors.iter().map(|t| t.name.clone()).collect();
        let host: Vec<Option<Vec<f32>>> = tensors
            .into_iter()
            .map(|t| match t.constant {
                Some(Constant::Float(v)) => Some(v),
                // Int constants (sizes, paddings, shapes) were read into the operators.
                Some(Constant::Int(_)) | None => None,
            })
            .collect();
        let is_kernel_op = |op: &Op| {
            matches!(
                op,
                Op::Conv2d { .. } | Op::DepthwiseConv2d { .. } | Op::TransposeConv2dBias { .. }
            )
        };
        let mut last_use = vec![usize::MAX; shapes.len()];
        // Constants read as plain operands (not only as a convolution's kernel or bias) are
        // uploaded in the generic layout; kernels in their operator's form only.
        let mut operand = vec![false; shapes.len()];
        for (s, node) in nodes.iter().enumerate() {
            for (k, &i) in node.inputs.iter().enumerate() {
                last_use[i] = s;
                operand[i] |= k == 0 || !is_kernel_op(&node.op);
            }
        }
        for &o in &outputs {
            operand[o] = true;
        }
        let is_output = |i: usize| outputs.contains(&i);
        let mut steps = Vec::with_capacity(nodes.len());
        for (s, node) in nodes.into_iter().enumerate() {
            let kernel = if is_kernel_op(&node.op) {
                let (w, b) = (node.inputs[1], node.inputs[2]);
                let weight = on_device(host[w].as_deref().unwrap_or_default(), &shapes[w], device);
                let weight = match node.op {
                    // [1, C·m, kh, kw] → [C·m, 1, kh, kw]: groups of one input channel.
                    // [O, I, kh, kw] → [I, O, kh, kw]: the transposed convolution's order.
                    Op::DepthwiseConv2d { .. } | Op::TransposeConv2dBias { .. } => {
                        weight.swap_dims(0, 1)
                    }
                    _ => weight,
                };
                let bias = host[b].clone().unwrap_or_default();
                let n = bias.len();
                Some((
                    weight,
                    Tensor::<1>::from_data(TensorData::new(bias, [n]), device),
                ))
            } else {
                None
            };
            let resize = match node.op {
                Op::ResizeBilinear { align_corners } => {
                    let (input, output) = (&shapes[node.inputs[0]], &shapes[node.output]);
                    let rows = resize_matrix(input[1], output[1], align_corners);
                    let cols = resize_matrix(input[2], output[2], align_corners);
                    Some((
                        Tensor::<2>::from_data(
                            TensorData::new(rows, [output[1], input[1]]),
                            device,
                        ),
                        Tensor::<2>::from_data(
                            TensorData::new(cols, [output[2], input[2]]),
                            device,
                        )
                        .transpose(),
                    ))
                }
                _ => None,
            };
            let release = node
                .inputs
                .iter()
                .copied()
                .filter(|&i| last_use[i] == s && !is_output(i))
                .collect();
            steps.push(Step {
                node,
                kernel,
                resize,
                release,
            });
        }
        let constants = host
            .iter()
            .zip(&shapes)
            .zip(&operand)
            .map(|((v, shape), &operand)| {
                v.as_ref()
                    .filter(|_| operand)
                    .map(|v| on_device(v, shape, device))
            })
            .collect();
        Graph {
            names,
            name,
            device: device.clone(),
            shapes,
            constants,
            steps,
            inputs,
            outputs,
        }
    }

    /// The graph's name in errors (its file, or what [`Graph::from_bytes`] was given).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The graph's inputs.
    pub fn inputs(&self) -> Vec<TensorSpec> {
        self.inputs.iter().map(|&i| self.spec(i)).collect()
    }

    /// The graph's outputs.
    pub fn outputs(&self) -> Vec<TensorSpec> {
        self.outputs.iter().map(|&i| self.spec(i)).collect()
    }

    fn spec(&self, i: usize) -> TensorSpec {
        TensorSpec {
            name: self.names[i].clone(),
            shape: self.shapes[i].clone(),
        }
    }

    /// Runs the graph on `inputs`, one per graph input, each in the layout [`Output::tensor`]
    /// describes (`[N, C, H, W]` for an image); returns every output.
    pub fn run(&self, inputs: Vec<Tensor<4>>) -> Result<Vec<Output>> {
        if inputs.len() != self.inputs.len() {
            return Err(TfliteError::Input {
                graph: self.name.clone(),
                index: inputs.len(),
                reason: format!(
                    "{} inputs given, the graph takes {}",
                    inputs.len(),
                    self.inputs.len()
                ),
            });
        }
        let mut values = self.constants.clone();
        for (k, (&i, x)) in self.inputs.iter().zip(inputs).enumerate() {
            let want = held_shape(&self.shapes[i]);
            if x.dims() != want {
                return Err(TfliteError::Input {
                    graph: self.name.clone(),
                    index: k,
                    reason: format!(
                        "shape {:?}, expected {want:?} (the file's {:?} in Burn's layout)",
                        x.dims(),
                        self.shapes[i]
                    ),
                });
            }
            if x.device() != self.device {
                return Err(TfliteError::Input {
                    graph: self.name.clone(),
                    index: k,
                    reason: "on another device than the graph".into(),
                });
            }
            values[i] = Some(x);
        }
        for step in &self.steps {
            let out = self.step(step, &values);
            values[step.node.output] = Some(out);
            for &i in &step.release {
                values[i] = None;
            }
        }
        self.outputs
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                // Every output is computed or given (checked at load); kept as an error, not a
                // panic, should that check ever miss a case.
                let tensor = values[i].clone().ok_or_else(|| TfliteError::Input {
                    graph: self.name.clone(),
                    index: k,
                    reason: format!("output {k} was not computed"),
                })?;
                Ok(Output {
                    spec: self.spec(i),
                    tensor,
                })
            })
            .collect()
    }

    fn step(&self, step: &Step, values: &[Option<Tensor<4>>]) -> Tensor<4> {
        let node = &step.node;
        let input = |k: usize| {
            values[node.inputs[k]]
                .clone()
                .expect("operators run after their inputs (checked at load)")
        };
        let rank = |k: usize| self.shapes[node.inputs[k]].len();
        let out_shape = &self.shapes[node.output];
        match &node.op {
            Op::Conv2d { window, activation } | Op::DepthwiseConv2d { window, activation } => {
                let x = input(0);
                let [_, channels, h, w] = x.dims();
                let (_, padding) = window.apply([h, w]).expect("checked at load");
                let groups = if matches!(node.op, Op::DepthwiseConv2d { .. }) {
                    channels
                } else {
                    1
                };
                let (kernel, bias) = step.kernel.clone().expect("uploaded with the graph");
                let y = conv2d(
                    x,
                    kernel,
                    Some(bias),
                    ConvOptions::new_with_padding(window.stride, padding, window.dilation, groups),
                );
                fused(y, *activation)
            }
            Op::TransposeConv2dBias { window, crop } => {
                let (kernel, bias) = step.kernel.clone().expect("uploaded with the graph");
                let y = conv_transpose2d(
                    input(0),
                    kernel,
                    Some(bias),
                    ConvTransposeOptions::new(window.stride, [0, 0], [0, 0], [1, 1], 1),
                );
                let [oh, ow] = [out_shape[1], out_shape[2]];
                y.narrow(2, crop[0], oh).narrow(3, crop[1], ow)
            }
            Op::MaxPool2d { window, activation } | Op::AveragePool2d { window, activation } => {
                let x = input(0);
                let [_, _, h, w] = x.dims();
                let (_, padding) = window.apply([h, w]).expect("checked at load");
                let y = if matches!(node.op, Op::MaxPool2d { .. }) {
                    max_pool2d(
                        x,
                        MaxPoolOptions::new(window.kernel)
                            .with_stride(window.stride)
                            .with_padding_pairs(padding),
                    )
                } else {
                    // TensorFlow Lite averages over the window's inputs, not its padding.
                    avg_pool2d(
                        x,
                        AvgPoolOptions::new(window.kernel)
                            .with_stride(window.stride)
                            .with_padding_pairs(padding)
                            .with_count_include_pad(false),
                    )
                };
                fused(y, *activation)
            }
            Op::Add { activation } | Op::Mul { activation } => {
                let r = out_shape.len();
                let a = to_rank(input(0), rank(0), r);
                let b = to_rank(input(1), rank(1), r);
                let y = if matches!(node.op, Op::Add { .. }) {
                    a + b
                } else {
                    a * b
                };
                fused(y, *activation)
            }
            Op::Concatenation { axis, activation } => {
                let parts: Vec<Tensor<4>> = (0..node.inputs.len()).map(input).collect();
                fused(Tensor::cat(parts, held_axis(*axis, rank(0))), *activation)
            }
            Op::Reshape => {
                let flat = to_file_order(input(0), rank(0));
                from_file_order(flat.reshape(padded(out_shape)), out_shape.len())
            }
            Op::Pad { pads } => {
                let mut x = input(0);
                let r = rank(0);
                for (d, &(before, after)) in pads.iter().enumerate() {
                    let axis = held_axis(d, r);
                    for (count, at_end) in [(before, false), (after, true)] {
                        if count == 0 {
                            continue;
                        }
                        let mut dims = x.dims();
                        dims[axis] = count;
                        let zeros = Tensor::<4>::zeros(dims, &self.device);
                        x = if at_end {
                            Tensor::cat(vec![x, zeros], axis)
                        } else {
                            Tensor::cat(vec![zeros, x], axis)
                        };
                    }
                }
                x
            }
            Op::ResizeBilinear { .. } => {
                // Two products with the interpolation weights (rows, then columns) rather than
                // Burn's `interpolate`, whose bilinear kernel gives wrong values on wgpu's
                // OpenGL backend (5 × 5 → 8 × 8: off by 0.34) while products hold everywhere.
                let (rows, cols_t) = step.resize.clone().expect("made with the graph");
                let x = input(0);
                let [n, c, h, w] = x.dims();
                let [oh, ow] = [out_shape[1], out_shape[2]];
                let x = x.reshape([n * c * h, w]).matmul(cols_t);
                let x = x.reshape([n * c, h, ow]);
                let rows = rows.unsqueeze_dim::<3>(0).expand([n * c, oh, h]);
                rows.matmul(x).reshape([n, c, oh, ow])
            }
            Op::DepthToSpace { block } => {
                let x = input(0);
                let [n, c, h, w] = x.dims();
                let b = *block;
                // Channel k of the input is (row offset, column offset, channel) = k split
                // as [b, b, C/b²] (TensorFlow's order).
                x.reshape([n, b, b, c / (b * b), h, w])
                    .permute([0, 3, 4, 1, 5, 2])
                    .reshape([n, c / (b * b), h * b, w * b])
            }
            Op::Logistic => activation::sigmoid(input(0)),
            Op::Relu => activation::relu(input(0)),
            Op::Relu6 => input(0).clamp(0.0, 6.0),
            Op::Tanh => input(0).tanh(),
            Op::HardSwish => {
                let x = input(0);
                x.clone() * (x + 3.0).clamp(0.0, 6.0) / 6.0
            }
        }
    }
}

fn fused(y: Tensor<4>, activation: Activation) -> Tensor<4> {
    match activation {
        Activation::None => y,
        Activation::Relu => activation::relu(y),
        Activation::ReluMinus1To1 => y.clamp(-1.0, 1.0),
        Activation::Relu6 => y.clamp(0.0, 6.0),
        Activation::Tanh => y.tanh(),
    }
}

/// The file's shape with leading ones up to rank 4.
fn padded(shape: &[usize]) -> [usize; 4] {
    let mut p = [1; 4];
    p[4 - shape.len()..].copy_from_slice(shape);
    p
}

/// The Burn shape a tensor of the file's `shape` is held in.
fn held_shape(shape: &[usize]) -> [usize; 4] {
    match shape {
        [n, h, w, c] => [*n, *c, *h, *w],
        _ => padded(shape),
    }
}

/// The Burn axis holding axis `axis` of a rank-`rank` tensor of the file.
fn held_axis(axis: usize, rank: usize) -> usize {
    if rank == 4 {
        [0, 2, 3, 1][axis]
    } else {
        axis + 4 - rank
    }
}

/// A held tensor in the file's element order (leading ones up to rank 4).
fn to_file_order(x: Tensor<4>, rank: usize) -> Tensor<4> {
    if rank == 4 {
        x.permute([0, 2, 3, 1])
    } else {
        x
    }
}

fn from_file_order(x: Tensor<4>, rank: usize) -> Tensor<4> {
    if rank == 4 {
        x.permute([0, 3, 1, 2])
    } else {
        x
    }
}

/// A held operand of rank `from` as one of rank `to` (a broadcast operand of lower rank).
fn to_rank(x: Tensor<4>, from: usize, to: usize) -> Tensor<4> {
    if from == to {
        x
    } else {
        from_file_order(x, to)
    }
}

/// TensorFlow Lite's bilinear weights from `input` to `output` positions along one axis, as an
/// `[output, input]` matrix: output `o` samples `(o + ½)·in/out − ½` (half-pixel centres) or
/// `o·(in − 1)/(out − 1)` (aligned corners), between the clamped neighbours below and above.
fn resize_matrix(input: usize, output: usize, align_corners: bool) -> Vec<f32> {
    let mut m = vec![0f32; output * input];
    let scale = if align_corners && output > 1 {
        (input as f32 - 1.0) / (output as f32 - 1.0)
    } else {
        input as f32 / output as f32
    };
    for o in 0..output {
        let at = if align_corners {
            o as f32 * scale
        } else {
            (o as f32 + 0.5) * scale - 0.5
        };
        let below = (at.floor().max(0.0) as usize).min(input - 1);
        let above = (at.ceil().max(0.0) as usize).min(input - 1);
        let frac = at - below as f32;
        m[o * input + below] += 1.0 - frac;
        m[o * input + above] += frac;
    }
    m
}

fn on_device(values: &[f32], shape: &[usize], device: &Device) -> Tensor<4> {
    let t = Tensor::<4>::from_data(TensorData::new(values.to_vec(), padded(shape)), device);
    from_file_order(t, shape.len())
}
