//! The command line: commands, their arguments and how they are read.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};

use client_sim::fleet::WorldSpec;
use client_sim::generate::Generator;
use client_sim::robot::RobotModel;
use client_sim::world::StartChoice;
use exploration::math::Point2;

/// A simulated robot fleet that explores a building map against the exploration executive.
#[derive(Debug, Parser)]
#[command(version, about)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Debug, Subcommand)]
pub(crate) enum Command {
    /// Explores one map with one team and prints what it measured.
    Run(Box<RunArgs>),
    /// Runs a matrix of missions from an experiment file, in parallel,
    /// resuming what an earlier call into the same folder left undone.
    Experiment(ExperimentArgs),
    /// Writes the results report from experiments already run.
    Report(ReportArgs),
    /// Loads an executive with many missions × many robots at real robots'
    /// rates, open-loop, and reports throughput, latency, triggers, the
    /// executive's CPU and memory, and its capacity against an empty call.
    Load(Box<LoadArgs>),
    /// Plots latency against offered load from `load --json` reports.
    LoadPlot(LoadPlotArgs),
    /// Prints how few steps any policy could take in each cell of an
    /// experiment (a lower bound on steps to full coverage), and each
    /// policy's mean steps against it from the experiment's runs.
    Bound(BoundArgs),
}

#[derive(Debug, Args)]
pub(crate) struct BoundArgs {
    /// The experiment file (TOML; see experiments/).
    #[arg(long)]
    pub(crate) config: PathBuf,
    /// Folder holding its runs.csv (default: docs/results/<experiment name>).
    #[arg(long)]
    pub(crate) runs: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub(crate) struct LoadPlotArgs {
    /// The plot's path without extension; a PNG and an SVG are written.
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Reports of `load --json`, one per offered load.
    #[arg(required = true)]
    pub(crate) reports: Vec<PathBuf>,
}

#[derive(Debug, Args)]
pub(crate) struct LoadArgs {
    /// Missions at once.
    #[arg(long, default_value_t = 20)]
    pub(crate) missions: usize,
    /// Robots per mission.
    #[arg(long, default_value_t = 50)]
    pub(crate) robots: usize,
    /// Seconds the robots run at their rates.
    #[arg(long, default_value_t = 60.0)]
    pub(crate) duration: f64,
    /// Heartbeats per robot per second.
    #[arg(long, default_value_t = 2.0)]
    pub(crate) heartbeat_hz: f64,
    /// Map updates (the sensor's footprint) per robot per second.
    #[arg(long, default_value_t = 1.0)]
    pub(crate) map_hz: f64,
    /// Multiplies both rates: a sweep of offered load.
    #[arg(long, default_value_t = 1.0)]
    pub(crate) rate_scale: f64,
    /// Robots' speed, metres per second.
    #[arg(long, default_value_t = 0.5)]
    pub(crate) speed: f64,
    /// Sensor range, metres (the patches are its footprint).
    #[arg(long, default_value_t = 3.0)]
    pub(crate) sensor_range: f64,
    /// The world every mission explores (default: the bundled Nav2
    /// warehouse, which 50 robots explore in under half a minute; after
    /// that a mission only reports: give a larger world for a longer run).
    #[command(flatten)]
    pub(crate) world: WorldArgs,
    /// Cell size, metres.
    #[arg(long, default_value_t = 0.15)]
    pub(crate) cell_size: f64,
    /// Coordination policy.
    #[arg(long, default_value = "minpos")]
    pub(crate) policy: String,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 1)]
    pub(crate) seed: u64,
    /// How the map patches carry their cells: occupancy-percent (a byte
    /// per cell, as ROS's OccupancyGrid) or probability (a float per cell
    /// and an unknown mask).
    #[arg(long, default_value = "occupancy-percent")]
    pub(crate) cell_encoding: client_sim::load::CellEncoding,
    /// Executive to load; without it one is started in this process.
    #[arg(long)]
    pub(crate) server: Option<String>,
    /// Operator token of that executive.
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKEN", hide_env_values = true)]
    pub(crate) token: Option<String>,
    #[command(flatten)]
    pub(crate) tls: TlsArgs,
    /// The executive's pid, to report its CPU and memory (default: this
    /// process when the executive is embedded).
    #[arg(long)]
    pub(crate) executive_pid: Option<u32>,
    /// Seconds of the closed-loop capacity phase (0: none).
    #[arg(long, default_value_t = 10.0)]
    pub(crate) capacity: f64,
    /// Concurrent callers in the capacity phase (default: one per robot,
    /// each sending its next call when the last is answered).
    #[arg(long)]
    pub(crate) capacity_callers: Option<usize>,
    /// Write the report as JSON to this file as well.
    #[arg(long)]
    pub(crate) json: Option<PathBuf>,
    /// Send every call when due even after a refusal asked the robot to
    /// hold its calls of that kind for a while (the retry hint).
    #[arg(long)]
    pub(crate) ignore_pushback: bool,
}

#[derive(Debug, Args)]
pub(crate) struct ExperimentArgs {
    /// The experiment file (TOML; see experiments/).
    #[arg(long)]
    pub(crate) config: PathBuf,
    /// Folder for runs.csv, summary.csv, curves and plots (default:
    /// docs/results/<experiment name>).
    #[arg(long)]
    pub(crate) out: Option<PathBuf>,
    /// Runs at a time (default: the number of cores).
    #[arg(long)]
    pub(crate) jobs: Option<usize>,
    /// Drive one executive for every run instead of one embedded per run.
    #[arg(long)]
    pub(crate) server: Option<String>,
    /// Operator token of the executive given by `--server`.
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKEN", hide_env_values = true)]
    pub(crate) token: Option<String>,
    /// Only redraw summary and plots from the runs already done.
    #[arg(long)]
    pub(crate) replot: bool,
}

#[derive(Debug, Args)]
pub(crate) struct ReportArgs {
    /// Where to write the report.
    #[arg(long, default_value = "docs/results.md")]
    pub(crate) out: PathBuf,
    /// Folder holding each experiment's results folder.
    #[arg(long, default_value = client_sim::report::DEFAULT_RESULTS)]
    pub(crate) results: PathBuf,
    /// The experiment files, in the order of the report.
    pub(crate) configs: Vec<PathBuf>,
}

/// TLS towards an executive given by `--server https://…`.
#[derive(Debug, Args)]
pub(crate) struct TlsArgs {
    /// PEM CA certificate(s) to trust for the executive's certificate
    /// (default: the system's roots, for an `https://` server).
    #[arg(long, env = "COORDINATOR_TLS_CA")]
    pub(crate) tls_ca: Option<PathBuf>,
    /// PEM client certificate, when the executive asks for one (mutual TLS).
    #[arg(long, env = "COORDINATOR_TLS_CLIENT_CERT", requires = "tls_key")]
    pub(crate) tls_cert: Option<PathBuf>,
    /// PEM key of --tls-cert.
    #[arg(long, env = "COORDINATOR_TLS_CLIENT_KEY", requires = "tls_cert")]
    pub(crate) tls_key: Option<PathBuf>,
}

impl TlsArgs {
    pub(crate) fn settings(&self) -> anyhow::Result<Option<exploration_proto::client::ClientTls>> {
        if self.tls_ca.is_none() && self.tls_cert.is_none() {
            return Ok(None);
        }
        let tls = exploration_proto::client::ClientTls::from_files(
            self.tls_ca.as_deref(),
            self.tls_cert.as_deref(),
            self.tls_key.as_deref(),
        )
        .context("cannot read the TLS files")?;
        Ok(Some(tls))
    }
}

/// A map or a generated world.
#[derive(Debug, Args)]
pub(crate) struct WorldArgs {
    /// ROS map_server YAML of the world to explore.
    #[arg(long, conflicts_with = "world")]
    pub(crate) map: Option<PathBuf>,
    /// A generated world instead of a map: unstructured[:density],
    /// office, corridor, maze[:corridor width m], empty.
    #[arg(long)]
    pub(crate) world: Option<String>,
    /// Size of a generated world, WIDTHxHEIGHT in metres.
    #[arg(long, default_value = "20x20")]
    pub(crate) size: String,
}

impl WorldArgs {
    /// The world asked for, or `default` when neither a map nor a generator was given.
    pub(crate) fn spec(&self, default: Option<PathBuf>) -> anyhow::Result<WorldSpec> {
        match (&self.map, &self.world, default) {
            (Some(map), None, _) => Ok(WorldSpec::Map(map.clone())),
            (None, Some(generator), _) => {
                let generator = Generator::parse(generator).map_err(|e| anyhow::anyhow!("--world {e}"))?;
                let (w, h) = parse_size(&self.size)?;
                Ok(WorldSpec::Generated { generator, width_m: w, height_m: h })
            }
            (None, None, Some(map)) => Ok(WorldSpec::Map(map)),
            _ => bail!("give --map PATH.yaml or --world KIND"),
        }
    }
}

#[derive(Debug, Args)]
pub(crate) struct RunArgs {
    #[command(flatten)]
    pub(crate) world: WorldArgs,
    /// Number of robots.
    #[arg(long, default_value_t = 3)]
    pub(crate) robots: usize,
    /// Coordination policy (ask the executive's ListPolicies for the list).
    #[arg(long, default_value = "burgard")]
    pub(crate) policy: String,
    /// Policy parameter, as key=value; repeatable.
    #[arg(long = "param", value_parser = parse_param)]
    pub(crate) params: Vec<(String, f64)>,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 1)]
    pub(crate) seed: u64,
    /// Executive to drive, e.g. http://127.0.0.1:50051, or replicas sharing
    /// a database, comma-separated (each call follows its mission to the
    /// replica that holds it); without it, one is started on a loopback
    /// port for the run.
    #[arg(long)]
    pub(crate) server: Option<String>,
    /// Operator token of that executive; for the embedded one, the token it
    /// is started with (otherwise a random one only this run knows).
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKEN", hide_env_values = true)]
    pub(crate) token: Option<String>,
    #[command(flatten)]
    pub(crate) tls: TlsArgs,
    /// Database file for the embedded executive (default: a temporary file).
    #[arg(long)]
    pub(crate) db: Option<PathBuf>,
    /// Simulation cell size in metres (Burgard et al. 2005: 0.15); maps are
    /// coarsened conservatively.
    #[arg(long, default_value_t = 0.15)]
    pub(crate) cell_size: f64,
    /// Sensor range, metres.
    #[arg(long, default_value_t = 4.0)]
    pub(crate) sensor_range: f64,
    /// Sensor field of view, degrees.
    #[arg(long, default_value_t = 360.0)]
    pub(crate) fov: f64,
    /// Robot speed, m/s (0.5: one cell per step).
    #[arg(long, default_value_t = 0.5)]
    pub(crate) speed: f64,
    /// Robot footprint radius, metres.
    #[arg(long, default_value_t = 0.0)]
    pub(crate) footprint: f64,
    /// A robot model for a heterogeneous team, repeatable, robot i taking
    /// model i mod count: sensor=M,fov=DEG,speed=MPS,footprint=M (omitted
    /// keys take the options above).
    #[arg(long = "model")]
    pub(crate) models: Vec<String>,
    /// Start: `auto` (roomiest cell), `random` (seeded), or `x,y` in metres.
    #[arg(long, default_value = "auto", allow_hyphen_values = true)]
    pub(crate) start: String,
    /// `together` (packed on distinct free cells around the start) or `spread` (each at a random cell).
    #[arg(long, default_value = "together")]
    pub(crate) layout: String,
    /// Probability that a move near another robot happens (Burgard et al.
    /// 2005: 0.7); 1 turns interference off.
    #[arg(long, default_value_t = 0.7)]
    pub(crate) interference: f64,
    /// Distance under which robots interfere, metres.
    #[arg(long, default_value_t = 1.0)]
    pub(crate) interference_radius: f64,
    /// Limited communication range: metres (`5`) or a share of the map's
    /// diameter (`0.3d`); unlimited without it.
    #[arg(long)]
    pub(crate) comm_range: Option<String>,
    /// Give up after this many steps.
    #[arg(long, default_value_t = 50_000)]
    pub(crate) max_steps: u64,
    /// How long robots keep retrying an unreachable executive, seconds.
    #[arg(long, default_value_t = 120.0)]
    pub(crate) retry_for: f64,
    /// Write a picture of the run (trajectories, start and end) to this PNG.
    #[arg(long)]
    pub(crate) picture: Option<PathBuf>,
    /// Print one JSON object on the last line instead of a summary.
    #[arg(long)]
    pub(crate) json: bool,
    /// No progress lines.
    #[arg(long)]
    pub(crate) quiet: bool,
    /// Failure injection: robot N dies (goes silent) at step S, as N@S; repeatable.
    #[arg(long = "kill", value_parser = parse_at_step)]
    pub(crate) kills: Vec<(usize, u64)>,
    /// Failure injection: robot N freezes (reports but cannot move) at step S, as N@S; repeatable.
    #[arg(long = "freeze", value_parser = parse_at_step)]
    pub(crate) freezes: Vec<(usize, u64)>,
    /// Failure injection: robot N reports targets in a rectangle unreachable,
    /// as N:x0,y0,x1,y1 (metres); repeatable.
    #[arg(long = "cannot-reach", value_parser = parse_cannot_reach)]
    pub(crate) cannot_reach: Vec<(usize, Point2, Point2)>,
    /// The mission's lease: a robot silent this long loses its task, seconds
    /// (executive default 15).
    #[arg(long)]
    pub(crate) lease: Option<f64>,
    /// The mission's stall timeout: a robot no closer to its target for this
    /// long has the task failed, seconds (executive default 30).
    #[arg(long)]
    pub(crate) stall: Option<f64>,
    /// Milliseconds of wall-clock time per step, to watch or steer the run
    /// with coordctl as it happens; 0 runs flat out (the default, or 40
    /// with --view).
    #[arg(long)]
    pub(crate) pace_ms: Option<u64>,
    /// Serve the embedded executive's live web view at this address
    /// (default 127.0.0.1:8080; port 0 picks a free one) and print its URL
    /// and a read-only token; the view stays up after the run until Ctrl-C.
    #[arg(long, num_args = 0..=1, default_missing_value = "127.0.0.1:8080", value_parser = coordinator::cli::listen_address)]
    pub(crate) view: Option<std::net::SocketAddr>,
    /// After exploring, follow the executive's home tasks until every robot
    /// is back at its start (or the mission's rendezvous).
    #[arg(long)]
    pub(crate) return_home: bool,
    /// Give the mission the world's rooms and corridors (the office
    /// generator's own, or the segmentation of the complete map), as Wurm
    /// et al. 2008 did in simulation; the `segmentation` policy then plans
    /// on them instead of segmenting the explored map online.
    #[arg(long)]
    pub(crate) given_segmentation: bool,
}

pub(crate) fn parse_at_step(s: &str) -> Result<(usize, u64), String> {
    let (robot, step) = s.split_once('@').ok_or_else(|| format!("{s:?} is not ROBOT@STEP (e.g. 1@300)"))?;
    let robot = robot.trim().trim_start_matches("robot-");
    Ok((
        robot.parse().map_err(|e| format!("{s:?}: the robot index is not a number: {e}"))?,
        step.trim().parse().map_err(|e| format!("{s:?}: the step is not a number: {e}"))?,
    ))
}

pub(crate) fn parse_cannot_reach(s: &str) -> Result<(usize, Point2, Point2), String> {
    let (robot, rect) = s.split_once(':').ok_or_else(|| format!("{s:?} is not ROBOT:x0,y0,x1,y1"))?;
    let robot = robot.trim().trim_start_matches("robot-");
    let numbers: Vec<f64> = rect
        .split(',')
        .map(|v| v.trim().parse::<f64>().map_err(|e| format!("{s:?}: {v:?} is not a number: {e}")))
        .collect::<Result<_, _>>()?;
    let [x0, y0, x1, y1] = numbers[..] else { return Err(format!("{s:?}: give four numbers x0,y0,x1,y1")) };
    Ok((
        robot.parse().map_err(|e| format!("{s:?}: the robot index is not a number: {e}"))?,
        Point2::new(x0.min(x1), y0.min(y1)),
        Point2::new(x0.max(x1), y0.max(y1)),
    ))
}

pub(crate) fn parse_param(s: &str) -> Result<(String, f64), String> {
    let (key, value) = s.split_once('=').ok_or_else(|| format!("{s:?} is not key=value"))?;
    let value: f64 = value.trim().parse().map_err(|e| format!("{s:?}: the value is not a number: {e}"))?;
    Ok((key.trim().to_owned(), value))
}

pub(crate) fn parse_start(s: &str) -> anyhow::Result<StartChoice> {
    Ok(match s {
        "auto" => StartChoice::Auto,
        "random" => StartChoice::Random,
        xy => {
            let (x, y) = xy.split_once(',').with_context(|| format!("--start {xy:?}: expected auto, random or x,y"))?;
            StartChoice::At(Point2::new(metres("--start", xy, x)?, metres("--start", xy, y)?))
        }
    })
}

pub(crate) fn parse_size(s: &str) -> anyhow::Result<(f64, f64)> {
    let (w, h) = s.split_once('x').with_context(|| format!("--size {s:?}: expected WIDTHxHEIGHT in metres"))?;
    Ok((metres("--size", s, w)?, metres("--size", s, h)?))
}

/// One number of metres in `flag`'s value `whole`: finite, or refused naming
/// the flag (a NaN start was "inside a wall", a letter "invalid float literal").
fn metres(flag: &str, whole: &str, part: &str) -> anyhow::Result<f64> {
    match part.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        _ => bail!("{flag} {whole:?}: {:?} is not a finite number of metres", part.trim()),
    }
}

pub(crate) fn parse_model(s: &str, base: RobotModel) -> anyhow::Result<RobotModel> {
    let mut model = base;
    for part in s.split(',').filter(|p| !p.trim().is_empty()) {
        let (key, value) = part.split_once('=').with_context(|| format!("--model {s:?}: expected key=value pairs"))?;
        let value: f64 = value.trim().parse().with_context(|| format!("--model {s:?}: {key} is not a number"))?;
        match key.trim() {
            "sensor" => model.sensor_range_m = value,
            "fov" => model.field_of_view_rad = value.to_radians(),
            "speed" => model.speed_mps = value,
            "footprint" => model.footprint_radius_m = value,
            other => bail!("--model {s:?}: unknown key {other:?} (sensor, fov, speed, footprint)"),
        }
    }
    Ok(model)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Maps' origins are often negative (the nav2 ones are), so a start
    /// in metres may be too; it is a value, not an option.
    #[test]
    fn a_start_may_be_negative() {
        let cli = Cli::try_parse_from("fleet-sim run --map m.yaml --start -3.5,-2".split_whitespace()).unwrap();
        let Command::Run(run) = cli.command else { panic!("{:?}", cli.command) };
        assert_eq!(parse_start(&run.start).unwrap(), StartChoice::At(Point2::new(-3.5, -2.0)));
    }

    #[test]
    fn the_command_line_is_consistent() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }
}
