//! `fleet-sim`: a simulated robot fleet driving the exploration executive.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, anyhow, bail, ensure};
use clap::{Args, Parser, Subcommand};
use tracing_subscriber::EnvFilter;

use client_sim::console::StdoutError;
use client_sim::experiment::Experiment;
use client_sim::fleet::{CommRange, Fault, FaultKind, Interference, Layout, WorldSpec};
use client_sim::generate::Generator;
use client_sim::robot::RobotModel;
use client_sim::world::StartChoice;
use client_sim::{RunConfig, RunReport};
use client_sim::{errln, outln};
use exploration::math::{Point2, ShortNumber};

/// Planning allocates a cost map per robot (megabytes each) and drops it
/// when the plan is made; the system allocator hands such blocks back to
/// the kernel and takes fresh zeroed pages for the next plan, so a fifth of
/// a replanning went to page faults. mimalloc keeps them.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Most calls of one kind a simulated robot sends per second under load.
const MAX_ROBOT_HZ: f64 = 100.0;

/// Longest `--retry-for`: a day of retrying an unreachable executive.
const MAX_RETRY_BUDGET: Duration = Duration::from_secs(86_400);

/// A simulated robot fleet that explores a building map against the exploration executive.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
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
struct BoundArgs {
    /// The experiment file (TOML; see experiments/).
    #[arg(long)]
    config: PathBuf,
    /// Folder holding its runs.csv (default: docs/results/<experiment name>).
    #[arg(long)]
    runs: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct LoadPlotArgs {
    /// The plot's path without extension; a PNG and an SVG are written.
    #[arg(long)]
    out: PathBuf,
    /// Reports of `load --json`, one per offered load.
    #[arg(required = true)]
    reports: Vec<PathBuf>,
}

#[derive(Debug, Args)]
struct LoadArgs {
    /// Missions at once.
    #[arg(long, default_value_t = 20)]
    missions: usize,
    /// Robots per mission.
    #[arg(long, default_value_t = 50)]
    robots: usize,
    /// Seconds the robots run at their rates.
    #[arg(long, default_value_t = 60.0)]
    duration: f64,
    /// Heartbeats per robot per second.
    #[arg(long, default_value_t = 2.0)]
    heartbeat_hz: f64,
    /// Map updates (the sensor's footprint) per robot per second.
    #[arg(long, default_value_t = 1.0)]
    map_hz: f64,
    /// Multiplies both rates: a sweep of offered load.
    #[arg(long, default_value_t = 1.0)]
    rate_scale: f64,
    /// Robots' speed, metres per second.
    #[arg(long, default_value_t = 0.5)]
    speed: f64,
    /// Sensor range, metres (the patches are its footprint).
    #[arg(long, default_value_t = 3.0)]
    sensor_range: f64,
    /// The world every mission explores (default: the bundled Nav2
    /// warehouse, which 50 robots explore in under half a minute; after
    /// that a mission only reports: give a larger world for a longer run).
    #[command(flatten)]
    world: WorldArgs,
    /// Cell size, metres.
    #[arg(long, default_value_t = 0.15)]
    cell_size: f64,
    /// Coordination policy.
    #[arg(long, default_value = "minpos")]
    policy: String,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// How the map patches carry their cells: occupancy-percent (a byte
    /// per cell, as ROS's OccupancyGrid) or probability (a float per cell
    /// and an unknown mask).
    #[arg(long, default_value = "occupancy-percent")]
    cell_encoding: client_sim::load::CellEncoding,
    /// Executive to load; without it one is started in this process.
    #[arg(long)]
    server: Option<String>,
    /// Operator token of that executive.
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKEN", hide_env_values = true)]
    token: Option<String>,
    #[command(flatten)]
    tls: TlsArgs,
    /// The executive's pid, to report its CPU and memory (default: this
    /// process when the executive is embedded).
    #[arg(long)]
    executive_pid: Option<u32>,
    /// Seconds of the closed-loop capacity phase (0: none).
    #[arg(long, default_value_t = 10.0)]
    capacity: f64,
    /// Concurrent callers in the capacity phase (default: one per robot,
    /// each sending its next call when the last is answered).
    #[arg(long)]
    capacity_callers: Option<usize>,
    /// Write the report as JSON to this file as well.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Send every call when due even after a refusal asked the robot to
    /// hold its calls of that kind for a while (the retry hint).
    #[arg(long)]
    ignore_pushback: bool,
}

#[derive(Debug, Args)]
struct ExperimentArgs {
    /// The experiment file (TOML; see experiments/).
    #[arg(long)]
    config: PathBuf,
    /// Folder for runs.csv, summary.csv, curves and plots (default:
    /// docs/results/<experiment name>).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Runs at a time (default: the number of cores).
    #[arg(long)]
    jobs: Option<usize>,
    /// Drive one executive for every run instead of one embedded per run.
    #[arg(long)]
    server: Option<String>,
    /// Operator token of the executive given by `--server`.
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Only redraw summary and plots from the runs already done.
    #[arg(long)]
    replot: bool,
}

#[derive(Debug, Args)]
struct ReportArgs {
    /// Where to write the report.
    #[arg(long, default_value = "docs/results.md")]
    out: PathBuf,
    /// Folder holding each experiment's results folder.
    #[arg(long, default_value = client_sim::report::DEFAULT_RESULTS)]
    results: PathBuf,
    /// The experiment files, in the order of the report.
    configs: Vec<PathBuf>,
}

/// TLS towards an executive given by `--server https://…`.
#[derive(Debug, Args)]
struct TlsArgs {
    /// PEM CA certificate(s) to trust for the executive's certificate
    /// (default: the system's roots, for an `https://` server).
    #[arg(long, env = "COORDINATOR_TLS_CA")]
    tls_ca: Option<PathBuf>,
    /// PEM client certificate, when the executive asks for one (mutual TLS).
    #[arg(long, env = "COORDINATOR_TLS_CLIENT_CERT", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM key of --tls-cert.
    #[arg(long, env = "COORDINATOR_TLS_CLIENT_KEY", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
}

impl TlsArgs {
    fn settings(&self) -> anyhow::Result<Option<exploration_proto::client::ClientTls>> {
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
struct WorldArgs {
    /// ROS map_server YAML of the world to explore.
    #[arg(long, conflicts_with = "world")]
    map: Option<PathBuf>,
    /// A generated world instead of a map: unstructured[:density],
    /// office, corridor, maze[:corridor width m], empty.
    #[arg(long)]
    world: Option<String>,
    /// Size of a generated world, WIDTHxHEIGHT in metres.
    #[arg(long, default_value = "20x20")]
    size: String,
}

impl WorldArgs {
    /// The world asked for, or `default` when neither a map nor a generator was given.
    fn spec(&self, default: Option<PathBuf>) -> anyhow::Result<WorldSpec> {
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
struct RunArgs {
    #[command(flatten)]
    world: WorldArgs,
    /// Number of robots.
    #[arg(long, default_value_t = 3)]
    robots: usize,
    /// Coordination policy (ask the executive's ListPolicies for the list).
    #[arg(long, default_value = "burgard")]
    policy: String,
    /// Policy parameter, as key=value; repeatable.
    #[arg(long = "param", value_parser = parse_param)]
    params: Vec<(String, f64)>,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Executive to drive, e.g. http://127.0.0.1:50051, or replicas sharing
    /// a database, comma-separated (each call follows its mission to the
    /// replica that holds it); without it, one is started on a loopback
    /// port for the run.
    #[arg(long)]
    server: Option<String>,
    /// Operator token of that executive; for the embedded one, the token it
    /// is started with (otherwise a random one only this run knows).
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKEN", hide_env_values = true)]
    token: Option<String>,
    #[command(flatten)]
    tls: TlsArgs,
    /// Database file for the embedded executive (default: a temporary file).
    #[arg(long)]
    db: Option<PathBuf>,
    /// Simulation cell size in metres (Burgard et al. 2005: 0.15); maps are
    /// coarsened conservatively.
    #[arg(long, default_value_t = 0.15)]
    cell_size: f64,
    /// Sensor range, metres.
    #[arg(long, default_value_t = 4.0)]
    sensor_range: f64,
    /// Sensor field of view, degrees.
    #[arg(long, default_value_t = 360.0)]
    fov: f64,
    /// Robot speed, m/s (0.5: one cell per step).
    #[arg(long, default_value_t = 0.5)]
    speed: f64,
    /// Robot footprint radius, metres.
    #[arg(long, default_value_t = 0.0)]
    footprint: f64,
    /// A robot model for a heterogeneous team, repeatable, robot i taking
    /// model i mod count: sensor=M,fov=DEG,speed=MPS,footprint=M (omitted
    /// keys take the options above).
    #[arg(long = "model")]
    models: Vec<String>,
    /// Start: `auto` (roomiest cell), `random` (seeded), or `x,y` in metres.
    #[arg(long, default_value = "auto")]
    start: String,
    /// `together` (packed on distinct free cells around the start) or `spread` (each at a random cell).
    #[arg(long, default_value = "together")]
    layout: String,
    /// Probability that a move near another robot happens (Burgard et al.
    /// 2005: 0.7); 1 turns interference off.
    #[arg(long, default_value_t = 0.7)]
    interference: f64,
    /// Distance under which robots interfere, metres.
    #[arg(long, default_value_t = 1.0)]
    interference_radius: f64,
    /// Limited communication range: metres (`5`) or a share of the map's
    /// diameter (`0.3d`); unlimited without it.
    #[arg(long)]
    comm_range: Option<String>,
    /// Give up after this many steps.
    #[arg(long, default_value_t = 50_000)]
    max_steps: u64,
    /// How long robots keep retrying an unreachable executive, seconds.
    #[arg(long, default_value_t = 120.0)]
    retry_for: f64,
    /// Write a picture of the run (trajectories, start and end) to this PNG.
    #[arg(long)]
    picture: Option<PathBuf>,
    /// Print one JSON object on the last line instead of a summary.
    #[arg(long)]
    json: bool,
    /// No progress lines.
    #[arg(long)]
    quiet: bool,
    /// Failure injection: robot N dies (goes silent) at step S, as N@S; repeatable.
    #[arg(long = "kill", value_parser = parse_at_step)]
    kills: Vec<(usize, u64)>,
    /// Failure injection: robot N freezes (reports but cannot move) at step S, as N@S; repeatable.
    #[arg(long = "freeze", value_parser = parse_at_step)]
    freezes: Vec<(usize, u64)>,
    /// Failure injection: robot N reports targets in a rectangle unreachable,
    /// as N:x0,y0,x1,y1 (metres); repeatable.
    #[arg(long = "cannot-reach", value_parser = parse_cannot_reach)]
    cannot_reach: Vec<(usize, Point2, Point2)>,
    /// The mission's lease: a robot silent this long loses its task, seconds
    /// (executive default 15).
    #[arg(long)]
    lease: Option<f64>,
    /// The mission's stall timeout: a robot no closer to its target for this
    /// long has the task failed, seconds (executive default 30).
    #[arg(long)]
    stall: Option<f64>,
    /// Milliseconds of wall-clock time per step, to watch or steer the run
    /// with coordctl as it happens; 0 runs flat out (the default, or 40
    /// with --view).
    #[arg(long)]
    pace_ms: Option<u64>,
    /// Serve the embedded executive's live web view at this address
    /// (default 127.0.0.1:8080; port 0 picks a free one) and print its URL
    /// and a read-only token; the view stays up after the run until Ctrl-C.
    #[arg(long, num_args = 0..=1, default_missing_value = "127.0.0.1:8080")]
    view: Option<std::net::SocketAddr>,
    /// After exploring, follow the executive's home tasks until every robot
    /// is back at its start (or the mission's rendezvous).
    #[arg(long)]
    return_home: bool,
    /// Give the mission the world's rooms and corridors (the office
    /// generator's own, or the segmentation of the complete map), as Wurm
    /// et al. 2008 did in simulation; the `segmentation` policy then plans
    /// on them instead of segmenting the explored map online.
    #[arg(long)]
    given_segmentation: bool,
}

fn parse_at_step(s: &str) -> Result<(usize, u64), String> {
    let (robot, step) = s.split_once('@').ok_or_else(|| format!("{s:?} is not ROBOT@STEP (e.g. 1@300)"))?;
    let robot = robot.trim().trim_start_matches("robot-");
    Ok((
        robot.parse().map_err(|e| format!("{s:?}: the robot index is not a number: {e}"))?,
        step.trim().parse().map_err(|e| format!("{s:?}: the step is not a number: {e}"))?,
    ))
}

fn parse_cannot_reach(s: &str) -> Result<(usize, Point2, Point2), String> {
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

fn parse_param(s: &str) -> Result<(String, f64), String> {
    let (key, value) = s.split_once('=').ok_or_else(|| format!("{s:?} is not key=value"))?;
    let value: f64 = value.trim().parse().map_err(|e| format!("{s:?}: the value is not a number: {e}"))?;
    Ok((key.trim().to_owned(), value))
}

fn parse_start(s: &str) -> anyhow::Result<StartChoice> {
    Ok(match s {
        "auto" => StartChoice::Auto,
        "random" => StartChoice::Random,
        xy => {
            let (x, y) = xy.split_once(',').with_context(|| format!("--start {xy:?}: expected auto, random or x,y"))?;
            StartChoice::At(Point2::new(x.trim().parse()?, y.trim().parse()?))
        }
    })
}

#[tokio::main]
async fn main() -> ExitCode {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn"));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    let done = match Cli::parse().command {
        Command::Run(args) => run(*args).await,
        Command::Experiment(args) => experiment(args).await,
        Command::Report(args) => report(args),
        Command::Load(args) => load(*args).await,
        Command::LoadPlot(args) => load_plot(args),
        Command::Bound(args) => bound(args),
    };
    match done {
        Ok(()) => ExitCode::SUCCESS,
        // `fleet-sim bound ... | head`: the reader had what it wanted.
        Err(e) if StdoutError::is_reader_gone(&e) => ExitCode::SUCCESS,
        Err(e) => {
            errln!("fleet-sim: {}", client_sim::console::report(e.as_ref()));
            ExitCode::FAILURE
        }
    }
}

async fn load(args: LoadArgs) -> anyhow::Result<()> {
    let seconds = |v: f64, flag: &str| {
        anyhow::ensure!(v.is_finite() && (0.0..=86_400.0).contains(&v), "{flag} must be seconds in [0, 86400]");
        Ok(Duration::from_secs_f64(v))
    };
    anyhow::ensure!(args.rate_scale > 0.0 && args.rate_scale.is_finite(), "--rate-scale must be positive");
    // A robot's own rates: a real one heartbeats at a few hertz. Beyond this
    // the schedule's periods shrink towards nothing and the tool, not the
    // executive, is what gets measured (1e9 Hz never finished).
    for (flag, hz) in [("--heartbeat-hz", args.heartbeat_hz), ("--map-hz", args.map_hz)] {
        let scaled = hz * args.rate_scale;
        anyhow::ensure!(
            (0.0..=MAX_ROBOT_HZ).contains(&scaled),
            "{flag} {} (× --rate-scale {}): a robot's rate must lie in [0, {MAX_ROBOT_HZ}] per second",
            ShortNumber(hz),
            ShortNumber(args.rate_scale)
        );
    }
    anyhow::ensure!(args.capacity_callers != Some(0), "--capacity-callers must be at least 1");
    anyhow::ensure!(args.executive_pid != Some(0), "--executive-pid must name a process (1 or more)");
    let warehouse = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../maps/nav2_warehouse.yaml");
    let world = args.world.spec(Some(warehouse))?;
    let config = client_sim::load::LoadConfig {
        missions: args.missions,
        robots: args.robots,
        duration: seconds(args.duration, "--duration")?,
        heartbeat_hz: args.heartbeat_hz * args.rate_scale,
        map_hz: args.map_hz * args.rate_scale,
        speed_mps: args.speed,
        sensor_range_m: args.sensor_range,
        world,
        cell_size: args.cell_size,
        policy: args.policy,
        seed: args.seed,
        executive_pid: args.executive_pid.or(args.server.is_none().then(std::process::id)),
        server: args.server,
        token: args.token,
        tls: args.tls.settings()?,
        capacity: seconds(args.capacity, "--capacity")?,
        capacity_callers: args.capacity_callers,
        cell_encoding: args.cell_encoding,
        honour_pushback: !args.ignore_pushback,
    };
    let report = client_sim::load::run(&config).await?;
    errln!("{}", report.summary().trim_end());
    let json = serde_json::to_string(&report)?;
    if let Some(path) = args.json {
        std::fs::write(&path, &json).with_context(|| format!("cannot write {}", path.display()))?;
    }
    outln!("{json}")?;
    Ok(())
}

fn load_plot(args: LoadPlotArgs) -> anyhow::Result<()> {
    let reports = args
        .reports
        .iter()
        .map(|path| {
            let text = coordinator::files::read_text_at_most(path, 256)
                .with_context(|| format!("cannot read {}", path.display()))?;
            serde_json::from_str(&text).with_context(|| format!("{} is not a load report", path.display()))
        })
        .collect::<anyhow::Result<Vec<serde_json::Value>>>()?;
    for file in client_sim::plots::draw_load_sweep(&reports, &args.out)? {
        outln!("{}", file.display())?;
    }
    Ok(())
}

async fn run(args: RunArgs) -> anyhow::Result<()> {
    if args.robots == 0 {
        bail!("--robots must be at least 1");
    }
    let world = args.world.spec(None)?;
    let mut config = RunConfig::on(world, args.robots, &args.policy);
    config.params = args.params.into_iter().collect::<BTreeMap<_, _>>();
    config.seed = args.seed;
    config.server = args.server;
    config.token = args.token;
    config.tls = args.tls.settings()?;
    config.db = args.db;
    config.cell_size = Some(args.cell_size);
    let base = RobotModel {
        sensor_range_m: args.sensor_range,
        field_of_view_rad: args.fov.to_radians(),
        speed_mps: args.speed,
        footprint_radius_m: args.footprint,
    };
    config.models = if args.models.is_empty() {
        vec![base]
    } else {
        args.models.iter().map(|m| parse_model(m, base)).collect::<anyhow::Result<_>>()?
    };
    config.start = parse_start(&args.start)?;
    config.layout = match args.layout.as_str() {
        "together" => Layout::Together,
        "spread" => Layout::Spread,
        other => bail!("--layout {other:?}: expected together or spread"),
    };
    config.interference = Interference::with(args.interference, args.interference_radius).map_err(|e| anyhow!(e))?;
    config.comm_range = args.comm_range.as_deref().map(CommRange::parse).transpose().map_err(|e| anyhow!(e))?;
    ensure!(args.max_steps >= 1, "--max-steps must be at least 1");
    config.max_steps = args.max_steps;
    config.retry_budget = Duration::try_from_secs_f64(args.retry_for)
        .ok()
        .filter(|budget| *budget <= MAX_RETRY_BUDGET)
        .with_context(|| format!("--retry-for {}: give seconds from 0 to a day", ShortNumber(args.retry_for)))?;
    config.progress = !args.quiet && !args.json;
    config.lease_s = args.lease;
    config.stall_s = args.stall;
    if args.view.is_some() && config.server.is_some() {
        bail!("--view shows the embedded executive; for one given by --server, start it with --http");
    }
    let pace_ms = args.pace_ms.unwrap_or(if args.view.is_some() { 40 } else { 0 });
    ensure!(pace_ms <= 60_000, "--pace-ms {pace_ms}: at most a minute (60000) per step");
    config.pace = (pace_ms > 0).then(|| Duration::from_millis(pace_ms));
    config.view = args.view;
    config.linger = args.view.is_some();
    config.return_home = args.return_home;
    config.given_segmentation = args.given_segmentation;
    config.faults = args
        .kills
        .iter()
        .map(|&(robot, step)| Fault { robot, kind: FaultKind::Dies(step) })
        .chain(args.freezes.iter().map(|&(robot, step)| Fault { robot, kind: FaultKind::Freezes(step) }))
        .chain(
            args.cannot_reach.iter().map(|&(robot, min, max)| Fault { robot, kind: FaultKind::CannotReach(min, max) }),
        )
        .collect();
    let report = client_sim::run(&config).await.context("the run failed")?;
    if let Some(path) = &args.picture {
        client_sim::experiment::draw_run(&report, path).with_context(|| format!("cannot write {}", path.display()))?;
    }
    if args.json {
        outln!("{}", serde_json::to_string(&report)?)?;
    } else {
        print_summary(&report, config.return_home)?;
    }
    Ok(())
}

async fn experiment(args: ExperimentArgs) -> anyhow::Result<()> {
    let experiment = Experiment::load(&args.config)?;
    let out = args.out.unwrap_or_else(|| PathBuf::from(client_sim::report::DEFAULT_RESULTS).join(&experiment.name));
    if args.replot {
        anyhow::ensure!(out.join("runs.csv").exists(), "--replot: no runs in {} to plot", out.display());
        client_sim::runs::summarize(&out)?;
        client_sim::plots::draw_plots(&experiment, &out)?;
        return Ok(());
    }
    let jobs = args.jobs.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let server = args.server.map(|url| client_sim::experiment::RemoteExecutive { url, token: args.token });
    client_sim::experiment::run_experiment(&args.config, &out, jobs, server, true)
        .await
        .with_context(|| format!("experiment {} failed", args.config.display()))?;
    errln!("results in {}", out.display());
    Ok(())
}

fn bound(args: BoundArgs) -> anyhow::Result<()> {
    use client_sim::bound::{against_runs, matrix_bounds};

    let experiment = Experiment::load(&args.config)?;
    let config_dir = args.config.parent().unwrap_or_else(|| std::path::Path::new("."));
    let bounds = matrix_bounds(&experiment, config_dir).map_err(anyhow::Error::msg)?;
    outln!("world,robots,comm_range,seed,travel,pairs,sweep,bound")?;
    for cell in &bounds {
        let (run, b) = (&cell.run, &cell.bound);
        outln!(
            "{},{},{},{},{},{},{},{}",
            run.world,
            run.robots,
            run.comm,
            run.seed,
            b.travel,
            b.pairs,
            b.sweep,
            b.steps()
        )?;
    }
    let dir = args.runs.unwrap_or_else(|| PathBuf::from(client_sim::report::DEFAULT_RESULTS).join(&experiment.name));
    let runs = client_sim::runs::read_runs(&dir)?;
    if runs.is_empty() {
        errln!("no runs in {} to hold against the bounds", dir.display());
        return Ok(());
    }
    outln!("\nlabel,robots,completed_runs,mean_steps,mean_bound,steps_over_bound")?;
    for a in against_runs(&bounds, &runs) {
        let ratio = a.mean_steps / a.mean_bound;
        outln!("{},{},{},{:.1},{:.1},{ratio:.3}", a.label, a.robots, a.runs, a.mean_steps, a.mean_bound)?;
    }
    Ok(())
}

fn report(args: ReportArgs) -> anyhow::Result<()> {
    let experiments = args
        .configs
        .iter()
        .map(|c| {
            let e = Experiment::load(c)?;
            let dir = args.results.join(&e.name);
            Ok((e, dir))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    client_sim::report::write_report(&experiments, &args.results, &args.out)?;
    errln!("wrote {}", args.out.display());
    Ok(())
}

fn parse_size(s: &str) -> anyhow::Result<(f64, f64)> {
    let (w, h) = s.split_once('x').with_context(|| format!("--size {s:?}: expected WIDTHxHEIGHT in metres"))?;
    Ok((w.trim().parse()?, h.trim().parse()?))
}

fn parse_model(s: &str, base: RobotModel) -> anyhow::Result<RobotModel> {
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

fn print_summary(r: &RunReport, return_home: bool) -> Result<(), StdoutError> {
    let steps = |t: Option<u64>| t.map_or("-".to_owned(), |t| t.to_string());
    outln!()?;
    outln!("mission {}  map {}  policy {}  robots {}  seed {}", r.mission_id, r.map, r.policy, r.robots, r.seed)?;
    outln!(
        "{}: {} after {} steps ({:.1} s wall time)",
        if r.completed { "completed" } else { "NOT completed" },
        r.ended,
        r.steps,
        r.wall_time_s
    )?;
    outln!("coverage {:.2} % of {} reachable cells ({} m cells)", 100.0 * r.coverage, r.reachable_cells, r.cell_size)?;
    outln!("steps to 50/90/95/100 %: {} / {} / {} / {}", steps(r.t50), steps(r.t90), steps(r.t95), steps(r.t100))?;
    let distances: Vec<String> = r.distance_per_robot.iter().map(|d| format!("{d:.1}")).collect();
    outln!("distance per robot (m): {}", distances.join(", "))?;
    outln!("replans {}  map updates {}  overlap {:.1} %", r.replans, r.map_updates, 100.0 * r.overlap)?;
    outln!(
        "targets abandoned before reached: {} ({:.2} per robot per 100 steps)",
        r.target_switches,
        r.switches_per_robot_per_100_steps()
    )?;
    match r.home_steps {
        Some(home) => outln!("every robot home {home} steps after exploration ended")?,
        None if return_home => outln!("not every robot got home within the step limit")?,
        None => {}
    }
    if let Some(f) = &r.fault_record {
        let states: Vec<String> = f.tasks_by_state.iter().map(|(s, n)| format!("{s} {n}")).collect();
        outln!("tasks: {}", states.join(", "))?;
        outln!(
            "failed for lack of progress {}  reported unreachable {}  robots lost at the end: {}",
            f.stalled_tasks,
            f.unreachable_tasks,
            if f.lost_robots.is_empty() { "none".to_owned() } else { f.lost_robots.join(", ") }
        )?;
    }
    Ok(())
}
