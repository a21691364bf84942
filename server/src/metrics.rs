//! What the executive counts, for Prometheus (`--metrics ADDR`, GET /metrics).
//!
//! Calls by method and status with latency histograms (the [`RpcMetricsLayer`]
//! in front of every service), replanning time by policy, the planner's
//! triggers and stale plans, store commit latency, shed calls, connections
//! open and turned away by listener, and, read
//! from the executive at each scrape, missions and robots by state and each
//! mission's frontier and coverage.

use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

/// A call's method and gRPC status.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct CallLabels {
    /// `Service/Method`.
    pub method: String,
    /// The gRPC status name, `OK` included.
    pub code: String,
}

/// One label.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct Label {
    /// Its value.
    pub name: String,
}

/// A listener, and why it turned connections away.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RefusalLabels {
    /// `gRPC`, `HTTP` or `health`.
    pub listener: String,
    /// `limit` (at its connection limit) or `accept error` (descriptors
    /// or memory ran out).
    pub reason: String,
}

/// Per mission.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct MissionLabel {
    /// The mission's id.
    pub mission: u64,
}

type Seconds = Family<Label, Histogram, fn() -> Histogram>;

fn latency_histogram() -> Histogram {
    // 100 µs to ~26 s.
    Histogram::new(exponential_buckets(1e-4, 2.0, 19))
}

/// Every metric of an executive.
#[derive(Debug)]
pub struct Metrics {
    registry: Registry,
    /// Calls answered, by method and status.
    pub calls: Family<CallLabels, Counter>,
    /// Time to answer, by method (to the response's headers: a stream's
    /// first message).
    pub call_seconds: Seconds,
    /// Time to make one plan, by policy.
    pub plan_seconds: Seconds,
    /// Times the planner of a mission was woken.
    pub planner_triggers: Counter,
    /// Plans made again because the mission changed while they were made.
    pub stale_plans: Counter,
    /// Plans waiting for or holding a planner thread.
    pub planner_busy: Gauge,
    /// Seconds planning threads slept to keep to their CPU budget.
    pub planner_paced_seconds: Counter<f64, AtomicU64>,
    /// Time to commit one changeset (or one group of them).
    pub store_commit: Histogram,
    /// Changesets committed per transaction.
    pub commit_group: Histogram,
    /// Time a robot's request waited for its mission (behind the mission's
    /// other requests and plans).
    pub mission_wait: Histogram,
    /// Time a changeset waited for room in the store's write queue, while
    /// its mission is held.
    pub store_queue_wait: Histogram,
    /// Time from a changeset queued to its being durable.
    pub store_durable_wait: Histogram,
    /// Time a changeset waited in the store's write queue for its group's
    /// transaction to begin.
    pub store_queued: Histogram,
    /// Map patches folded into map snapshots (see `store::compact`).
    pub patches_folded: Counter,
    /// Calls refused to shed load, by reason.
    pub shed: Family<Label, Counter>,
    /// Open connections, by listener.
    pub connections: Family<Label, Gauge>,
    /// Connections turned away (at the limit), and accepts that failed (out
    /// of descriptors), by listener.
    pub connections_refused: Family<RefusalLabels, Counter>,
    /// Missions by state (at the scrape).
    pub missions: Family<Label, Gauge>,
    /// Robots by state; lost robots count as `lost` (at the scrape).
    pub robots: Family<Label, Gauge>,
    /// Frontier cells of each mission (at the scrape).
    pub frontier_cells: Family<MissionLabel, Gauge>,
    /// Known share of each mission's grid (at the scrape).
    pub coverage: Family<MissionLabel, Gauge<f64, AtomicU64>>,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    /// Every metric, registered under the `coordinator_` prefix.
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("coordinator");
        let metrics = Self {
            calls: Family::default(),
            call_seconds: Family::new_with_constructor(latency_histogram),
            plan_seconds: Family::new_with_constructor(latency_histogram),
            planner_triggers: Counter::default(),
            stale_plans: Counter::default(),
            planner_busy: Gauge::default(),
            planner_paced_seconds: Counter::default(),
            store_commit: latency_histogram(),
            commit_group: Histogram::new(exponential_buckets(1.0, 2.0, 10)),
            mission_wait: latency_histogram(),
            store_queue_wait: latency_histogram(),
            store_durable_wait: latency_histogram(),
            store_queued: latency_histogram(),
            patches_folded: Counter::default(),
            shed: Family::default(),
            connections: Family::default(),
            connections_refused: Family::default(),
            missions: Family::default(),
            robots: Family::default(),
            frontier_cells: Family::default(),
            coverage: Family::default(),
            registry: Registry::default(),
        };
        registry.register("calls", "gRPC calls answered, by method and status", metrics.calls.clone());
        registry.register("call_seconds", "Time to answer a gRPC call, by method", metrics.call_seconds.clone());
        registry.register("plan_seconds", "Time to make one plan, by policy", metrics.plan_seconds.clone());
        registry.register("planner_triggers", "Times a mission's planner was woken", metrics.planner_triggers.clone());
        registry.register(
            "stale_plans",
            "Plans made again because the mission changed meanwhile",
            metrics.stale_plans.clone(),
        );
        registry.register(
            "planner_busy",
            "Plans waiting for or holding a planner thread",
            metrics.planner_busy.clone(),
        );
        registry.register(
            "planner_paced_seconds",
            "Seconds planning threads slept to keep to their CPU budget (--planner-cpu)",
            metrics.planner_paced_seconds.clone(),
        );
        registry.register("store_commit_seconds", "Time to commit one transaction", metrics.store_commit.clone());
        registry.register("store_commit_group", "Changesets committed per transaction", metrics.commit_group.clone());
        // Where a robot's request waits.
        for (name, help, waited) in [
            (
                "mission_wait_seconds",
                "Time a robot's request waited for its mission (its other requests and plans)",
                &metrics.mission_wait,
            ),
            (
                "store_queue_wait_seconds",
                "Time a changeset waited for room in the store's write queue, its mission held",
                &metrics.store_queue_wait,
            ),
            (
                "store_durable_wait_seconds",
                "Time from a changeset queued for writing to its being durable",
                &metrics.store_durable_wait,
            ),
            (
                "store_queued_seconds",
                "Time a changeset waited in the write queue for its group's transaction to begin",
                &metrics.store_queued,
            ),
        ] {
            registry.register(name, help, waited.clone());
        }
        registry.register(
            "patches_folded",
            "Map patches folded into map snapshots and so out of the patch log",
            metrics.patches_folded.clone(),
        );
        registry.register("shed", "Calls refused to shed load, by reason", metrics.shed.clone());
        registry.register("connections", "Open connections, by listener", metrics.connections.clone());
        registry.register(
            "connections_refused",
            "Connections turned away at the limit, and failed accepts (out of descriptors), by listener",
            metrics.connections_refused.clone(),
        );
        registry.register("missions", "Missions by state", metrics.missions.clone());
        registry.register("robots", "Robots by state (lost robots as lost)", metrics.robots.clone());
        registry.register("frontier_cells", "Frontier cells of each mission", metrics.frontier_cells.clone());
        registry.register("coverage", "Known share of each mission's grid", metrics.coverage.clone());
        Self { registry, ..metrics }
    }

    /// Records one plan of `policy`.
    pub fn observe_plan(&self, policy: &str, took: Duration) {
        self.plan_seconds.get_or_create(&Label { name: policy.to_owned() }).observe(took.as_secs_f64());
    }

    /// Counts one call refused to shed load.
    pub fn shed(&self, reason: &str) {
        self.shed.get_or_create(&Label { name: reason.to_owned() }).inc();
    }

    /// The metrics in the Prometheus text format.
    pub fn encode(&self) -> String {
        let mut out = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::text::encode(&mut out, &self.registry);
        out
    }
}

/// Counts and times every gRPC call: a tower layer in front of the services.
#[derive(Debug, Clone)]
pub struct RpcMetricsLayer(pub Arc<Metrics>);

impl<S> tower::Layer<S> for RpcMetricsLayer {
    type Service = RpcMetrics<S>;

    fn layer(&self, inner: S) -> Self::Service {
        RpcMetrics { inner, metrics: Arc::clone(&self.0) }
    }
}

/// See [`RpcMetricsLayer`].
#[derive(Debug, Clone)]
pub struct RpcMetrics<S> {
    inner: S,
    metrics: Arc<Metrics>,
}

/// `exploration.v1.Fleet/UpdateMap` from `/exploration.v1.Fleet/UpdateMap`.
fn method_of(path: &str) -> String {
    path.trim_start_matches('/').to_owned()
}

/// The gRPC status of a response whose headers carry it (errors, which
/// tonic answers trailers-only); `OK` otherwise.
fn code_of<B>(response: &http::Response<B>) -> String {
    let code = response
        .headers()
        .get("grpc-status")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<i32>().ok())
        .unwrap_or(0);
    format!("{:?}", tonic::Code::from_i32(code))
}

impl<S, B, R> tower::Service<http::Request<B>> for RpcMetrics<S>
where
    S: tower::Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = Pin<Box<dyn std::future::Future<Output = Result<Self::Response, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let method = method_of(request.uri().path());
        let metrics = Arc::clone(&self.metrics);
        let started = Instant::now();
        let response = self.inner.call(request);
        Box::pin(async move {
            let response = response.await?;
            metrics
                .call_seconds
                .get_or_create(&Label { name: method.clone() })
                .observe(started.elapsed().as_secs_f64());
            metrics.calls.get_or_create(&CallLabels { method, code: code_of(&response) }).inc();
            Ok(response)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_text_format_names_every_family() {
        let metrics = Metrics::new();
        metrics.observe_plan("minpos", Duration::from_millis(12));
        metrics.shed("mission queue full");
        metrics
            .calls
            .get_or_create(&CallLabels { method: "exploration.v1.Fleet/UpdateMap".into(), code: "Ok".into() })
            .inc();
        let text = metrics.encode();
        for needle in [
            "coordinator_plan_seconds_count{name=\"minpos\"} 1",
            "coordinator_shed_total{name=\"mission queue full\"} 1",
            "coordinator_calls_total{method=\"exploration.v1.Fleet/UpdateMap\",code=\"Ok\"} 1",
            "# TYPE coordinator_store_commit_seconds histogram",
            "# TYPE coordinator_mission_wait_seconds histogram",
            "# TYPE coordinator_store_queue_wait_seconds histogram",
            "# TYPE coordinator_store_durable_wait_seconds histogram",
            "# TYPE coordinator_store_queued_seconds histogram",
        ] {
            assert!(text.contains(needle), "{needle} missing from\n{text}");
        }
    }
}
