//! The experiments' plots, as PNG and SVG: exploration time against team
//! size with 95 % confidence bars (Burgard et al. 2005 Fig. 9, Bautin et al.
//! 2011 Figs. 9–10), coverage over time (Simmons et al. 2000 Figs. 8–10),
//! the gain of one policy over another in percent (Wurm et al. 2008 Fig. 5)
//! and exploration time against communication range (Burgard et al. Fig. 12).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Once;

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::experiment::config::{Experiment, ExperimentError, PlotSpec};
use crate::picture::PALETTE;
use crate::runs::{Row, read_runs, samples};
use crate::stats::welch;

static FONT: Once = Once::new();

/// Plots carry their own font, so a machine without fonts draws them alike.
fn register_font() {
    FONT.call_once(|| {
        let bytes: &'static [u8] = include_bytes!("../assets/DejaVuSans.ttf");
        // A failure leaves plotters without text, which the draw reports.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, bytes);
    });
}

fn colour(k: usize) -> RGBColor {
    let [r, g, b] = PALETTE[k % PALETTE.len()];
    RGBColor(r, g, b)
}

/// One line of a plot: label, points (x, y, ± half-width).
type Series = (String, Vec<(f64, f64, f64)>);

struct Figure {
    title: String,
    x_label: String,
    y_label: String,
    series: Vec<Series>,
    /// Draw error bars.
    bars: bool,
}

fn err<E: std::fmt::Display>(e: E) -> ExperimentError {
    ExperimentError::Plot(e.to_string())
}

fn render<DB: DrawingBackend>(area: DrawingArea<DB, Shift>, figure: &Figure) -> Result<(), ExperimentError>
where
    DB::ErrorType: 'static,
{
    area.fill(&WHITE).map_err(err)?;
    let points = figure.series.iter().flat_map(|s| s.1.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y, e) in points {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y - e);
        y1 = y1.max(y + e);
    }
    if !x0.is_finite() {
        return Ok(());
    }
    // Half a robot of room on count axes; 5 % on axes of shares (0..1).
    let pad_x = ((x1 - x0) * 0.05).max(if x1 - x0 >= 2.0 { 0.5 } else { 0.02 });
    let pad_y = ((y1 - y0) * 0.08).max(1e-6);
    let y_low = if y0 >= 0.0 { 0.0f64.max(y0 - pad_y).min(y0) } else { y0 - pad_y };
    let mut chart = ChartBuilder::on(&area)
        .caption(&figure.title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d((x0 - pad_x)..(x1 + pad_x), y_low..(y1 + pad_y))
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc(&figure.x_label)
        .y_desc(&figure.y_label)
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(err)?;
    for (k, (label, pts)) in figure.series.iter().enumerate() {
        let c = colour(k);
        chart
            .draw_series(LineSeries::new(pts.iter().map(|&(x, y, _)| (x, y)), c.stroke_width(2)))
            .map_err(err)?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
        if figure.bars {
            chart
                .draw_series(pts.iter().map(|&(x, y, e)| ErrorBar::new_vertical(x, y - e, y, y + e, c.filled(), 8)))
                .map_err(err)?;
            chart.draw_series(pts.iter().map(|&(x, y, _)| Circle::new((x, y), 3, c.filled()))).map_err(err)?;
        }
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(err)?;
    area.present().map_err(err)?;
    Ok(())
}

fn save(figure: &Figure, base: &Path) -> Result<Vec<PathBuf>, ExperimentError> {
    register_font();
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    render(BitMapBackend::new(&png, (900, 600)).into_drawing_area(), figure)?;
    render(SVGBackend::new(&svg, (900, 600)).into_drawing_area(), figure)?;
    Ok(vec![png, svg])
}

fn metric_name(metric: &str) -> &str {
    match metric {
        "steps" => "exploration time (steps)",
        "t50" => "steps to 50 % coverage",
        "t90" => "steps to 90 % coverage",
        "t95" => "steps to 95 % coverage",
        "t100" => "steps to 100 % coverage",
        "distance" => "distance per robot (m)",
        "wall_time_s" => "wall time per run (s)",
        other => other,
    }
}

/// The communication range as a number for the x axis: the share of the
/// diameter ("0.3d"), metres, or 1 for unlimited.
fn range_value(s: &str) -> f64 {
    if s == "unlimited" {
        return 1.0;
    }
    s.trim_end_matches(['d', 'm']).parse().unwrap_or(f64::NAN)
}

/// Draws one plot for one world; returns the files written.
pub fn draw(
    experiment: &Experiment,
    spec: &PlotSpec,
    world: &str,
    rows: &[Row],
    out: &Path,
    base: &Path,
) -> Result<Vec<PathBuf>, ExperimentError> {
    let labels: Vec<String> = if spec.policies.is_empty() {
        experiment.policies.iter().map(|p| if p.label.is_empty() { p.name.clone() } else { p.label.clone() }).collect()
    } else {
        spec.policies.clone()
    };
    let first_comm = experiment.comm_ranges.first().cloned().unwrap_or_else(|| "unlimited".into());
    let data = samples(rows, &spec.metric);
    let title = |default: String| if spec.title.is_empty() { default } else { format!("{} ({world})", spec.title) };
    let figure = match spec.kind.as_str() {
        "time_vs_robots" => Figure {
            title: title(format!("{} against team size, {world}", metric_name(&spec.metric))),
            x_label: "robots".into(),
            y_label: metric_name(&spec.metric).into(),
            bars: true,
            series: labels
                .iter()
                .map(|label| {
                    let pts = experiment
                        .robots
                        .iter()
                        .filter_map(|&n| {
                            data.get(&(world.to_owned(), label.clone(), n, first_comm.clone()))
                                .map(|s| (n as f64, s.mean(), s.ci95()))
                        })
                        .collect();
                    (label.clone(), pts)
                })
                .collect(),
        },
        "gain_vs_robots" => {
            let baseline = spec.baseline.clone().unwrap_or_default();
            Figure {
                title: title(format!("gain over {baseline} in {} (%), {world}", spec.metric)),
                x_label: "robots".into(),
                y_label: format!("runtime gain over {baseline} (%)"),
                bars: true,
                series: labels
                    .iter()
                    .filter(|l| **l != baseline)
                    .map(|label| {
                        let pts = experiment
                            .robots
                            .iter()
                            .filter_map(|&n| {
                                let key = |l: &str| (world.to_owned(), l.to_owned(), n, first_comm.clone());
                                let (base, ours) = (data.get(&key(&baseline))?, data.get(&key(label))?);
                                let (difference, half, _) = welch(base, ours);
                                let m = base.mean();
                                Some((n as f64, 100.0 * difference / m, 100.0 * half / m))
                            })
                            .collect();
                        (label.clone(), pts)
                    })
                    .collect(),
            }
        }
        "time_vs_comm_range" => {
            let mut series = Vec::new();
            for label in &labels {
                for &n in &experiment.robots {
                    let pts: Vec<(f64, f64, f64)> = experiment
                        .comm_ranges
                        .iter()
                        .filter_map(|c| {
                            data.get(&(world.to_owned(), label.clone(), n, c.clone()))
                                .map(|s| (range_value(c), s.mean(), s.ci95()))
                        })
                        .collect();
                    if !pts.is_empty() {
                        series.push((format!("{label}, {n} robots"), pts));
                    }
                }
            }
            Figure {
                title: title(format!("{} against communication range, {world}", metric_name(&spec.metric))),
                x_label: "communication range (share of the map's diameter; 1 = unlimited)".into(),
                y_label: metric_name(&spec.metric).into(),
                bars: true,
                series,
            }
        }
        "coverage_over_time" => {
            let robots = spec.robots.unwrap_or(experiment.robots[0]);
            let curves = read_curves(out)?;
            let series = labels
                .iter()
                .map(|label| {
                    let prefix = format!("{world}|{label}|{robots}|{first_comm}|");
                    let mine: Vec<&Vec<f32>> =
                        curves.iter().filter(|(id, _)| id.starts_with(&prefix)).map(|(_, c)| c).collect();
                    let longest = mine.iter().map(|c| c.len()).max().unwrap_or(0);
                    let stride = (longest / 300).max(1);
                    let pts = (0..longest)
                        .step_by(stride)
                        .map(|t| {
                            let mean =
                                mine.iter().map(|c| f64::from(*c.get(t).or(c.last()).unwrap_or(&0.0))).sum::<f64>()
                                    / mine.len().max(1) as f64;
                            (t as f64, 100.0 * mean, 0.0)
                        })
                        .collect();
                    (label.clone(), pts)
                })
                .collect();
            Figure {
                title: title(format!("coverage over time, {robots} robots, {world}")),
                x_label: "steps".into(),
                y_label: "reachable free space known (%)".into(),
                bars: false,
                series,
            }
        }
        other => return Err(ExperimentError::Plot(format!("unknown plot kind {other:?}"))),
    };
    save(&figure, base)
}

fn read_curves(out: &Path) -> Result<Vec<(String, Vec<f32>)>, ExperimentError> {
    let path = out.join("curves.jsonl");
    let text = std::fs::read_to_string(&path).unwrap_or_default();
    let mut curves: BTreeMap<String, Vec<f32>> = BTreeMap::new();
    for line in text.lines() {
        let value: serde_json::Value = serde_json::from_str(line).map_err(err)?;
        let (Some(id), Some(curve)) = (value["id"].as_str(), value["curve"].as_array()) else { continue };
        curves.insert(id.to_owned(), curve.iter().filter_map(|v| v.as_f64()).map(|v| v as f32).collect());
    }
    Ok(curves.into_iter().collect())
}

/// Latency against offered load from `fleet-sim load --json` reports: p50
/// and p99 of each call, milliseconds on a log axis (a sweep spans from a
/// few milliseconds to seconds past saturation). Returns the files written.
pub fn draw_load_sweep(reports: &[serde_json::Value], base: &Path) -> Result<Vec<PathBuf>, ExperimentError> {
    // Figures a load run can give: a hand-edited report with absurd ones
    // would make the axes unbounded (plotters then never finishes its ticks).
    let plausible = |v: f64| v.is_finite() && (0.0..=1e9).contains(&v);
    let mut series: BTreeMap<String, Vec<(f64, f64)>> = BTreeMap::new();
    for report in reports {
        let Some(offered) = report["offered_per_s"].as_f64().filter(|v| plausible(*v)) else { continue };
        let Some(calls) = report["calls"].as_object() else { continue };
        for (call, figures) in calls {
            for quantile in ["p50", "p99"] {
                if let Some(ms) = figures["latency_ms"][quantile].as_f64().filter(|v| plausible(*v)) {
                    series.entry(format!("{call} {quantile}")).or_default().push((offered, ms.max(0.01)));
                }
            }
        }
    }
    for points in series.values_mut() {
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    register_font();
    let png = base.with_extension("png");
    let svg = base.with_extension("svg");
    render_log(BitMapBackend::new(&png, (900, 600)).into_drawing_area(), &series)?;
    render_log(SVGBackend::new(&svg, (900, 600)).into_drawing_area(), &series)?;
    Ok(vec![png, svg])
}

fn render_log<DB: DrawingBackend>(
    area: DrawingArea<DB, Shift>,
    series: &BTreeMap<String, Vec<(f64, f64)>>,
) -> Result<(), ExperimentError>
where
    DB::ErrorType: 'static,
{
    area.fill(&WHITE).map_err(err)?;
    let points = || series.values().flatten();
    let x1 = points().map(|p| p.0).fold(0.0, f64::max);
    let (y0, y1) = points().fold((f64::INFINITY, 0.0f64), |(lo, hi), p| (lo.min(p.1), hi.max(p.1)));
    if x1 <= 0.0 || !y0.is_finite() {
        return Ok(());
    }
    let mut chart = ChartBuilder::on(&area)
        .caption("latency against offered load", ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d(0.0..x1 * 1.05, (y0 * 0.8..y1 * 1.25).log_scale())
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("offered calls per second")
        .y_desc("latency from when the call was due (ms)")
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(err)?;
    for (k, (label, pts)) in series.iter().enumerate() {
        // A call's p50 and p99 share a colour; the p99 is the solid line.
        let c = colour(k / 2);
        let style = if label.ends_with("p99") { c.stroke_width(2) } else { c.mix(0.5).stroke_width(1) };
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), style))
            .map_err(err)?
            .label(label)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
        chart.draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled()))).map_err(err)?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(err)?;
    area.present().map_err(err)?;
    Ok(())
}

/// Draws every plot of the experiment from its results.
pub fn draw_plots(experiment: &Experiment, out: &Path) -> Result<Vec<PathBuf>, ExperimentError> {
    let rows = read_runs(out)?;
    let mut written = Vec::new();
    for (k, spec) in experiment.plots.iter().enumerate() {
        let worlds: Vec<String> = match &spec.world {
            Some(w) => vec![w.clone()],
            None => experiment.worlds.iter().map(|w| w.name.clone()).collect(),
        };
        for world in worlds {
            let base = out.join(format!("plot{}-{}-{}", k + 1, spec.kind, world).replace(['/', ' '], "_"));
            let drawn = draw(experiment, spec, &world, &rows, out, &base)?;
            written.extend(drawn);
        }
    }
    Ok(written)
}
