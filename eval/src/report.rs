//! Evaluation outputs: `per_subject.csv`, `per_view.csv`, `summary.json` and `report.md`, plus
//! the accuracy-vs-time table and Pareto plot of a sweep.
//!
//! LPIPS and FID appear only when computed from real weights; otherwise the report says
//! [`WEIGHTS_MISSING`] and the fields are `null`, never a
//! substitute number.

use crate::error::EvalError;
use lifegom_render::atomic_file::write_atomic;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::evaluate::{SplitScores, ViewScore, mean_of, per_subject};
use crate::metrics::{ErrorByRegion, SILHOUETTE_BAND_PX};
use crate::per_scene::FitPoint;
use crate::plot::{Chart, PALETTE, Scale, Series, Style, render_panels};
use crate::validation::StepScore;

/// The line printed and written when perceptual weights are absent.
pub const WEIGHTS_MISSING: &str =
    "LPIPS/FID not computed: weights missing (`lifegom-weights fetch` gets them; see README)";

/// Means over a split (the numbers of a results table row).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Summary {
    /// Views scored.
    pub views: usize,
    /// Subjects scored.
    pub subjects: usize,
    /// Mean PSNR (dB).
    pub psnr: f64,
    /// Mean SSIM.
    pub ssim: f64,
    /// Mean LPIPS-Alex ×1000 (LPIPS*), when computed.
    pub lpips_alex_x1000: Option<f64>,
    /// Mean LPIPS-VGG ×1000, when computed.
    pub lpips_vgg_x1000: Option<f64>,
    /// FID between the prediction and ground-truth crops, when computed.
    pub fid: Option<f64>,
    /// Images per set FID compared (FIDs are comparable only at equal counts).
    #[serde(default)]
    pub fid_images: Option<usize>,
    /// Mean reconstruction time per subject (ms).
    pub recon_ms: f64,
    /// Mean render time per view (ms).
    pub render_ms: f64,
    /// Gaussians per rendered view.
    pub num_gaussians: usize,
    /// Feedback steps.
    pub iterations: usize,
    /// Subdivisions.
    pub subdivide: u32,
    /// Mean MSE split by the silhouette, when the views had masks.
    #[serde(default)]
    pub regions: Option<ErrorByRegion>,
}

impl Summary {
    /// Summarises a split's scores (`fid` computed elsewhere).
    pub fn of(scores: &SplitScores, fid: Option<f64>) -> Self {
        let subjects = per_subject(&scores.views);
        let recon: Vec<f64> = subjects
            .iter()
            .filter_map(|(_, v)| v.first().map(|x| x.recon_ms))
            .collect();
        Self {
            views: scores.views.len(),
            subjects: subjects.len(),
            psnr: mean_of(&scores.views, |v| Some(v.psnr)).unwrap_or(f64::NAN),
            ssim: mean_of(&scores.views, |v| Some(v.ssim)).unwrap_or(f64::NAN),
            lpips_alex_x1000: mean_of(&scores.views, |v| v.lpips_alex).map(|x| x * 1000.0),
            lpips_vgg_x1000: mean_of(&scores.views, |v| v.lpips_vgg).map(|x| x * 1000.0),
            fid,
            fid_images: fid.map(|_| scores.images.pred.len()),
            recon_ms: if recon.is_empty() {
                f64::NAN
            } else {
                recon.iter().sum::<f64>() / recon.len() as f64
            },
            render_ms: mean_of(&scores.views, |v| Some(v.render_ms)).unwrap_or(f64::NAN),
            num_gaussians: scores.num_gaussians,
            iterations: scores.iterations,
            subdivide: scores.subdivide,
            regions: {
                let errors: Vec<&ErrorByRegion> = scores
                    .views
                    .iter()
                    .filter_map(|v| v.regions.as_ref())
                    .collect();
                (!errors.is_empty()).then(|| ErrorByRegion::mean(errors))
            },
        }
    }
}

/// One row of the "Where the error sits" table.
fn region_row(name: &str, e: &ErrorByRegion) -> String {
    let total = e.total();
    let share = if total > 0.0 {
        format!("{:.0} %", 100.0 * e.silhouette / total)
    } else {
        "—".into()
    };
    format!(
        "| {name} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {share} |",
        total * 1e4,
        e.silhouette * 1e4,
        e.inside * 1e4,
        e.outside * 1e4,
        e.silhouette_foreground * 1e4,
        (e.silhouette - e.silhouette_foreground) * 1e4,
    )
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("n/a".into(), |x| format!("{x:.digits$}"))
}

/// A FID cell with its image count: `51.27 (n = 24)`.
fn fid_cell(fid: Option<f64>, images: Option<usize>) -> String {
    match (fid, images) {
        (Some(f), Some(n)) => format!("{f:.2} (n = {n})"),
        (f, _) => opt(f, 2),
    }
}

/// Said under every table with a FID.
pub const FID_NOTE: &str = "FID over a few dozen images is strongly biased upwards: it is comparable only between rows with the same image count n (the paper's 51.27 is over the whole THuman2.0 test split). LPIPS* is LPIPS × 1000, the paper's unit (its LPIPS* is the VGG one).";

/// Writes `per_view.csv` and `per_subject.csv`.
pub fn write_csvs(out: &Path, views: &[ViewScore]) -> Result<(), EvalError> {
    std::fs::create_dir_all(out).map_err(|e| EvalError::write(out, e))?;
    let mut s = String::from("subject,frame,psnr,ssim,lpips_alex,lpips_vgg,recon_ms,render_ms\n");
    for v in views {
        let _ = writeln!(
            s,
            "{},{},{:.4},{:.5},{},{},{:.1},{:.2}",
            v.subject,
            v.frame_name,
            v.psnr,
            v.ssim,
            opt(v.lpips_alex, 5),
            opt(v.lpips_vgg, 5),
            v.recon_ms,
            v.render_ms
        );
    }
    let path = out.join("per_view.csv");
    write_atomic(&path, s.as_bytes()).map_err(|e| EvalError::write(&path, e))?;
    let mut s = String::from(
        "subject,views,psnr,ssim,lpips_alex_x1000,lpips_vgg_x1000,recon_ms,render_ms\n",
    );
    for (subject, vs) in per_subject(views) {
        let _ = writeln!(
            s,
            "{},{},{:.4},{:.5},{},{},{:.1},{:.2}",
            subject,
            vs.len(),
            mean_of(&vs, |v| Some(v.psnr)).unwrap_or(f64::NAN),
            mean_of(&vs, |v| Some(v.ssim)).unwrap_or(f64::NAN),
            opt(mean_of(&vs, |v| v.lpips_alex).map(|x| x * 1000.0), 2),
            opt(mean_of(&vs, |v| v.lpips_vgg).map(|x| x * 1000.0), 2),
            vs.first().map_or(f64::NAN, |v| v.recon_ms),
            mean_of(&vs, |v| Some(v.render_ms)).unwrap_or(f64::NAN),
        );
    }
    let path = out.join("per_subject.csv");
    write_atomic(&path, s.as_bytes()).map_err(|e| EvalError::write(&path, e))?;
    Ok(())
}

/// One row of the accuracy-vs-time sweep.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepRow {
    /// Image side (px) the sweep point ran at.
    pub size: u32,
    /// The summary at this setting.
    pub summary: Summary,
}

/// Everything `report.md` shows.
#[derive(Debug, Clone, Default)]
pub struct Report {
    /// Heading.
    pub title: String,
    /// Free lines under the heading (command, checkpoint, machine, backend).
    pub context: Vec<String>,
    /// The model's summary.
    pub summary: Option<Summary>,
    /// Other trained models scored on the same views (name, summary), e.g. an earlier version
    /// of the demo model.
    pub other_models: Vec<(String, Summary)>,
    /// The baselines evaluated (name, summary), e.g. the template in one colour and projective
    /// texturing ([`crate::baselines`]).
    pub baselines: Vec<(String, Summary)>,
    /// Notes (e.g. [`WEIGHTS_MISSING`], random encoder init).
    pub notes: Vec<String>,
    /// Comparison sheets (relative paths under the report's folder).
    pub sheets: Vec<PathBuf>,
    /// Animations and other pictures (relative paths), with captions.
    pub pictures: Vec<(String, PathBuf)>,
    /// Accuracy-vs-time sweep rows.
    pub sweep: Vec<SweepRow>,
    /// The per-scene optimisation baseline after K gradient steps (same axes as the sweep).
    pub per_scene: Vec<FitPoint>,
    /// Each trained model's scores after every feedback step `t = 1..T` (name, scores).
    pub feedback_steps: Vec<(String, Vec<StepScore>)>,
}

fn table_row(name: &str, s: &Summary) -> String {
    format!(
        "| {name} | {} | {} | {:.2} | {:.4} | {} | {} | {} | {:.0} | {:.1} |",
        s.iterations,
        s.subdivide,
        s.psnr,
        s.ssim,
        opt(s.lpips_alex_x1000, 1),
        opt(s.lpips_vgg_x1000, 1),
        fid_cell(s.fid, s.fid_images),
        s.recon_ms,
        s.render_ms
    )
}

const TABLE_HEAD: &str = "| | T | subdiv | PSNR ↑ | SSIM ↑ | LPIPS*-alex ↓ | LPIPS*-vgg ↓ | FID ↓ | recon ms | render ms |\n|---|---|---|---|---|---|---|---|---|---|";

impl Report {
    /// Renders the markdown.
    pub fn markdown(&self) -> String {
        let mut md = format!("# {}\n\n", self.title);
        for line in &self.context {
            let _ = writeln!(md, "- {line}");
        }
        md.push('\n');
        for note in &self.notes {
            let _ = writeln!(md, "> {note}\n");
        }
        if self.summary.is_some() || !self.baselines.is_empty() {
            md.push_str("## Results\n\n");
            md.push_str(TABLE_HEAD);
            md.push('\n');
            if let Some(s) = &self.summary {
                md.push_str(&table_row("model", s));
                md.push('\n');
            }
            for (name, b) in self.other_models.iter().chain(&self.baselines) {
                md.push_str(&table_row(name, b));
                md.push('\n');
            }
            if let Some(s) = &self.summary {
                let _ = writeln!(
                    md,
                    "\n{} views of {} subjects, {} Gaussians per view. PSNR/SSIM on the protocol's region (THuman: GT bounding box grown to 1000×500 at 1024², scaled); recon ms per subject, render ms per view (host wall clock).",
                    s.views, s.subjects, s.num_gaussians
                );
                if s.fid.is_some() {
                    let _ = writeln!(md, "\n{FID_NOTE}");
                }
            }
        }
        if let Some((_, first)) = self.feedback_steps.first() {
            md.push_str("\n## Every feedback step\n\nThe same targets scored after each feedback step t of one reconstruction (PSNR / SSIM / LPIPS*-alex).\n\n|");
            for s in first {
                let _ = write!(md, " | t = {}", s.t);
            }
            md.push_str(" | gain, t = 1 → T (dB) |\n|---|");
            md.push_str(&"---|".repeat(first.len() + 1));
            md.push('\n');
            for (name, steps) in &self.feedback_steps {
                let _ = write!(md, "| {name}");
                for s in steps {
                    let lpips = opt(s.lpips_alex.map(|x| x * 1000.0), 1);
                    let _ = write!(md, " | {:.2} / {:.4} / {lpips}", s.psnr, s.ssim);
                }
                let gain = match (steps.first(), steps.last()) {
                    (Some(a), Some(b)) => format!("{:+.2}", b.psnr - a.psnr),
                    _ => "—".into(),
                };
                let _ = writeln!(md, " | {gain} |");
            }
        }
        if let Some(first) = self.sweep.first() {
            md.push_str("\n## What accuracy costs in time\n\n");
            let count = |n: usize, one: &str, many: &str| {
                format!("{n} {}", if n == 1 { one } else { many })
            };
            let people = first.summary.subjects;
            let same_as_results = match &self.summary {
                Some(s) if s.subjects == people => " (the people of the results above)".to_owned(),
                Some(s) => format!(
                    " (the results above: {})",
                    count(s.subjects, "person", "people")
                ),
                None => String::new(),
            };
            let _ = writeln!(
                md,
                "Every row is scored on the same {} ({}){same_as_results}.\n",
                count(people, "person", "people"),
                count(first.summary.views, "view", "views"),
            );
            md.push_str("| size | T | subdiv | Gaussians | PSNR ↑ | SSIM ↑ | LPIPS*-alex ↓ | LPIPS*-vgg ↓ | FID ↓ | recon ms | render ms |\n|---|---|---|---|---|---|---|---|---|---|---|\n");
            for r in &self.sweep {
                let s = &r.summary;
                let _ = writeln!(
                    md,
                    "| {} | {} | {} | {} | {:.2} | {:.4} | {} | {} | {} | {:.0} | {:.1} |",
                    r.size,
                    s.iterations,
                    s.subdivide,
                    s.num_gaussians,
                    s.psnr,
                    s.ssim,
                    opt(s.lpips_alex_x1000, 1),
                    opt(s.lpips_vgg_x1000, 1),
                    fid_cell(s.fid, s.fid_images),
                    s.recon_ms,
                    s.render_ms
                );
            }
        }
        if !self.per_scene.is_empty() {
            md.push_str(
                "\n## Per-scene optimisation: gradient steps instead of learned feedback\n\n",
            );
            let _ = writeln!(
                md,
                "The template in its mean colour fitted to the source views by Adam through the differentiable renderer (the training loss on the sources), scored after K steps on the same targets ({} subjects).\n",
                self.per_scene[0].subjects
            );
            md.push_str("| K | PSNR ↑ | SSIM ↑ | LPIPS*-alex ↓ | LPIPS*-vgg ↓ | FID ↓ | fit ms per subject |\n|---|---|---|---|---|---|---|\n");
            for p in &self.per_scene {
                let _ = writeln!(
                    md,
                    "| {} | {:.2} | {:.4} | {} | {} | {} | {:.0} |",
                    p.steps,
                    p.psnr,
                    p.ssim,
                    opt(p.lpips_alex.map(|x| x * 1000.0), 1),
                    opt(p.lpips_vgg.map(|x| x * 1000.0), 1),
                    fid_cell(p.fid, p.fid_images),
                    p.ms
                );
            }
        }
        if !self.sweep.is_empty() || !self.per_scene.is_empty() {
            md.push_str("\n![accuracy vs time](pareto.png)\n");
        }
        let region_rows: Vec<String> = self
            .summary
            .iter()
            .map(|s| ("model".to_owned(), s))
            .chain(
                self.other_models
                    .iter()
                    .chain(&self.baselines)
                    .map(|(n, s)| (n.clone(), s)),
            )
            .filter_map(|(name, s)| s.regions.map(|e| region_row(&name, &e)))
            .chain(self.per_scene.iter().filter_map(|p| {
                p.regions
                    .map(|e| region_row(&format!("per-scene optimisation, K = {}", p.steps), &e))
            }))
            .collect();
        if !region_rows.is_empty() {
            let _ = writeln!(
                md,
                "\n## Where the error sits\n\nThe mean squared error of the metric region (×10⁴; PSNR is −10·log10 of a view's MSE) split by the ground-truth silhouette: the pixels within {SILHOUETTE_BAND_PX} px of it (either side), the foreground farther in and the background farther out. The three add up to the MSE; a gap in the band is geometry (outline, pose, hair and loose clothes), a gap inside is appearance. The band is split by side: on the person's side its error comes from wrong colours at the edge or from an avatar too small to cover it, on the background side only from an avatar spilling over.\n\n| | MSE ×10⁴ | silhouette band | inside | outside | band, person's side | band, background side | band's share |\n|---|---|---|---|---|---|---|---|"
            );
            for row in region_rows {
                let _ = writeln!(md, "{row}");
            }
        }
        if !self.sheets.is_empty() {
            md.push_str("\n## Ground truth | prediction | error (×4)\n\n");
            for s in &self.sheets {
                let _ = writeln!(md, "![{}]({})\n", s.display(), s.display());
            }
        }
        for (caption, path) in &self.pictures {
            let _ = writeln!(md, "\n### {caption}\n\n![{caption}]({})\n", path.display());
        }
        md
    }

    /// Writes `report.md` (and `pareto.png` / `.svg` when there is a sweep or a per-scene fit)
    /// into `out`; with LPIPS computed, the chart has an LPIPS panel beside the PSNR one.
    pub fn write(&self, out: &Path) -> Result<(), EvalError> {
        std::fs::create_dir_all(out).map_err(|e| EvalError::write(out, e))?;
        if !self.sweep.is_empty() || !self.per_scene.is_empty() {
            let path = out.join("pareto.png");
            let chart = |metric| {
                pareto_chart(
                    metric,
                    &self.sweep,
                    self.summary.as_ref(),
                    &self.other_models,
                    &self.baselines,
                    &self.per_scene,
                )
            };
            let lpips = chart(ParetoMetric::LpipsVgg);
            let figure = if lpips.series.iter().any(|s| !s.points.is_empty()) {
                render_panels(&[chart(ParetoMetric::Psnr), lpips], 1400, 480)
            } else {
                chart(ParetoMetric::Psnr).render(760, 460)
            };
            figure
                .save_png_and_svg(&path)
                .map_err(|e| EvalError::write(&e.path, e.reason))?;
        }
        let path = out.join("report.md");
        write_atomic(&path, self.markdown().as_bytes()).map_err(|e| EvalError::write(&path, e))
    }
}

/// The quality axis of [`pareto_chart`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ParetoMetric {
    /// PSNR (dB), higher is better.
    Psnr,
    /// LPIPS*-vgg (LPIPS × 1000), lower is better; points without it are left out.
    LpipsVgg,
}

impl ParetoMetric {
    fn of(self, s: &Summary) -> Option<f64> {
        match self {
            Self::Psnr => Some(s.psnr),
            Self::LpipsVgg => s.lpips_vgg_x1000,
        }
    }

    fn of_fit(self, p: &FitPoint) -> Option<f64> {
        match self {
            Self::Psnr => Some(p.psnr),
            Self::LpipsVgg => p.lpips_vgg.map(|x| x * 1000.0),
        }
    }
}

/// Quality (`metric`) against reconstruction time: the sweep's points, one series per
/// subdivision level, labelled `T<n>` (and the size when several sizes were swept) — or,
/// without a sweep, the evaluated model's own point —, other trained models' points labelled
/// `T<n>`, the per-scene optimisation's points labelled `K<steps>`, and the no-learning
/// baselines: every way of building an avatar on the same axes.
pub fn pareto_chart(
    metric: ParetoMetric,
    rows: &[SweepRow],
    model: Option<&Summary>,
    other_models: &[(String, Summary)],
    baselines: &[(String, Summary)],
    per_scene: &[FitPoint],
) -> Chart {
    let sizes: std::collections::BTreeSet<u32> = rows.iter().map(|r| r.size).collect();
    let mut levels: Vec<u32> = rows.iter().map(|r| r.summary.subdivide).collect();
    levels.sort_unstable();
    levels.dedup();
    let mut series: Vec<Series> = levels
        .iter()
        .enumerate()
        .map(|(k, level)| {
            let pts: Vec<(&SweepRow, f64)> = rows
                .iter()
                .filter(|r| r.summary.subdivide == *level)
                .filter_map(|r| Some((r, metric.of(&r.summary)?)))
                .collect();
            Series {
                name: format!("model, subdiv {level}"),
                points: pts.iter().map(|(r, y)| (r.summary.recon_ms, *y)).collect(),
                labels: pts
                    .iter()
                    .map(|(r, _)| {
                        if sizes.len() > 1 {
                            format!("T{} {} px", r.summary.iterations, r.size)
                        } else {
                            format!("T{}", r.summary.iterations)
                        }
                    })
                    .collect(),
                color: PALETTE[k % PALETTE.len()],
                ..Default::default()
            }
        })
        .collect();
    let single = |name: String, m: &Summary, color| Series {
        name,
        points: metric.of(m).map(|y| (m.recon_ms, y)).into_iter().collect(),
        labels: metric
            .of(m)
            .map(|_| format!("T{}", m.iterations))
            .into_iter()
            .collect(),
        color,
        ..Default::default()
    };
    if let (true, Some(m)) = (rows.is_empty(), model) {
        series.push(single(
            format!("model, subdiv {}", m.subdivide),
            m,
            PALETTE[0],
        ));
    }
    let first_other = series.len();
    for (k, (name, m)) in other_models.iter().enumerate() {
        series.push(single(
            name.clone(),
            m,
            PALETTE[(first_other + k) % PALETTE.len()],
        ));
    }
    let next = series.len();
    if !per_scene.is_empty() {
        let pts: Vec<(&FitPoint, f64)> = per_scene
            .iter()
            .filter_map(|p| Some((p, metric.of_fit(p)?)))
            .collect();
        series.push(Series {
            name: "per-scene optimisation".into(),
            points: pts.iter().map(|(p, y)| (p.ms, *y)).collect(),
            labels: pts.iter().map(|(p, _)| format!("K{}", p.steps)).collect(),
            color: PALETTE[next % PALETTE.len()],
            ..Default::default()
        });
    }
    let next = series.len();
    for (k, (name, b)) in baselines.iter().enumerate() {
        series.push(Series {
            name: name.clone(),
            points: metric
                .of(b)
                .map(|y| (b.recon_ms.max(1e-3), y))
                .into_iter()
                .collect(),
            labels: vec![String::new()],
            color: PALETTE[(next + k) % PALETTE.len()],
            ..Default::default()
        });
    }
    let (title, y_label) = match metric {
        ParetoMetric::Psnr => ("PSNR vs reconstruction time", "PSNR (dB, higher is better)"),
        ParetoMetric::LpipsVgg => (
            "LPIPS* vs reconstruction time",
            "LPIPS*-vgg (x1000, lower is better)",
        ),
    };
    Chart {
        title: title.into(),
        x_label: "reconstruction time per person (ms)".into(),
        y_label: y_label.into(),
        x_scale: Scale::Log10,
        y_scale: Scale::Linear,
        series,
        style: Style::Markers,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evaluate::MetricImages;

    fn view(subject: &str, psnr: f64, lpips: Option<f64>) -> ViewScore {
        ViewScore {
            subject: subject.into(),
            frame_name: format!("scene_{subject}_x"),
            psnr,
            ssim: 0.9,
            lpips_alex: lpips,
            lpips_vgg: None,
            recon_ms: 100.0,
            render_ms: 5.0,
            regions: None,
        }
    }

    #[test]
    fn summary_means_and_missing_perceptual_metrics_stay_missing() {
        let scores = SplitScores {
            views: vec![
                view("a", 20.0, None),
                view("a", 22.0, None),
                view("b", 30.0, None),
            ],
            images: MetricImages::default(),
            num_gaussians: 10,
            iterations: 3,
            subdivide: 1,
        };
        let s = Summary::of(&scores, None);
        assert_eq!((s.views, s.subjects), (3, 2));
        assert!((s.psnr - 24.0).abs() < 1e-12);
        assert_eq!(s.lpips_alex_x1000, None);
        let md = Report {
            title: "t".into(),
            summary: Some(s),
            notes: vec![WEIGHTS_MISSING.into()],
            ..Default::default()
        }
        .markdown();
        assert!(md.contains(WEIGHTS_MISSING));
        assert!(md.contains("| n/a |"), "{md}");
        let with = SplitScores {
            views: vec![view("a", 20.0, Some(0.1)), view("b", 20.0, Some(0.3))],
            ..scores
        };
        assert!((Summary::of(&with, None).lpips_alex_x1000.unwrap() - 200.0).abs() < 1e-9);
    }

    /// Another trained model scored on the same views (the previous demo model in the
    /// quickstart) gets a row of the results table and a point of the accuracy-vs-time chart.
    #[test]
    fn other_models_are_rows_and_points() {
        let scores = |psnr: f64, iterations: usize| SplitScores {
            views: vec![view("a", psnr, None), view("b", psnr, None)],
            images: MetricImages::default(),
            num_gaussians: 10,
            iterations,
            subdivide: 1,
        };
        let report = Report {
            title: "t".into(),
            summary: Some(Summary::of(&scores(24.0, 3), None)),
            other_models: vec![(
                "v1.lgck (step 7)".into(),
                Summary::of(&scores(21.0, 2), None),
            )],
            per_scene: vec![FitPoint {
                steps: 30,
                psnr: 22.0,
                ssim: 0.8,
                ms: 900.0,
                subjects: 2,
                lpips_alex: None,
                lpips_vgg: None,
                fid: None,
                fid_images: None,
                regions: Some(ErrorByRegion {
                    silhouette: 3e-3,
                    silhouette_foreground: 2.5e-3,
                    inside: 2e-3,
                    outside: 1e-3,
                }),
            }],
            ..Default::default()
        };
        let md = report.markdown();
        assert!(md.contains("| v1.lgck (step 7) | 2 | 1 | 21.00 |"), "{md}");
        // Only the per-scene point has masks: the error table has its row alone.
        assert!(
            md.contains("| per-scene optimisation, K = 30 | 60.0 | 30.0 | 20.0 | 10.0 | 25.0 | 5.0 | 50 % |\n"),
            "{md}"
        );
        assert!(!md.contains("| model | 0.0"), "{md}");
        let chart = pareto_chart(
            ParetoMetric::Psnr,
            &report.sweep,
            report.summary.as_ref(),
            &report.other_models,
            &report.baselines,
            &report.per_scene,
        );
        let names: Vec<&str> = chart.series.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "model, subdiv 1",
                "v1.lgck (step 7)",
                "per-scene optimisation"
            ]
        );
        assert_eq!(chart.series[1].points, [(100.0, 21.0)]);
        assert_eq!(chart.series[1].labels, ["T2"]);
    }

    /// The sweep's table says how many people its rows are scored on, and whether they are the
    /// people of the results table (issue 37: a sweep of one person was once plotted beside
    /// baselines scored on eight).
    #[test]
    fn sweep_table_names_its_people() {
        let scores = |subjects: &[&str]| SplitScores {
            views: subjects.iter().map(|s| view(s, 20.0, None)).collect(),
            images: MetricImages::default(),
            num_gaussians: 10,
            iterations: 3,
            subdivide: 1,
        };
        let all = Summary::of(&scores(&["a", "b", "c"]), None);
        let one = Summary::of(&scores(&["a"]), None);
        let report = |sweep: &Summary| Report {
            title: "t".into(),
            summary: Some(all.clone()),
            sweep: vec![SweepRow {
                size: 64,
                summary: sweep.clone(),
            }],
            ..Default::default()
        };
        let md = report(&all).markdown();
        assert!(
            md.contains("the same 3 people (3 views) (the people of the results above)"),
            "{md}"
        );
        let md = report(&one).markdown();
        assert!(
            md.contains("the same 1 person (1 view) (the results above: 3 people)"),
            "{md}"
        );
    }

    #[test]
    fn csvs_have_one_line_per_view_and_subject() {
        let dir = std::env::temp_dir().join(format!("lifegom-report-{}", std::process::id()));
        write_csvs(
            &dir,
            &[
                view("a", 20.0, None),
                view("a", 22.0, None),
                view("b", 30.0, None),
            ],
        )
        .unwrap();
        let per_subject = std::fs::read_to_string(dir.join("per_subject.csv")).unwrap();
        assert_eq!(per_subject.lines().count(), 3);
        assert!(per_subject.contains("a,2,21.0000"), "{per_subject}");
        let per_view = std::fs::read_to_string(dir.join("per_view.csv")).unwrap();
        assert_eq!(per_view.lines().count(), 4);
    }
}
