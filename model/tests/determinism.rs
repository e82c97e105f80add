//! Same seed → same avatar. In its own test binary because Burn's device RNG is process-wide:
//! tests running in parallel in one process would draw from it between `seed` and `init`.

mod common;

use burn::tensor::Device;
use common::reconstruct;

#[test]
fn same_seed_same_avatar_single_view() {
    let device = Device::flex();
    let a = reconstruct(&device, 7);
    let b = reconstruct(&device, 7);
    assert!(a.iter().all(|v| v.is_finite()));
    assert!(a == b, "same seed gave different avatars");
    let c = reconstruct(&device, 8);
    assert!(
        a != c,
        "a different seed should give a different (random-init) avatar"
    );
}
