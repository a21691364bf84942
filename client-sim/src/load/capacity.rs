//! The closed-loop phase: the most calls per second the executive
//! answers, map updates beside the empty call (the transport's limit).

use std::sync::Arc;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use tokio::task::JoinSet;
use tonic::transport::Channel;

use exploration_proto::v1 as pb;

use super::report::{CapacityReport, Latency, new_histogram};
use super::{LoadConfig, Placed, footprint, pose_at};
use crate::fleet::SimError;
use crate::world::World;

/// The closed-loop phase: as many empty calls, then as many map updates, as
/// `callers` concurrent callers get answered. Each caller goes round its
/// share of the robots, on each robot's own connection, for both kinds of
/// call; the empty call is also timed over one shared connection.
pub(super) async fn measure(
    url: &str,
    config: &LoadConfig,
    robots: &[Placed],
    world: &Arc<World>,
) -> Result<CapacityReport, SimError> {
    let callers = config.capacity_callers.unwrap_or(robots.len()).max(1);
    let shares: Arc<Vec<Vec<Placed>>> = Arc::new(
        (0..callers)
            .map(|c| robots.iter().skip(c).step_by(callers).cloned().collect::<Vec<_>>())
            .filter(|mine| !mine.is_empty())
            .collect(),
    );
    let shared = exploration_proto::client::endpoint(url, config.tls.as_ref())
        .map_err(|e| SimError::Fleet(format!("bad executive URL or TLS settings: {e}")))?
        .connect_lazy();
    let empty_one_connection =
        closed_loop(config.capacity, callers, false, move |_| empty_call(shared.clone())).await.0;
    let mine = Arc::clone(&shares);
    let empty = closed_loop(config.capacity, shares.len(), false, move |c| {
        let (robot, _) = &mine[c.caller][c.round % mine[c.caller].len()];
        empty_call(robot.connection.clone())
    })
    .await
    .0;
    // The robots stand still in this phase, so each one's footprint is the
    // same at every call: built once, the generator (which shares the
    // machine with the executive) spends its CPU on the calls.
    let (range, encoding) = (config.sensor_range_m, config.cell_encoding);
    let footprints: Arc<Vec<Vec<pb::MapPatch>>> = Arc::new(
        shares.iter().map(|mine| mine.iter().map(|(_, at)| footprint(world, *at, range, encoding)).collect()).collect(),
    );
    let mine = Arc::clone(&shares);
    let (updates, latency) = closed_loop(config.capacity, shares.len(), true, move |c| {
        let k = c.round % mine[c.caller].len();
        let (robot, at) = &mine[c.caller][k];
        let request = pb::UpdateMapRequest {
            robot_id: robot.id,
            seq: robot.next_seq.fetch_add(1, Ordering::AcqRel),
            pose: Some(pose_at(*at, 0.0)),
            patches: vec![footprints[c.caller][k].clone()],
            ..Default::default()
        };
        let mut client = robot.client.clone();
        async move {
            match client.update_map(request).await {
                Ok(_) => true,
                // Refused to shed load: wait as asked, as the robots and
                // the project's clients do, instead of asking again at once.
                Err(status) => {
                    if let Some(wait) = exploration_proto::client::retry_pushback(&status) {
                        tokio::time::sleep(wait).await;
                    }
                    false
                }
            }
        }
    })
    .await;
    let latency = Latency::of(&latency);
    Ok(CapacityReport {
        callers,
        empty_calls_per_s: empty,
        empty_calls_one_connection_per_s: empty_one_connection,
        map_updates_per_s: updates,
        share: if empty > 0.0 { updates / empty } else { 0.0 },
        map_update_latency_ms: latency,
    })
}

/// One empty unary call on `connection`; whether it was answered OK.
fn empty_call(connection: Channel) -> impl std::future::Future<Output = bool> + Send {
    let mut health = tonic_health::pb::health_client::HealthClient::new(connection);
    async move { health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.is_ok() }
}

/// Which call a closed-loop caller makes next.
#[derive(Debug, Clone, Copy)]
struct Turn {
    caller: usize,
    round: usize,
}

/// `callers` callers each making the call `call` returns, one after the
/// other, for `length`: calls answered OK per second, and their latency
/// when `timed`. The empty calls are not timed: a lock per call around the
/// one histogram would slow the very reference they are. (A histogram per
/// caller instead would be 188 kB each, 1 µs to 1 h at three digits:
/// 188 MB for a thousand callers.)
async fn closed_loop<F, Fut>(length: Duration, callers: usize, timed: bool, call: F) -> (f64, Histogram<u64>)
where
    F: Fn(Turn) -> Fut + Send + Sync + 'static,
    Fut: std::future::Future<Output = bool> + Send + 'static,
{
    let go = Arc::new(AtomicBool::new(true));
    let count = Arc::new(AtomicU64::new(0));
    let latency = Arc::new(Mutex::new(new_histogram()));
    let call = Arc::new(call);
    let mut workers = JoinSet::new();
    for caller in 0..callers {
        let (go, count, latency, call) = (Arc::clone(&go), Arc::clone(&count), Arc::clone(&latency), Arc::clone(&call));
        workers.spawn(async move {
            let mut round = 0;
            while go.load(Ordering::Acquire) {
                let sent = Instant::now();
                if call(Turn { caller, round }).await {
                    count.fetch_add(1, Ordering::AcqRel);
                    if timed {
                        let micros = sent.elapsed().as_micros().max(1) as u64;
                        latency.lock().unwrap_or_else(|e| e.into_inner()).saturating_record(micros);
                    }
                }
                round += 1;
            }
        });
    }
    let started = Instant::now();
    tokio::time::sleep(length).await;
    go.store(false, Ordering::Release);
    let rate = count.load(Ordering::Acquire) as f64 / started.elapsed().as_secs_f64();
    while workers.join_next().await.is_some() {}
    let histogram = latency.lock().unwrap_or_else(|e| e.into_inner()).clone();
    (rate, histogram)
}
