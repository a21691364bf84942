//! HTTP beside gRPC, on its own listener: the Prometheus metrics (GET
//! /metrics). It reads through the executive like any other client.

use std::sync::Arc;

use axum::Router;
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::get;

use crate::executive::Executive;

/// The HTTP routes over `executive`.
pub fn router(executive: Arc<Executive>) -> Router {
    Router::new().route("/metrics", get(metrics)).with_state(executive)
}

async fn metrics(State(executive): State<Arc<Executive>>) -> impl IntoResponse {
    let body = executive.metrics().await;
    ([(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], body)
}
