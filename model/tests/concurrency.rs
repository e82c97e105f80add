//! The host threading modes give the same avatar. In its own test binary because Burn's device
//! RNG is process-wide (see `common`).

mod common;

use burn::tensor::Device;
use common::reconstruct_with;
use lifegom_model::reconstructor::HostConcurrency;

/// The fusion's rendered branch on its own thread or in line: the same avatar and gradient, in
/// training (dropout masks drawn) with two views.
#[test]
fn concurrency_modes_agree() {
    let device = Device::flex().autodiff();
    let branches = reconstruct_with(&device, 5, 2, HostConcurrency::Branches);
    let sequential = reconstruct_with(&device, 5, 2, HostConcurrency::Sequential);
    assert!(branches.iter().all(|v| v.is_finite()));
    assert!(branches == sequential, "the modes disagree");
}
