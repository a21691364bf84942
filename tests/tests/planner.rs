//! Missions planned off the request path: requests are acknowledged as soon
//! as they are durable, the planner assigns targets in the background and
//! pushes them on the robots' streams; the metrics show it working.

mod common;

use common::{TestExecutive, patch, register, update};
use exploration_proto::v1 as pb;

/// The value of a metric line starting with `prefix` (0 when absent).
fn metric(text: &str, prefix: &str) -> f64 {
    text.lines().filter(|l| l.starts_with(prefix)).filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok()).sum()
}

/// Reads a robot's assignment stream until it carries a task. Bounded: a
/// robot the planner never serves fails the test instead of hanging it.
async fn until_assigned(stream: &mut tonic::Streaming<pb::Assignment>, seconds: u64) {
    let assigned = async {
        while let Some(assignment) = stream.message().await.unwrap() {
            if assignment.task_id != 0 {
                return;
            }
        }
        panic!("the stream ended");
    };
    tokio::time::timeout(std::time::Duration::from_secs(seconds), assigned)
        .await
        .unwrap_or_else(|_| panic!("a task within {seconds} s"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn plans_arrive_on_the_streams_and_the_metrics_move() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start_with_http(coordinator::Config::new(dir.path().join("async.db"))).await;
    let http = exec.http.unwrap();
    let before = common::http_get(http, "/metrics").await;
    assert_eq!(metric(&before, "coordinator_plan_seconds_count"), 0.0);

    let mut missions = exec.missions();
    let mission = missions
        .create_mission(pb::CreateMissionRequest {
            name: "async".into(),
            frame: Some(common::frame(60, 30)),
            policy: Some(pb::PolicySpec { name: "minpos".into(), params: Default::default() }),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!mission.lockstep);
    let mut fleet = exec.fleet();
    let mut streams = Vec::new();
    let mut robots = Vec::new();
    for (i, x) in [0.5, 1.5, 2.5].into_iter().enumerate() {
        let robot = register(&mut fleet, mission.id, &format!("r{i}"), x, 0.5).await;
        let stream = fleet.watch_assignment(pb::WatchAssignmentRequest { robot_id: robot.id }).await.unwrap();
        streams.push(stream.into_inner());
        robots.push(robot);
    }
    // The left half is known: each update is acknowledged as applied.
    for (i, robot) in robots.iter().enumerate() {
        let answer = fleet
            .update_map(update(robot.id, 1, 0.5 + i as f64, 0.5, vec![patch(0, 0, 30, 30, 0.1)]))
            .await
            .unwrap()
            .into_inner();
        assert_eq!(answer.applied_seq, 1);
    }
    // The planner's targets arrive on every stream.
    for stream in &mut streams {
        until_assigned(stream, 30).await;
    }
    let after = common::http_get(http, "/metrics").await;
    assert!(metric(&after, "coordinator_plan_seconds_count{name=\"minpos\"}") >= 1.0, "{after}");
    assert!(metric(&after, "coordinator_planner_triggers_total") >= 1.0);
    assert_eq!(metric(&after, "coordinator_calls_total{method=\"exploration.v1.Fleet/UpdateMap\",code=\"Ok\"}"), 3.0);
    assert_eq!(metric(&after, "coordinator_robots{name=\"idle\"}"), 3.0);
    assert_eq!(metric(&after, "coordinator_missions{name=\"active\"}"), 1.0);
    let frontier = metric(&after, &format!("coordinator_frontier_cells{{mission=\"{}\"}}", mission.id));
    assert!(frontier > 0.0, "{after}");
    let coverage = metric(&after, &format!("coordinator_coverage{{mission=\"{}\"}}", mission.id));
    assert!((coverage - 0.5).abs() < 1e-9, "{coverage}");
    assert!(metric(&after, "coordinator_store_commit_seconds_count") >= 1.0);
    // Each map update waited for its mission, for room in the write queue,
    // and for its write to be durable.
    for waited in ["mission_wait", "store_queue_wait", "store_durable_wait", "store_queued"] {
        assert!(metric(&after, &format!("coordinator_{waited}_seconds_count")) >= 3.0, "{waited}: {after}");
    }
    exec.stop().await;
}

/// With a CPU budget (`--planner-cpu`; by default half a container's CPU
/// limit), the planning threads sleep when their CPU time runs ahead of it,
/// and the plans still arrive. Without the budget wired into the plans'
/// searches and jobs nothing sleeps, and the count stays at zero.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn plans_on_a_cpu_budget_wait_for_it_and_still_arrive() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = coordinator::Config::new(dir.path().join("budget.db"));
    // A twentieth of a core: a search of a few milliseconds is ahead of it.
    config.executive.planner_cpu = Some(0.05);
    let exec = TestExecutive::start_with_http(config).await;
    let http = exec.http.unwrap();
    let mut missions = exec.missions();
    let mission = missions
        .create_mission(pb::CreateMissionRequest {
            name: "budget".into(),
            frame: Some(common::frame(240, 120)),
            policy: Some(pb::PolicySpec { name: "burgard".into(), params: Default::default() }),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let mut fleet = exec.fleet();
    let mut streams = Vec::new();
    for (i, x) in [0.5, 6.0, 11.5].into_iter().enumerate() {
        let robot = register(&mut fleet, mission.id, &format!("r{i}"), x, 0.5).await;
        let stream = fleet.watch_assignment(pb::WatchAssignmentRequest { robot_id: robot.id }).await.unwrap();
        streams.push(stream.into_inner());
        fleet.update_map(update(robot.id, 1, x, 0.5, vec![patch(0, 0, 120, 120, 0.1)])).await.unwrap();
    }
    for stream in &mut streams {
        until_assigned(stream, 60).await;
    }
    let after = common::http_get(http, "/metrics").await;
    assert!(metric(&after, "coordinator_plan_seconds_count{name=\"burgard\"}") >= 1.0, "{after}");
    assert!(metric(&after, "coordinator_planner_paced_seconds_total") > 0.0, "{after}");
    exec.stop().await;
}

/// More robot requests than a mission's queue holds are refused at once with
/// RESOURCE_EXHAUSTED and a retry hint, counted as shed; when the burst is
/// over, calls go through again by themselves.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_beyond_a_missions_queue_is_shed_and_the_mission_recovers() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = coordinator::Config::new(dir.path().join("shed.db"));
    config.executive.max_queued_per_mission = 2;
    let exec = TestExecutive::start_with_http(config).await;
    let mut missions = exec.missions();
    let mission = common::create_mission(&mut missions, 60, 30, "nearest").await;
    let mut fleet = exec.fleet();
    let robot = register(&mut fleet, mission.id, "r", 0.5, 0.5).await;
    let mut burst = tokio::task::JoinSet::new();
    for seq in 1..=300 {
        let mut client = exec.fleet();
        burst.spawn(async move {
            client.update_map(update(robot.id, seq, 0.5, 0.5, vec![patch(0, 0, 60, 30, 0.1)])).await.map(|_| ())
        });
    }
    let outcomes = burst.join_all().await;
    let shed: Vec<&tonic::Status> = outcomes
        .iter()
        .filter_map(|o| o.as_ref().err())
        .filter(|s| s.code() == tonic::Code::ResourceExhausted)
        .collect();
    assert!(!shed.is_empty(), "a burst of 300 over a queue of 2 sheds some");
    assert!(shed.iter().all(|s| s.metadata().get("grpc-retry-pushback-ms").is_some()), "with a retry hint");
    assert!(outcomes.iter().any(Result::is_ok), "and admits others");
    // After the burst, a call goes through at once.
    let latest = missions.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner();
    let next = latest.robots[0].last_map_seq + 1;
    fleet.update_map(update(robot.id, next, 0.5, 0.5, vec![])).await.unwrap();
    let metrics = common::http_get(exec.http.unwrap(), "/metrics").await;
    assert!(metric(&metrics, "coordinator_shed_total") >= shed.len() as f64, "{metrics}");
    exec.stop().await;
}

/// A mission does not hold its robots back while the disk writes: map
/// updates of one mission that arrive while one is being written are
/// written together in the next transaction (the mission's lock is not held
/// across the write), and every one acknowledged is durable.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_missions_map_updates_share_the_disks_flushes() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("flushes.db");
    let exec = TestExecutive::start_with_http(coordinator::Config::new(db.clone())).await;
    let mut missions = exec.missions();
    let mission = missions
        .create_mission(pb::CreateMissionRequest {
            name: "flushes".into(),
            frame: Some(common::frame(60, 30)),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!mission.lockstep, "planned off the request path, as a live fleet is");
    let mut fleet = exec.fleet();
    let mut robots = Vec::new();
    for i in 0..16 {
        robots.push(register(&mut fleet, mission.id, &format!("r{i}"), 0.5 + f64::from(i) * 0.2, 0.5).await.id);
    }
    let mut calls = tokio::task::JoinSet::new();
    for (i, robot) in robots.iter().copied().enumerate() {
        let mut client = exec.fleet();
        calls.spawn(async move {
            for seq in 1..=10u64 {
                let x = ((i as u32 * 3 + seq as u32) % 55, i as u32);
                let at = 0.5 + i as f64 * 0.2;
                client.update_map(update(robot, seq, at, 0.5, vec![patch(x.0, x.1, 5, 5, 0.1)])).await.unwrap();
            }
        });
    }
    calls.join_all().await;
    let metrics = common::http_get(exec.http.unwrap(), "/metrics").await;
    let (changesets, transactions) = (
        metric(&metrics, "coordinator_store_commit_group_sum"),
        metric(&metrics, "coordinator_store_commit_group_count"),
    );
    assert!(changesets > transactions, "{changesets} changesets in {transactions} transactions: one at a time");
    let live = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(live.map_updates, 160);
    exec.stop().await;

    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let stored = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(stored.map_updates, 160);
    let listed = missions.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert!(listed.robots.iter().all(|r| r.last_map_seq == 10), "{:?}", listed.robots);
    exec.stop().await;
}

/// The executive folds a mission's patch log while it runs (here after
/// every 4 patches, looked at every 20 ms), the metric counts the folded
/// patches, and the log in the file holds only the patches after them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_patch_log_is_folded_while_the_executive_runs() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("fold.db");
    let mut config = coordinator::Config::new(&db);
    config.compaction = coordinator::Compaction { after_patches: 4, period: std::time::Duration::from_millis(20) };
    let exec = TestExecutive::start_with_http(config).await;
    let http = exec.http.unwrap();
    let mut missions = exec.missions();
    let mission = common::create_mission(&mut missions, 40, 20, "nearest").await;
    let mut fleet = exec.fleet();
    let robot = register(&mut fleet, mission.id, "r", 0.5, 0.5).await;
    for seq in 1..=9u64 {
        let x = (seq as u32 * 3) % 30;
        fleet.update_map(update(robot.id, seq, 0.5, 0.5, vec![patch(x, 0, 8, 8, 0.1)])).await.unwrap();
    }
    let map_before = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    // The compactor runs on its own period: wait for the metric, bounded.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while metric(&common::http_get(http, "/metrics").await, "coordinator_patches_folded_total") < 8.0 {
        assert!(std::time::Instant::now() < deadline, "nothing was folded in a minute");
        tokio::task::yield_now().await;
    }
    exec.stop().await;

    let store = coordinator::SqliteStore::open(&db, coordinator::Durability::Full).await.unwrap();
    assert_eq!(coordinator::store::Store::unfolded_patches(&store, mission.id).await.unwrap(), 1);
    store.close().await;
    drop(store);
    let exec = TestExecutive::start(&db).await;
    let map_after = exec.missions().get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(map_after.cells, map_before.cells);
    exec.stop().await;
}
