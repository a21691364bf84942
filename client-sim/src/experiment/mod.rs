//! The experiment runner: a matrix of worlds × team sizes × policies ×
//! communication ranges × seeds, each a real mission against an executive
//! over gRPC, run in parallel, resumable, with a time limit per run.
//!
//! An experiment is a TOML file (see `experiments/`). Its results go to a
//! folder: `runs.csv` (one row per run, every setting and every figure),
//! `curves.jsonl` (each run's coverage after every step), `summary.csv`
//! (means with 95 % confidence intervals per cell of the matrix), the plots
//! (PNG and SVG) and pictures of runs.

pub mod config;

use std::collections::BTreeSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

pub use config::{CheckSpec, Experiment, ExperimentError, PlotSpec, PolicyEntry, SimSettings, WorldEntry};
use config::{io, parse_range};

use crate::fleet::{Interference, Layout, RunConfig, RunReport, WorldSpec};
use crate::generate::Generator;
use crate::picture::{PALETTE, Picture, segment_tint};
use crate::robot::RobotModel;
use crate::runs::{RUN_COLUMNS, RunsFile, read_runs, summarize};
use crate::world::StartChoice;

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
pub(crate) fn run_config(
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
        (None, Some(g)) => {
            WorldSpec::Generated { generator: Generator::parse(g)?, width_m: world.width_m, height_m: world.height_m }
        }
        (None, None) => return Err("a world needs a map or a generator".into()),
    };
    let sim = &experiment.sim;
    let mut config = RunConfig::on(world_spec, spec.robots, &policy.name);
    config.params = policy.params.clone();
    config.given_segmentation = policy.given_segmentation;
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
    config.interference = Interference::with(sim.interference, sim.interference_radius)?;
    config.comm_range = parse_range(&spec.comm)?;
    config.max_steps = sim.max_steps;
    Ok(config)
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
                format!("{:.4}", r.switches_per_robot_per_100_steps()),
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
    let mut runs_file = RunsFile::open(out)?;
    let curves_path = out.join("curves.jsonl");
    let mut curves_file =
        std::fs::OpenOptions::new().create(true).append(true).open(&curves_path).map_err(io(&curves_path))?;
    let todo: Vec<RunSpec> = matrix(&experiment).into_iter().filter(|r| !done.contains(&r.id)).collect();
    let total = todo.len();
    if progress {
        crate::errln!("{}: {} runs to do, {} already done", experiment.name, total, done.len());
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
            record(joined, &mut runs_file, &mut curves_file, out, &experiment, &started, total, progress)?;
        }
    }
    while let Some(joined) = tasks.join_next().await {
        record(joined, &mut runs_file, &mut curves_file, out, &experiment, &started, total, progress)?;
    }
    summarize(out)?;
    crate::plots::draw_plots(&experiment, out)?;
    Ok(())
}

type Finished = (RunSpec, String, (Result<RunReport, String>, bool));

#[allow(clippy::too_many_arguments)]
fn record(
    joined: Result<Finished, tokio::task::JoinError>,
    runs_file: &mut RunsFile,
    curves_file: &mut std::fs::File,
    out: &Path,
    experiment: &Experiment,
    started: &Instant,
    total: usize,
    progress: bool,
) -> Result<(), ExperimentError> {
    static FINISHED: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let (spec, policy, (outcome, timed_out)) = match joined {
        Ok(f) => f,
        Err(e) => return Err(ExperimentError::Plot(format!("a run panicked: {e}"))),
    };
    runs_file.append(&report_row(&spec, &policy, &outcome, timed_out))?;
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
        crate::errln!("[{finished}/{total}] {} — {status} — elapsed {elapsed:.0} s, ETA {eta:.0} s", spec.id);
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
