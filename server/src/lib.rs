//! The exploration executive.
//!
//! Robots connect over gRPC, send map patches, poses and bids, and receive
//! target assignments; operators create and watch missions. Data flows one
//! way through the layers:
//!
//! - [`service`]: tonic handlers; validate, convert proto ↔ [`domain`], call
//!   the executive, map [`error::Error`] to a status in one place.
//! - [`executive`]: every mission's live state; replanning triggers, task
//!   lifecycle, assignment streams. Calls the policies of the `exploration`
//!   crate and the [`store`].
//! - [`store`]: persistence behind the [`store::Store`] trait; SQLite today.
//!
//! [`run`] serves an already bound listener until a shutdown future
//! resolves, so tests bind port 0 and binaries bind what they are told.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

use exploration_proto::v1 as pb;

pub mod admission;
pub mod auth;
pub mod cli;
pub mod clock;
pub mod connections;
pub mod cpu_limit;
pub mod domain;
pub mod error;
pub mod executive;
/// Files an operator names, read up to a limit (shared with the clients).
pub use exploration_proto::files;
pub mod http;
pub mod metrics;
pub mod run_to_end;
pub mod service;
pub mod store;
pub mod validate;

pub use clock::{Clock, ManualClock};
pub use connections::ConnectionLimits;
pub use executive::{Executive, ExecutiveSettings, ReplicaSettings};
pub use store::compact::Compaction;
pub use store::sqlite::{Durability, SqliteStore};
pub use store::{Claimant, Location, PostgresStore};

/// How to run an executive.
#[derive(Debug, Clone)]
pub struct Config {
    /// The database: a SQLite file (created if missing) or a PostgreSQL URL.
    pub db: store::Location,
    /// How hard SQLite works to keep each commit (PostgreSQL: as the
    /// server is set, `synchronous_commit`).
    pub durability: Durability,
    /// Limits and knobs.
    pub executive: ExecutiveSettings,
    /// The operator token (named "operator"); without it and without a
    /// tokens file the executive runs open (no token checked).
    pub operator_token: Option<String>,
    /// A file of named operator and viewer tokens, reread when it changes.
    pub operator_tokens_file: Option<PathBuf>,
    /// Serve TLS instead of plaintext.
    pub tls: Option<TlsConfig>,
    /// gRPC's connection limits: how many at once, when an idle one is closed.
    pub connections: ConnectionLimits,
    /// Limits on the HTTP listener's connections (the view and /metrics).
    pub http_connections: ConnectionLimits,
    /// When the patch log is folded into map snapshots.
    pub compaction: Compaction,
    /// When robots' calls are refused because a queue stands (see
    /// [`admission`]); `None` (the default): never.
    pub shedding: Option<admission::QueueDelay>,
}

impl Config {
    /// Defaults for a database.
    pub fn new(db: impl Into<store::Location>) -> Self {
        Self {
            db: db.into(),
            durability: Durability::default(),
            executive: ExecutiveSettings::default(),
            operator_token: None,
            operator_tokens_file: None,
            tls: None,
            connections: ConnectionLimits::default(),
            http_connections: ConnectionLimits::side_listener(HTTP_CONNECTIONS),
            compaction: Compaction::default(),
            shedding: None,
        }
    }
}

/// The executive's certificate and key, and the CA that client certificates
/// must chain to when robots must present one (mutual TLS).
#[derive(Clone)]
pub struct TlsConfig {
    /// PEM certificate chain.
    pub cert_pem: Vec<u8>,
    /// PEM private key.
    pub key_pem: Vec<u8>,
    /// PEM CA certificates for client certificates; `None`: none asked for.
    pub client_ca_pem: Option<Vec<u8>>,
}

impl std::fmt::Debug for TlsConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TlsConfig").field("client_ca", &self.client_ca_pem.is_some()).finish_non_exhaustive()
    }
}

impl TlsConfig {
    /// Reads the PEM files.
    pub fn from_files(cert: &Path, key: &Path, client_ca: Option<&Path>) -> std::io::Result<Self> {
        let read = files::read_pem;
        Ok(Self { cert_pem: read(cert)?, key_pem: read(key)?, client_ca_pem: client_ca.map(read).transpose()? })
    }
}

/// Why serving stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The database could not be opened or loaded.
    #[error("could not open the store {location}: {cause}")]
    Store {
        /// The file, or the URL without its password.
        location: String,
        /// Why not.
        #[source]
        cause: store::StoreError,
    },
    /// Missions could not be restored.
    #[error("could not restore missions: {0}")]
    Restore(#[from] error::Error),
    /// The operator tokens are unusable.
    #[error("{0}")]
    Tokens(#[from] auth::TokensError),
    /// The reflection service could not be built.
    #[error("could not build the reflection service: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The transport failed.
    #[error("{0}")]
    Transport(#[from] tonic::transport::Error),
    /// The HTTP listener cannot serve HTTPS with the TLS settings.
    #[error(transparent)]
    Https(#[from] http::HttpsError),
    /// Replicas asked for on a database that one executive keeps.
    #[error("replicas share a PostgreSQL database (--db postgres://...); the SQLite file {0} is kept by one executive")]
    ReplicasNeedPostgres(String),
}

/// Expires leases and detects stalls until `stop`: every
/// [`executive::SWEEP_PERIOD`] on the wall clock, or at each move of a
/// manual clock (then the mover waits for it; see [`clock`]).
async fn sweep_until(executive: Arc<Executive>, clock: Clock, stop: CancellationToken) {
    let sweep = || async {
        if let Err(e) = executive.sweep().await {
            tracing::error!(error = %e, "lease and stall sweep failed; retrying at the next tick");
        }
    };
    match clock {
        Clock::Manual(handle) => {
            let mut moves = handle.moves();
            loop {
                tokio::select! {
                    () = stop.cancelled() => return,
                    changed = moves.changed() => {
                        if changed.is_err() {
                            return;
                        }
                        let moved = *moves.borrow_and_update();
                        sweep().await;
                        handle.mark_swept(moved);
                    }
                }
            }
        }
        Clock::Tokio => {
            let mut ticks = tokio::time::interval(executive::SWEEP_PERIOD);
            ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    () = stop.cancelled() => return,
                    _ = ticks.tick() => sweep().await,
                }
            }
        }
    }
}

/// Largest request the executive decodes (a map update with big patches).
pub const MAX_MESSAGE_BYTES: usize = exploration_proto::MAX_MESSAGE_BYTES;

/// Connections the plaintext health listener (`Listeners::health`) holds
/// at once; more are closed as they arrive.
pub const HEALTH_CONNECTIONS: usize = 64;

/// Connections the HTTP listener holds at once by default: operators'
/// browsers and a Prometheus scraper need a few; the rest of the process's
/// descriptors are gRPC's (whose own limit is separate).
pub const HTTP_CONNECTIONS: usize = 1_024;

/// Serves the executive on `listener` until `shutdown` resolves, then stops
/// accepting, ends assignment streams, lets in-flight requests finish and
/// closes the database.
pub async fn run(
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
    config: Config,
) -> Result<(), ServeError> {
    run_with(Listeners { grpc: listener, http: None, health: None }, shutdown, config).await
}

/// What an executive serves on: gRPC, and optionally HTTP (`/metrics`).
#[derive(Debug)]
pub struct Listeners {
    /// The gRPC services.
    pub grpc: TcpListener,
    /// The HTTP routes (see [`http`]); none when `None`.
    pub http: Option<TcpListener>,
    /// The gRPC health service alone, in plaintext: for probes that speak
    /// no TLS (Kubernetes' gRPC probes), while the API keeps it. No token
    /// crosses it.
    pub health: Option<TcpListener>,
}

/// [`run`] with every listener.
pub async fn run_with(
    listeners: Listeners,
    shutdown: impl Future<Output = ()> + Send + 'static,
    config: Config,
) -> Result<(), ServeError> {
    let Listeners { grpc: listener, http: http_listener, health: health_listener } = listeners;
    let auth = auth::Authenticator::new(config.operator_token.as_deref(), config.operator_tokens_file.as_deref())?;
    let address = listener.local_addr().ok();
    warn_about_exposure(&auth, address, config.tls.is_some());
    let streams_end = CancellationToken::new();
    let metrics = Arc::new(metrics::Metrics::new());
    // Where gRPC has TLS, so has HTTP: the view's API carries tokens too.
    let http_grace = config.http_connections.drain_grace;
    let http_listener = http_listener.map(|listener| {
        connections::Incoming::new("HTTP", listener, config.http_connections.clone()).counted_in(&metrics)
    });
    let http_listener = match (http_listener, &config.tls) {
        (Some(listener), Some(tls)) => {
            Some(HttpListener::Tls(http::TlsListener::new(listener, tls, streams_end.clone())?))
        }
        (Some(listener), None) => Some(HttpListener::Plain(listener)),
        (None, _) => None,
    };
    if let (Some(_), Location::Sqlite(path)) = (&config.executive.replica, &config.db) {
        return Err(ServeError::ReplicasNeedPostgres(path.display().to_string()));
    }
    let store = config
        .db
        .open(config.durability, config.executive.replica.is_some(), Some(Arc::clone(&metrics)))
        .await
        .map_err(|cause| ServeError::Store { location: config.db.to_string(), cause })?;
    let clock = config.executive.clock.clone();
    let executive = match Executive::open(Arc::clone(&store), config.executive, Arc::clone(&metrics)).await {
        Ok(executive) => Arc::new(executive),
        Err(e) => {
            store.close().await;
            return Err(e.into());
        }
    };
    let admission = admission::AdmissionLayer::new(config.shedding, clock.clone(), Arc::clone(&metrics));
    let sweeper = tokio::spawn(sweep_until(executive.clone(), clock, streams_end.clone()));
    let lease_keeper = tokio::spawn(executive::keep_leases_until(executive.clone(), streams_end.clone()));
    let holds: store::compact::Holds = {
        let executive = Arc::clone(&executive);
        Arc::new(move |mission| executive.holds(mission))
    };
    let compactor = tokio::spawn(store::compact::run(
        Arc::clone(&store),
        holds,
        config.compaction,
        Arc::clone(&metrics),
        streams_end.clone(),
    ));
    let http_server = http_listener.map(|listener| {
        let stop = streams_end.clone().cancelled_owned();
        let app = http::router(Arc::clone(&executive), auth.clone(), streams_end.clone());
        // The connection's info carries its activity to `ActivityLayer`.
        let app = app.into_make_service_with_connect_info::<connections::ConnectionInfo>();
        match listener {
            HttpListener::Plain(listener) => {
                tracing::info!(address = ?listener.local_addr().ok(), "HTTP serving the mission view (/) and /metrics");
                tokio::spawn(async move { axum::serve(listener, app).with_graceful_shutdown(stop).await })
            }
            HttpListener::Tls(listener) => {
                let address = axum::serve::Listener::local_addr(&listener).ok();
                tracing::info!(?address, "HTTPS serving the mission view (/) and /metrics");
                tokio::spawn(async move { axum::serve(listener, app).with_graceful_shutdown(stop).await })
            }
        }
    });
    let (missions, fleet) = service::ExplorationService::new(Arc::clone(&executive), streams_end.clone())
        .into_servers(auth, MAX_MESSAGE_BYTES);

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<service::MissionsService>().await;
    health.set_serving::<service::FleetService>().await;
    let health_server = health_listener.map(|listener| {
        tracing::info!(address = ?listener.local_addr().ok(), "serving the gRPC health service alone, in plaintext");
        let stop = streams_end.clone().cancelled_owned();
        // Probes need a few connections; whoever else reaches this port
        // must not hold the descriptors gRPC needs.
        let limits = ConnectionLimits::side_listener(HEALTH_CONNECTIONS);
        let incoming = connections::Incoming::new("health", listener, limits).counted_in(&metrics);
        tokio::spawn(
            tonic::transport::Server::builder()
                .layer(connections::ActivityLayer)
                .add_service(health_service.clone())
                .serve_with_incoming_shutdown(incoming, stop),
        )
    });
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    tracing::info!(?address, db = %config.db, tls = config.tls.is_some(), "executive serving");
    let incoming = connections::Incoming::new("gRPC", listener, config.connections.clone()).counted_in(&metrics);
    let drain = {
        let health = health.clone();
        let streams_end = streams_end.clone();
        async move {
            shutdown.await;
            tracing::info!("shutting down: draining requests");
            health.set_not_serving::<service::FleetService>().await;
            streams_end.cancel();
        }
    };
    let mut server = tonic::transport::Server::builder()
        // Dead peers are found by TCP keepalive; idle live ones are closed by `connections`.
        .tcp_keepalive(Some(std::time::Duration::from_secs(30)))
        .tcp_nodelay(true);
    if let Some(tls) = &config.tls {
        let mut settings = tonic::transport::ServerTlsConfig::new()
            .identity(tonic::transport::Identity::from_pem(&tls.cert_pem, &tls.key_pem));
        if let Some(ca) = &tls.client_ca_pem {
            settings = settings.client_ca_root(tonic::transport::Certificate::from_pem(ca));
        }
        server = server.tls_config(settings)?;
    }
    let serve = server
        .layer(connections::ActivityLayer)
        .layer(metrics::RpcMetricsLayer(Arc::clone(&metrics)))
        .layer(admission)
        .layer(run_to_end::RunToEndLayer)
        .add_service(health_service)
        .add_service(reflection)
        .add_service(reflection_alpha)
        .add_service(missions)
        .add_service(fleet)
        .serve_with_incoming_shutdown(incoming, drain);
    let grace = config.connections.drain_grace;
    let draining_too_long = async {
        streams_end.cancelled().await;
        tokio::time::sleep(grace).await;
    };
    let served = tokio::select! {
        served = serve => served,
        () = draining_too_long => {
            tracing::warn!(?grace, "connections still open after the drain grace: closing them");
            Ok(())
        }
    };
    streams_end.cancel();
    if let Err(e) = sweeper.await {
        tracing::error!(error = %e, "lease sweeper failed");
    }
    if let Err(e) = lease_keeper.await {
        tracing::error!(error = %e, "the mission lease keeper failed");
    }
    if let Err(e) = compactor.await {
        tracing::error!(error = %e, "the patch log compactor failed");
    }
    if let Some(server) = health_server {
        drained("health listener", server, grace).await;
    }
    if let Some(server) = http_server {
        drained("HTTP listener", server, http_grace).await;
    }
    executive.close().await;
    // Everything it wrote is durable: the other replicas may take its missions now.
    executive.release_leases().await;
    store.close().await;
    served?;
    tracing::info!("executive stopped");
    Ok(())
}

/// Waits for a listener beside gRPC to finish its connections, for at most
/// `grace`: a peer that never sends a request would otherwise hold the
/// shutdown, and the store's close, for as long as it stays connected.
async fn drained<E: std::fmt::Display>(
    listener: &'static str,
    mut server: tokio::task::JoinHandle<Result<(), E>>,
    grace: std::time::Duration,
) {
    match tokio::time::timeout(grace, &mut server).await {
        Ok(Ok(Ok(()))) => {}
        Ok(Ok(Err(e))) => tracing::error!(listener, error = %e, "the listener failed"),
        Ok(Err(e)) => tracing::error!(listener, error = %e, "the listener's task failed"),
        Err(_) => {
            // Its connections' own tasks end with the runtime.
            tracing::warn!(listener, ?grace, "connections still open after the drain grace: not waiting for them");
            server.abort();
        }
    }
}

/// The HTTP listener, plain or behind TLS.
enum HttpListener {
    Plain(connections::Incoming),
    Tls(http::TlsListener),
}

/// Says in the log when callers are not checked, or when their tokens would
/// cross a network in plaintext.
fn warn_about_exposure(auth: &auth::Authenticator, address: Option<std::net::SocketAddr>, tls: bool) {
    let loopback = address.is_some_and(|a| a.ip().is_loopback());
    if auth.is_open() {
        tracing::warn!(
            "no operator token configured: every caller may administer missions (open mode){}",
            if loopback { "" } else { "; this address is reachable from other machines" }
        );
    } else if !tls && !loopback {
        tracing::warn!(
            ?address,
            "bearer tokens will cross the network in plaintext: serve with --tls-cert and --tls-key"
        );
    }
}
