//! The frozen affine on Burn's CubeCL backend: one thread per channel, and the cache of results
//! by input buffers (see [`super`]).

use std::collections::VecDeque;
use std::sync::{Mutex, PoisonError};

use burn::backend::TensorMetadata;
use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::server::Handle;
use burn_cubecl::tensor::CubeTensor;
use lifegom_render::cube::host::{
    THREADS_1D, arg, cast_to, count_1d, prepare, tensor_arg, tensor_f32,
};

use super::op::FrozenAffineOps;

/// Results kept at most; the oldest goes first. The Point Transformer has a few dozen frozen BNs.
const CACHED: usize = 256;

/// One cached result: the inputs it was made from (held, so nothing writes them in place while
/// cached), `ε`'s bits and the outputs.
struct Entry {
    inputs: [Handle; 4],
    epsilon: u32,
    outputs: (CubeTensor, CubeTensor),
}

static CACHE: Mutex<VecDeque<Entry>> = Mutex::new(VecDeque::new());

/// Whether `a` and `b` are the same range of the same buffer (memory ids are never reused).
fn same_range(a: &Handle, b: &Handle) -> bool {
    a.memory.descriptor() == b.memory.descriptor()
        && a.offset_start == b.offset_start
        && a.offset_end == b.offset_end
}

#[cube(launch)]
fn frozen_affine_kernel(
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    scale: &mut [f32],
    shift: &mut [f32],
    channels: usize,
    epsilon: f32,
) {
    let c = ABSOLUTE_POS;
    if c < channels {
        let s = gamma[c] / f32::sqrt(var[c] + epsilon);
        scale[c] = s;
        shift[c] = beta[c] - mean[c] * s;
    }
}

impl FrozenAffineOps for CubeBackend {
    fn frozen_affine(
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f32,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let dtype = gamma.dtype();
        let c = gamma.shape()[0];
        let (client, device) = (gamma.client.clone(), gamma.device.clone());
        let inputs = [gamma, beta, mean, var].map(prepare);
        let handles = inputs.each_ref().map(|t| t.handle.clone());
        let mut cache = CACHE.lock().unwrap_or_else(PoisonError::into_inner);
        let found = cache.iter().find(|e| {
            e.epsilon == epsilon.to_bits()
                && e.inputs.iter().zip(&handles).all(|(a, b)| same_range(a, b))
        });
        if let Some(entry) = found {
            let (s, t) = entry.outputs.clone();
            return (cast_to(s, dtype), cast_to(t, dtype));
        }
        let [gamma, beta, mean, var] = inputs;
        let outputs = [(); 2].map(|()| client.empty(4 * c.max(1)));
        if c > 0 {
            frozen_affine_kernel::launch(
                &client,
                count_1d(c),
                CubeDim::new_1d(THREADS_1D),
                tensor_arg(&gamma),
                tensor_arg(&beta),
                tensor_arg(&mean),
                tensor_arg(&var),
                arg(&outputs[0], c),
                arg(&outputs[1], c),
                c,
                epsilon,
            );
        }
        let [s, t] = outputs.map(|h| tensor_f32(&client, &device, h, &[c]));
        if cache.len() == CACHED {
            cache.pop_front();
        }
        cache.push_back(Entry {
            inputs: handles,
            epsilon: epsilon.to_bits(),
            outputs: (s.clone(), t.clone()),
        });
        (cast_to(s, dtype), cast_to(t, dtype))
    }
}
