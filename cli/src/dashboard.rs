//! What `lifegom-train` shows while it trains (design.md §9.6).
//!
//! - **In a terminal**: burn-train's dashboard, the renderer a burn-train `Learner` shows
//!   (`TuiMetricsRendererWrapper`, its `tui` feature): the weighted loss terms, the target-view
//!   PSNR after each feedback step `t`, steps per second, and at every validation the PSNR of
//!   each `t` on the unseen subjects, drawn against the training curves of the same name; a
//!   progress bar over the run's steps. The dashboard puts the terminal in raw mode, where
//!   Ctrl-C is a key press, not a signal: `q` (then confirming) asks the run to stop, and the
//!   loop ends after the current step with a checkpoint, as Ctrl-C does elsewhere.
//! - **Otherwise** (a pipe, a log file, a batch job): one progress line on stderr (indicatif's,
//!   which draws nothing when stderr is not a terminal either), or nothing at all (the tests).
//!
//! Either way `metrics.jsonl` and `validation.jsonl` stay the run's record; the display only
//! shows them.

use std::collections::HashSet;
use std::io::IsTerminal;
use std::sync::Arc;

use burn_train::Interrupter;
use burn_train::logger::TrainingProgressLogger;
use burn_train::metric::{
    MetricDefinition, MetricEntry, MetricId, NumericAttributes, NumericEntry, SerializedEntry,
};
use burn_train::renderer::tui::TuiMetricsRendererWrapper;
use burn_train::renderer::{MetricState, MetricsRenderer, MetricsRendererTraining};
use lifegom_train::trainer::StepStats;

/// Which display a run gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DisplayKind {
    /// burn-train's terminal dashboard.
    Dashboard,
    /// One progress line on stderr.
    Line,
    /// Nothing.
    Hidden,
}

impl DisplayKind {
    /// The dashboard when asked for progress and stdout is a terminal, the progress line when
    /// asked for progress elsewhere, nothing otherwise. Under an MPI launcher the line: Open
    /// MPI hands its ranks a pseudo-terminal even when `mpirun`'s own output is a file, and
    /// forwards no key presses to them.
    pub fn choose(progress: bool) -> Self {
        let launched = lifegom_train::data_parallel::launcher_rank_variable().is_some();
        match (progress, std::io::stdout().is_terminal() && !launched) {
            (false, _) => Self::Hidden,
            (true, true) => Self::Dashboard,
            (true, false) => Self::Line,
        }
    }
}

/// The running display (module docs).
pub enum Display {
    /// burn-train's dashboard.
    Dashboard(Box<Dashboard>),
    /// A progress line (hidden when nothing should show).
    Line(indicatif::ProgressBar),
}

impl Display {
    /// Starts a display of a run at step `first` of `total`.
    pub fn start(kind: DisplayKind, first: u64, total: u64) -> Self {
        match kind {
            DisplayKind::Dashboard => Self::Dashboard(Box::new(Dashboard::start(first, total))),
            DisplayKind::Line => {
                let bar = indicatif::ProgressBar::new(total);
                bar.set_style(
                    indicatif::ProgressStyle::with_template(
                        "{elapsed_precise} [{bar:30}] {pos}/{len} {per_sec} ETA {eta} {msg}",
                    )
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
                );
                bar.set_position(first);
                Self::Line(bar)
            }
            DisplayKind::Hidden => Self::Line(indicatif::ProgressBar::hidden()),
        }
    }

    /// Shows the step that just ended.
    pub fn step(&mut self, stats: &StepStats) {
        match self {
            Self::Dashboard(d) => d.step(stats),
            Self::Line(bar) => {
                let total = stats
                    .losses
                    .iter()
                    .find(|(n, _)| n == "total")
                    .map_or(f64::NAN, |(_, v)| *v);
                bar.set_position(stats.step);
                bar.set_message(format!("loss {total:.4} PSNR {:.2} dB", stats.psnr_target));
            }
        }
    }

    /// Shows a validation's PSNR of each feedback step (dB, `t = 1…T`).
    pub fn validation(&mut self, psnr: &[f64]) {
        if let Self::Dashboard(d) = self {
            d.validation(psnr);
        }
    }

    /// Whether the user asked the dashboard to stop the run.
    pub fn stop_requested(&self) -> bool {
        match self {
            Self::Dashboard(d) => d.interrupter.should_stop(),
            Self::Line(_) => false,
        }
    }

    /// Closes the display (the dashboard gives the terminal back).
    pub fn finish(self) {
        match self {
            Self::Dashboard(mut d) => {
                d.renderer.end_split();
                // The dashboard prints burn-train's summary, which needs its event store: none.
                let _ = d.renderer.on_train_end(None);
            }
            Self::Line(bar) => bar.finish_and_clear(),
        }
    }
}

/// burn-train's dashboard, fed from the trainer's statistics.
pub struct Dashboard {
    renderer: TuiMetricsRendererWrapper,
    interrupter: Interrupter,
    registered: HashSet<String>,
}

/// Which curve a value belongs to.
#[derive(Clone, Copy)]
enum Split {
    Train,
    Valid,
}

impl Dashboard {
    fn start(first: u64, total: u64) -> Self {
        let interrupter = Interrupter::new();
        let mut renderer = TuiMetricsRendererWrapper::new(interrupter.clone(), None);
        // The dashboard counts epochs and items; a run here is one pass over `total` steps.
        renderer.start(1, 0, Some(total as usize), Some("lifegom-train"));
        renderer.start_split("train", total as usize);
        renderer.update_split(first as usize);
        Self {
            renderer,
            interrupter,
            registered: HashSet::new(),
        }
    }

    fn step(&mut self, stats: &StepStats) {
        for (name, value) in &stats.losses {
            let title = if name == "total" {
                "Loss".to_string()
            } else {
                format!("Loss {name}")
            };
            self.value(Split::Train, &title, *value, None, false);
        }
        for (t, psnr) in stats.psnr_target_steps.iter().enumerate() {
            self.value(Split::Train, &psnr_name(t), *psnr, Some("dB"), true);
        }
        if stats.seconds > 0.0 {
            self.value(
                Split::Train,
                "Steps per second",
                1.0 / stats.seconds,
                Some("steps/s"),
                true,
            );
        }
        self.renderer.update_split(stats.step as usize);
    }

    fn validation(&mut self, psnr: &[f64]) {
        for (t, value) in psnr.iter().enumerate() {
            self.value(Split::Valid, &psnr_name(t), *value, Some("dB"), true);
        }
    }

    /// Hands one value of the curve `name` to the renderer, registering the curve first.
    fn value(
        &mut self,
        split: Split,
        name: &str,
        value: f64,
        unit: Option<&str>,
        higher_is_better: bool,
    ) {
        let id = MetricId::new(Arc::new(name.to_string()));
        if self.registered.insert(name.to_string()) {
            self.renderer.register_metric(MetricDefinition {
                metric_id: id.clone(),
                name: Arc::new(name.to_string()),
                description: None,
                attributes: NumericAttributes {
                    unit: unit.map(str::to_string),
                    higher_is_better,
                }
                .into(),
            });
        }
        let shown = match unit {
            Some(u) => format!("{value:.3} {u}"),
            None => format!("{value:.5}"),
        };
        let entry = MetricEntry::new(id, SerializedEntry::new(shown, value.to_string()));
        let state = MetricState::Numeric(entry, Some(NumericEntry::Value(value)));
        match split {
            Split::Train => self.renderer.update_train(state),
            Split::Valid => self.renderer.update_valid(state),
        }
    }
}

/// The curve of the target PSNR after feedback step `t` (0-based): one name for training and
/// validation, so the dashboard draws both in one chart.
fn psnr_name(t: usize) -> String {
    format!("PSNR t={}", t + 1)
}
