//! The experiment runner: a matrix of worlds × team sizes × policies ×
//! communication ranges × seeds, each a real mission against an executive
//! over gRPC, run in parallel, resumable, with a time limit per run.
//!
//! An experiment is a TOML file (see `experiments/`). Its results go to a
//! folder: `runs.csv` (one row per run, every setting and every figure),
//! `curves.jsonl` (each run's coverage after every step), `summary.csv`
//! (means with 95 % confidence intervals per cell of the matrix), the plots
//! (PNG and SVG) and pictures of runs.

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Deserialize;

use crate::fleet::{CommRange, DEFAULT_MODEL, Interference, Layout, RunConfig, RunReport, WorldSpec};
use crate::generate::Generator;
use crate::picture::{PALETTE, Picture, segment_tint};
use crate::robot::RobotModel;
use crate::stats::Sample;
use crate::world::StartChoice;

/// An experiment, as its TOML file describes it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Experiment {
    /// Short name; the results folder is named after it.
    pub name: String,
    /// The paper and figure it mirrors.
    #[serde(default)]
    pub paper: String,
    /// The paper's claim, in one line.
    #[serde(default)]
    pub claim: String,
    /// Commentary for the report: how our setting differs, why we agree or not.
    #[serde(default)]
    pub notes: String,
    /// Seeds 1 ..= seeds for every cell.
    pub seeds: u64,
    /// A run taking longer is stopped and recorded as timed out.
    #[serde(default = "default_time_limit")]
    pub time_limit_s: f64,
    /// Simulator settings for every run.
    #[serde(default)]
    pub sim: SimSettings,
    /// The worlds.
    pub worlds: Vec<WorldEntry>,
    /// Team sizes.
    pub robots: Vec<usize>,
    /// Policies (with parameters).
    pub policies: Vec<PolicyEntry>,
    /// Communication ranges: "unlimited", metres ("5"), or a share of the
    /// map's diameter ("0.3d"). Default: unlimited only.
    #[serde(default)]
    pub comm_ranges: Vec<String>,
    /// Plots to draw.
    #[serde(default)]
    pub plots: Vec<PlotSpec>,
    /// Claims to test.
    #[serde(default)]
    pub checks: Vec<CheckSpec>,
    /// Draw a picture of seed 1 of every cell.
    #[serde(default)]
    pub pictures: bool,
}

fn default_time_limit() -> f64 {
    600.0
}

/// Simulator settings (the papers' values are the defaults).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimSettings {
    /// Cell size, metres (Burgard et al. 2005: 0.15).
    pub cell_size: f64,
    /// Sensor range, metres.
    pub sensor_range: f64,
    /// Field of view, degrees.
    pub fov: f64,
    /// Speed, m/s (0.5: a cell per step).
    pub speed: f64,
    /// Footprint radius, metres.
    pub footprint: f64,
    /// Heterogeneous teams: robot i takes model i mod len (overrides the above).
    pub models: Vec<ModelEntry>,
    /// Probability a move near another robot happens (0.7); 1: none.
    pub interference: f64,
    /// Interference distance, metres.
    pub interference_radius: f64,
    /// "random" (a seeded random start, as the papers), "auto" (roomiest cell).
    pub start: String,
    /// "together" or "spread".
    pub layout: String,
    /// Step limit per run.
    pub max_steps: u64,
}

impl Default for SimSettings {
    fn default() -> Self {
        Self {
            cell_size: 0.15,
            sensor_range: DEFAULT_MODEL.sensor_range_m,
            fov: 360.0,
            speed: DEFAULT_MODEL.speed_mps,
            footprint: 0.0,
            models: Vec::new(),
            interference: 0.7,
            interference_radius: 1.0,
            start: "random".into(),
            layout: "together".into(),
            max_steps: 30_000,
        }
    }
}

/// One robot model of a heterogeneous team.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelEntry {
    /// Sensor range, metres.
    pub sensor_range: f64,
    /// Field of view, degrees.
    pub fov: f64,
    /// Speed, m/s.
    pub speed: f64,
    /// Footprint radius, metres.
    pub footprint: f64,
}

/// A world of the matrix.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldEntry {
    /// Its name in the results.
    pub name: String,
    /// A map_server YAML, relative to the experiment file, or `$SHARED/…`
    /// for the shared collection (`EXPLORATION_SHARED_MAPS`).
    pub map: Option<String>,
    /// A generator: unstructured[:density], office, corridor, maze[:width], empty.
    pub generator: Option<String>,
    /// Generated width, metres.
    #[serde(default = "default_side")]
    pub width_m: f64,
    /// Generated height, metres.
    #[serde(default = "default_side")]
    pub height_m: f64,
    /// Cell size for this world, overriding the simulator's.
    pub cell_size: Option<f64>,
}

fn default_side() -> f64 {
    20.0
}

/// A policy of the matrix.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolicyEntry {
    /// The policy.
    pub name: String,
    /// Its label in the results (default: the name).
    #[serde(default)]
    pub label: String,
    /// Parameter overrides.
    #[serde(default)]
    pub params: BTreeMap<String, f64>,
}

impl PolicyEntry {
    fn label(&self) -> &str {
        if self.label.is_empty() { &self.name } else { &self.label }
    }
}

/// A plot to draw from the results.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlotSpec {
    /// `time_vs_robots`, `coverage_over_time`, `gain_vs_robots`, `time_vs_comm_range`.
    pub kind: String,
    /// The figure plotted: steps, t50, t90, t95, t100, distance, replans, wall_time_s.
    #[serde(default = "default_metric")]
    pub metric: String,
    /// Only this world (default: one plot per world).
    pub world: Option<String>,
    /// Team size (coverage_over_time).
    pub robots: Option<usize>,
    /// Baseline label (gain_vs_robots).
    pub baseline: Option<String>,
    /// Labels plotted (default: all).
    #[serde(default)]
    pub policies: Vec<String>,
    /// Title (default: from the kind).
    #[serde(default)]
    pub title: String,
}

fn default_metric() -> String {
    "steps".into()
}

/// A claim to test on the results.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckSpec {
    /// What the claim says, in a few words.
    pub claim: String,
    /// `faster`: `better` significantly lower than `worse` (Welch, 95 %);
    /// `similar`: no significant difference; `gain`: mean gain of `better`
    /// over `worse` in percent, against `expected_gain`.
    pub kind: String,
    /// Label expected better.
    pub better: String,
    /// Label compared with.
    pub worse: String,
    /// The figure compared.
    #[serde(default = "default_metric")]
    pub metric: String,
    /// Team sizes to test (default: all above 1).
    #[serde(default)]
    pub robots: Vec<usize>,
    /// Worlds to test (default: all).
    #[serde(default)]
    pub worlds: Vec<String>,
    /// Communication range to test (default: unlimited).
    pub comm_range: Option<String>,
    /// For `gain`: the paper's figure, percent.
    pub expected_gain: Option<f64>,
}

/// Why an experiment could not run.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    /// Reading or writing a file.
    #[error("{path}: {source}")]
    Io {
        /// Which file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The configuration is not valid.
    #[error("{path}: {message}")]
    Config {
        /// Which file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Drawing a plot.
    #[error("plot {0}")]
    Plot(String),
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> ExperimentError + '_ {
    move |source| ExperimentError::Io { path: path.to_owned(), source }
}

impl Experiment {
    /// Reads an experiment file.
    pub fn load(path: &Path) -> Result<Self, ExperimentError> {
        let text = std::fs::read_to_string(path).map_err(io(path))?;
        let experiment: Self = toml::from_str(&text)
            .map_err(|e| ExperimentError::Config { path: path.to_owned(), message: e.to_string() })?;
        let bad = |message: String| ExperimentError::Config { path: path.to_owned(), message };
        if experiment.seeds == 0 || experiment.robots.is_empty() || experiment.policies.is_empty() {
            return Err(bad("seeds, robots and policies must not be empty".into()));
        }
        for w in &experiment.worlds {
            match (&w.map, &w.generator) {
                (Some(_), None) => {}
                (None, Some(g)) if Generator::parse(g).is_some() => {}
                _ => return Err(bad(format!("world {:?}: give either map or a known generator", w.name))),
            }
        }
        for r in &experiment.comm_ranges {
            parse_range(r).ok_or_else(|| bad(format!("communication range {r:?}: unlimited, metres or 0.3d")))?;
        }
        Ok(experiment)
    }
}

/// A communication range: `None` for unlimited.
fn parse_range(s: &str) -> Option<Option<CommRange>> {
    let s = s.trim();
    if s == "unlimited" {
        return Some(None);
    }
    match s.strip_suffix('d') {
        Some(share) => share.trim().parse().ok().map(|v| Some(CommRange::OfDiameter(v))),
        None => s.trim_end_matches('m').parse().ok().map(|v| Some(CommRange::Metres(v))),
    }
}

/// One run of the matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct RunSpec {
    /// Unique key: world, label, robots, range, seed.
    pub id: String,
    /// World name.
    pub world: String,
    /// Policy label.
    pub label: String,
    /// Team size.
    pub robots: usize,
    /// Communication range as written ("unlimited").
    pub comm: String,
    /// Seed.
    pub seed: u64,
}

/// Every run of an experiment, in a fixed order: worlds, ranges, sizes,
/// policies, then seeds (so partial results cover every cell early).
pub fn matrix(experiment: &Experiment) -> Vec<RunSpec> {
    let ranges =
        if experiment.comm_ranges.is_empty() { vec!["unlimited".to_owned()] } else { experiment.comm_ranges.clone() };
    let mut runs = Vec::new();
    for seed in 1..=experiment.seeds {
        for world in &experiment.worlds {
            for comm in &ranges {
                for &robots in &experiment.robots {
                    for policy in &experiment.policies {
                        let label = policy.label().to_owned();
                        runs.push(RunSpec {
                            id: format!("{}|{}|{}|{}|{}", world.name, label, robots, comm, seed),
                            world: world.name.clone(),
                            label,
                            robots,
                            comm: comm.clone(),
                            seed,
                        });
                    }
                }
            }
        }
    }
    runs
}

/// An executive that every run of an experiment drives, instead of one
/// embedded per run.
#[derive(Debug, Clone)]
pub struct RemoteExecutive {
    /// Its gRPC URL, e.g. `http://127.0.0.1:50051`.
    pub url: String,
    /// Its operator token, if it requires one.
    pub token: Option<String>,
}

/// The run configuration of one run of the matrix.
fn run_config(
    experiment: &Experiment,
    dir: &Path,
    spec: &RunSpec,
    server: Option<&RemoteExecutive>,
) -> Result<RunConfig, String> {
    let world = experiment.worlds.iter().find(|w| w.name == spec.world).ok_or("unknown world")?;
    let policy = experiment.policies.iter().find(|p| p.label() == spec.label).ok_or("unknown policy")?;
    let world_spec = match (&world.map, &world.generator) {
        (Some(map), _) => {
            let path = match map.strip_prefix("$SHARED/") {
                Some(rest) => PathBuf::from(
                    std::env::var_os("EXPLORATION_SHARED_MAPS")
                        .ok_or("needs EXPLORATION_SHARED_MAPS for the shared maps")?,
                )
                .join(rest),
                None => dir.join(map),
            };
            WorldSpec::Map(path)
        }
        (None, Some(g)) => WorldSpec::Generated {
            generator: Generator::parse(g).ok_or("unknown generator")?,
            width_m: world.width_m,
            height_m: world.height_m,
        },
        (None, None) => return Err("a world needs a map or a generator".into()),
    };
    let sim = &experiment.sim;
    let mut config = RunConfig::on(world_spec, spec.robots, &policy.name);
    config.params = policy.params.clone();
    config.seed = spec.seed;
    if let Some(server) = server {
        config.server = Some(server.url.clone());
        config.token = server.token.clone();
    }
    config.cell_size = Some(world.cell_size.unwrap_or(sim.cell_size));
    config.models = if sim.models.is_empty() {
        vec![RobotModel {
            sensor_range_m: sim.sensor_range,
            field_of_view_rad: sim.fov.to_radians(),
            speed_mps: sim.speed,
            footprint_radius_m: sim.footprint,
        }]
    } else {
        sim.models
            .iter()
            .map(|m| RobotModel {
                sensor_range_m: m.sensor_range,
                field_of_view_rad: m.fov.to_radians(),
                speed_mps: m.speed,
                footprint_radius_m: m.footprint,
            })
            .collect()
    };
    config.start = match sim.start.as_str() {
        "random" => StartChoice::Random,
        "auto" => StartChoice::Auto,
        other => return Err(format!("unknown start {other:?}")),
    };
    config.layout = match sim.layout.as_str() {
        "together" => Layout::Together,
        "spread" => Layout::Spread,
        other => return Err(format!("unknown layout {other:?}")),
    };
    config.interference = (sim.interference < 1.0)
        .then_some(Interference { radius_m: sim.interference_radius, success: sim.interference });
    config.comm_range = parse_range(&spec.comm).ok_or("bad communication range")?;
    config.max_steps = sim.max_steps;
    Ok(config)
}

/// The columns of `runs.csv`.
const RUN_COLUMNS: [&str; 25] = [
    "id",
    "world",
    "policy",
    "label",
    "robots",
    "comm_range",
    "seed",
    "status",
    "error",
    "completed",
    "steps",
    "t50",
    "t90",
    "t95",
    "t100",
    "coverage",
    "distance_mean",
    "distance_max",
    "idle_steps",
    "overlap",
    "replans",
    "map_updates",
    "wall_time_s",
    "reachable_cells",
    "comm_range_m",
];

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) { format!("\"{}\"", s.replace('"', "\"\"")) } else { s.to_owned() }
}

fn csv_row(fields: &[String]) -> String {
    fields.iter().map(|f| csv_field(f)).collect::<Vec<_>>().join(",")
}

/// Splits a CSV line written by [`csv_row`].
fn csv_split(line: &str) -> Vec<String> {
    let mut fields = Vec::new();
    let mut field = String::new();
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                field.push('"');
                chars.next();
            }
            ('"', _) => quoted = !quoted,
            (',', false) => fields.push(std::mem::take(&mut field)),
            (c, _) => field.push(c),
        }
    }
    fields.push(field);
    fields
}

/// One row of `runs.csv`, by column name.
pub type Row = BTreeMap<String, String>;

/// Reads `runs.csv` of a results folder.
pub fn read_runs(dir: &Path) -> Result<Vec<Row>, ExperimentError> {
    let path = dir.join("runs.csv");
    if !path.exists() {
        return Ok(Vec::new());
    }
    let text = std::fs::read_to_string(&path).map_err(io(&path))?;
    let mut lines = text.lines();
    let Some(header) = lines.next() else { return Ok(Vec::new()) };
    let header = csv_split(header);
    Ok(lines.filter(|l| !l.trim().is_empty()).map(|l| header.iter().cloned().zip(csv_split(l)).collect()).collect())
}

fn report_row(spec: &RunSpec, policy: &str, outcome: &Result<RunReport, String>, timed_out: bool) -> Vec<String> {
    let opt = |v: Option<u64>| v.map_or(String::new(), |v| v.to_string());
    let mut row = vec![
        spec.id.clone(),
        spec.world.clone(),
        policy.to_owned(),
        spec.label.clone(),
        spec.robots.to_string(),
        spec.comm.clone(),
        spec.seed.to_string(),
    ];
    match outcome {
        Ok(r) => {
            let mean = r.distance_per_robot.iter().sum::<f64>() / r.distance_per_robot.len().max(1) as f64;
            let max = r.distance_per_robot.iter().copied().fold(0.0, f64::max);
            row.extend([
                "ok".to_owned(),
                String::new(),
                r.completed.to_string(),
                r.steps.to_string(),
                opt(r.t50),
                opt(r.t90),
                opt(r.t95),
                opt(r.t100),
                format!("{:.6}", r.coverage),
                format!("{mean:.3}"),
                format!("{max:.3}"),
                r.idle_steps.to_string(),
                format!("{:.6}", r.overlap),
                r.replans.to_string(),
                r.map_updates.to_string(),
                format!("{:.3}", r.wall_time_s),
                r.reachable_cells.to_string(),
                r.comm_range_m.map_or(String::new(), |m| format!("{m:.3}")),
            ]);
        }
        Err(e) => {
            row.push(if timed_out { "timeout" } else { "failed" }.to_owned());
            row.push(e.clone());
            row.extend(std::iter::repeat_n(String::new(), RUN_COLUMNS.len() - row.len()));
        }
    }
    row
}

/// Runs an experiment into `out`, skipping runs already in its `runs.csv`;
/// `jobs` runs at a time; `server` drives one executive for all runs
/// instead of one embedded per run.
pub async fn run_experiment(
    config_path: &Path,
    out: &Path,
    jobs: usize,
    server: Option<RemoteExecutive>,
    progress: bool,
) -> Result<(), ExperimentError> {
    let experiment = Arc::new(Experiment::load(config_path)?);
    let dir = config_path.parent().unwrap_or(Path::new(".")).to_owned();
    std::fs::create_dir_all(out).map_err(io(out))?;
    let done: BTreeSet<String> = read_runs(out)?.into_iter().filter_map(|r| r.get("id").cloned()).collect();
    let runs_path = out.join("runs.csv");
    let mut runs_file =
        std::fs::OpenOptions::new().create(true).append(true).open(&runs_path).map_err(io(&runs_path))?;
    if done.is_empty() && runs_file.metadata().map(|m| m.len() == 0).unwrap_or(true) {
        writeln!(runs_file, "{}", RUN_COLUMNS.join(",")).map_err(io(&runs_path))?;
    }
    let curves_path = out.join("curves.jsonl");
    let mut curves_file =
        std::fs::OpenOptions::new().create(true).append(true).open(&curves_path).map_err(io(&curves_path))?;
    let todo: Vec<RunSpec> = matrix(&experiment).into_iter().filter(|r| !done.contains(&r.id)).collect();
    let total = todo.len();
    if progress {
        eprintln!("{}: {} runs to do, {} already done", experiment.name, total, done.len());
    }
    let started = Instant::now();
    let semaphore = Arc::new(tokio::sync::Semaphore::new(jobs.max(1)));
    let mut tasks = tokio::task::JoinSet::new();
    for spec in todo {
        let permit = semaphore.clone().acquire_owned().await.map_err(|e| ExperimentError::Plot(e.to_string()))?;
        let (task_experiment, dir, server) = (experiment.clone(), dir.clone(), server.clone());
        tasks.spawn(async move {
            let experiment = task_experiment;
            let _permit = permit;
            let policy =
                experiment.policies.iter().find(|p| p.label() == spec.label).map_or(String::new(), |p| p.name.clone());
            let limit = Duration::from_secs_f64(experiment.time_limit_s);
            let outcome = match run_config(&experiment, &dir, &spec, server.as_ref()) {
                Err(e) => (Err(e), false),
                Ok(config) => match tokio::time::timeout(limit, crate::fleet::run(&config)).await {
                    Ok(Ok(report)) => (Ok(report), false),
                    Ok(Err(e)) => (Err(e.to_string()), false),
                    Err(_) => (Err(format!("time limit of {:.0} s reached", limit.as_secs_f64())), true),
                },
            };
            (spec, policy, outcome)
        });
        // Drain what finished, to write results as they come.
        while let Some(joined) = tasks.try_join_next() {
            record(joined, &mut runs_file, &mut curves_file, out, &experiment, &runs_path, &started, total, progress)?;
        }
    }
    while let Some(joined) = tasks.join_next().await {
        record(joined, &mut runs_file, &mut curves_file, out, &experiment, &runs_path, &started, total, progress)?;
    }
    summarize(&experiment, out)?;
    draw_plots(&experiment, out)?;
    Ok(())
}

type Finished = (RunSpec, String, (Result<RunReport, String>, bool));

#[allow(clippy::too_many_arguments)]
fn record(
    joined: Result<Finished, tokio::task::JoinError>,
    runs_file: &mut std::fs::File,
    curves_file: &mut std::fs::File,
    out: &Path,
    experiment: &Experiment,
    runs_path: &Path,
    started: &Instant,
    total: usize,
    progress: bool,
) -> Result<(), ExperimentError> {
    static FINISHED: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let (spec, policy, (outcome, timed_out)) = match joined {
        Ok(f) => f,
        Err(e) => return Err(ExperimentError::Plot(format!("a run panicked: {e}"))),
    };
    writeln!(runs_file, "{}", csv_row(&report_row(&spec, &policy, &outcome, timed_out))).map_err(io(runs_path))?;
    runs_file.flush().map_err(io(runs_path))?;
    if let Ok(report) = &outcome {
        let curve: Vec<f32> = report.coverage_curve.iter().map(|c| (c * 10_000.0).round() / 10_000.0).collect();
        let line = serde_json::json!({ "id": spec.id, "curve": curve });
        writeln!(curves_file, "{line}").map_err(io(&out.join("curves.jsonl")))?;
        if experiment.pictures && spec.seed == 1 {
            let name = format!("run-{}-{}-{}r-{}.png", spec.world, spec.label, spec.robots, spec.comm)
                .replace(['/', ' '], "_");
            let _ = std::fs::create_dir_all(out.join("pictures"));
            draw_run(report, &out.join("pictures").join(name)).map_err(|e| ExperimentError::Plot(e.to_string()))?;
        }
    }
    let finished = FINISHED.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
    if progress {
        let elapsed = started.elapsed().as_secs_f64();
        let eta = elapsed / finished as f64 * (total.saturating_sub(finished)) as f64;
        let status = match &outcome {
            Ok(r) => format!("{} steps{}", r.steps, if r.completed { "" } else { " (incomplete)" }),
            Err(e) => format!("FAILED: {e}"),
        };
        eprintln!("[{finished}/{total}] {} — {status} — elapsed {elapsed:.0} s, ETA {eta:.0} s", spec.id);
    }
    Ok(())
}

/// A picture of one run: the true map, each robot's trajectory in its own
/// colour, starts as discs and ends as squares (Burgard et al. 2005 Fig. 3),
/// and the segments for `segmentation`.
pub fn draw_run(report: &RunReport, path: &Path) -> Result<(), image::ImageError> {
    let Some(world) = &report.world else { return Ok(()) };
    let frame = world.frame;
    let mut picture = Picture::new(frame, 1200, |cell| {
        let i = frame.index(cell);
        if world.blocked[i] {
            return [40, 40, 40];
        }
        match report.segments.as_ref().map(|s| s[i]) {
            Some(label) if label != 0 => segment_tint(label),
            _ if world.reachable[i] => [255, 255, 255],
            _ => [200, 200, 200],
        }
    });
    for (k, trajectory) in report.trajectories.iter().enumerate() {
        picture.path(trajectory, PALETTE[k % PALETTE.len()]);
    }
    for (k, trajectory) in report.trajectories.iter().enumerate() {
        if let (Some(first), Some(last)) = (trajectory.first(), trajectory.last()) {
            picture.marker(*first, PALETTE[k % PALETTE.len()], false);
            picture.marker(*last, PALETTE[k % PALETTE.len()], true);
        }
    }
    picture.save(path)
}

/// The cells of the matrix: (world, label, robots, comm).
type CellKey = (String, String, usize, String);

fn metric(row: &Row, name: &str) -> Option<f64> {
    row.get(name).and_then(|v| v.parse().ok())
}

/// Groups the successful runs' figures by cell.
pub fn samples(rows: &[Row], name: &str) -> BTreeMap<CellKey, Sample> {
    let mut out: BTreeMap<CellKey, Vec<(u64, f64)>> = BTreeMap::new();
    for row in rows.iter().filter(|r| r.get("status").map(String::as_str) == Some("ok")) {
        let key =
            (row["world"].clone(), row["label"].clone(), row["robots"].parse().unwrap_or(0), row["comm_range"].clone());
        let value = if name == "distance" { metric(row, "distance_mean") } else { metric(row, name) };
        let seed = row.get("seed").and_then(|s| s.parse().ok()).unwrap_or(0);
        if let Some(v) = value {
            out.entry(key).or_default().push((seed, v));
        }
    }
    out.into_iter().map(|(k, v)| (k, Sample::seeded(v))).collect()
}

/// Writes `summary.csv`: per cell, runs, completions, and mean ± 95 % CI of each figure.
pub fn summarize(experiment: &Experiment, out: &Path) -> Result<(), ExperimentError> {
    let rows = read_runs(out)?;
    let figures = ["steps", "t50", "t90", "t95", "t100", "distance", "idle_steps", "overlap", "replans", "wall_time_s"];
    let per_figure: Vec<BTreeMap<CellKey, Sample>> = figures.iter().map(|f| samples(&rows, f)).collect();
    let mut cells: BTreeMap<CellKey, (usize, usize, usize)> = BTreeMap::new();
    for row in &rows {
        let key =
            (row["world"].clone(), row["label"].clone(), row["robots"].parse().unwrap_or(0), row["comm_range"].clone());
        let entry = cells.entry(key).or_default();
        entry.0 += 1;
        if row.get("completed").map(String::as_str) == Some("true") {
            entry.1 += 1;
        }
        if row.get("status").map(String::as_str) != Some("ok") {
            entry.2 += 1;
        }
    }
    let path = out.join("summary.csv");
    let mut file = std::fs::File::create(&path).map_err(io(&path))?;
    let mut header = vec!["world", "label", "robots", "comm_range", "runs", "completed", "failed"]
        .into_iter()
        .map(str::to_owned)
        .collect::<Vec<_>>();
    for f in figures {
        header.extend([format!("{f}_mean"), format!("{f}_ci95"), format!("{f}_n")]);
    }
    writeln!(file, "{}", header.join(",")).map_err(io(&path))?;
    for (key, (runs, completed, failed)) in &cells {
        let mut row = vec![
            key.0.clone(),
            key.1.clone(),
            key.2.to_string(),
            key.3.clone(),
            runs.to_string(),
            completed.to_string(),
            failed.to_string(),
        ];
        for samples in &per_figure {
            match samples.get(key) {
                Some(s) => row.extend([format!("{:.4}", s.mean()), format!("{:.4}", s.ci95()), s.len().to_string()]),
                None => row.extend([String::new(), String::new(), "0".into()]),
            }
        }
        writeln!(file, "{}", csv_row(&row)).map_err(io(&path))?;
    }
    let _ = experiment;
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
            let drawn = crate::plots::draw(experiment, spec, &world, &rows, out, &base)?;
            written.extend(drawn);
        }
    }
    Ok(written)
}
