//! Kernel launches on the CubeCL devices (wgpu), counted at the launch site, and the
//! read-backs (syncs) between them.
//!
//! At the quickstart's size a GPU training step is bound by how many kernels it launches, not by
//! what they compute (BENCHMARKS.md, "On a GPU"): the launch count is the figure to drive down,
//! and it needs no GPU to read: lavapipe launches the same kernels as a card (to within 0.1 % in
//! BENCHMARKS.md, "On a GPU (NVIDIA H200, 2026-11-26, 2b993fa)").
//!
//! CubeCL calls an installed [`LaunchObserver`] on the issuing thread for every kernel, before it
//! reaches the server. [`LaunchCounter`] tallies those calls per kernel name; with
//! [`KernelTiming::Resolved`] it also asks CubeCL to time each launch on the device and sums the
//! durations. Resolved timing reads every measurement back before the next launch, so kernels
//! run one at a time: the per-kernel times say where device time goes, and a step timed with
//! them on is not the step's time (the benchmarks report both, and say which is which).
//!
//! Launch sites say little on their own with Burn's fusion on: its ops run on the fusion
//! stream's thread, where no model span is open, so most launches land under `(no span)`.
//! [`StageAttribution`] fixes that for diagnosis (`train-bench --attribute-launches`): a
//! `tracing` layer that, on the model's thread, waits for the device at every stage boundary
//! (a read-back, which drains the stream) and files every launch under the stage the model was
//! in when it was queued (`launches_per_step_by_stage`). The waits serialise the step, so its
//! time is not the step's time, and fusion cannot fuse across a boundary (a few more launches).
//! Under it each stage's launches are also split by kernel (`launches_per_step_by_stage_kernel`,
//! keys `stage :: kernel`): where a kernel's count comes from is what picks the next change.
//!
//! ```no_run
//! use lifegom_cli::launches::{KernelTiming, LaunchCounter};
//! let counter = LaunchCounter::install(KernelTiming::Off);
//! // ... one step on a wgpu device ...
//! let step = counter.take();
//! println!("{} launches", step.total_launches());
//! ```

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use burn_cubecl::cubecl::config::{TypeNameFormatLevel, type_name_format};
use burn_cubecl::cubecl::logging::{
    LaunchObservation, LaunchObserver, TimingMethod, TimingRequest,
};

/// Whether each launch is also timed on the device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum KernelTiming {
    /// Count only: launches run as they would unobserved.
    #[default]
    Off,
    /// Time every launch, reading the measurement back before the next one (module docs).
    Resolved,
}

impl KernelTiming {
    /// The benchmarks' `--kernel-times` flag.
    pub fn from_flag(kernel_times: bool) -> Self {
        if kernel_times {
            Self::Resolved
        } else {
            Self::Off
        }
    }

    /// The benchmark JSON's `kernel_timing` value.
    pub fn name(self) -> &'static str {
        match self {
            Self::Off => "off",
            Self::Resolved => "resolved",
        }
    }
}

/// One kernel's launches and device time over a stretch of work.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct KernelTally {
    /// Launches issued.
    pub launches: u64,
    /// Summed device time of the timed launches (zero unless timing was asked for).
    pub device_time: Duration,
    /// Launches whose time came from the host clock around a blocking submit rather than a
    /// device timestamp (wgpu falls back to it once its timestamp queries run out).
    pub host_timed: u64,
}

impl KernelTally {
    /// Adds `other`'s launches and times to this one's.
    fn merge(&mut self, other: &KernelTally) {
        self.launches += other.launches;
        self.device_time += other.device_time;
        self.host_timed += other.host_timed;
    }
}

/// Launch tallies over a stretch of work.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LaunchTally {
    /// Per kernel, keyed by the kernel's short name (generics dropped, as CubeCL's own
    /// profiling log names them).
    pub kernels: BTreeMap<String, KernelTally>,
    /// Launches per innermost `tracing` span open on the thread that issued them, or per model
    /// stage under a [`StageAttribution`].
    pub by_span: BTreeMap<String, u64>,
    /// Launches per model stage and kernel short name, keyed `stage :: kernel`; empty unless a
    /// [`StageAttribution`] was installed.
    pub by_stage_kernel: BTreeMap<String, u64>,
    /// Device time of the timed launches per innermost span open when each was timed (empty
    /// unless timing was asked for). Burn's ops run on its fusion stream's thread, where no model
    /// span is open, also with `LIFEGOM_FUSION=off` (which removes the fusers, not the stream):
    /// they are filed under `(no span)`, and the named spans hold the kernels launched on the
    /// model's thread, such as the autodiff backward's and the rasterizer's (design.md §1.4).
    pub device_time_by_span: BTreeMap<String, Duration>,
    /// Read-backs from the device per tensor name
    /// ([`lifegom_render::readback::take_device_reads`]): each a sync, after which the card
    /// idles until the host queues more.
    pub device_reads: BTreeMap<String, u64>,
}

impl LaunchTally {
    /// Every launch in the tally.
    pub fn total_launches(&self) -> u64 {
        self.kernels.values().map(|k| k.launches).sum()
    }

    /// Summed device time of every timed launch.
    pub fn total_device_time(&self) -> Duration {
        self.kernels.values().map(|k| k.device_time).sum()
    }

    /// Adds `other`'s tallies to this one's.
    pub fn add(&mut self, other: &LaunchTally) {
        for (name, k) in &other.kernels {
            self.kernels.entry(name.clone()).or_default().merge(k);
        }
        for (span, n) in &other.by_span {
            *self.by_span.entry(span.clone()).or_default() += n;
        }
        for (span, t) in &other.device_time_by_span {
            *self.device_time_by_span.entry(span.clone()).or_default() += *t;
        }
        for (key, n) in &other.by_stage_kernel {
            *self.by_stage_kernel.entry(key.clone()).or_default() += n;
        }
        for (tensor, n) in &other.device_reads {
            *self.device_reads.entry(tensor.clone()).or_default() += n;
        }
    }

    /// The benchmark JSON fields for `per_step` tallies (one per timed step):
    /// `kernel_launches` (median per step), `top_kernels`, the `top` kernels by launches
    /// per step (with device milliseconds per step when they were timed), `device_reads`
    /// (median read-backs per step) and `device_reads_by_tensor` (per step).
    pub fn json_fields(
        per_step: &[LaunchTally],
        top: usize,
    ) -> serde_json::Map<String, serde_json::Value> {
        let mut fields = serde_json::Map::new();
        if per_step.is_empty() {
            return fields;
        }
        let round2 = |x: f64| (x * 100.0).round() / 100.0;
        let median_per_step = |count: &dyn Fn(&LaunchTally) -> u64| {
            let counts: Vec<f64> = per_step.iter().map(|t| count(t) as f64).collect();
            serde_json::json!(crate::profile::median(&counts).unwrap_or(f64::NAN).round())
        };
        let steps = per_step.len() as f64;
        let mean_per_step = |counts: &BTreeMap<String, u64>| {
            let means: serde_json::Map<String, serde_json::Value> = counts
                .iter()
                .map(|(key, n)| (key.clone(), serde_json::json!(round2(*n as f64 / steps))))
                .collect();
            serde_json::Value::Object(means)
        };
        fields.insert(
            "kernel_launches".into(),
            median_per_step(&LaunchTally::total_launches),
        );
        let mut sum = LaunchTally::default();
        for t in per_step {
            sum.add(t);
        }
        let timed = sum.total_device_time() > Duration::ZERO;
        let mut kernels: Vec<(&String, &KernelTally)> = sum.kernels.iter().collect();
        let key = |k: &KernelTally| {
            if timed {
                k.device_time.as_secs_f64()
            } else {
                k.launches as f64
            }
        };
        kernels.sort_by(|a, b| key(b.1).total_cmp(&key(a.1)).then(a.0.cmp(b.0)));
        let top_kernels: Vec<serde_json::Value> = kernels
            .iter()
            .take(top)
            .map(|(name, k)| {
                let mut entry = serde_json::json!({
                    "kernel": name,
                    "launches_per_step": round2(k.launches as f64 / steps),
                });
                if timed {
                    entry["device_ms_per_step"] =
                        serde_json::json!(round2(k.device_time.as_secs_f64() * 1e3 / steps));
                }
                entry
            })
            .collect();
        fields.insert("top_kernels".into(), serde_json::Value::Array(top_kernels));
        fields.insert(
            "device_reads".into(),
            median_per_step(&|t| t.device_reads.values().sum()),
        );
        fields.insert(
            "device_reads_by_tensor".into(),
            mean_per_step(&sum.device_reads),
        );
        fields.insert(
            "launches_per_step_by_span".into(),
            mean_per_step(&sum.by_span),
        );
        if !sum.by_stage_kernel.is_empty() {
            fields.insert(
                "launches_per_step_by_stage_kernel".into(),
                mean_per_step(&sum.by_stage_kernel),
            );
        }
        if timed {
            fields.insert(
                "kernel_device_ms_per_step".into(),
                serde_json::json!(round2(sum.total_device_time().as_secs_f64() * 1e3 / steps)),
            );
            let ms_by_span: serde_json::Map<String, serde_json::Value> = sum
                .device_time_by_span
                .iter()
                .map(|(span, t)| {
                    let ms = round2(t.as_secs_f64() * 1e3 / steps);
                    (span.clone(), serde_json::json!(ms))
                })
                .collect();
            fields.insert(
                "kernel_device_ms_per_step_by_span".into(),
                serde_json::Value::Object(ms_by_span),
            );
            let host_timed: u64 = sum.kernels.values().map(|k| k.host_timed).sum();
            fields.insert("host_timed_launches".into(), serde_json::json!(host_timed));
        }
        fields
    }
}

/// The model's stage path while a [`StageAttribution`] is installed (`None` otherwise); every
/// launch is filed under it. Paths are interned: a run has a few dozen.
static MODEL_STAGE: Mutex<Option<&'static str>> = Mutex::new(None);

/// `path` as a `&'static str`, leaked once per distinct path.
fn intern(path: String) -> &'static str {
    static PATHS: Mutex<BTreeMap<String, &'static str>> = Mutex::new(BTreeMap::new());
    let mut paths = PATHS.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(interned) = paths.get(&path) {
        return interned;
    }
    let interned: &'static str = Box::leak(path.clone().into_boxed_str());
    paths.insert(path, interned);
    interned
}

/// A `tracing` layer that files every kernel launch under the model stage (span path) that
/// queued it (module docs): on the thread that made it, each span's entry and exit first wait
/// for the device with `drain`, so the launches of the stage just left have been issued, then
/// name the stage now current. Spans on other threads (the fusion stream's, a planning thread)
/// neither wait nor change the stage: only one thread runs the model.
pub struct StageAttribution {
    model_thread: std::thread::ThreadId,
    drain: Box<dyn Fn() + Send + Sync>,
}

impl StageAttribution {
    /// Attribution to the spans of the calling thread; `drain` waits until every kernel queued
    /// so far has been launched (e.g. reading a fresh one-element tensor back on the model's
    /// device). Launches before the first span are filed under `(no stage)`.
    pub fn new(drain: impl Fn() + Send + Sync + 'static) -> Self {
        *MODEL_STAGE.lock().unwrap_or_else(PoisonError::into_inner) = Some("(no stage)");
        Self {
            model_thread: std::thread::current().id(),
            drain: Box::new(drain),
        }
    }

    /// On the model's thread: waits for the device, then makes `stage` (a span path, or none
    /// when the outermost span was left) the current one.
    fn switch(&self, stage: impl FnOnce() -> String) {
        if std::thread::current().id() != self.model_thread {
            return;
        }
        // Before any lock of the registry's: the stream's thread enters spans of its own while
        // it runs what the drain waits for.
        (self.drain)();
        let stage = intern(stage());
        *MODEL_STAGE.lock().unwrap_or_else(PoisonError::into_inner) = Some(stage);
    }
}

impl Drop for StageAttribution {
    fn drop(&mut self) {
        *MODEL_STAGE.lock().unwrap_or_else(PoisonError::into_inner) = None;
    }
}

/// The path `outer/…/inner` of the span `id` (its own name last), or of its parent only.
fn span_path<S>(
    id: &tracing::span::Id,
    ctx: &tracing_subscriber::layer::Context<'_, S>,
    with_self: bool,
) -> String
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
{
    let Some(span) = ctx.span(id) else {
        return "(no stage)".into();
    };
    let mut names: Vec<&str> = span.scope().map(|s| s.name()).collect();
    if !with_self {
        names.remove(0);
    }
    names.reverse();
    if names.is_empty() {
        "(no stage)".into()
    } else {
        names.join("/")
    }
}

impl<S> tracing_subscriber::Layer<S> for StageAttribution
where
    S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
{
    fn on_enter(&self, id: &tracing::span::Id, ctx: tracing_subscriber::layer::Context<'_, S>) {
        self.switch(|| span_path(id, &ctx, true));
    }

    fn on_exit(&self, id: &tracing::span::Id, ctx: tracing_subscriber::layer::Context<'_, S>) {
        self.switch(|| span_path(id, &ctx, false));
    }
}

/// The observer CubeCL calls; its tally is shared with the [`LaunchCounter`] that installed it.
struct Observer {
    timing: KernelTiming,
    tally: Mutex<BTreeMap<&'static str, KernelTally>>,
    /// Launches per innermost `tracing` span open on the issuing thread: which stage of the
    /// model issues them (the stage names of `train-bench`'s `stages_ms`).
    by_span: Mutex<BTreeMap<&'static str, u64>>,
    /// Under a [`StageAttribution`]: launches per (stage, raw kernel name).
    by_stage_kernel: Mutex<BTreeMap<(&'static str, &'static str), u64>>,
    /// Device time per innermost span open on the thread when the launch was timed: under
    /// [`TimingRequest::Resolved`] that is the issuing thread, right after the launch.
    time_by_span: Mutex<BTreeMap<&'static str, Duration>>,
}

/// The model stage of a [`StageAttribution`] when one is installed, else the name of the
/// innermost `tracing` span open on this thread.
fn current_span() -> &'static str {
    model_stage().unwrap_or_else(|| {
        tracing::Span::current()
            .metadata()
            .map_or("(no span)", |m| m.name())
    })
}

/// The model stage when a [`StageAttribution`] is installed.
fn model_stage() -> Option<&'static str> {
    *MODEL_STAGE.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Observer {
    fn with_kernel(&self, kernel: &'static str, f: impl FnOnce(&mut KernelTally)) {
        // A panic elsewhere while the lock was held leaves counts that are still counts.
        let mut tally = self.tally.lock().unwrap_or_else(PoisonError::into_inner);
        f(tally.entry(kernel).or_default());
    }
}

impl LaunchObserver for Observer {
    fn launched(&self, kernel: &'static str) {
        self.with_kernel(kernel, |k| k.launches += 1);
        let stage = model_stage();
        let span = stage.unwrap_or_else(current_span);
        *self
            .by_span
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(span)
            .or_default() += 1;
        if stage.is_some() {
            *self
                .by_stage_kernel
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .entry((span, kernel))
                .or_default() += 1;
        }
    }

    fn timing(&self) -> TimingRequest {
        match self.timing {
            KernelTiming::Off => TimingRequest::None,
            KernelTiming::Resolved => TimingRequest::Resolved,
        }
    }

    fn timed(&self, kernel: &'static str, duration: Duration, method: TimingMethod) {
        self.with_kernel(kernel, |k| {
            k.device_time += duration;
            if method == TimingMethod::System {
                k.host_timed += 1;
            }
        });
        *self
            .time_by_span
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(current_span())
            .or_default() += duration;
    }
}

/// Counts every kernel launch of the process from [`install`](Self::install) until it drops.
///
/// One at a time per process: CubeCL has a single observer slot, and a second counter replaces
/// the first for its lifetime.
pub struct LaunchCounter {
    observer: Arc<Observer>,
    _observation: LaunchObservation,
}

impl LaunchCounter {
    /// Starts counting when `device` is a CubeCL device (wgpu); `None` on the CPU backends,
    /// which launch no kernels.
    pub fn on_cube_device(device: &burn::tensor::Device, timing: KernelTiming) -> Option<Self> {
        (!lifegom_render::device::runs_on_host(device)).then(|| Self::install(timing))
    }

    /// The benchmark JSON fields of `per_step` tallies ([`LaunchTally::json_fields`]) and the
    /// counter's `kernel_timing`.
    pub fn json_fields(
        &self,
        per_step: &[LaunchTally],
        top: usize,
    ) -> serde_json::Map<String, serde_json::Value> {
        let mut fields = LaunchTally::json_fields(per_step, top);
        fields.insert(
            "kernel_timing".into(),
            serde_json::json!(self.observer.timing.name()),
        );
        // Under a stage attribution the tally's keys are model stages (module docs).
        if model_stage().is_some()
            && let Some(stages) = fields.remove("launches_per_step_by_span")
        {
            fields.insert("launches_per_step_by_stage".into(), stages);
        }
        fields
    }

    /// Starts counting.
    pub fn install(timing: KernelTiming) -> Self {
        let observer = Arc::new(Observer {
            timing,
            tally: Mutex::new(BTreeMap::new()),
            by_span: Mutex::new(BTreeMap::new()),
            by_stage_kernel: Mutex::new(BTreeMap::new()),
            time_by_span: Mutex::new(BTreeMap::new()),
        });
        let _observation = LaunchObservation::new(observer.clone());
        Self {
            observer,
            _observation,
        }
    }

    /// The launches since the last call (or since installing), by short kernel name, and the
    /// device read-backs since then.
    ///
    /// Launches are counted when issued, so call this after the work's results were read back
    /// (the benchmarks' steps end in a read-back) to attribute them to the right stretch.
    pub fn take(&self) -> LaunchTally {
        let raw = drain(&self.observer.tally);
        let mut tally = LaunchTally {
            by_span: owned_keys(drain(&self.observer.by_span)),
            device_time_by_span: owned_keys(drain(&self.observer.time_by_span)),
            device_reads: owned_keys(lifegom_render::readback::take_device_reads()),
            ..LaunchTally::default()
        };
        for (kernel, k) in raw {
            let name = type_name_format(kernel, TypeNameFormatLevel::Short);
            tally.kernels.entry(name).or_default().merge(&k);
        }
        for ((stage, kernel), n) in drain(&self.observer.by_stage_kernel) {
            let name = type_name_format(kernel, TypeNameFormatLevel::Short);
            *tally
                .by_stage_kernel
                .entry(format!("{stage} :: {name}"))
                .or_default() += n;
        }
        tally
    }
}

/// Takes a shared map's entries, leaving it empty. A panic elsewhere while the lock was held
/// leaves counts that are still counts.
fn drain<K: Ord, V>(map: &Mutex<BTreeMap<K, V>>) -> BTreeMap<K, V> {
    std::mem::take(&mut *map.lock().unwrap_or_else(PoisonError::into_inner))
}

/// The map with its span names owned.
fn owned_keys<V>(map: BTreeMap<&'static str, V>) -> BTreeMap<String, V> {
    map.into_iter().map(|(k, v)| (k.to_owned(), v)).collect()
}

impl std::fmt::Debug for LaunchCounter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LaunchCounter")
            .field("timing", &self.observer.timing)
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The JSON fields: the median of the per-step totals and the top kernels, ordered by
    /// launches, then by name; the median read-backs per step and each tensor's mean.
    #[test]
    fn json_fields_median_and_top() {
        let step = |pairs: &[(&str, u64)], reads: u64| LaunchTally {
            kernels: pairs
                .iter()
                .map(|(n, c)| {
                    (
                        n.to_string(),
                        KernelTally {
                            launches: *c,
                            ..KernelTally::default()
                        },
                    )
                })
                .collect(),
            by_span: [("fusion".to_owned(), pairs.iter().map(|(_, c)| c).sum())].into(),
            device_reads: [("loss".to_owned(), 1), ("count".to_owned(), reads)].into(),
            ..LaunchTally::default()
        };
        let steps = [
            step(&[("add", 10), ("mul", 5)], 3),
            step(&[("add", 12), ("mul", 5), ("matmul", 1)], 1),
            step(&[("add", 20), ("mul", 5)], 1),
        ];
        let fields = LaunchTally::json_fields(&steps, 2);
        assert_eq!(fields["kernel_launches"], serde_json::json!(18.0));
        let top = fields["top_kernels"].as_array().expect("an array");
        assert_eq!(top.len(), 2);
        assert_eq!(top[0]["kernel"], "add");
        assert_eq!(top[0]["launches_per_step"], serde_json::json!(14.0));
        assert_eq!(top[1]["kernel"], "mul");
        assert_eq!(
            fields["launches_per_step_by_span"]["fusion"],
            serde_json::json!(19.33)
        );
        assert!(!fields.contains_key("kernel_device_ms_per_step"));
        assert!(!fields.contains_key("kernel_device_ms_per_step_by_span"));
        assert!(!fields.contains_key("launches_per_step_by_stage_kernel"));
        assert_eq!(fields["device_reads"], serde_json::json!(2.0));
        assert_eq!(
            fields["device_reads_by_tensor"]["count"],
            serde_json::json!(1.67)
        );
        assert_eq!(
            fields["device_reads_by_tensor"]["loss"],
            serde_json::json!(1.0)
        );
        assert!(LaunchTally::json_fields(&[], 3).is_empty());
    }

    /// Timed steps: kernels ordered by device time, and the device time per span averaged
    /// over the steps.
    #[test]
    fn json_fields_device_time_by_span() {
        let ms = Duration::from_millis;
        let step = |conv: u64, add: u64| LaunchTally {
            kernels: [
                (
                    "conv".to_owned(),
                    KernelTally {
                        launches: 1,
                        device_time: ms(conv),
                        host_timed: 0,
                    },
                ),
                (
                    "add".to_owned(),
                    KernelTally {
                        launches: 9,
                        device_time: ms(add),
                        host_timed: 0,
                    },
                ),
            ]
            .into(),
            by_span: [("encoder".to_owned(), 10)].into(),
            device_time_by_span: [
                ("encoder".to_owned(), ms(conv)),
                ("fusion".to_owned(), ms(add)),
            ]
            .into(),
            by_stage_kernel: [("encoder :: conv".to_owned(), 1 + conv / 50)].into(),
            device_reads: BTreeMap::new(),
        };
        let fields = LaunchTally::json_fields(&[step(30, 2), step(50, 4)], 1);
        assert_eq!(fields["top_kernels"][0]["kernel"], "conv");
        assert_eq!(fields["kernel_device_ms_per_step"], serde_json::json!(43.0));
        let by_span = &fields["kernel_device_ms_per_step_by_span"];
        assert_eq!(by_span["encoder"], serde_json::json!(40.0));
        assert_eq!(by_span["fusion"], serde_json::json!(3.0));
        assert_eq!(
            fields["launches_per_step_by_stage_kernel"]["encoder :: conv"],
            serde_json::json!(1.5)
        );
    }

    /// A stage attribution names the model thread's span path on every entry and exit, after
    /// waiting for the device each time; spans on another thread neither wait nor move the
    /// stage; dropping it restores span names.
    #[test]
    fn stage_attribution_follows_the_model_thread() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        use tracing_subscriber::layer::SubscriberExt;

        let drains = Arc::new(AtomicUsize::new(0));
        let counted = drains.clone();
        let attribution = StageAttribution::new(move || {
            counted.fetch_add(1, Ordering::SeqCst);
        });
        let subscriber = tracing_subscriber::registry().with(attribution);
        tracing::subscriber::with_default(subscriber, || {
            assert_eq!(current_span(), "(no stage)");
            let outer = tracing::info_span!("step").entered();
            assert_eq!(current_span(), "step");
            {
                let _inner = tracing::info_span!("fusion").entered();
                assert_eq!(current_span(), "step/fusion");
                // Another thread's span (the fusion stream's, a planning thread) changes nothing.
                let dispatch = tracing::dispatcher::get_default(|d| d.clone());
                std::thread::spawn(move || {
                    tracing::dispatcher::with_default(&dispatch, || {
                        let _other = tracing::info_span!("elsewhere").entered();
                    });
                })
                .join()
                .expect("the thread ran");
                assert_eq!(current_span(), "step/fusion");
            }
            assert_eq!(current_span(), "step");
            drop(outer);
            assert_eq!(current_span(), "(no stage)");
        });
        // Two entries and two exits on the model thread, none for the other thread's span.
        assert_eq!(drains.load(Ordering::SeqCst), 4);
        assert_eq!(current_span(), "(no span)");
    }
}
