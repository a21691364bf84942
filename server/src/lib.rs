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
use std::path::PathBuf;
use std::sync::Arc;

use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

use exploration_proto::v1 as pb;

pub mod auth;
pub mod clock;
pub mod domain;
pub mod error;
pub mod executive;
pub mod service;
pub mod store;

pub use clock::{Clock, ManualClock};
pub use executive::{Executive, ExecutiveSettings};
pub use store::sqlite::{Durability, SqliteStore};

/// How to run an executive.
#[derive(Debug, Clone)]
pub struct Config {
    /// The SQLite database file (created if missing).
    pub db_path: PathBuf,
    /// How hard SQLite works to keep each commit.
    pub durability: Durability,
    /// Limits and knobs.
    pub executive: ExecutiveSettings,
    /// The operator token; without one the executive runs open (no token checked).
    pub operator_token: Option<String>,
}

impl Config {
    /// Defaults for a database file.
    pub fn new(db_path: impl Into<PathBuf>) -> Self {
        Self {
            db_path: db_path.into(),
            durability: Durability::default(),
            executive: ExecutiveSettings::default(),
            operator_token: None,
        }
    }
}

/// Why serving stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The database could not be opened or loaded.
    #[error("could not open the store: {0}")]
    Store(#[from] store::StoreError),
    /// Missions could not be restored.
    #[error("could not restore missions: {0}")]
    Restore(#[from] error::Error),
    /// The reflection service could not be built.
    #[error("could not build the reflection service: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The transport failed.
    #[error("transport error: {0}")]
    Transport(#[from] tonic::transport::Error),
}

/// Expires leases and detects stalls every [`executive::SWEEP_PERIOD`] until `stop`.
async fn sweep_until(executive: Arc<Executive>, stop: CancellationToken) {
    let mut ticks = tokio::time::interval(executive::SWEEP_PERIOD);
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            () = stop.cancelled() => return,
            _ = ticks.tick() => {
                if let Err(e) = executive.sweep().await {
                    tracing::error!(error = %e, "lease and stall sweep failed; retrying at the next tick");
                }
            }
        }
    }
}

/// Largest request the executive decodes (a map update with big patches).
pub const MAX_MESSAGE_BYTES: usize = 64 * 1024 * 1024;

/// Serves the executive on `listener` until `shutdown` resolves, then stops
/// accepting, ends assignment streams, lets in-flight requests finish and
/// closes the database.
pub async fn run(
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
    config: Config,
) -> Result<(), ServeError> {
    let store = SqliteStore::open(&config.db_path, config.durability).await?;
    let executive = Arc::new(Executive::open(Arc::new(store.clone()), config.executive).await?);
    let streams_end = CancellationToken::new();
    let auth = match config.operator_token.as_deref().map(str::trim).filter(|t| !t.is_empty()) {
        Some(token) => auth::Authenticator::with_operator_token(token),
        None => {
            tracing::warn!("no operator token configured: every caller may administer missions (open mode)");
            auth::Authenticator::open()
        }
    };
    let sweeper = tokio::spawn(sweep_until(executive.clone(), streams_end.clone()));
    let service = service::ExplorationService::new(executive, auth, streams_end.clone());

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<pb::missions_server::MissionsServer<service::ExplorationService>>().await;
    health.set_serving::<pb::fleet_server::FleetServer<service::ExplorationService>>().await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    let address = listener.local_addr().ok();
    tracing::info!(?address, db = %config.db_path.display(), "executive serving");
    let incoming = tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true));
    let drain = {
        let health = health.clone();
        let streams_end = streams_end.clone();
        async move {
            shutdown.await;
            tracing::info!("shutting down: draining requests");
            health.set_not_serving::<pb::fleet_server::FleetServer<service::ExplorationService>>().await;
            streams_end.cancel();
        }
    };
    tonic::transport::Server::builder()
        .add_service(health_service)
        .add_service(reflection)
        .add_service(reflection_alpha)
        .add_service(
            pb::missions_server::MissionsServer::new(service.clone()).max_decoding_message_size(MAX_MESSAGE_BYTES),
        )
        .add_service(pb::fleet_server::FleetServer::new(service).max_decoding_message_size(MAX_MESSAGE_BYTES))
        .serve_with_incoming_shutdown(incoming, drain)
        .await?;
    streams_end.cancel();
    if let Err(e) = sweeper.await {
        tracing::error!(error = %e, "lease sweeper failed");
    }
    store.close().await;
    tracing::info!("executive stopped");
    Ok(())
}
