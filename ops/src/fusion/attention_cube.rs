//! The fusion layers' attention core (`softmax(q·kᵀ/√d_k)·v` per head, over sequences of a few
//! views) on Burn's CubeCL backend (design.md §7.4): the same formulas as the CPU slice code
//! (`super::kernels`) in `f32`, one forward and one backward launch per call.
//!
//! One cube of [`CUBE_THREADS`] threads per problem and head `(b, h)`; its threads stride over
//! the head's `d_k` channels, so neighbouring threads read neighbouring floats. Each score
//! `q_i·k_j` (and in the backward each `g_i·v_j`) is a sum over channels that the cube reduces in
//! shared memory (`super::cube`'s fixed tree, the same in every run); every thread receives it
//! and keeps its query's row of scores in a local array of at most [`MAX_KEYS`] entries.
//!
//! - `attention_forward_kernel`: for each query `i`, the scores, their softmax `p` (shifted by
//!   the row's maximum) and `out_i = Σ_j p_ij·v_j`, each thread writing its channels.
//! - `attention_backward_kernel`: for each query `i`, `p` again, `∂p_ij = g_i·v_j`,
//!   `∂s_ij = p_ij·(∂p_ij − Σ_l p_il·∂p_il)`, then `∂q_i = Σ_j ∂s_ij·k_j/√d_k`, and each thread
//!   adds `∂s_ij·q_i/√d_k` and `p_ij·g_i` into its channels of `∂k_j` and `∂v_j`. The cube owns
//!   its head's slice of every output and each thread its channels: no atomics.
//!
//! Burn's composition costs four layout copies, two batched products and a five-op softmax
//! forward, and about twice that backward, per call.

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use lifegom_render::cube::host::{arg, cast_to, count_cubes, prepare, tensor_arg, tensor_f32};

use super::cube::cube_sum;
use super::op::{AttentionHeads, AttentionInputs, AttentionKernels, FusionAttentionOps};

/// Threads of each cube (a power of two: the shared-memory sum halves it).
const CUBE_THREADS: u32 = 64;

/// The longest key sequence the kernels take (the scores of one query live in a local array);
/// longer ones run as Burn's composition (`super::attention`).
pub(crate) const MAX_KEYS: usize = 16;

/// The sizes every kernel indexes with.
#[derive(CubeType, CubeLaunch)]
struct Dims {
    /// Problems (vertices).
    batch: usize,
    /// Queries and keys per problem.
    len_q: usize,
    len_k: usize,
    /// Channels in all, heads, channels per head.
    d: usize,
    heads: usize,
    dk: usize,
    /// `1/√d_k`.
    scale: f32,
}

/// The problem and head of this cube, or `batch·heads` past the end.
#[cube]
fn problem_of_cube() -> usize {
    (CUBE_POS_Y * CUBE_COUNT_X + CUBE_POS_X) as usize
}

/// `Σ_c a[row_a, c]·b[row_b, c]` over the head's channels, reduced over the cube.
#[cube]
#[allow(clippy::too_many_arguments)]
fn head_dot(
    a: &[f32],
    b: &[f32],
    row_a: usize,
    row_b: usize,
    head: usize,
    shared: &mut Shared<[f32]>,
    dims: &Dims,
) -> f32 {
    let mut partial = 0.0f32;
    let mut c = UNIT_POS as usize;
    while c < dims.dk {
        let ch = head * dims.dk + c;
        partial += a[row_a * dims.d + ch] * b[row_b * dims.d + ch];
        c += CUBE_DIM as usize;
    }
    cube_sum(shared, partial)
}

/// The softmax of query `i`'s scores over the keys, into `p` (the first `len_k` entries).
#[cube]
#[allow(clippy::too_many_arguments)]
fn softmax_row(
    query: &[f32],
    key: &[f32],
    b: usize,
    head: usize,
    i: usize,
    p: &mut Array<f32>,
    shared: &mut Shared<[f32]>,
    dims: &Dims,
) {
    let row_q = b * dims.len_q + i;
    let mut max = f32::new(-3.4028235e38);
    for j in 0..dims.len_k {
        let s = head_dot(query, key, row_q, b * dims.len_k + j, head, shared, dims) * dims.scale;
        p[j] = s;
        max = f32::max(max, s);
    }
    let mut sum = 0.0f32;
    for j in 0..dims.len_k {
        let e = f32::exp(p[j] - max);
        p[j] = e;
        sum += e;
    }
    for j in 0..dims.len_k {
        p[j] /= sum;
    }
}

#[cube(launch)]
fn attention_forward_kernel(
    query: &[f32],
    key: &[f32],
    value: &[f32],
    out: &mut [f32],
    dims: &Dims,
) {
    let mut shared = Shared::<[f32]>::new_slice(CUBE_THREADS as usize);
    let mut p = Array::<f32>::new(MAX_KEYS);
    let problem = problem_of_cube();
    // The same for every thread of the cube, so the barriers inside are reached by all.
    if problem < dims.batch * dims.heads {
        let b = problem / dims.heads;
        let head = problem % dims.heads;
        for i in 0..dims.len_q {
            softmax_row(query, key, b, head, i, &mut p, &mut shared, dims);
            let row_q = b * dims.len_q + i;
            let mut c = UNIT_POS as usize;
            while c < dims.dk {
                let ch = head * dims.dk + c;
                let mut acc = 0.0f32;
                for j in 0..dims.len_k {
                    acc += p[j] * value[(b * dims.len_k + j) * dims.d + ch];
                }
                out[row_q * dims.d + ch] = acc;
                c += CUBE_DIM as usize;
            }
        }
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
fn attention_backward_kernel(
    query: &[f32],
    key: &[f32],
    value: &[f32],
    grad: &[f32],
    query_grad: &mut [f32],
    key_grad: &mut [f32],
    value_grad: &mut [f32],
    dims: &Dims,
) {
    let mut shared = Shared::<[f32]>::new_slice(CUBE_THREADS as usize);
    let mut p = Array::<f32>::new(MAX_KEYS);
    let mut ds = Array::<f32>::new(MAX_KEYS);
    let problem = problem_of_cube();
    if problem < dims.batch * dims.heads {
        let b = problem / dims.heads;
        let head = problem % dims.heads;
        for i in 0..dims.len_q {
            softmax_row(query, key, b, head, i, &mut p, &mut shared, dims);
            let row_q = b * dims.len_q + i;
            let mut dot = 0.0f32;
            for j in 0..dims.len_k {
                let dp = head_dot(
                    grad,
                    value,
                    row_q,
                    b * dims.len_k + j,
                    head,
                    &mut shared,
                    dims,
                );
                ds[j] = dp;
                dot += p[j] * dp;
            }
            for j in 0..dims.len_k {
                ds[j] = p[j] * (ds[j] - dot) * dims.scale;
            }
            let mut c = UNIT_POS as usize;
            while c < dims.dk {
                let ch = head * dims.dk + c;
                let q = query[row_q * dims.d + ch];
                let g = grad[row_q * dims.d + ch];
                let mut dq = 0.0f32;
                for j in 0..dims.len_k {
                    let at = (b * dims.len_k + j) * dims.d + ch;
                    dq += ds[j] * key[at];
                    if i == 0 {
                        key_grad[at] = ds[j] * q;
                        value_grad[at] = p[j] * g;
                    } else {
                        key_grad[at] += ds[j] * q;
                        value_grad[at] += p[j] * g;
                    }
                }
                query_grad[row_q * dims.d + ch] = dq;
                c += CUBE_DIM as usize;
            }
        }
    }
}

/// The launch sizes of `inputs`.
fn dims_of(inputs: &AttentionInputs<CubeBackend>) -> (usize, usize, usize, usize, usize) {
    let (q, k) = (inputs.query.shape(), inputs.key.shape());
    (q[0], q[1], k[1], q[2], inputs.heads)
}

fn dims_arg((batch, len_q, len_k, d, heads): (usize, usize, usize, usize, usize)) -> DimsLaunch {
    let dk = d / heads;
    DimsLaunch::new(batch, len_q, len_k, d, heads, dk, 1.0 / (dk as f32).sqrt())
}

fn cube_forward(inputs: AttentionInputs<CubeBackend>) -> FloatTensor<CubeBackend> {
    let _span = tracing::trace_span!("cube_fusion_attention").entered();
    let dims = dims_of(&inputs);
    let (batch, len_q, len_k, d, heads) = dims;
    assert!(
        len_k <= MAX_KEYS,
        "fusion attention over {len_k} keys (at most {MAX_KEYS})"
    );
    let dtype = inputs.query.dtype();
    let (client, device) = (inputs.query.client.clone(), inputs.query.device.clone());
    let [query, key, value] = [inputs.query, inputs.key, inputs.value].map(prepare);
    let len = batch * len_q * d;
    let out = client.empty(4 * len.max(1));
    if batch * heads > 0 && len_q > 0 {
        attention_forward_kernel::launch(
            &client,
            count_cubes(batch * heads),
            CubeDim::new_1d(CUBE_THREADS),
            tensor_arg(&query),
            tensor_arg(&key),
            tensor_arg(&value),
            arg(&out, len),
            dims_arg(dims),
        );
    }
    cast_to(tensor_f32(&client, &device, out, &[batch, len_q, d]), dtype)
}

fn cube_backward(
    inputs: AttentionInputs<CubeBackend>,
    grad: FloatTensor<CubeBackend>,
) -> [FloatTensor<CubeBackend>; 3] {
    let _span = tracing::trace_span!("cube_fusion_attention_backward").entered();
    let dims = dims_of(&inputs);
    let (batch, len_q, len_k, d, heads) = dims;
    let dtypes = [&inputs.query, &inputs.key, &inputs.value].map(|t| t.dtype());
    let (client, device) = (inputs.query.client.clone(), inputs.query.device.clone());
    let [query, key, value, grad] = [inputs.query, inputs.key, inputs.value, grad].map(prepare);
    let (len_qs, len_ks) = (batch * len_q * d, batch * len_k * d);
    let query_grad = client.empty(4 * len_qs.max(1));
    // The kernel writes every key and value gradient at the first query; with no queries they
    // are zero.
    let [key_grad, value_grad] = [(); 2].map(|()| {
        if len_q > 0 {
            client.empty(4 * len_ks.max(1))
        } else {
            lifegom_render::cube::host::zeros_f32(&client, &device, len_ks)
        }
    });
    if batch * heads > 0 && len_q > 0 {
        attention_backward_kernel::launch(
            &client,
            count_cubes(batch * heads),
            CubeDim::new_1d(CUBE_THREADS),
            tensor_arg(&query),
            tensor_arg(&key),
            tensor_arg(&value),
            tensor_arg(&grad),
            arg(&query_grad, len_qs),
            arg(&key_grad, len_ks),
            arg(&value_grad, len_ks),
            dims_arg(dims),
        );
    }
    [
        cast_to(
            tensor_f32(&client, &device, query_grad, &[batch, len_q, d]),
            dtypes[0],
        ),
        cast_to(
            tensor_f32(&client, &device, key_grad, &[batch, len_k, d]),
            dtypes[1],
        ),
        cast_to(
            tensor_f32(&client, &device, value_grad, &[batch, len_k, d]),
            dtypes[2],
        ),
    ]
}

impl FusionAttentionOps for CubeBackend {
    fn fusion_attention(
        query: FloatTensor<Self>,
        key: FloatTensor<Self>,
        value: FloatTensor<Self>,
        heads: AttentionHeads,
    ) -> FloatTensor<Self> {
        cube_forward(AttentionInputs {
            query,
            key,
            value,
            heads: heads.0,
        })
    }
}

impl AttentionKernels for CubeBackend {
    fn attention_forward(inputs: AttentionInputs<Self>) -> FloatTensor<Self> {
        cube_forward(inputs)
    }

    fn attention_backward(
        inputs: AttentionInputs<Self>,
        grad: FloatTensor<Self>,
    ) -> [FloatTensor<Self>; 3] {
        cube_backward(inputs, grad)
    }
}
