//! Wall time per stage, from the `tracing` spans the libraries already open.
//!
//! [`StageTimer`] is a `tracing-subscriber` layer: every span gets a path made of its ancestors'
//! names (`train_step/reconstruct/feedback_step/render_views`), and the time between entering
//! and leaving it is added to that path's total. A span entered several times in one step (the
//! T feedback steps, the N views) sums into one entry, so a step's profile is a flat map from
//! path to milliseconds, and a parent's time includes its children's.
//!
//! The CPU backends (ndarray, Flex) execute each op when it is called, so a span's time is the
//! work done inside it. On wgpu a span only measures the time to enqueue.
//!
//! A timer made with [`StageTimer::with_process_cpu`] also gives each path the CPU time the whole
//! process used while the span was entered (`CLOCK_PROCESS_CPUTIME_ID`, all threads). Their ratio
//! says how busy the cores were in that stage: about 1 for a stage that runs on one thread, up to
//! the thread count for one that keeps them all working, so an idle core shows which stage leaves
//! it idle. Reading that clock is not free (its docs), so the plain timer leaves it out.
//!
//! ```
//! use lifegom_cli::profile::StageTimer;
//! use tracing_subscriber::layer::SubscriberExt;
//!
//! let timer = StageTimer::default();
//! let subscriber = tracing_subscriber::registry().with(timer.clone());
//! tracing::subscriber::with_default(subscriber, || {
//!     let _outer = tracing::info_span!("step").entered();
//!     let _inner = tracing::debug_span!("render").entered();
//! });
//! let totals = timer.take();
//! assert!(totals.contains_key("step/render"));
//! ```

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use tracing::span::{Attributes, Id};
use tracing::{Metadata, Subscriber};
use tracing_subscriber::Layer;
use tracing_subscriber::layer::Context;
use tracing_subscriber::registry::LookupSpan;

/// Accumulated wall (and, when asked for, process CPU) time per span path. Clones share one
/// table.
#[derive(Debug, Clone, Default)]
pub struct StageTimer {
    totals: Arc<Mutex<BTreeMap<String, StageTime>>>,
    process_cpu: bool,
}

/// One span path's totals.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTime {
    /// Wall time inside the span.
    pub wall: Duration,
    /// CPU time of the whole process (every thread) while inside the span; zero unless the
    /// timer reads it ([`StageTimer::with_process_cpu`]) and the platform has the clock.
    pub cpu: Duration,
}

impl StageTime {
    /// Process CPU seconds per wall second inside the span (`None` for an empty span).
    pub fn cpu_per_wall(&self) -> Option<f64> {
        (self.wall > Duration::ZERO).then(|| self.cpu.as_secs_f64() / self.wall.as_secs_f64())
    }
}

/// What the layer keeps in each span's extensions.
struct SpanClock {
    path: String,
    /// Wall clock and process CPU clock when the span was entered.
    entered: Option<(Instant, Duration)>,
}

impl StageTimer {
    /// A timer that also reads the process CPU clock at every span's entry and exit.
    ///
    /// That clock sums every thread's run time, and for a thread running on another core the
    /// kernel first brings that thread's count up to date there: on the 2-core VM a training
    /// step timed this way took a few per cent longer (BENCHMARKS.md, 2026-11-26: "which stages
    /// leave a core idle"). Use it to see which stages leave a core idle, and the plain timer for
    /// step times.
    pub fn with_process_cpu() -> Self {
        Self {
            process_cpu: true,
            ..Self::default()
        }
    }

    /// The totals since the last call, emptying the table.
    pub fn take(&self) -> BTreeMap<String, StageTime> {
        std::mem::take(&mut *self.totals.lock().unwrap_or_else(PoisonError::into_inner))
    }
}

/// CPU time used so far by every thread of this process, at nanosecond resolution (unlike
/// [`process_cpu_times`], which counts clock ticks); zero off Unix.
pub fn process_cpu_clock() -> Duration {
    #[cfg(unix)]
    {
        let mut ts = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `ts` is a valid, writable timespec for the duration of the call.
        if unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) } == 0 {
            return Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32);
        }
    }
    Duration::ZERO
}

impl<S> Layer<S> for StageTimer
where
    S: Subscriber + for<'a> LookupSpan<'a>,
{
    fn enabled(&self, metadata: &Metadata<'_>, _ctx: Context<'_, S>) -> bool {
        // Stages are info/debug spans; trace spans are per-kernel detail whose bookkeeping
        // would cost more than the finest stage they split.
        metadata.is_span() && *metadata.level() <= tracing::Level::DEBUG
    }

    fn on_new_span(&self, attrs: &Attributes<'_>, id: &Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(id) else { return };
        let name = attrs.metadata().name();
        let path = span
            .parent()
            .and_then(|p| {
                p.extensions()
                    .get::<SpanClock>()
                    .map(|c| format!("{}/{name}", c.path))
            })
            .unwrap_or_else(|| name.to_string());
        span.extensions_mut().insert(SpanClock {
            path,
            entered: None,
        });
    }

    fn on_enter(&self, id: &Id, ctx: Context<'_, S>) {
        if let Some(span) = ctx.span(id)
            && let Some(clock) = span.extensions_mut().get_mut::<SpanClock>()
        {
            let cpu = if self.process_cpu {
                process_cpu_clock()
            } else {
                Duration::ZERO
            };
            clock.entered = Some((Instant::now(), cpu));
        }
    }

    fn on_exit(&self, id: &Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(id) else { return };
        let mut ext = span.extensions_mut();
        let Some(clock) = ext.get_mut::<SpanClock>() else {
            return;
        };
        if let Some((wall, cpu)) = clock.entered.take() {
            let wall = wall.elapsed();
            let cpu = if self.process_cpu {
                process_cpu_clock().saturating_sub(cpu)
            } else {
                Duration::ZERO
            };
            let mut totals = self.totals.lock().unwrap_or_else(PoisonError::into_inner);
            let total = totals.entry(clock.path.clone()).or_default();
            total.wall += wall;
            total.cpu += cpu;
        }
    }
}

/// CPU time (user + system) this process has used, from `/proc/self/stat`; `None` where that
/// file does not exist (not Linux). Resolution: one clock tick (10 ms at the usual 100 Hz).
pub fn process_cpu_seconds() -> Option<f64> {
    process_cpu_times().map(|t| t.user + t.system)
}

/// CPU seconds a process has spent in user and in kernel mode.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CpuTimes {
    /// In the program's own code and its libraries.
    pub user: f64,
    /// In the kernel on its behalf: system calls and page faults (zero-filling fresh memory).
    pub system: f64,
}

/// [`CpuTimes`] of this process so far, from `/proc/self/stat`; `None` off Linux.
pub fn process_cpu_times() -> Option<CpuTimes> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name (which may hold spaces): state is field 3,
    // utime and stime are fields 14 and 15, in clock ticks.
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // USER_HZ is 100 on every Linux architecture Rust targets (it is fixed by the ABI).
    Some(CpuTimes {
        user: utime / 100.0,
        system: stime / 100.0,
    })
}

/// The process's peak resident memory so far in MiB (`VmHWM` of `/proc/self/status`); `None`
/// off Linux.
pub fn peak_resident_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kib: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kib / 1024.0)
}

/// The median of `values` (the upper middle one for an even count); `None` when empty.
pub fn median(values: &[f64]) -> Option<f64> {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracing_subscriber::layer::SubscriberExt;

    #[test]
    fn process_figures_are_read_on_linux() {
        if cfg!(target_os = "linux") {
            let t = process_cpu_times().expect("/proc/self/stat");
            assert!(t.user >= 0.0 && t.system >= 0.0);
            let before = peak_resident_mib().expect("/proc/self/status");
            let block = vec![1u8; 64 << 20];
            std::hint::black_box(&block);
            let after = peak_resident_mib().expect("/proc/self/status");
            assert!(
                after >= before + 60.0,
                "peak {before} → {after} MiB after touching 64 MiB"
            );
        }
    }

    #[test]
    fn nested_and_repeated_spans_sum_per_path() {
        let timer = StageTimer::default();
        let subscriber = tracing_subscriber::registry().with(timer.clone());
        tracing::subscriber::with_default(subscriber, || {
            let _step = tracing::info_span!("step").entered();
            for _ in 0..3 {
                let _r = tracing::debug_span!("render").entered();
                std::thread::sleep(Duration::from_millis(2));
            }
            // Trace spans are not timed.
            let _t = tracing::trace_span!("kernel").entered();
        });
        let totals = timer.take();
        let render = totals["step/render"].wall;
        assert!(render >= Duration::from_millis(6), "{totals:?}");
        assert!(
            totals["step"].wall >= render,
            "a parent includes its children"
        );
        assert!(!totals.keys().any(|k| k.contains("kernel")), "{totals:?}");
        assert!(timer.take().is_empty(), "take empties the table");
    }

    #[test]
    fn cpu_time_and_median() {
        if cfg!(target_os = "linux") {
            assert!(process_cpu_seconds().is_some_and(|s| s >= 0.0));
        }
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[]), None);
    }
}
