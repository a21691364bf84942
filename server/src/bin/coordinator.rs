//! `coordinator`: the exploration executive daemon.

use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, ValueEnum};
use tracing_subscriber::EnvFilter;

use std::time::Duration;

use coordinator::admission::QueueDelay;
use coordinator::cli::listen_address;
use coordinator::{
    Claimant, Compaction, Config, ConnectionLimits, Durability, ExecutiveSettings, Location, ReplicaSettings, TlsConfig,
};

/// Planning allocates a cost map per robot (megabytes each) and drops it
/// when the plan is made; the system allocator hands such blocks back to
/// the kernel and takes fresh zeroed pages for the next plan, so a fifth of
/// a replanning went to page faults. mimalloc keeps them.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Most threads either planner setting may ask for.
const MAX_PLANNER_THREADS: usize = 1024;

/// The exploration executive: coordinates robot fleets exploring unknown buildings.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Address to serve gRPC on: IP:PORT, or HOST:PORT (its first address).
    #[arg(long, env = "COORDINATOR_LISTEN", default_value = "127.0.0.1:50051", value_parser = listen_address)]
    listen: SocketAddr,
    /// The database: a SQLite file (created if missing), or a PostgreSQL
    /// URL (`postgres://user:password@host:5432/name`).
    #[arg(long, env = "COORDINATOR_DB", default_value = "coordinator.db")]
    db: Location,
    /// `full`: every acknowledged write survives a power cut; `normal`: it
    /// survives a crash of the process (faster).
    #[arg(long, env = "COORDINATOR_DURABILITY", value_enum, default_value_t = DurabilityArg::Full)]
    durability: DurabilityArg,
    /// Threads a replanning may use (default: all cores).
    #[arg(long, env = "COORDINATOR_PLANNER_THREADS")]
    planner_threads: Option<usize>,
    /// Plans made off the request path at once, and the threads one of
    /// them may use when it is the only one (default: one core fewer than
    /// all, at least one; at most --planner-threads). Lockstep missions
    /// plan with --planner-threads.
    #[arg(long, env = "COORDINATOR_BACKGROUND_PLANNER_THREADS")]
    background_planner_threads: Option<usize>,
    /// CPU the planning threads may use on average, in cores, or
    /// `unlimited` (default: half the CPU limit of this process's cgroup,
    /// a container's `limits: cpu`, when it has one; otherwise unlimited).
    /// Under a limit, a plan that spends a period's quota at once makes
    /// every request wait for the next period.
    #[arg(long, env = "COORDINATOR_PLANNER_CPU", value_parser = parse_planner_cpu)]
    planner_cpu: Option<PlannerCpu>,
    /// Map patches a mission's log holds before the oldest are folded into
    /// a snapshot of the map, which then replaces them (0: never fold; the
    /// log then grows with every map update for as long as the mission lives).
    #[arg(long, env = "COORDINATOR_COMPACT_AFTER_PATCHES", default_value_t = Compaction::default().after_patches)]
    compact_after_patches: u32,
    /// The operator token (at least 16 characters), recorded as "operator":
    /// required for mission administration and overrides; robots then need
    /// the tokens their registration returns. Without it and without
    /// --operator-tokens the executive runs open (every caller may do everything).
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKEN", hide_env_values = true)]
    operator_token: Option<String>,
    /// A file of named tokens, one `NAME ROLE SHA256` per line (ROLE is
    /// `operator` or `viewer`; SHA256 is `printf %s TOKEN | sha256sum`). The
    /// name is recorded as who acted. Reread when it changes: a token is
    /// revoked by removing its line.
    #[arg(long, env = "COORDINATOR_OPERATOR_TOKENS")]
    operator_tokens: Option<PathBuf>,
    /// PEM certificate chain to serve TLS with (needs --tls-key).
    #[arg(long, env = "COORDINATOR_TLS_CERT", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, env = "COORDINATOR_TLS_KEY", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// PEM CA certificates: clients must present a certificate signed by one
    /// of them (mutual TLS).
    #[arg(long, env = "COORDINATOR_TLS_CLIENT_CA", requires = "tls_cert")]
    tls_client_ca: Option<PathBuf>,
    /// Most gRPC connections held at once; more are closed as they arrive.
    #[arg(long, env = "COORDINATOR_MAX_CONNECTIONS", default_value_t = 10_000)]
    max_connections: usize,
    /// Most connections the --http listener holds at once (more are closed
    /// as they arrive), each closed after a minute with no request open (a
    /// live view is one) or with its peer taking nothing: whoever reaches
    /// that port must not be able to take the descriptors gRPC needs.
    #[arg(long, env = "COORDINATOR_HTTP_MAX_CONNECTIONS", default_value_t = coordinator::HTTP_CONNECTIONS)]
    http_max_connections: usize,
    /// Refuse robots' calls (map updates, heartbeats, bids, each kind on its
    /// own) at once with RESOURCE_EXHAUSTED and a retry hint while none has
    /// been answered within this many milliseconds for five times
    /// --shed-interval-ms (for one within fifty of a refusal), some being in
    /// flight: a queue that stands (CoDel's test). 20 suits 1 000 robots on
    /// two cores under a CPU limit; 0 (the default): never refuse for that.
    #[arg(long, env = "COORDINATOR_SHED_TARGET_MS", default_value_t = 0)]
    shed_target_ms: u64,
    /// See --shed-target-ms.
    #[arg(long, env = "COORDINATOR_SHED_INTERVAL_MS", default_value_t = 100)]
    shed_interval_ms: u64,
    /// Seconds after which a connection with no open call is closed, as is
    /// one whose peer takes nothing written to it for that long.
    #[arg(long, env = "COORDINATOR_IDLE_TIMEOUT", default_value_t = 300.0)]
    idle_timeout: f64,
    /// Serve HTTP at this address: the live mission view (GET /) and
    /// Prometheus metrics (GET /metrics); off unless given. HTTPS, with the
    /// same certificate and client CA, when gRPC has TLS.
    #[arg(long, visible_alias = "metrics", env = "COORDINATOR_HTTP", value_parser = listen_address)]
    http: Option<SocketAddr>,
    /// Serve the gRPC health service alone, in plaintext, at this address
    /// too: for probes that speak no TLS (Kubernetes' gRPC probes) when the
    /// API is served with TLS. Off unless given.
    #[arg(long, env = "COORDINATOR_HEALTH_LISTEN", value_parser = listen_address)]
    health_listen: Option<SocketAddr>,
    /// Log format.
    #[arg(long, env = "COORDINATOR_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    log_format: LogFormat,
    /// Run as one of several replicas sharing the PostgreSQL database of
    /// --db, under this name (unique among them; a pod's name, say). Each
    /// mission is then held by one replica at a time, through a lease.
    #[arg(long, env = "COORDINATOR_REPLICA_ID")]
    replica_id: Option<String>,
    /// The URL clients reach this replica at, which the others give to the
    /// clients of the missions it holds (default: http(s)://--listen,
    /// unless it listens on every address).
    #[arg(long, env = "COORDINATOR_ADVERTISE", requires = "replica_id")]
    advertise: Option<String>,
    /// Seconds a replica's claim on a mission lasts unless renewed (it
    /// renews every third of it): about how long a dead replica's missions
    /// wait for another.
    #[arg(long, env = "COORDINATOR_LEASE_PERIOD", default_value_t = 5.0)]
    lease_period: f64,
    /// Seconds after a lease ran out before another replica may claim the
    /// mission (room for clocks that disagree a little).
    #[arg(long, env = "COORDINATOR_LEASE_GRACE", default_value_t = 1.0)]
    lease_grace: f64,
}

/// The share of a CPU limit plans may use when `--planner-cpu` is not given.
const PLANNER_SHARE_OF_LIMIT: f64 = 0.5;

/// What `--planner-cpu` says.
#[derive(Debug, Clone, Copy)]
enum PlannerCpu {
    Cores(f64),
    Unlimited,
}

fn parse_planner_cpu(text: &str) -> Result<PlannerCpu, String> {
    if text == "unlimited" {
        return Ok(PlannerCpu::Unlimited);
    }
    match text.parse::<f64>() {
        Ok(cores) if cores.is_finite() && cores >= 0.001 && cores <= MAX_PLANNER_THREADS as f64 => {
            Ok(PlannerCpu::Cores(cores))
        }
        _ => Err(format!("expected `unlimited` or a number of cores from 0.001 to {MAX_PLANNER_THREADS}")),
    }
}

/// The planning threads' CPU budget: the flag's, or a share of the
/// cgroup's limit.
fn planner_cpu(flag: Option<PlannerCpu>) -> Option<f64> {
    let cores = match flag {
        Some(PlannerCpu::Cores(cores)) => Some(cores),
        Some(PlannerCpu::Unlimited) => None,
        None => coordinator::cpu_limit::cgroup_cpu_limit().map(|limit| limit * PLANNER_SHARE_OF_LIMIT),
    };
    match cores {
        Some(cores) => tracing::info!(cores, "planning threads keep to a CPU budget"),
        None => tracing::info!("planning threads have no CPU budget"),
    }
    cores
}

/// When robots' calls are refused for a standing queue, checked.
fn shedding(target_ms: u64, interval_ms: u64) -> anyhow::Result<Option<QueueDelay>> {
    const MOST_MS: u64 = 60_000;
    anyhow::ensure!(target_ms <= MOST_MS, "--shed-target-ms must be 0 (off) to {MOST_MS}");
    anyhow::ensure!((1..=MOST_MS).contains(&interval_ms), "--shed-interval-ms must be 1 to {MOST_MS}");
    Ok((target_ms > 0)
        .then(|| QueueDelay { target: Duration::from_millis(target_ms), interval: Duration::from_millis(interval_ms) }))
}

/// The replica settings the flags give, checked.
fn replica_settings(args: &Args, tls: bool, bound: SocketAddr) -> anyhow::Result<Option<ReplicaSettings>> {
    // Checked with or without --replica-id: a value that would be refused
    // with it is not silently taken without it.
    for (flag, seconds, min) in [("--lease-period", args.lease_period, 0.3), ("--lease-grace", args.lease_grace, 0.0)] {
        anyhow::ensure!(seconds.is_finite() && (min..=600.0).contains(&seconds), "{flag} must be {min} to 600 seconds");
    }
    let Some(id) = &args.replica_id else { return Ok(None) };
    anyhow::ensure!(
        !id.is_empty() && id.len() <= 128 && id.bytes().all(|b| b.is_ascii_graphic()),
        "--replica-id must be 1 to 128 printable ASCII characters without spaces"
    );
    let advertise = match &args.advertise {
        Some(url) => url.clone(),
        None => {
            anyhow::ensure!(
                !args.listen.ip().is_unspecified(),
                "--advertise is needed when --listen is {} (every address): the URL other machines reach this \
                 replica at",
                args.listen
            );
            // The address bound, not the one asked for: `--listen HOST:0`
            // gets its port from the system.
            format!("{}://{bound}", if tls { "https" } else { "http" })
        }
    };
    anyhow::ensure!(
        advertise.len() <= 512 && advertise.bytes().all(|b| b.is_ascii_graphic()),
        "--advertise must be an http:// or https:// URL of at most 512 printable characters"
    );
    // Clients dial it as they dial --server: what they would misread is refused here.
    exploration_proto::client::check_url(&advertise).context("--advertise")?;
    Ok(Some(ReplicaSettings {
        claimant: Claimant { id: id.clone(), address: advertise },
        lease: Duration::from_secs_f64(args.lease_period),
        grace: Duration::from_secs_f64(args.lease_grace),
    }))
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum DurabilityArg {
    Full,
    Normal,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

#[tokio::main]
async fn main() -> ExitCode {
    let args = Args::parse();
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    match args.log_format {
        LogFormat::Text => tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_ansi(coordinator::cli::colours_on(&std::io::stdout()))
            .init(),
        LogFormat::Json => tracing_subscriber::fmt().json().with_env_filter(filter).init(),
    }
    match serve(args).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line, each cause once; a closed stderr is no reason to panic.
            let _ = writeln!(std::io::stderr(), "coordinator: {}", coordinator::error::report(e.as_ref()));
            ExitCode::FAILURE
        }
    }
}

/// Checks the arguments, binds the listeners and serves until a signal.
async fn serve(args: Args) -> anyhow::Result<()> {
    anyhow::ensure!(
        !args.db.to_string().is_empty(),
        "--db is empty: give a database file (created if missing) or a postgres:// URL"
    );
    let listener = tokio::net::TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let tls = args.tls_cert.is_some();
    let bound = listener.local_addr().context("the address listened on")?;
    let replica = replica_settings(&args, tls, bound)?;
    let mut config = Config::new(args.db);
    config.operator_token = args.operator_token;
    config.operator_tokens_file = args.operator_tokens;
    if let (Some(cert), Some(key)) = (&args.tls_cert, &args.tls_key) {
        config.tls = Some(
            TlsConfig::from_files(cert, key, args.tls_client_ca.as_deref())
                .context("cannot read the TLS certificate, key or client CA")?,
        );
    }
    anyhow::ensure!(
        // Under a second, a call's pause or a moment's backpressure would
        // close the connection under it.
        (1.0..=1e6).contains(&args.idle_timeout),
        "--idle-timeout must be a number of seconds from 1 to 1e6"
    );
    // 0 would refuse every caller, the health checks included.
    anyhow::ensure!(args.max_connections >= 1, "--max-connections must be at least 1");
    anyhow::ensure!(args.http_max_connections >= 1, "--http-max-connections must be at least 1");
    config.http_connections = ConnectionLimits::side_listener(args.http_max_connections);
    config.connections = ConnectionLimits {
        max_connections: args.max_connections,
        idle_timeout: Duration::from_secs_f64(args.idle_timeout),
        ..ConnectionLimits::default()
    };
    coordinator::connections::open_files_for(
        args.max_connections.saturating_add(args.http_max_connections).saturating_add(coordinator::HEALTH_CONNECTIONS),
    );
    config.shedding = shedding(args.shed_target_ms, args.shed_interval_ms)?;
    config.durability = match args.durability {
        DurabilityArg::Full => Durability::Full,
        DurabilityArg::Normal => Durability::Normal,
    };
    config.compaction.after_patches = args.compact_after_patches;
    for (flag, threads) in
        [("--planner-threads", args.planner_threads), ("--background-planner-threads", args.background_planner_threads)]
    {
        // Each planning thread is spawned at start-up: a mistyped count must
        // not start a million of them.
        anyhow::ensure!(
            threads.is_none_or(|n| (1..=MAX_PLANNER_THREADS).contains(&n)),
            "{flag} must be 1 to {MAX_PLANNER_THREADS}"
        );
    }
    let defaults = ExecutiveSettings::default();
    config.executive = ExecutiveSettings {
        replica,
        planner_threads: args.planner_threads.unwrap_or(defaults.planner_threads).max(1),
        background_planner_threads: args
            .background_planner_threads
            .unwrap_or(defaults.background_planner_threads)
            .max(1),
        planner_cpu: planner_cpu(args.planner_cpu),
        ..defaults
    };
    let http = match args.http {
        Some(address) => Some(
            tokio::net::TcpListener::bind(address)
                .await
                .with_context(|| format!("cannot listen for HTTP on {address}"))?,
        ),
        None => None,
    };
    let health = match args.health_listen {
        Some(address) => Some(
            tokio::net::TcpListener::bind(address)
                .await
                .with_context(|| format!("cannot listen for health checks on {address}"))?,
        ),
        None => None,
    };
    let listeners = coordinator::Listeners { grpc: listener, http, health };
    coordinator::run_with(listeners, shutdown_signal(), config).await.context("the executive failed")
}

/// Resolves on SIGTERM or SIGINT.
async fn shutdown_signal() {
    let interrupt = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!(error = %e, "cannot listen for SIGINT");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = interrupt => tracing::info!("SIGINT received"),
        () = terminate => tracing::info!("SIGTERM received"),
    }
}
