//! What an adversarial user found (issue "a service a fleet can depend on"),
//! each as the test that would have caught it: real executives on port 0,
//! real SQLite files, a real full disk, the real binaries.

mod common;

use std::collections::HashSet;
use std::time::Duration;

use common::{TestExecutive, coordinator_exits, create_mission, patch, register, update};
use exploration_proto::v1 as pb;
use tonic::Code;

fn bid(x: f64, y: f64, min: f64, max: f64) -> pb::Bid {
    pb::Bid {
        target: Some(pb::Point { x, y }),
        path_cost: 1.0,
        information_gain: 100.0,
        gain_region: Some(pb::Rect { min_x: min, min_y: min, max_x: max, max_y: max }),
    }
}

/// Defect 1: one bid whose gain region spans ±10⁶ m made Simmons allocate
/// 1.6 PB and abort, and again at every start, since the bid was stored.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bid_region_beyond_the_map_cannot_kill_the_executive() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("bids.db");
    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = missions
        .create_mission(pb::CreateMissionRequest {
            name: "simmons".into(),
            frame: Some(pb::MapFrame { resolution: 0.05, origin: None, width: 200, height: 200 }),
            policy: Some(pb::PolicySpec { name: "simmons".into(), params: Default::default() }),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let robot = register(&mut fleet, mission.id, "r1", 1.0, 1.0).await;
    fleet.update_map(update(robot.id, 1, 1.0, 1.0, vec![patch(10, 10, 30, 30, 0.05)])).await.unwrap();
    let request = pb::SubmitBidsRequest { robot_id: robot.id, bids: vec![bid(1.0, 1.0, -1e6, 1e6)] };
    let accepted = fleet.submit_bids(request).await.unwrap().into_inner();
    assert_eq!(accepted.accepted, 1, "the region counts where it meets the map");
    let heartbeat = || pb::HeartbeatRequest {
        robot_id: robot.id,
        pose: Some(pb::Pose { x: 1.0, y: 1.0, theta: 0.0 }),
        state: pb::RobotState::Idle as i32,
        ..Default::default()
    };
    fleet.heartbeat(heartbeat()).await.unwrap();

    // A bid off the map is refused as a whole, naming the field, and the
    // stored bids stay.
    let off =
        pb::SubmitBidsRequest { robot_id: robot.id, bids: vec![bid(1.0, 1.0, 0.0, 2.0), bid(50.0, 1.0, 0.0, 2.0)] };
    let status = fleet.submit_bids(off).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("bids[1].target"), "{}", status.message());
    let nowhere = pb::SubmitBidsRequest { robot_id: robot.id, bids: vec![bid(1.0, 1.0, 500.0, 600.0)] };
    let status = fleet.submit_bids(nowhere).await.unwrap_err();
    assert!(status.message().contains("bids[0].gain_region"), "{}", status.message());

    // And after a restart on the same file, the stored bid plans fine.
    exec.stop().await;
    let exec = TestExecutive::start(&db).await;
    exec.fleet().heartbeat(heartbeat()).await.unwrap();
    exec.stop().await;
}

/// Defect 2: on a full disk, writes failed with INTERNAL and then later ones
/// were acknowledged but never committed (a pooled connection left inside a
/// transaction); after space came back every write waited and failed "database
/// is locked", and a restart lost the acknowledged writes and reused ids.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_refuses_writes_keeps_reads_and_loses_nothing() {
    let Some(disk) = common::Tmpfs::mount("4m", "the full-disk test") else { return };
    let db = disk.path().join("full.db");
    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = create_mission(&mut missions, 200, 200, "nearest").await;
    let robot = register(&mut fleet, mission.id, "r1", 1.0, 1.0).await;
    let ballast = disk.fill_leaving(160 * 1024);

    // Map updates until the disk refuses one, then a few more of every kind.
    let send = |seq: u64| update(robot.id, seq, 1.0, 1.0, vec![patch((seq % 3 * 60) as u32, 0, 60, 60, 0.1)]);
    let mut acknowledged = 0u64;
    let mut seq = 1;
    let mut refusals = 0;
    let mut created = Vec::new();
    while refusals < 6 {
        assert!(seq < 500, "the disk never filled");
        match fleet.update_map(send(seq)).await {
            Ok(_) => {
                acknowledged += 1;
                seq += 1;
            }
            Err(status) => {
                assert_eq!(status.code(), Code::ResourceExhausted, "a full disk is no internal error: {status:?}");
                assert!(status.message().contains("disk is full"), "{}", status.message());
                refusals += 1;
                // Reads still work, and show only what was acknowledged.
                let now = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap();
                assert_eq!(now.into_inner().map_updates, acknowledged);
                match missions
                    .create_mission(pb::CreateMissionRequest {
                        name: "while full".into(),
                        frame: Some(common::frame(10, 10)),
                        ..Default::default()
                    })
                    .await
                {
                    Ok(m) => created.push(m.into_inner().id),
                    Err(status) => assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}"),
                }
            }
        }
    }
    // Space comes back: the executive recovers by itself, at once.
    std::fs::remove_file(ballast).unwrap();
    fleet.update_map(send(seq)).await.expect("writes work again once space is freed");
    acknowledged += 1;
    let after = create_mission(&mut missions, 10, 10, "nearest").await;
    created.push(after.id);
    exec.stop().await;

    // Everything acknowledged is in the store; no identity is given twice.
    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let stored = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(stored.map_updates, acknowledged);
    let robots = missions.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(robots.robots[0].last_map_seq, seq);
    let listed: Vec<u64> = missions
        .list_missions(pb::ListMissionsRequest::default())
        .await
        .unwrap()
        .into_inner()
        .missions
        .iter()
        .map(|m| m.id)
        .collect();
    for id in &created {
        assert!(listed.contains(id), "acknowledged mission {id} is stored: {listed:?}");
    }
    let next = create_mission(&mut missions, 10, 10, "nearest").await;
    assert!(next.id > *created.iter().max().unwrap(), "mission ids are not reused: {} after {created:?}", next.id);
    exec.stop().await;
}

/// Map updates of one mission are applied while their writes are under way
/// (the executive's `writer`). When the disk refuses some of several in
/// flight, the mission drops what was not written: every update
/// acknowledged is in the store, nothing else is, and the live state (the
/// count, each robot's sequence number, the fused map) is what the store
/// holds, before and after a restart.
/// Both when plans are made off the request path and in lockstep (where a
/// plan made on the refused update is refused with it).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_map_updates_on_a_filling_disk_lose_nothing_acknowledged() {
    updates_on_a_filling_disk(false).await;
    updates_on_a_filling_disk(true).await;
}

async fn updates_on_a_filling_disk(lockstep: bool) {
    let Some(disk) = common::Tmpfs::mount("4m", "the concurrent full-disk test") else { return };
    let db = disk.path().join("full.db");
    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let request = pb::CreateMissionRequest {
        name: "filling".into(),
        frame: Some(common::frame(200, 200)),
        policy: Some(pb::PolicySpec { name: "nearest".into(), params: Default::default() }),
        lockstep,
        ..Default::default()
    };
    let mission = missions.create_mission(request).await.unwrap().into_inner();
    let mut robots = Vec::new();
    for i in 0..6 {
        robots.push(register(&mut fleet, mission.id, &format!("r{i}"), 1.0 + f64::from(i) * 0.2, 1.0).await.id);
    }
    let ballast = disk.fill_leaving(160 * 1024);
    let send = |robot: u64, i: usize, seq: u64| {
        let band = patch((seq % 3 * 60) as u32, i as u32 * 30, 60, 30, 0.1 + 0.1 * (seq % 2) as f32);
        update(robot, seq, 1.0 + i as f64 * 0.2, 1.0, vec![band])
    };
    let mut calls = tokio::task::JoinSet::new();
    for (i, robot) in robots.iter().copied().enumerate() {
        let mut client = exec.fleet();
        calls.spawn(async move {
            let (mut seq, mut refusals) = (1u64, 0);
            while refusals < 4 {
                assert!(seq < 500, "the disk never filled");
                match client.update_map(send(robot, i, seq)).await {
                    Ok(_) => seq += 1,
                    Err(status) => {
                        assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
                        refusals += 1;
                    }
                }
            }
            (robot, seq - 1)
        });
    }
    let acknowledged = calls.join_all().await;
    let total: u64 = acknowledged.iter().map(|(_, last)| last).sum();
    let live = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(live.map_updates, total, "the live state counts what was acknowledged");
    let listed = missions.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner();
    for (robot, last) in &acknowledged {
        let seq = listed.robots.iter().find(|r| r.id == *robot).unwrap().last_map_seq;
        assert_eq!(seq, *last, "robot {robot}: its last acknowledged update");
    }

    // Space comes back: every robot goes on where it was acknowledged.
    std::fs::remove_file(ballast).unwrap();
    for (i, (robot, last)) in acknowledged.iter().enumerate() {
        fleet.update_map(send(*robot, i, last + 1)).await.expect("writes work again once space is freed");
    }
    let live_map = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    exec.stop().await;

    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let stored = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(stored.map_updates, total + robots.len() as u64);
    let stored_map = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(stored_map.cells, live_map.cells, "the map the store holds is the one the robots were shown");
    exec.stop().await;
}

/// Defect 3: region ids were taken with load() + 1 under each mission's own
/// lock, so simultaneous calls on different missions collided.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forbidding_regions_on_many_missions_at_once_never_collides() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("regions.db")).await;
    let mut missions = exec.missions();
    let mut ids = Vec::new();
    for _ in 0..4 {
        ids.push(create_mission(&mut missions, 40, 30, "nearest").await.id);
    }
    let mut calls = tokio::task::JoinSet::new();
    for round in 0..50 {
        for &mission_id in &ids {
            let mut client = exec.missions();
            calls.spawn(async move {
                let x = f64::from(round % 30) * 0.1;
                let area = pb::Rect { min_x: x, min_y: 0.0, max_x: x + 0.5, max_y: 0.5 };
                client
                    .forbid_region(pb::ForbidRegionRequest { mission_id, area: Some(area), ..Default::default() })
                    .await
                    .map(|r| r.into_inner().id)
            });
        }
    }
    let mut regions = HashSet::new();
    while let Some(result) = calls.join_next().await {
        let id = result.unwrap().expect("every simultaneous call succeeds");
        assert!(regions.insert(id), "region {id} given twice");
    }
    assert_eq!(regions.len(), 200);
    exec.stop().await;
}

/// Creates `count` missions of `width` × 1 cells at once; their outcomes.
async fn create_at_once(exec: &TestExecutive, width: u32, count: usize) -> Vec<Result<(), Code>> {
    let mut calls = tokio::task::JoinSet::new();
    for _ in 0..count {
        let mut client = exec.missions();
        calls.spawn(async move {
            client
                .create_mission(pb::CreateMissionRequest {
                    name: "at the limit".into(),
                    frame: Some(common::frame(width, 1)),
                    ..Default::default()
                })
                .await
                .map(|_| ())
                .map_err(|s| s.code())
        });
    }
    calls.join_all().await
}

/// Defect 4: the quotas were checked before the store was asked and counted
/// after, so simultaneous creates all passed a check at the limit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quotas_hold_when_many_missions_are_created_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = coordinator::Config::new(dir.path().join("quota.db"));
    config.executive.max_total_cells = 400;
    config.executive.max_missions = 20;
    let exec = TestExecutive::start_with(config).await;
    let mut missions = exec.missions();
    for _ in 0..15 {
        create_mission(&mut missions, 5, 5, "nearest").await;
    }
    // 375 of 400 cells in use: of eight 25-cell missions exactly one fits.
    let results = create_at_once(&exec, 25, 8).await;
    assert_eq!(results.iter().filter(|r| r.is_ok()).count(), 1, "{results:?}");
    assert!(results.iter().all(|r| r.is_ok() || *r == Err(Code::ResourceExhausted)), "{results:?}");
    // 16 of 20 missions (and no cells left): none of thirty more.
    let results = create_at_once(&exec, 1, 30).await;
    assert!(results.iter().all(|r| *r == Err(Code::ResourceExhausted)), "{results:?}");
    let listed = missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner().missions;
    assert_eq!(listed.len(), 16);
    exec.stop().await;

    // The mission limit alone, with cells to spare.
    let mut config = coordinator::Config::new(dir.path().join("count.db"));
    config.executive.max_missions = 10;
    let exec = TestExecutive::start_with(config).await;
    let mut missions = exec.missions();
    for _ in 0..5 {
        create_mission(&mut missions, 5, 5, "nearest").await;
    }
    let results = create_at_once(&exec, 1, 30).await;
    assert_eq!(results.iter().filter(|r| r.is_ok()).count(), 5, "{results:?}");
    let listed = missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner().missions;
    assert_eq!(listed.len(), 10);
    exec.stop().await;
}

/// Defect 5: a second coordinator on the same file started, each saw only its
/// own new missions, and their ids collided.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_coordinator_on_the_same_database_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("shared.db");
    let exec = TestExecutive::start(&db).await;
    create_mission(&mut exec.missions(), 10, 10, "nearest").await;
    let (ok, stderr) = tokio::task::spawn_blocking({
        let db = db.clone();
        move || coordinator_exits(&[], &db)
    })
    .await
    .unwrap();
    assert!(!ok, "the second executive must not start");
    assert!(stderr.contains("in use by another executive"), "{stderr}");
    assert!(stderr.contains(&format!("pid {}", std::process::id())), "names the holder: {stderr}");
    // The first one goes on undisturbed.
    create_mission(&mut exec.missions(), 10, 10, "nearest").await;
    exec.stop().await;
}

/// A file that is not a database (or a folder) stops the start with one
/// line that names it and says why once, not a chain repeating itself.
#[test]
fn a_file_that_is_not_a_database_is_named_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("garbage.db");
    std::fs::write(&garbage, vec![0x5a; 100_000]).unwrap();
    let folder = dir.path().join("folder.db");
    std::fs::create_dir(&folder).unwrap();
    for (db, cause) in [(&garbage, "file is not a database"), (&folder, "is a folder")] {
        let (ok, stderr) = coordinator_exits(&[], db);
        assert!(!ok, "{}: the executive must not start", db.display());
        let said = stderr.lines().filter(|l| l.starts_with("coordinator: ")).collect::<Vec<_>>();
        assert_eq!(said.len(), 1, "{stderr}");
        assert!(said[0].contains(&db.display().to_string()), "names the file: {stderr}");
        assert_eq!(said[0].matches(cause).count(), 1, "says why once: {stderr}");
        assert!(!stderr.contains("Caused by") && !stderr.contains("panicked"), "{stderr}");
    }
    let (ok, stderr) = coordinator_exits(&[], std::path::Path::new(""));
    assert!(!ok && stderr.contains("--db is empty: give a database file"), "{stderr}");
}

/// Defect 6: an empty or blank operator token silently ran open.
#[test]
fn a_blank_operator_token_refuses_to_start() {
    let dir = tempfile::tempdir().unwrap();
    for token in ["", "   "] {
        let (ok, stderr) = coordinator_exits(&["--operator-token", token], &dir.path().join("t.db"));
        assert!(!ok, "{token:?} must not start an open executive");
        assert!(stderr.contains("operator token is empty"), "{stderr}");
    }
}

/// A planner thread count is refused outside 1..=1024 before any thread
/// is started (a mistyped `--planner-threads 1000000` spawned them all).
#[test]
fn absurd_planner_thread_counts_refuse_to_start() {
    let dir = tempfile::tempdir().unwrap();
    for flag in ["--planner-threads", "--background-planner-threads"] {
        for count in ["0", "1000000"] {
            let (ok, stderr) = coordinator_exits(&[flag, count], &dir.path().join("t.db"));
            assert!(!ok, "{flag} {count} must not start");
            assert!(stderr.contains(&format!("{flag} must be 1 to 1024")), "{stderr}");
        }
    }
}

/// Defect 7: a corrupt value in the database panicked or aborted at start
/// (negative durations, 1e300 seconds, 2e7-cell grids) or was truncated.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_database_stops_the_start_naming_the_row() {
    use sqlx::Connection;
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("corrupt.db");
    let exec = TestExecutive::start(&db).await;
    create_mission(&mut exec.missions(), 10, 10, "nearest").await;
    exec.stop().await;
    for (edit, expected) in [
        ("UPDATE missions SET lease_s = 1e300", "missions row 1: lease_s"),
        ("UPDATE missions SET replan_interval_s = -2", "missions row 1: replan_interval_s"),
        ("UPDATE missions SET width = 20000, height = 2000", "missions row 1: width × height"),
        ("UPDATE missions SET width = 4294967297", "missions row 1: width"),
    ] {
        let mut raw = sqlx::SqliteConnection::connect(&format!("sqlite:{}", db.display())).await.unwrap();
        sqlx::query(edit).execute(&mut raw).await.unwrap();
        raw.close().await.unwrap();
        let file = db.clone();
        let (ok, stderr) = tokio::task::spawn_blocking(move || coordinator_exits(&[], &file)).await.unwrap();
        assert!(!ok, "{edit}: the executive must not start");
        assert!(stderr.contains(expected), "{edit}: {stderr}");
        assert!(!stderr.contains("panicked"), "{edit}: {stderr}");
        let mut raw = sqlx::SqliteConnection::connect(&format!("sqlite:{}", db.display())).await.unwrap();
        sqlx::query("UPDATE missions SET lease_s = 15, replan_interval_s = 30, width = 10, height = 10")
            .execute(&mut raw)
            .await
            .unwrap();
        raw.close().await.unwrap();
    }
}

/// A codec that sends raw bytes, to speak malformed protobuf.
#[derive(Debug, Clone, Default)]
struct RawBytes;

impl tonic::codec::Codec for RawBytes {
    type Encode = Vec<u8>;
    type Decode = Vec<u8>;
    type Encoder = RawBytes;
    type Decoder = RawBytes;

    fn encoder(&mut self) -> Self::Encoder {
        RawBytes
    }

    fn decoder(&mut self) -> Self::Decoder {
        RawBytes
    }
}

impl tonic::codec::Encoder for RawBytes {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn encode(&mut self, item: Vec<u8>, dst: &mut tonic::codec::EncodeBuf<'_>) -> Result<(), tonic::Status> {
        use bytes::BufMut;
        dst.put_slice(&item);
        Ok(())
    }
}

impl tonic::codec::Decoder for RawBytes {
    type Item = Vec<u8>;
    type Error = tonic::Status;

    fn decode(&mut self, src: &mut tonic::codec::DecodeBuf<'_>) -> Result<Option<Vec<u8>>, tonic::Status> {
        use bytes::Buf;
        let mut out = vec![0; src.remaining()];
        src.copy_to_slice(&mut out);
        Ok(Some(out))
    }
}

/// Defect 8, the smaller findings, each changing nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn smaller_findings_get_precise_statuses_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("small.db")).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = create_mission(&mut missions, 40, 30, "nearest").await;
    let a = register(&mut fleet, mission.id, "a", 1.0, 1.0).await;
    let b = register(&mut fleet, mission.id, "b", 3.0, 1.0).await;
    fleet.update_map(update(a.id, 1, 1.0, 1.0, vec![patch(0, 0, 40, 15, 0.1)])).await.unwrap();
    let events_before = common::events(&mut missions, mission.id).await;

    // SetPolicy with a 1 MiB actor: refused; with a 1 MiB reason: cut.
    let huge = "x".repeat(1 << 20);
    let set = |actor: &str, reason: &str| pb::SetPolicyRequest {
        mission_id: mission.id,
        policy: Some(pb::PolicySpec { name: "minpos".into(), params: Default::default() }),
        actor: actor.into(),
        reason: reason.into(),
    };
    assert_eq!(missions.set_policy(set(&huge, "")).await.unwrap_err().code(), Code::InvalidArgument);
    missions.set_policy(set("ops", &huge)).await.unwrap();
    let events = common::events(&mut missions, mission.id).await;
    let detail = &events.last().unwrap().detail;
    assert!(detail.len() < 1_000, "the reason is cut: {} bytes", detail.len());

    // Names with line breaks or NUL: refused (a \n forged lines in the text log).
    for bad in ["robot\nforged", "ro\rbot", "nul\0"] {
        let status = fleet.register_robot(common::registration(mission.id, bad, 1.0, 1.0)).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{bad:?}");
        assert!(status.message().contains("control character"), "{}", status.message());
    }

    // ARRIVED naming another robot's task: refused, and a's state is kept.
    let assignment_b = fleet.get_assignment(pb::GetAssignmentRequest { robot_id: b.id }).await.unwrap().into_inner();
    assert_ne!(assignment_b.task_id, 0, "b has a task");
    let robots = |m: &mut pb::missions_client::MissionsClient<tonic::transport::Channel>| {
        let mut m = m.clone();
        async move { m.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner().robots }
    };
    let before = robots(&mut missions).await;
    let status = fleet
        .heartbeat(pb::HeartbeatRequest {
            robot_id: a.id,
            pose: Some(pb::Pose { x: 1.0, y: 1.0, theta: 0.0 }),
            state: pb::RobotState::Arrived as i32,
            task_id: assignment_b.task_id,
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::FailedPrecondition);
    let after = robots(&mut missions).await;
    assert_eq!(before, after);

    // A rectangle spanning 2³² cells and more overlaps the map: accepted.
    let everywhere = pb::Rect { min_x: -1e9, min_y: -1e9, max_x: 1e9, max_y: 1e9 };
    let region = missions
        .forbid_region(pb::ForbidRegionRequest { mission_id: mission.id, area: Some(everywhere), ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    let kept = region.area.unwrap();
    assert_eq!((kept.min_x, kept.min_y, kept.max_x, kept.max_y), (0.0, 0.0, 4.0, 3.0), "kept as the map's part");
    missions
        .allow_region(pb::AllowRegionRequest { mission_id: mission.id, region_id: region.id, ..Default::default() })
        .await
        .unwrap();

    // An origin of 1e308: refused naming the field.
    let status = missions
        .create_mission(pb::CreateMissionRequest {
            name: "far".into(),
            frame: Some(pb::MapFrame {
                resolution: 0.1,
                origin: Some(pb::Point { x: 1e308, y: 0.0 }),
                width: 10,
                height: 10,
            }),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("frame.origin.x"), "{}", status.message());

    // A million peers: refused.
    let mut flood = update(a.id, 2, 1.0, 1.0, vec![]);
    flood.peers = (1..=1_000_000).collect();
    flood.peers_reported = true;
    let status = fleet.update_map(flood).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(status.message().contains("peers"), "{}", status.message());

    // Malformed protobuf: the caller's error, not an internal one.
    let mut grpc = tonic::client::Grpc::new(exec.channel());
    grpc.ready().await.unwrap();
    let path = http::uri::PathAndQuery::from_static("/exploration.v1.Missions/GetMission");
    let status = grpc.unary(tonic::Request::new(vec![0xff, 0xff, 0xff]), path, RawBytes).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");

    // Nothing above changed the mission but the policy and the region's two events.
    let events = common::events(&mut missions, mission.id).await;
    assert_eq!(events.len(), events_before.len() + 3);
    let stored = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!((stored.map_updates, stored.robots), (1, 2));
    exec.stop().await;
}

/// Reads from a raw TCP connection until the server closes it.
async fn until_closed(stream: &mut tokio::net::TcpStream) {
    use tokio::io::AsyncReadExt;
    let mut buf = [0u8; 1024];
    loop {
        match stream.read(&mut buf).await {
            Ok(0) | Err(_) => return,
            Ok(_) => {}
        }
    }
}

/// Defect 8, continued: idle connections were never closed (3 000 held).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_are_closed_but_streams_are_not() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = coordinator::Config::new(dir.path().join("idle.db"));
    config.connections.idle_timeout = Duration::from_millis(300);
    let exec = TestExecutive::start_with(config).await;
    let mut missions = exec.missions();
    let mission = create_mission(&mut missions, 40, 30, "nearest").await;
    let channel = tonic::transport::Endpoint::from_shared(exec.url.clone()).unwrap().connect().await.unwrap();
    let mut fleet = pb::fleet_client::FleetClient::new(channel);
    let robot = register(&mut fleet, mission.id, "r", 1.0, 1.0).await;
    // A connection carrying an open stream is busy, not idle.
    let mut stream =
        fleet.watch_assignment(pb::WatchAssignmentRequest { robot_id: robot.id }).await.unwrap().into_inner();
    stream.message().await.unwrap().expect("the current assignment");

    // A connection that never asks anything is closed after the idle time.
    let mut idle = tokio::net::TcpStream::connect(exec.address).await.unwrap();
    tokio::time::timeout(Duration::from_secs(20), until_closed(&mut idle)).await.expect("the idle one is closed");

    // The stream outlived the idle time and still delivers.
    fleet.update_map(update(robot.id, 1, 1.0, 1.0, vec![patch(0, 0, 40, 15, 0.1)])).await.unwrap();
    let next = tokio::time::timeout(Duration::from_secs(20), stream.message()).await.unwrap().unwrap();
    assert!(next.is_some_and(|a| a.task_id != 0), "the stream still delivers assignments");
    exec.stop().await;
}

/// Defect 8, continued: nothing bounded how many connections were open.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_beyond_the_limit_are_refused_until_one_closes() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = coordinator::Config::new(dir.path().join("limit.db"));
    config.connections.max_connections = 2;
    config.connections.idle_timeout = Duration::from_secs(3600);
    // The raw connections below never speak HTTP/2: shutdown does not wait for them.
    config.connections.drain_grace = Duration::from_millis(100);
    // Served without the readiness probe of TestExecutive, whose own
    // connection would count against the limit of two.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap();
    let stop = tokio_util::sync::CancellationToken::new();
    let served = tokio::spawn(coordinator::run(listener, stop.clone().cancelled_owned(), config));
    let first = tokio::net::TcpStream::connect(address).await.unwrap();
    let _second = tokio::net::TcpStream::connect(address).await.unwrap();
    // Nothing closes a connection within the hour but the limit.
    let mut third = tokio::net::TcpStream::connect(address).await.unwrap();
    tokio::time::timeout(Duration::from_secs(20), until_closed(&mut third)).await.expect("over the limit: closed");
    // Once one closes, calls get through again.
    drop(first);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        let channel = tonic::transport::Endpoint::from_shared(format!("http://{address}")).unwrap().connect_lazy();
        let mut missions = pb::missions_client::MissionsClient::new(channel);
        if missions.list_missions(pb::ListMissionsRequest::default()).await.is_ok() {
            break;
        }
        assert!(tokio::time::Instant::now() < deadline, "a freed place is given to the next connection");
        tokio::task::yield_now().await;
    }
    stop.cancel();
    served.await.unwrap().unwrap();
}

/// Another program on the same database file (an operator's `sqlite3`
/// shell inside `BEGIN IMMEDIATE`, say) holds SQLite's write lock while the
/// robots of ten missions send map updates. Each call is answered
/// UNAVAILABLE once SQLite's busy timeout (5 s) has passed for the groups it
/// waited behind (about 20 s at most here: a mission's own plan may be
/// queued first), and none of them is written; when the lock is released,
/// updates go through again and every acknowledged one is in the store. (A
/// group that failed that way was written again changeset by changeset,
/// each waiting out the busy timeout anew: nine missions' updates grouped
/// together took 45 s and more.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_program_holding_the_write_lock_gets_every_call_answered_in_time() {
    use sqlx::Connection;
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("held.db");
    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let send = |robot: u64, seq: u64| update(robot, seq, 0.5, 0.5, vec![patch(seq as u32, 0, 5, 5, 0.1)]);
    let mut robots = Vec::new();
    for _ in 0..10 {
        let mission = create_mission(&mut missions, 60, 30, "nearest").await;
        let robot = register(&mut fleet, mission.id, "r", 0.5, 0.5).await;
        fleet.update_map(send(robot.id, 1)).await.unwrap();
        robots.push((mission.id, robot.id));
    }

    let mut other = sqlx::SqliteConnection::connect(&format!("sqlite://{}", db.display())).await.unwrap();
    sqlx::query("BEGIN IMMEDIATE").execute(&mut other).await.unwrap();
    let deadline = Duration::from_secs(45);
    let mut calls = tokio::task::JoinSet::new();
    for &(_, robot) in &robots {
        let mut client = exec.fleet();
        let mut request = tonic::Request::new(send(robot, 2));
        request.set_timeout(deadline);
        calls.spawn(async move { client.update_map(request).await });
    }
    for outcome in calls.join_all().await {
        let status = outcome.expect_err("nothing is written while the lock is held");
        assert_eq!(status.code(), Code::Unavailable, "answered before the deadline of {deadline:?}: {status:?}");
        assert!(status.message().contains("nothing of this request was written"), "{}", status.message());
    }
    sqlx::query("ROLLBACK").execute(&mut other).await.unwrap();
    drop(other);

    // Released: the same updates go through, and only they are stored.
    for &(_, robot) in &robots {
        fleet.update_map(send(robot, 2)).await.expect("writes work again once the lock is released");
    }
    exec.stop().await;
    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    for &(mission_id, _) in &robots {
        let stored = missions.get_mission(pb::GetMissionRequest { mission_id }).await.unwrap().into_inner();
        assert_eq!(stored.map_updates, 2, "mission {mission_id}: the two acknowledged updates, no other");
    }
    exec.stop().await;
}
