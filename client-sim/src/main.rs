//! `fleet-sim`: a simulated robot fleet driving the exploration executive.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use tracing_subscriber::EnvFilter;

use client_sim::world::StartChoice;
use client_sim::{RunConfig, RunReport};
use exploration::math::Point2;

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
    Run(RunArgs),
}

#[derive(Debug, Args)]
struct RunArgs {
    /// ROS map_server YAML of the world to explore.
    #[arg(long)]
    map: PathBuf,
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
    /// Executive to drive, e.g. http://127.0.0.1:50051; without it, one is
    /// started on a loopback port for the run.
    #[arg(long)]
    server: Option<String>,
    /// Database file for the embedded executive (default: a temporary file).
    #[arg(long)]
    db: Option<PathBuf>,
    /// Simulation cell size in metres; the map is coarsened conservatively.
    #[arg(long, default_value_t = 0.1)]
    cell_size: f64,
    /// Sensor range, metres.
    #[arg(long, default_value_t = 4.0)]
    sensor_range: f64,
    /// Sensor field of view, degrees.
    #[arg(long, default_value_t = 360.0)]
    fov: f64,
    /// Robot footprint radius, metres.
    #[arg(long, default_value_t = 0.0)]
    footprint: f64,
    /// Start: `auto` (roomiest cell), `random` (seeded), or `x,y` in metres.
    #[arg(long, default_value = "auto")]
    start: String,
    /// Give up after this many steps.
    #[arg(long, default_value_t = 50_000)]
    max_steps: u64,
    /// How long robots keep retrying an unreachable executive, seconds.
    #[arg(long, default_value_t = 120.0)]
    retry_for: f64,
    /// Print one JSON object on the last line instead of a summary.
    #[arg(long)]
    json: bool,
    /// No progress lines.
    #[arg(long)]
    quiet: bool,
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
async fn main() -> anyhow::Result<()> {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn"));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    match Cli::parse().command {
        Command::Run(args) => run(args).await,
    }
}

async fn run(args: RunArgs) -> anyhow::Result<()> {
    if args.robots == 0 {
        bail!("--robots must be at least 1");
    }
    let mut config = RunConfig::new(&args.map, args.robots, &args.policy);
    config.params = args.params.into_iter().collect::<BTreeMap<_, _>>();
    config.seed = args.seed;
    config.server = args.server;
    config.db = args.db;
    config.cell_size = Some(args.cell_size);
    config.model.sensor_range_m = args.sensor_range;
    config.model.field_of_view_rad = args.fov.to_radians();
    config.model.footprint_radius_m = args.footprint;
    config.start = parse_start(&args.start)?;
    config.max_steps = args.max_steps;
    config.retry_budget = Duration::from_secs_f64(args.retry_for);
    config.progress = !args.quiet && !args.json;
    let report = client_sim::run(&config).await.with_context(|| format!("the run on {} failed", args.map.display()))?;
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print_summary(&report);
    }
    Ok(())
}

fn print_summary(r: &RunReport) {
    let steps = |t: Option<u64>| t.map_or("-".to_owned(), |t| t.to_string());
    println!();
    println!("mission {}  map {}  policy {}  robots {}  seed {}", r.mission_id, r.map, r.policy, r.robots, r.seed);
    println!(
        "{}: {} after {} steps ({:.1} s wall time)",
        if r.completed { "completed" } else { "NOT completed" },
        r.ended,
        r.steps,
        r.wall_time_s
    );
    println!("coverage {:.2} % of {} reachable cells ({} m cells)", 100.0 * r.coverage, r.reachable_cells, r.cell_size);
    println!("steps to 50/90/95/100 %: {} / {} / {} / {}", steps(r.t50), steps(r.t90), steps(r.t95), steps(r.t100));
    let distances: Vec<String> = r.distance_per_robot.iter().map(|d| format!("{d:.1}")).collect();
    println!("distance per robot (m): {}", distances.join(", "));
    println!("replans {}  map updates {}  overlap {:.1} %", r.replans, r.map_updates, 100.0 * r.overlap);
}
