//! The kernel-launch counter on wgpu (lavapipe in CI). CubeCL's launch observer is one slot for
//! the whole process, so launches of any test running beside this one would be counted too:
//! this check has a test binary to itself.

use burn::tensor::Tensor;
use lifegom_cli::launches::{KernelTiming, LaunchCounter};
use lifegom_render::device::{DeviceChoice, wgpu_available};
use tracing_subscriber::layer::SubscriberExt;

/// A fixed sequence of ops launches the same kernels every time it runs, each launch is put
/// under the span open when it was issued, and a new counter counts only what runs after it.
#[test]
fn counts_wgpu_launches_per_span() {
    if !wgpu_available() {
        assert!(
            std::env::var_os("LIFEGOM_REQUIRE_WGPU").is_none(),
            "LIFEGOM_REQUIRE_WGPU is set but no wgpu adapter came up"
        );
        eprintln!("skipping: no wgpu adapter");
        return;
    }
    let device = DeviceChoice::Wgpu.device();
    let a = Tensor::<1>::from_floats([1.0, 2.0, 3.0], &device);
    let work = || (a.clone() * 2.0).exp().sum().into_data();
    // Compile the kernels first: the count must not depend on what ran before.
    let _ = work();
    let subscriber = tracing_subscriber::registry();
    tracing::subscriber::with_default(
        subscriber.with(tracing_subscriber::filter::LevelFilter::TRACE),
        || {
            let counter = LaunchCounter::install(KernelTiming::Off);
            {
                let _span = tracing::info_span!("once").entered();
                let _ = work();
            }
            let once = counter.take();
            {
                let _span = tracing::info_span!("twice").entered();
                let _ = work();
                let _ = work();
            }
            let twice = counter.take();
            // A scalar multiply, an exp and a sum: at least three kernels.
            assert!(once.total_launches() >= 3, "{once:?}");
            assert_eq!(
                twice.total_launches(),
                2 * once.total_launches(),
                "{twice:?}"
            );
            assert_eq!(
                once.by_span.get("once"),
                Some(&once.total_launches()),
                "{once:?}"
            );
            assert_eq!(
                twice.by_span.get("twice"),
                Some(&twice.total_launches()),
                "{twice:?}"
            );
            let per_kernel: u64 = twice.kernels.values().map(|k| k.launches).sum();
            assert_eq!(per_kernel, twice.total_launches());
            // A second counter starts from nothing: what ran before it is not in its tally.
            drop(counter);
            let _ = work();
            let next = LaunchCounter::install(KernelTiming::Off);
            let _ = work();
            assert_eq!(next.take().total_launches(), once.total_launches());
        },
    );
}
