//! The stage timer's CPU column counts every thread of the process. The process CPU clock also
//! counts any other test running beside this one, so this check has a test binary to itself.

use std::time::{Duration, Instant};

use lifegom_cli::profile::StageTimer;
use tracing_subscriber::layer::SubscriberExt;

fn spin(d: Duration) {
    let start = Instant::now();
    let mut x = 0u64;
    while start.elapsed() < d {
        x = std::hint::black_box(x.wrapping_add(1));
    }
}

/// A span that spins on two threads uses about two CPU seconds per wall second (one on a
/// one-core machine); one that sleeps uses about none.
#[test]
fn span_cpu_time_counts_every_thread() {
    if !cfg!(target_os = "linux") {
        return;
    }
    let timer = StageTimer::with_process_cpu();
    let subscriber = tracing_subscriber::registry().with(timer.clone());
    tracing::subscriber::with_default(subscriber, || {
        {
            let _both = tracing::debug_span!("both").entered();
            std::thread::scope(|s| {
                s.spawn(|| spin(Duration::from_millis(80)));
                spin(Duration::from_millis(80));
            });
        }
        let _idle = tracing::debug_span!("idle").entered();
        std::thread::sleep(Duration::from_millis(40));
    });
    let totals = timer.take();
    let idle = totals["idle"].cpu_per_wall().expect("timed");
    assert!(idle < 0.3, "a sleeping span used {idle} CPU per wall");
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get().min(2));
    let both = totals["both"].cpu_per_wall().expect("timed");
    assert!(
        both > 0.6 * cores as f64 && both < 2.3,
        "two spinning threads used {both} CPU per wall on {cores} cores"
    );
}
