//! HTTP beside gRPC, on its own listener: the Prometheus metrics
//! (`GET /metrics`) and the live mission view ([`view`]). Both read through
//! the executive like any other client. HTTPS ([`tls`]) when gRPC has TLS.

mod cells;
mod tls;
mod view;

pub use tls::HttpsError;
pub(crate) use tls::TlsListener;

use std::sync::Arc;

use axum::Router;
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;
use tokio_util::sync::CancellationToken;

use crate::auth::Authenticator;
use crate::executive::Executive;

/// What every route reads.
#[derive(Clone)]
pub(crate) struct Shared {
    executive: Arc<Executive>,
    /// The tokens the gRPC services check.
    auth: Arc<Authenticator>,
    /// Cancelled when the executive stops: live streams end.
    stop: CancellationToken,
    /// One permit per live stream open (see [`view::MAX_LIVE_STREAMS`]).
    live_streams: Arc<tokio::sync::Semaphore>,
}

/// The HTTP routes over `executive`; the view's API checks tokens with
/// `auth`, and its streams end when `stop` is cancelled.
pub fn router(executive: Arc<Executive>, auth: Authenticator, stop: CancellationToken) -> Router {
    let live_streams = Arc::new(tokio::sync::Semaphore::new(view::MAX_LIVE_STREAMS));
    let shared = Shared { executive, auth: Arc::new(auth), stop, live_streams };
    Router::new()
        .route("/metrics", get(metrics))
        .route("/", get(view::page))
        .route("/api/missions", get(view::missions))
        .route("/api/missions/{id}/live", get(view::live))
        .with_state(shared)
        // A live view is an open request: its connection is not idle.
        .layer(crate::connections::ActivityLayer)
}

async fn metrics(State(shared): State<Shared>) -> impl IntoResponse {
    let body = shared.executive.metrics().await;
    ([(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], body)
}
