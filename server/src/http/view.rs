//! The live mission view: one page, and the JSON it reads.
//!
//! `GET /` is the page (embedded in the binary, no build step). It reads
//! `GET /api/missions`, and follows one mission through
//! `GET /api/missions/{id}/live`, a stream of server-sent events: the first
//! carries the whole map, each later one only the rectangles of the map that
//! changed (from the mission's [map log](crate::executive::MapChanges)), the
//! robots, the mission's counters, and now and then the latest tasks,
//! events and segmentation. The page reads the stream with `fetch`, not
//! `EventSource`, so that the token travels in the `Authorization` header,
//! never in a URL.
//!
//! The API obeys the gRPC API's tokens: any valid token may read, as it may
//! through `GetMission` and `WatchMission`.

use std::sync::Arc;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::{FromRequestParts, Path, State};
use axum::http::request::Parts;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use tokio_util::sync::CancellationToken;

use exploration::grid::{CellClass, classify};

use super::Shared;
use super::cells::{Classes, MOST_SEGMENTATION_RUNS, each_run, runs};
use crate::auth::Caller;
use crate::domain::{MissionEvent, TaskRecord};
use crate::error::Error;
use crate::executive::{Executive, MapChanges, MissionSummary, RobotSummary};
use crate::store::TaskFilter;

/// The page, with its script and style inline.
const PAGE: &str = include_str!("view.html");

/// Least time between two updates of one stream: a person cannot follow
/// faster, and a busy mission would otherwise send one per map patch.
const UPDATE_GAP: Duration = Duration::from_millis(250);
/// Longest a live view goes without a byte: within the minute after which
/// proxies commonly close a silent response (nginx's `proxy_read_timeout`),
/// and often enough that a viewer gone away is noticed (by the write).
const KEEP_ALIVE: Duration = Duration::from_secs(20);

/// How often the latest tasks and events (read from the store) are sent.
const HISTORY_GAP: Duration = Duration::from_secs(1);

/// How often a changed segmentation is sent (it is as large as the map).
const SEGMENTATION_GAP: Duration = Duration::from_secs(5);

/// Tasks and events shown.
const LATEST: usize = 12;

/// Live streams open at once. Each reads the mission several times a
/// second; more viewers are refused (503 with Retry-After) rather than
/// slowing the executive for its robots.
pub(super) const MAX_LIVE_STREAMS: usize = 64;

pub(super) async fn page() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8"), (header::CACHE_CONTROL, "no-store")], PAGE)
}

/// The caller, authenticated by the same rules as every gRPC call.
pub(super) struct Authenticated;

impl FromRequestParts<Shared> for Authenticated {
    type Rejection = Response;

    async fn from_request_parts(parts: &mut Parts, state: &Shared) -> Result<Self, Self::Rejection> {
        let metadata = tonic::metadata::MetadataMap::from_headers(parts.headers.clone());
        state
            .auth
            .caller(&metadata, |robot| state.executive.robot_token_hash(robot))
            .map(|_: Caller| Authenticated)
            .map_err(error_response)
    }
}

/// `GET /api/missions`: every mission with its counters.
pub(super) async fn missions(State(state): State<Shared>, _caller: Authenticated) -> Response {
    match state.executive.missions().await {
        Ok(missions) => json(&missions.iter().map(MissionJson::from).collect::<Vec<_>>()),
        Err(e) => error_response(e),
    }
}

/// `GET /api/missions/{id}/live`: the mission as server-sent events.
pub(super) async fn live(State(state): State<Shared>, Path(id): Path<String>, _caller: Authenticated) -> Response {
    // Read here rather than by axum, whose refusal is plain text that
    // echoes the raw segment (control characters included).
    let Ok(id) = id.parse::<u64>() else {
        return error_response(Error::InvalidArgument(format!(
            "{id:?} is not a mission id (a number from 0 to 2^64 - 1)"
        )));
    };
    let Ok(permit) = Arc::clone(&state.live_streams).try_acquire_owned() else {
        let message = format!("{MAX_LIVE_STREAMS} live views are open, the most this executive serves; retry later");
        let mut refused = error_response(Error::Overloaded(message));
        refused.headers_mut().insert(header::RETRY_AFTER, header::HeaderValue::from_static("5"));
        return refused;
    };
    let mut cursor = Cursor::default();
    let first = match Frame::read(&state.executive, id, &mut cursor).await {
        Ok(frame) => frame,
        Err(e) => return error_response(e),
    };
    let (sender, receiver) = tokio::sync::mpsc::channel::<Bytes>(4);
    let (executive, stop) = (state.executive.clone(), state.stop.clone());
    tokio::spawn(async move {
        follow(executive, stop, id, (first, cursor), sender).await;
        drop(permit);
    });
    let body = Body::from_stream(futures::StreamExt::map(tokio_stream::wrappers::ReceiverStream::new(receiver), |b| {
        Ok::<_, std::convert::Infallible>(b)
    }));
    (
        [
            (header::CONTENT_TYPE, "text/event-stream"),
            (header::CACHE_CONTROL, "no-store"),
            (header::HeaderName::from_static("x-accel-buffering"), "no"),
        ],
        body,
    )
        .into_response()
}

/// Sends `first`, then an update whenever the mission changes (at most one
/// per [`UPDATE_GAP`]), until the viewer goes away, the mission is gone or
/// the executive stops.
async fn follow(
    executive: Arc<Executive>,
    stop: CancellationToken,
    id: u64,
    (first, mut cursor): (Frame, Cursor),
    sender: tokio::sync::mpsc::Sender<Bytes>,
) {
    let Ok(mut changed) = executive.subscribe(id).await else { return };
    if sender.send(first.event()).await.is_err() {
        return;
    }
    loop {
        tokio::select! {
            () = stop.cancelled() => return,
            () = sender.closed() => return,
            moved = changed.changed() => if moved.is_err() { return },
            () = tokio::time::sleep(KEEP_ALIVE) => {
                // A comment, which readers skip: a quiet mission's view
                // outlives a proxy's read timeout (see `KEEP_ALIVE`).
                if sender.send(Bytes::from_static(b": quiet\n\n")).await.is_err() {
                    return;
                }
                continue;
            }
        }
        tokio::select! {
            () = stop.cancelled() => return,
            () = tokio::time::sleep(UPDATE_GAP) => {}
        }
        changed.borrow_and_update();
        let frame = match Frame::read(&executive, id, &mut cursor).await {
            Ok(frame) => frame,
            Err(e) => {
                tracing::debug!(mission = id, error = %e, "live view ends");
                return;
            }
        };
        if sender.send(frame.event()).await.is_err() {
            return;
        }
    }
}

/// What a stream has sent so far; `None`: nothing yet.
#[derive(Debug, Default)]
struct Cursor {
    map_version: Option<u64>,
    history_at: Option<tokio::time::Instant>,
    segmentation_at: Option<tokio::time::Instant>,
    segmentation_computed: Option<i64>,
}

/// Whether `last` is none, or at least `gap` before `now`.
fn due(last: Option<tokio::time::Instant>, now: tokio::time::Instant, gap: Duration) -> bool {
    last.is_none_or(|t| now.duration_since(t) >= gap)
}

/// One update of the live view.
#[derive(Debug, Serialize)]
struct Frame {
    mission: MissionJson,
    robots: Vec<RobotJson>,
    map: MapJson,
    /// Newest first; absent when not refreshed in this update.
    #[serde(skip_serializing_if = "Option::is_none")]
    tasks: Option<Vec<TaskJson>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    events: Option<Vec<EventJson>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    segmentation: Option<SegmentationJson>,
}

impl Frame {
    /// The mission now, with what changed since `cursor` (everything the
    /// first time), moving `cursor` on.
    async fn read(executive: &Executive, id: u64, cursor: &mut Cursor) -> Result<Self, Error> {
        let mission = MissionJson::from(&executive.mission(id).await?);
        let robots = executive.robots(id).await?.iter().map(RobotJson::from).collect();
        let changes = executive.map_changes(id, cursor.map_version).await?;
        cursor.map_version = Some(changes.version);
        let now = tokio::time::Instant::now();
        let (mut tasks, mut events) = (None, None);
        if due(cursor.history_at, now, HISTORY_GAP) {
            cursor.history_at = Some(now);
            let latest = executive.tasks(TaskFilter::mission(id, LATEST as u32)).await?;
            tasks = Some(latest.iter().map(TaskJson::from).collect());
            let latest = executive.latest_events(id, LATEST as u32).await?;
            events = Some(latest.iter().map(EventJson::from).collect());
        }
        let mut segmentation = None;
        if due(cursor.segmentation_at, now, SEGMENTATION_GAP) {
            cursor.segmentation_at = Some(now);
            if let Some(stored) = executive.segmentation(id).await?
                && Some(stored.computed_at.millis()) != cursor.segmentation_computed
            {
                cursor.segmentation_computed = Some(stored.computed_at.millis());
                let labels = &stored.segmentation.labels;
                let fragmented = each_run(labels.iter()).nth(MOST_SEGMENTATION_RUNS).is_some();
                segmentation = Some(SegmentationJson {
                    computed_at_ms: stored.computed_at.millis(),
                    width: stored.segmentation.frame.width,
                    height: stored.segmentation.frame.height,
                    runs: if fragmented { Vec::new() } else { runs(labels.iter().copied()) },
                    fragmented,
                });
            }
        }
        Ok(Self { mission, robots, map: MapJson::from(changes), tasks, events, segmentation })
    }

    /// The frame as one server-sent event, written once (it may carry
    /// megabytes of map). JSON escapes line breaks, so it is one data line.
    fn event(&self) -> Bytes {
        let mut event = b"event: update\ndata: ".to_vec();
        if let Err(e) = serde_json::to_writer(&mut event, self) {
            event.truncate("event: update\ndata: ".len());
            event.extend_from_slice(serde_json::json!({ "error": e.to_string() }).to_string().as_bytes());
        }
        event.extend_from_slice(b"\n\n");
        Bytes::from(event)
    }
}

#[derive(Debug, Serialize)]
struct MissionJson {
    id: u64,
    name: String,
    state: &'static str,
    paused: bool,
    policy: &'static str,
    robots: usize,
    known_cells: u64,
    frontier_cells: u64,
    /// Known cells over the cells of the map's frame, percent.
    coverage_percent: f64,
    replans: u64,
    map_updates: u64,
    width: u32,
    height: u32,
    resolution: f64,
    origin: [f64; 2],
    forbidden: Vec<[f64; 4]>,
    given_segmentation: bool,
}

impl From<&MissionSummary> for MissionJson {
    fn from(m: &MissionSummary) -> Self {
        let frame = m.record.spec.frame;
        let cells = frame.len().max(1) as f64;
        Self {
            id: m.record.id,
            name: m.record.spec.name.clone(),
            state: m.record.state.as_str(),
            paused: m.record.paused,
            policy: m.record.spec.policy.name(),
            robots: m.robots,
            known_cells: m.known_cells,
            frontier_cells: m.frontier_cells,
            coverage_percent: 100.0 * m.known_cells as f64 / cells,
            replans: m.record.replans,
            map_updates: m.record.map_updates,
            width: frame.width,
            height: frame.height,
            resolution: frame.resolution,
            origin: [frame.origin.x, frame.origin.y],
            forbidden: m.forbidden.iter().map(|r| [r.min.x, r.min.y, r.max.x, r.max.y]).collect(),
            given_segmentation: m.given_segmentation,
        }
    }
}

#[derive(Debug, Serialize)]
struct RobotJson {
    id: u64,
    name: String,
    state: &'static str,
    lost: bool,
    x: f64,
    y: f64,
    heading: f64,
    target: Option<[f64; 2]>,
    task: Option<&'static str>,
    distance_m: f64,
}

impl From<&RobotSummary> for RobotJson {
    fn from(r: &RobotSummary) -> Self {
        let record = &r.record;
        Self {
            id: record.id,
            name: record.name.clone(),
            state: record.state.as_str(),
            lost: record.lost,
            x: record.pose.position.x,
            y: record.pose.position.y,
            heading: record.pose.heading,
            target: r.target.map(|t| [t.x, t.y]),
            task: r.task_kind.map(|k| k.as_str()),
            distance_m: record.distance_m,
        }
    }
}

/// Cell classes as the page draws them.
const UNKNOWN: u8 = 0;
const FREE: u8 = 1;
const OCCUPIED: u8 = 2;
const UNCERTAIN: u8 = 3;

#[derive(Debug, Serialize)]
struct MapJson {
    version: u64,
    full: bool,
    /// Changed rectangles; cells as classes (0 unknown, 1 free, 2
    /// occupied, 3 uncertain), row-major from the bottom row, in runs or
    /// packed (see [`Classes`]).
    patches: Vec<PatchJson>,
}

#[derive(Debug, Serialize)]
struct PatchJson {
    x: i32,
    y: i32,
    width: u32,
    height: u32,
    /// `runs` or `packed` (see [`Classes`]).
    #[serde(flatten)]
    cells: Classes,
}

impl From<MapChanges> for MapJson {
    fn from(changes: MapChanges) -> Self {
        let class = |v: &u8| match classify(*v) {
            CellClass::Unknown => UNKNOWN,
            CellClass::Free => FREE,
            CellClass::Occupied => OCCUPIED,
            CellClass::Uncertain => UNCERTAIN,
        };
        let patches = changes
            .patches
            .into_iter()
            .map(|(rect, cells)| PatchJson {
                x: rect.x,
                y: rect.y,
                width: rect.width,
                height: rect.height,
                cells: Classes::encode(&cells.iter().map(class).collect::<Vec<u8>>()),
            })
            .collect();
        Self { version: changes.version, full: changes.full, patches }
    }
}

#[derive(Debug, Serialize)]
struct TaskJson {
    id: u64,
    robot_id: u64,
    kind: &'static str,
    state: &'static str,
    target: [f64; 2],
    created_by: String,
    /// The latest transition: when, why.
    at_ms: i64,
    cause: String,
}

impl From<&TaskRecord> for TaskJson {
    fn from(t: &TaskRecord) -> Self {
        let last = t.transitions.last();
        Self {
            id: t.id,
            robot_id: t.robot_id,
            kind: t.kind.as_str(),
            state: t.state.as_str(),
            target: [t.target.x, t.target.y],
            created_by: t.created_by.clone(),
            at_ms: last.map_or(0, |l| l.at.millis()),
            cause: last.map(|l| l.cause.clone()).unwrap_or_default(),
        }
    }
}

#[derive(Debug, Serialize)]
struct EventJson {
    at_ms: i64,
    kind: String,
    detail: String,
    actor: String,
}

impl From<&MissionEvent> for EventJson {
    fn from(e: &MissionEvent) -> Self {
        Self { at_ms: e.at.millis(), kind: e.kind.clone(), detail: e.detail.clone(), actor: e.actor.clone() }
    }
}

#[derive(Debug, Serialize)]
struct SegmentationJson {
    computed_at_ms: i64,
    width: u32,
    height: u32,
    /// `[label, count, ...]` row-major from the bottom row; 0: no segment.
    runs: Vec<u32>,
    /// More than [`MOST_SEGMENTATION_RUNS`] runs: none are sent (the map
    /// behind it is a pattern no building makes).
    fragmented: bool,
}

fn json(value: &impl Serialize) -> Response {
    match serde_json::to_vec(value) {
        Ok(body) => ([(header::CONTENT_TYPE, "application/json")], body).into_response(),
        Err(e) => error_response(Error::Internal(e.to_string())),
    }
}

/// The one place errors become HTTP answers: the status that matches the
/// gRPC code, and the message as JSON.
fn error_response(error: Error) -> Response {
    let status = match &error {
        Error::InvalidArgument(_) => StatusCode::BAD_REQUEST,
        Error::NotFound(_) => StatusCode::NOT_FOUND,
        Error::AlreadyExists(_) | Error::FailedPrecondition(_) => StatusCode::CONFLICT,
        Error::ResourceExhausted(_) => StatusCode::TOO_MANY_REQUESTS,
        Error::Unauthenticated(_) => StatusCode::UNAUTHORIZED,
        Error::PermissionDenied(_) => StatusCode::FORBIDDEN,
        Error::Overloaded(_) | Error::ShuttingDown | Error::Elsewhere { .. } => StatusCode::SERVICE_UNAVAILABLE,
        Error::Store(_) | Error::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
    };
    let body = serde_json::json!({ "error": error.to_string() }).to_string();
    (status, [(header::CONTENT_TYPE, "application/json")], body).into_response()
}
