//! The kernel-launch counter on wgpu (lavapipe in CI), with Burn's kernel fusion on. CubeCL's launch observer is one slot for
//! the whole process, so launches of any test running beside this one would be counted too:
//! this check has a test binary to itself.

use burn::tensor::{Int, Tensor};
use lifegom_cli::launches::{KernelTiming, LaunchCounter};
use lifegom_render::select::select_rows;
use lifegom_render::testing::wgpu_test_device;
use tracing_subscriber::layer::SubscriberExt;

/// A fixed sequence of ops launches the same kernels every time it runs, a new counter counts
/// only what runs after it, and a custom op's launches count under the span open where it was
/// recorded, although Burn's fusion stream runs it on its own thread (where Burn's own ops carry
/// no span).
#[test]
fn counts_wgpu_launches_per_span() {
    let Some(device) = wgpu_test_device() else {
        return;
    };
    let a = Tensor::<1>::from_floats([1.0, 2.0, 3.0], &device);
    let work = || (a.clone() * 2.0).exp().sum().into_data();
    // The row gather's backward is a deferred custom op (lifegom_render::cube::deferred).
    let ad = device.clone().autodiff();
    let gather_backward = || {
        let x = Tensor::<1>::from_floats([-1.0, 2.0, 3.0], &ad).require_grad();
        let rows = Tensor::<1, Int>::from_ints([2, 0, 2], &ad);
        let grads = select_rows(x.clone(), 0, rows).sum().backward();
        x.grad(&grads).unwrap().into_data()
    };
    // Compile the kernels first: the count must not depend on what ran before.
    let _ = work();
    let _ = gather_backward();
    let subscriber = tracing_subscriber::registry();
    // INFO, as the benchmarks run: the ops' own trace spans stay off, so a launch counts under
    // the stage that asked for it.
    tracing::subscriber::with_default(
        subscriber.with(tracing_subscriber::filter::LevelFilter::INFO),
        || {
            let counter = LaunchCounter::install(KernelTiming::Off);
            let _ = work();
            let once = counter.take();
            let _ = work();
            let _ = work();
            let twice = counter.take();
            assert!(once.total_launches() >= 1, "{once:?}");
            assert_eq!(
                twice.total_launches(),
                2 * once.total_launches(),
                "{twice:?}"
            );
            let per_kernel: u64 = twice.kernels.values().map(|k| k.launches).sum();
            assert_eq!(per_kernel, twice.total_launches());
            {
                let _span = tracing::info_span!("gather_stage").entered();
                let _ = gather_backward();
            }
            let gather = counter.take();
            assert!(
                gather.by_span.get("gather_stage").copied().unwrap_or(0) >= 1,
                "{gather:?}"
            );
            // A second counter starts from nothing: what ran before it is not in its tally.
            drop(counter);
            let _ = work();
            let next = LaunchCounter::install(KernelTiming::Off);
            let _ = work();
            assert_eq!(next.take().total_launches(), once.total_launches());
        },
    );
}
