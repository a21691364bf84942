//! Overload: robots' calls are refused at once while a queue stands, and
//! admitted again by themselves once it is gone (see `coordinator::admission`).

mod common;

use std::time::Duration;

use sqlx::Connection;
use tonic::Code;

use common::*;
use coordinator::admission::QueueDelay;
use coordinator::{Clock, Config};
use exploration_proto::v1 as pb;

const TARGET: Duration = Duration::from_millis(20);
const INTERVAL: Duration = Duration::from_millis(100);
/// A first queue must stand five intervals (a slow fsync is not overload).
const FIRST: Duration = Duration::from_millis(500);

/// Another program holds SQLite's write lock, so a map update stays in
/// flight (applied, waiting to be durable) for as long as the test keeps
/// it. Once no map update has been answered within the target for five
/// intervals, the next one is refused with RESOURCE_EXHAUSTED and a retry
/// hint, and nothing of it is written. Heartbeats, which are answered in
/// time, and operators' calls are not refused. When the lock is released
/// the stuck update is answered and map updates are admitted again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn map_updates_are_refused_while_one_is_stuck_and_admitted_once_it_is_answered() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("queue.db");
    let (clock, time) = Clock::manual();
    let mut config = Config::new(db.as_path());
    config.executive.clock = clock;
    config.shedding = Some(QueueDelay { target: TARGET, interval: INTERVAL });
    let exec = TestExecutive::start_with(config).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = missions.create_mission(request_for("nearest")).await.unwrap().into_inner();
    let stuck = register(&mut fleet, mission.id, "stuck", 0.5, 0.5).await;
    let probe = register(&mut fleet, mission.id, "probe", 2.5, 0.5).await;
    // A robot of a mission with no map yet: no target, so its heartbeats
    // only say it lives, and never wait for the disk.
    let idle_mission = missions.create_mission(request_for("nearest")).await.unwrap().into_inner();
    let idle = register(&mut fleet, idle_mission.id, "idle", 0.5, 0.5).await;
    let send = |robot: u64, seq: u64| update(robot, seq, 0.5, 0.5, vec![patch(seq as u32, 0, 5, 5, 0.1)]);
    fleet.update_map(send(stuck.id, 1)).await.expect("admitted while nothing is in flight");

    let mut other = sqlx::SqliteConnection::connect(&format!("sqlite://{}", db.display())).await.unwrap();
    sqlx::query("BEGIN IMMEDIATE").execute(&mut other).await.unwrap();
    let in_flight = {
        let mut client = exec.fleet();
        let request = send(stuck.id, 2);
        tokio::spawn(async move { client.update_map(request).await })
    };

    // Applied once queued (the count moves), answered once durable: in flight.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(4);
    while map_updates(&mut missions, mission.id).await < 2 {
        assert!(tokio::time::Instant::now() < deadline, "the second update was never applied");
        tokio::task::yield_now().await;
    }
    time.advance(FIRST - Duration::from_millis(1));
    // Admitted before five intervals have passed; it waits behind the lock too.
    let admitted = {
        let mut client = exec.fleet();
        let request = send(probe.id, 1);
        tokio::spawn(async move { client.update_map(request).await })
    };
    while map_updates(&mut missions, mission.id).await < 3 {
        assert!(tokio::time::Instant::now() < deadline, "an update within the five intervals was not admitted");
        tokio::task::yield_now().await;
    }
    time.advance(Duration::from_millis(1));
    let refused = fleet.update_map(send(probe.id, 2)).await.expect_err("refused once five intervals have passed");
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    // Long enough for a robot sending at 1-2 Hz to hold a call or two.
    let hint = exploration_proto::client::retry_pushback(&refused);
    assert_eq!(hint, Some(INTERVAL * 10), "refused with a hint of ten intervals: {refused:?}");
    assert!(refused.message().contains("UpdateMap calls have been answered late"), "{}", refused.message());
    let beat = pb::HeartbeatRequest {
        robot_id: idle.id,
        pose: Some(pb::Pose { x: 0.5, y: 0.5, theta: 0.0 }),
        state: pb::RobotState::Idle as i32,
        ..Default::default()
    };
    let beat = fleet.heartbeat(beat).await;
    assert!(beat.is_ok(), "heartbeats are not held back by a queue of map updates: {beat:?}");
    let view = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await;
    assert!(view.is_ok(), "an operator's read is not refused: {view:?}");
    let mut health = tonic_health::pb::health_client::HealthClient::new(exec.channel());
    health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.expect("health answers");

    sqlx::query("ROLLBACK").execute(&mut other).await.unwrap();
    drop(other);
    in_flight.await.unwrap().expect("the stuck update is written once the lock is released");
    admitted.await.unwrap().expect("so is the one admitted within the interval");
    // Nothing is in flight now: admitted again without any call on time.
    time.advance(INTERVAL);
    fleet.update_map(send(probe.id, 3)).await.expect("admitted once the queue is gone");

    let stored = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(
        stored.map_updates, 4,
        "the stuck robot's two updates and the probe's two admitted; nothing refused was written"
    );
    exec.stop().await;
}

/// Planned off the request path, as robots' missions are: a lockstep
/// mission plans and writes under its lock after each update.
fn request_for(policy: &str) -> pb::CreateMissionRequest {
    pb::CreateMissionRequest { lockstep: false, ..mission_request(60, 30, policy) }
}

async fn map_updates(
    missions: &mut exploration_proto::v1::missions_client::MissionsClient<tonic::transport::Channel>,
    id: u64,
) -> u64 {
    missions.get_mission(pb::GetMissionRequest { mission_id: id }).await.unwrap().into_inner().map_updates
}

/// Shedding, connection and replica lease settings out of range are
/// refused at start, naming the flag.
#[test]
fn absurd_shedding_and_connection_settings_refuse_to_start() {
    let dir = tempfile::tempdir().unwrap();
    for (args, says) in [
        (["--shed-target-ms", "60001"], "--shed-target-ms must be 0 (off) to 60000"),
        (["--shed-interval-ms", "0"], "--shed-interval-ms must be 1 to 60000"),
        (["--shed-interval-ms", "1000000"], "--shed-interval-ms must be 1 to 60000"),
        // Every connection closed at once; no number at all.
        (["--idle-timeout", "1e-9"], "--idle-timeout must be a number of seconds from 1 to 1e6"),
        (["--idle-timeout", "NaN"], "--idle-timeout must be a number of seconds from 1 to 1e6"),
        // Checked without --replica-id too (it was taken silently there).
        (["--lease-period", "inf"], "--lease-period must be 0.3 to 600 seconds"),
        (["--lease-grace", "1e9"], "--lease-grace must be 0 to 600 seconds"),
    ] {
        let (ok, stderr) = coordinator_exits(&args, &dir.path().join("t.db"));
        assert!(!ok, "{args:?} must not start");
        assert!(stderr.contains(says), "{stderr}");
    }
}
