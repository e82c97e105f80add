//! Small TensorFlow Lite files made in code, for tests (not part of the API): the reader's
//! unit tests and the workspace's reader fuzzer start from them, since the MediaPipe graphs
//! are fetched, not committed.

use crate::op::{TRANSPOSE_CONV_BIAS, code};
use crate::schema::tflite as fb;

/// Values of a constant tensor.
#[derive(Debug, Clone)]
pub enum Data {
    /// Stored as f32.
    F32(Vec<f32>),
    /// Stored as IEEE half floats (what `DEQUANTIZE` then reads).
    F16(Vec<f32>),
    /// Stored as int32 (sizes, paddings).
    I32(Vec<i32>),
    /// Stored sparse: rows dense, the last dimension CSR, of this dense row-major matrix
    /// (rank 2 or a `[O, 1, 1, I]` kernel taken as `[O, I]`).
    SparseRows(Vec<f32>),
}

/// A graph under construction.
#[derive(Debug, Default)]
pub struct TestGraph {
    tensors: Vec<fb::Tensor>,
    buffers: Vec<fb::Buffer>,
    codes: Vec<fb::OperatorCode>,
    ops: Vec<fb::Operator>,
    inputs: Vec<i32>,
    outputs: Vec<i32>,
}

/// A builtin operator's options, for [`TestGraph::op`].
pub enum Options {
    /// None.
    None,
    /// Convolution: padding SAME (else VALID), stride, fused RELU6 (else none).
    Conv {
        same: bool,
        stride: i32,
        relu6: bool,
    },
    /// Depthwise convolution, as `Conv`.
    Depthwise { same: bool, stride: i32 },
    /// Pooling: padding SAME (else VALID), stride, filter.
    Pool {
        same: bool,
        stride: i32,
        filter: i32,
    },
    /// Concatenation along `axis`.
    Concat { axis: i32 },
    /// Bilinear resizing with half-pixel centres.
    Resize,
    /// Depth to space with this block.
    DepthToSpace(i32),
    /// MediaPipe's transposed convolution: SAME (else VALID) and its stride.
    TransposeConv { same: bool, stride: i32 },
}

impl TestGraph {
    /// An empty graph (buffer 0 is the format's empty sentinel).
    pub fn new() -> Self {
        Self {
            buffers: vec![fb::Buffer::default()],
            ..Self::default()
        }
    }

    /// Adds a tensor of `shape`, constant when `data` is given; returns its index.
    pub fn tensor(&mut self, name: &str, shape: &[usize], data: Option<Data>) -> i32 {
        let mut tensor = fb::Tensor {
            shape: Some(shape.iter().map(|&d| d as i32).collect()),
            type_: fb::TensorType::Float32,
            name: Some(name.to_string()),
            ..fb::Tensor::default()
        };
        if let Some(data) = data {
            let bytes: Vec<u8> = match &data {
                Data::F32(v) => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                Data::F16(v) => {
                    tensor.type_ = fb::TensorType::Float16;
                    v.iter()
                        .flat_map(|&x| half::f16::from_f32(x).to_le_bytes())
                        .collect()
                }
                Data::I32(v) => {
                    tensor.type_ = fb::TensorType::Int32;
                    v.iter().flat_map(|x| x.to_le_bytes()).collect()
                }
                Data::SparseRows(dense) => {
                    let cols = *shape.last().expect("a sparse tensor has a shape");
                    let rows = dense.len() / cols;
                    let (mut segments, mut indices, mut values) = (vec![0], Vec::new(), Vec::new());
                    for r in 0..rows {
                        for c in 0..cols {
                            if dense[r * cols + c] != 0.0 {
                                indices.push(c as i32);
                                values.push(dense[r * cols + c]);
                            }
                        }
                        segments.push(indices.len() as i32);
                    }
                    let rank = shape.len();
                    let mut dims: Vec<fb::DimensionMetadata> = shape[..rank - 1]
                        .iter()
                        .map(|&d| fb::DimensionMetadata {
                            format: fb::DimensionType::Dense,
                            dense_size: d as i32,
                            ..Default::default()
                        })
                        .collect();
                    dims.push(fb::DimensionMetadata {
                        format: fb::DimensionType::SparseCsr,
                        array_segments: Some(fb::SparseIndexVector::Int32Vector(Box::new(
                            fb::Int32Vector {
                                // Dense leading dimensions: the CSR level's parent is the row.
                                values: Some(segments),
                            },
                        ))),
                        array_indices: Some(fb::SparseIndexVector::Uint16Vector(Box::new(
                            fb::Uint16Vector {
                                values: Some(indices.iter().map(|&i| i as u16).collect()),
                            },
                        ))),
                        ..Default::default()
                    });
                    tensor.sparsity = Some(Box::new(fb::SparsityParameters {
                        traversal_order: Some((0..rank as i32).collect()),
                        block_map: None,
                        dim_metadata: Some(dims),
                    }));
                    values.iter().flat_map(|x: &f32| x.to_le_bytes()).collect()
                }
            };
            tensor.buffer = self.buffers.len() as u32;
            self.buffers.push(fb::Buffer {
                data: Some(bytes),
                ..Default::default()
            });
        }
        self.tensors.push(tensor);
        self.tensors.len() as i32 - 1
    }

    /// Marks tensor `t` a graph input.
    pub fn input(&mut self, t: i32) {
        self.inputs.push(t);
    }

    /// Marks tensor `t` a graph output.
    pub fn output(&mut self, t: i32) {
        self.outputs.push(t);
    }

    /// Adds operator `builtin` (a TensorFlow Lite number; [`code::CUSTOM`] for the transposed
    /// convolution) from `inputs` to `output`.
    pub fn op(&mut self, builtin: i32, inputs: &[i32], output: i32, options: Options) {
        let custom = matches!(options, Options::TransposeConv { .. });
        let opcode = self.codes.len() as u32;
        self.codes.push(fb::OperatorCode {
            deprecated_builtin_code: builtin.min(127) as i8,
            custom_code: custom.then(|| TRANSPOSE_CONV_BIAS.to_string()),
            version: 1,
            builtin_code: builtin,
        });
        let padding = |same: bool| {
            if same {
                fb::Padding::Same
            } else {
                fb::Padding::Valid
            }
        };
        let mut custom_options = None;
        let builtin_options = match options {
            Options::None => None,
            Options::Conv {
                same,
                stride,
                relu6,
            } => Some(fb::BuiltinOptions::Conv2DOptions(Box::new(
                fb::Conv2DOptions {
                    padding: padding(same),
                    stride_w: stride,
                    stride_h: stride,
                    fused_activation_function: if relu6 {
                        fb::ActivationFunctionType::Relu6
                    } else {
                        fb::ActivationFunctionType::None
                    },
                    dilation_w_factor: 1,
                    dilation_h_factor: 1,
                },
            ))),
            Options::Depthwise { same, stride } => Some(
                fb::BuiltinOptions::DepthwiseConv2DOptions(Box::new(fb::DepthwiseConv2DOptions {
                    padding: padding(same),
                    stride_w: stride,
                    stride_h: stride,
                    depth_multiplier: 1,
                    fused_activation_function: fb::ActivationFunctionType::None,
                    dilation_w_factor: 1,
                    dilation_h_factor: 1,
                })),
            ),
            Options::Pool {
                same,
                stride,
                filter,
            } => Some(fb::BuiltinOptions::Pool2DOptions(Box::new(
                fb::Pool2DOptions {
                    padding: padding(same),
                    stride_w: stride,
                    stride_h: stride,
                    filter_width: filter,
                    filter_height: filter,
                    fused_activation_function: fb::ActivationFunctionType::None,
                },
            ))),
            Options::Concat { axis } => Some(fb::BuiltinOptions::ConcatenationOptions(Box::new(
                fb::ConcatenationOptions {
                    axis,
                    fused_activation_function: fb::ActivationFunctionType::None,
                },
            ))),
            Options::Resize => Some(fb::BuiltinOptions::ResizeBilinearOptions(Box::new(
                fb::ResizeBilinearOptions {
                    align_corners: false,
                    half_pixel_centers: true,
                },
            ))),
            Options::DepthToSpace(block_size) => Some(fb::BuiltinOptions::DepthToSpaceOptions(
                Box::new(fb::DepthToSpaceOptions { block_size }),
            )),
            Options::TransposeConv { same, stride } => {
                let ints = [if same { 1i32 } else { 2 }, stride, stride];
                custom_options = Some(ints.iter().flat_map(|i| i.to_le_bytes()).collect());
                None
            }
        };
        self.ops.push(fb::Operator {
            opcode_index: opcode,
            inputs: Some(inputs.to_vec()),
            outputs: Some(vec![output]),
            builtin_options,
            custom_options,
        });
    }

    /// The file's bytes.
    pub fn finish(self) -> Vec<u8> {
        let model = fb::Model {
            version: 3,
            operator_codes: Some(self.codes),
            subgraphs: Some(vec![fb::SubGraph {
                tensors: Some(self.tensors),
                inputs: Some(self.inputs),
                outputs: Some(self.outputs),
                operators: Some(self.ops),
                name: Some("main".into()),
            }]),
            description: Some("lifegom test graph".into()),
            buffers: Some(self.buffers),
        };
        let mut builder = planus::Builder::new();
        let bytes = builder.finish(&model, None);
        // planus 1.3.0 writes a file identifier before the root offset, where the format
        // (and every reader) has it after; so the file is finished without one and the
        // identifier inserted after the root offset. Every other offset is relative to its
        // own position, and nothing else spans the insertion.
        let root = u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) + 4;
        let mut file = root.to_le_bytes().to_vec();
        file.extend_from_slice(b"TFL3");
        file.extend_from_slice(&bytes[4..]);
        file
    }
}

/// A deterministic value pattern in about [-1, 1].
pub fn pattern(n: usize, seed: u32) -> Vec<f32> {
    (0..n)
        .map(|i| {
            let x = (i as u32)
                .wrapping_mul(2_654_435_761)
                .wrapping_add(seed.wrapping_mul(40_503));
            (x >> 8) as f32 / (1u32 << 23) as f32 - 1.0
        })
        .collect()
}

/// A graph of every operator the reader runs, input `[1, 8, 8, 3]`, outputs `[1, 8, 8, 2]`
/// (an image) and `[1, 16]` (a vector): PAD, CONV_2D (f16 weights behind DEQUANTIZE, stride 2,
/// SAME, fused RELU6), DEPTHWISE_CONV_2D, a sparse 1 × 1 CONV_2D behind DENSIFY, ADD, MUL by a
/// per-channel constant, HARD_SWISH, MAX_POOL_2D, AVERAGE_POOL_2D, RESIZE_BILINEAR,
/// DEPTH_TO_SPACE, the custom transposed convolution, CONCATENATION, LOGISTIC, RELU, RESHAPE.
pub fn small_graph() -> Vec<u8> {
    let mut g = TestGraph::new();
    let x = g.tensor("input", &[1, 8, 8, 3], None);
    g.input(x);
    // PAD one row and column at the end: [1, 9, 9, 3].
    let pads = g.tensor(
        "pads",
        &[4, 2],
        Some(Data::I32(vec![0, 0, 0, 1, 0, 1, 0, 0])),
    );
    let padded = g.tensor("padded", &[1, 9, 9, 3], None);
    g.op(code::PAD, &[x, pads], padded, Options::None);
    // CONV_2D 3 × 3 stride 2 SAME, f16 weights: [1, 5, 5, 4].
    let w16 = g.tensor("w16", &[4, 3, 3, 3], Some(Data::F16(pattern(108, 1))));
    let w = g.tensor("w", &[4, 3, 3, 3], None);
    g.op(code::DEQUANTIZE, &[w16], w, Options::None);
    let b = g.tensor("b", &[4], Some(Data::F32(pattern(4, 2))));
    let c1 = g.tensor("conv", &[1, 5, 5, 4], None);
    g.op(
        code::CONV_2D,
        &[padded, w, b],
        c1,
        Options::Conv {
            same: true,
            stride: 2,
            relu6: true,
        },
    );
    // DEPTHWISE 3 × 3 SAME: [1, 5, 5, 4].
    let dw = g.tensor("dw", &[1, 3, 3, 4], Some(Data::F32(pattern(36, 3))));
    let db = g.tensor("db", &[4], Some(Data::F32(pattern(4, 4))));
    let d1 = g.tensor("depthwise", &[1, 5, 5, 4], None);
    g.op(
        code::DEPTHWISE_CONV_2D,
        &[c1, dw, db],
        d1,
        Options::Depthwise {
            same: true,
            stride: 1,
        },
    );
    // A sparse 1 × 1 kernel behind DENSIFY.
    let mut sparse = pattern(16, 5);
    for (i, v) in sparse.iter_mut().enumerate() {
        if i % 3 != 0 {
            *v = 0.0;
        }
    }
    let ws = g.tensor("ws_sparse", &[4, 1, 1, 4], Some(Data::SparseRows(sparse)));
    let wd = g.tensor("ws", &[4, 1, 1, 4], None);
    g.op(code::DENSIFY, &[ws], wd, Options::None);
    let bs = g.tensor("bs", &[4], Some(Data::F32(vec![0.0; 4])));
    let p1 = g.tensor("pointwise", &[1, 5, 5, 4], None);
    g.op(
        code::CONV_2D,
        &[d1, wd, bs],
        p1,
        Options::Conv {
            same: false,
            stride: 1,
            relu6: false,
        },
    );
    let sum = g.tensor("sum", &[1, 5, 5, 4], None);
    g.op(code::ADD, &[p1, c1], sum, Options::None);
    let scale = g.tensor("scale", &[4], Some(Data::F32(vec![0.5, -1.0, 2.0, 1.5])));
    let scaled = g.tensor("scaled", &[1, 5, 5, 4], None);
    g.op(code::MUL, &[sum, scale], scaled, Options::None);
    let hs = g.tensor("hard_swish", &[1, 5, 5, 4], None);
    g.op(code::HARD_SWISH, &[scaled], hs, Options::None);
    // MAX_POOL 2 × 2 stride 2 SAME: [1, 3, 3, 4]; AVERAGE_POOL 3 × 3 stride 1 SAME.
    let mp = g.tensor("max_pool", &[1, 3, 3, 4], None);
    g.op(
        code::MAX_POOL_2D,
        &[hs],
        mp,
        Options::Pool {
            same: true,
            stride: 2,
            filter: 2,
        },
    );
    let ap = g.tensor("avg_pool", &[1, 3, 3, 4], None);
    g.op(
        code::AVERAGE_POOL_2D,
        &[mp],
        ap,
        Options::Pool {
            same: true,
            stride: 1,
            filter: 3,
        },
    );
    // RESIZE to 4 × 4, DEPTH_TO_SPACE to [1, 8, 8, 1].
    let size = g.tensor("size", &[2], Some(Data::I32(vec![4, 4])));
    let up = g.tensor("resized", &[1, 4, 4, 4], None);
    g.op(code::RESIZE_BILINEAR, &[ap, size], up, Options::Resize);
    let d2s = g.tensor("depth_to_space", &[1, 8, 8, 1], None);
    g.op(code::DEPTH_TO_SPACE, &[up], d2s, Options::DepthToSpace(2));
    // The transposed convolution 2 × 2 stride 2 of the 4 × 4 map: [1, 8, 8, 1].
    let tw = g.tensor("tw", &[1, 2, 2, 4], Some(Data::F32(pattern(16, 6))));
    let tb = g.tensor("tb", &[1], Some(Data::F32(vec![0.25])));
    let tc = g.tensor("transpose_conv", &[1, 8, 8, 1], None);
    g.op(
        code::CUSTOM,
        &[up, tw, tb],
        tc,
        Options::TransposeConv {
            same: true,
            stride: 2,
        },
    );
    let cat = g.tensor("concat", &[1, 8, 8, 2], None);
    g.op(
        code::CONCATENATION,
        &[d2s, tc],
        cat,
        Options::Concat { axis: 3 },
    );
    let out = g.tensor("image", &[1, 8, 8, 2], None);
    g.op(code::LOGISTIC, &[cat], out, Options::None);
    g.output(out);
    // A vector output: a VALID 2 × 2 pool of the 3 × 3 map, RELU, reshaped: [1, 16].
    let small = g.tensor("pooled", &[1, 2, 2, 4], None);
    g.op(
        code::MAX_POOL_2D,
        &[ap],
        small,
        Options::Pool {
            same: false,
            stride: 1,
            filter: 2,
        },
    );
    let relu = g.tensor("relu", &[1, 2, 2, 4], None);
    g.op(code::RELU, &[small], relu, Options::None);
    let vec = g.tensor("vector", &[1, 16], None);
    g.op(code::RESHAPE, &[relu], vec, Options::None);
    g.output(vec);
    g.finish()
}
