//! A tensor's last axis as consecutive blocks of columns, each its own tensor: the rasterizer's
//! `[H, W, 4]` image as colour and alpha, the Gaussians-on-Mesh rows as means and covariances
//! (design.md §5.7).
//!
//! Burn splits with one slice per block. On a GPU that is a copy kernel per block forward, and
//! backward, per block, a zero-filled tensor of the whole width and a slice-assign into it, then
//! an addition per further block: about four launches a block where one in all suffices each
//! way. [`split_columns`] writes every block in one launch, and its backward writes every
//! block's gradient into its columns in one launch, zeros for the blocks that took none.
//!
//! The blocks are several autodiff nodes, and Burn runs each alone. As for the shared layers
//! of the model crate, a node between the source and the blocks collects them: each block's
//! node files its gradient with it and, the first time, registers a placeholder for it (the
//! source's own handle: the right shape, no copy), so that Burn reaches it; Burn then runs it
//! after every block's node, since it is shallower, and it makes the source's gradient from
//! what was filed (the `op` module).
//!
//! [`join_columns`] is the inverse, Burn's `cat` on the last axis: on a GPU one launch
//! forward, where `cat` takes one per block, and one backward (the split), where `cat`'s
//! backward is a slice per block.
//!
//! On the CPU backends the blocks are Burn's `narrow` and the join its `cat`, which cost
//! nothing there.

mod cube;
pub mod op;

use burn::backend::Dispatch;
use burn::tensor::Tensor;

use crate::device::runs_on_host;
use op::{ColumnBlocks, MAX_BLOCKS, SplitOps};

/// `t` `[.., C]` as blocks `[.., widths[0]]`, `[.., widths[1]]`, … of consecutive columns (module
/// docs). The widths are positive and sum to `C`.
///
/// # Panics
///
/// If the widths are not positive or do not sum to `C`.
pub fn split_columns<const D: usize>(t: Tensor<D>, widths: &[usize]) -> Vec<Tensor<D>> {
    let dims = t.dims();
    let width = dims[D - 1];
    assert!(
        widths.iter().all(|&w| w > 0) && widths.iter().sum::<usize>() == width,
        "blocks of widths {widths:?} must tile {width} columns"
    );
    if runs_on_host(&t.device()) || widths.len() > MAX_BLOCKS || widths.len() < 2 {
        let mut start = 0;
        return widths
            .iter()
            .map(|&w| {
                start += w;
                t.clone().narrow(D - 1, start - w, w)
            })
            .collect();
    }
    let rows = dims[..D - 1].iter().product();
    let blocks = ColumnBlocks::new(widths);
    let (b0, b1, b2, b3) =
        <Dispatch as SplitOps>::split_columns(t.reshape([rows, width]).into_dispatch(), blocks);
    [b0, b1, b2, b3]
        .into_iter()
        .zip(widths)
        .map(|(block, &w)| {
            let mut shape = dims;
            shape[D - 1] = w;
            Tensor::<2>::from_dispatch(block).reshape(shape)
        })
        .collect()
}

/// `parts` `[.., w_i]` side by side, `[.., Σ w_i]`: `Tensor::cat(parts, D − 1)` (module docs).
///
/// # Panics
///
/// If `parts` is empty or their leading axes differ.
pub fn join_columns<const D: usize>(parts: Vec<Tensor<D>>) -> Tensor<D> {
    assert!(!parts.is_empty(), "nothing to join");
    let dims = parts[0].dims();
    assert!(
        parts.iter().all(|p| p.dims()[..D - 1] == dims[..D - 1]),
        "joined blocks have the same leading axes"
    );
    if runs_on_host(&parts[0].device()) || parts.len() > MAX_BLOCKS || parts.len() < 2 {
        return Tensor::cat(parts, D - 1);
    }
    let widths: Vec<usize> = parts.iter().map(|p| p.dims()[D - 1]).collect();
    let rows = dims[..D - 1].iter().product();
    let mut flat: Vec<_> = parts
        .into_iter()
        .zip(&widths)
        .map(|(p, &w)| p.reshape([rows, w]).into_dispatch())
        .collect();
    while flat.len() < MAX_BLOCKS {
        flat.push(flat[0].clone());
    }
    let [b0, b1, b2, b3]: [_; MAX_BLOCKS] = flat.try_into().expect("four slots");
    let joined = Tensor::<2>::from_dispatch(<Dispatch as SplitOps>::join_columns(
        b0,
        b1,
        b2,
        b3,
        ColumnBlocks::new(&widths),
    ));
    let mut shape = dims;
    shape[D - 1] = widths.iter().sum();
    joined.reshape(shape)
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};

    use crate::device::DeviceChoice;
    use crate::testing::{Rng, read, wgpu_test_device};

    /// Splits a `[5, 4, 9]` tensor into blocks of `widths` on `device`, uses each block in a
    /// different way (some not at all, as a loss may leave the depth unused), and returns the
    /// blocks and the source's gradient.
    fn run(device: &Device, widths: &[usize], used: &[bool]) -> Vec<Vec<f32>> {
        let width = widths.iter().sum();
        // Sources one row long (a weight's row blocks) split into views of their buffer.
        let shape = if width > 9 {
            [1, 1, width]
        } else {
            [5, 4, width]
        };
        let mut rng = Rng::new(5);
        let values: Vec<f32> = (0..shape.iter().product())
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let t = Tensor::<3>::from_data(TensorData::new(values, shape), device).require_grad();
        let blocks = split_columns(t.clone(), widths);
        let mut loss = Tensor::<1>::zeros([1], device);
        for (i, (block, &use_it)) in blocks.iter().zip(used).enumerate() {
            if use_it {
                loss = loss + (block.clone() * (i as f32 + 1.0)).tanh().sum();
            }
        }
        let grads = loss.backward();
        let mut out: Vec<Vec<f32>> = blocks.into_iter().map(read).collect();
        out.push(read(t.grad(&grads).expect("the source's gradient")));
        out
    }

    /// Joins blocks of `widths` (made from one generator, `[5, 4, w]` each) on `device`, weighs
    /// the join, and returns it and every block's gradient.
    fn run_join(device: &Device, widths: &[usize]) -> Vec<Vec<f32>> {
        let mut rng = Rng::new(6);
        let total: usize = widths.iter().sum();
        let parts: Vec<Tensor<3>> = widths
            .iter()
            .map(|&w| {
                let values: Vec<f32> = (0..5 * 4 * w).map(|_| rng.range_f32(-1.0, 1.0)).collect();
                Tensor::<3>::from_data(TensorData::new(values, [5, 4, w]), device).require_grad()
            })
            .collect();
        let weights: Vec<f32> = (0..5 * 4 * total)
            .map(|_| rng.range_f32(-1.0, 1.0))
            .collect();
        let weights = Tensor::<3>::from_data(TensorData::new(weights, [5, 4, total]), device);
        let joined = join_columns(parts.clone());
        let grads = (joined.clone().tanh() * weights).sum().backward();
        let mut out = vec![read(joined)];
        out.extend(
            parts
                .iter()
                .map(|p| read(p.grad(&grads).expect("a block's gradient"))),
        );
        out
    }

    /// On lavapipe the join and its blocks' gradients equal Burn's `cat` on Flex, for two to
    /// four blocks.
    #[test]
    fn join_matches_cat_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let ad = device.autodiff();
        let flex = DeviceChoice::Flex.device().autodiff();
        for widths in [&[3, 6][..], &[1, 5, 2], &[2, 2, 2, 3]] {
            let gpu = run_join(&ad, widths);
            let cpu = run_join(&flex, widths);
            for (i, (a, b)) in gpu.iter().zip(&cpu).enumerate() {
                assert_eq!(a.len(), b.len(), "{widths:?}: part {i}");
                for (j, (u, v)) in a.iter().zip(b).enumerate() {
                    assert!(
                        (u - v).abs() <= 1e-6 * (1.0 + v.abs()),
                        "{widths:?}, part {i}[{j}]: {u} against {v}"
                    );
                }
            }
        }
    }

    /// On lavapipe the blocks and the source's gradient equal Burn's slices on Flex exactly
    /// (copies, and one addend per element), for two to four blocks, with blocks that take no
    /// gradient; and for sources of one row, whose blocks are views of the source where they
    /// all start at multiples of 256 floats (a binding's alignment on every runtime divides
    /// 1 KiB) and copies where one does not.
    #[test]
    fn split_matches_slices_wgpu() {
        let Some(device) = wgpu_test_device() else {
            return;
        };
        let ad = device.autodiff();
        let flex = DeviceChoice::Flex.device().autodiff();
        for (widths, used) in [
            (&[3, 6][..], &[true, true][..]),
            (&[3, 1, 5], &[true, false, true]),
            (&[2, 2, 2, 3], &[false, true, true, true]),
            (&[8, 1], &[false, true]),
            (&[256, 512, 3], &[true, true, true]),
            (&[256, 5, 256], &[true, false, true]),
        ] {
            let gpu = run(&ad, widths, used);
            let cpu = run(&flex, widths, used);
            assert_eq!(gpu.len(), cpu.len());
            for (i, (a, b)) in gpu.iter().zip(&cpu).enumerate() {
                assert_eq!(a.len(), b.len(), "{widths:?}: part {i}");
                for (j, (u, v)) in a.iter().zip(b).enumerate() {
                    assert!(
                        (u - v).abs() <= 1e-6 * (1.0 + v.abs()),
                        "{widths:?}, part {i}[{j}]: {u} against {v}"
                    );
                }
            }
        }
    }
}
