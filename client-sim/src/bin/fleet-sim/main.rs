//! `fleet-sim`: a simulated robot fleet driving the exploration executive.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, anyhow, bail, ensure};
use clap::Parser;
use tracing_subscriber::EnvFilter;

use client_sim::console::StdoutError;
use client_sim::experiment::Experiment;
use client_sim::fleet::{CommRange, Fault, FaultKind, Interference, Layout};
use client_sim::robot::RobotModel;
use client_sim::{RunConfig, RunReport};
use client_sim::{errln, outln};
use exploration::math::ShortNumber;

/// Planning allocates a cost map per robot (megabytes each) and drops it
/// when the plan is made; the system allocator hands such blocks back to
/// the kernel and takes fresh zeroed pages for the next plan, so a fifth of
/// a replanning went to page faults. mimalloc keeps them.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Most simulated robots one load test runs: each is a gRPC client with
/// its own connection.
const MAX_LOAD_ROBOTS: usize = 100_000;

/// Most calls of one kind a simulated robot sends per second under load.
const MAX_ROBOT_HZ: f64 = 100.0;

/// Longest `--retry-for`: a day of retrying an unreachable executive.
const MAX_RETRY_BUDGET: Duration = Duration::from_secs(86_400);

mod cli;

use cli::{
    BoundArgs, Cli, Command, ExperimentArgs, LoadArgs, LoadPlotArgs, ReportArgs, RunArgs, parse_model, parse_start,
};

#[tokio::main]
async fn main() -> ExitCode {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(coordinator::cli::colours_on(&std::io::stderr()))
        .init();
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
    let team = args.missions.checked_mul(args.robots).filter(|&n| n <= MAX_LOAD_ROBOTS).with_context(|| {
        format!("--missions {} × --robots {}: at most {MAX_LOAD_ROBOTS} robots in all", args.missions, args.robots)
    })?;
    // A connection per robot and per capacity caller, and the executive's
    // end of each when it runs in this process.
    let callers = team.saturating_add(args.capacity_callers.unwrap_or(team));
    coordinator::connections::open_files_for(if args.server.is_some() { callers } else { callers.saturating_mul(2) });
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
