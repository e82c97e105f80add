//! Reconstructions called from several threads at once all finish. A pass runs on one of
//! rayon's threads (`lifegom_render::device::on_pool_thread`); when its fusion branch was a
//! thread of its own, two passes at once on a two-core machine deadlocked, each rayon worker
//! blocked joining a branch thread whose ops waited for a free worker. In its own test binary
//! because Burn's device RNG is process-wide (see `common`).

mod common;

use std::sync::mpsc;
use std::time::Duration;

use burn::tensor::Device;
use common::reconstruct_with;
use lifegom_model::reconstructor::HostConcurrency;

#[test]
fn concurrent_reconstructions_finish() {
    let callers = 2 * rayon::current_num_threads() + 1;
    let (done, finished) = mpsc::channel();
    for caller in 0..callers {
        let done = done.clone();
        std::thread::spawn(move || {
            // Training mode on half the callers: autodiff graphs and dropout masks too.
            let device = if caller % 2 == 0 {
                Device::flex()
            } else {
                Device::flex().autodiff()
            };
            let avatar = reconstruct_with(&device, caller as u64, 2, HostConcurrency::Branches);
            done.send(avatar.iter().all(|v| v.is_finite())).ok();
        });
    }
    for caller in 0..callers {
        let finite = finished
            .recv_timeout(Duration::from_secs(120))
            .unwrap_or_else(|_| {
                panic!("only {caller} of {callers} reconstructions finished in 120 s")
            });
        assert!(finite, "a reconstruction has non-finite values");
    }
}
