//! A small fleet explores a bundled real map against a real executive with
//! a real SQLite file, and the database holds the whole story afterwards.

mod common;

use client_sim::RunConfig;
use common::{TestExecutive, bundled_map};
use sqlx::Row;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_robots_explore_the_depot_and_the_database_keeps_every_transition() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("fleet.db");
    let exec = TestExecutive::start(&db).await;
    let mut config = RunConfig::new(bundled_map("nav2_depot"), 3, "burgard");
    config.server = Some(exec.url.clone());
    config.cell_size = Some(0.2);
    config.seed = 3;
    let report = client_sim::run(&config).await.unwrap();
    assert!(report.completed, "{report:?}");
    assert_eq!(report.coverage, 1.0);
    assert!(report.t50 <= report.t90 && report.t90 <= report.t100, "{report:?}");
    assert_eq!(report.updates_acknowledged, report.map_updates, "an acknowledged update is missing or doubled");
    assert_eq!(report.stream_lags, 0, "the assignment stream fell behind the responses");
    assert!(report.distance_per_robot.iter().all(|d| *d > 1.0), "{report:?}");
    exec.stop().await;

    // The file alone tells what happened.
    let pool = sqlx::SqlitePool::connect(&format!("sqlite://{}", db.display())).await.unwrap();
    let (policy, updates): (String, i64) = sqlx::query_as("SELECT policy, map_updates FROM missions WHERE id = ?1")
        .bind(report.mission_id as i64)
        .fetch_one(&pool)
        .await
        .unwrap();
    assert_eq!(policy, "burgard");
    assert_eq!(updates as u64, report.map_updates);
    let robots: Vec<(String, i64)> =
        sqlx::query_as("SELECT name, last_map_seq FROM robots ORDER BY id").fetch_all(&pool).await.unwrap();
    assert_eq!(robots.iter().map(|r| r.0.as_str()).collect::<Vec<_>>(), ["robot-0", "robot-1", "robot-2"]);
    let logged: i64 = sqlx::query_scalar("SELECT COUNT(DISTINCT robot_id || ':' || seq) FROM map_patches")
        .fetch_one(&pool)
        .await
        .unwrap();
    assert!(logged > 0 && logged as u64 <= report.map_updates);
    // Every task starts assigned by the policy and every ended task says how.
    let tasks = sqlx::query("SELECT id, state FROM tasks").fetch_all(&pool).await.unwrap();
    assert!(tasks.len() >= 3);
    for task in &tasks {
        let id: i64 = task.get("id");
        let transitions: Vec<(Option<String>, String, String, String)> = sqlx::query_as(
            "SELECT from_state, to_state, cause, actor FROM task_transitions WHERE task_id = ?1 ORDER BY id",
        )
        .bind(id)
        .fetch_all(&pool)
        .await
        .unwrap();
        assert_eq!(transitions[0].0, None);
        assert_eq!(transitions[0].1, "assigned");
        assert_eq!(transitions[0].3, "policy");
        let state: String = task.get("state");
        assert_eq!(transitions.last().unwrap().1, state, "task {id}'s state is its last transition");
        for pair in transitions.windows(2) {
            assert_eq!(pair[0].1, pair[1].0.clone().unwrap(), "task {id}: transitions chain");
            assert!(!pair[1].2.is_empty(), "task {id}: every transition has a cause");
        }
    }
    let reached: i64 =
        sqlx::query_scalar("SELECT COUNT(*) FROM tasks WHERE state = 'reached'").fetch_one(&pool).await.unwrap();
    let preempted: i64 =
        sqlx::query_scalar("SELECT COUNT(*) FROM tasks WHERE state = 'preempted'").fetch_one(&pool).await.unwrap();
    assert!(reached + preempted > 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_same_seed_gives_the_same_run() {
    let run = || async {
        let mut config = RunConfig::new(bundled_map("mrpb_maze"), 2, "burgard");
        config.cell_size = Some(0.3);
        config.seed = 11;
        client_sim::run(&config).await.unwrap()
    };
    let (a, b) = (run().await, run().await);
    assert!(a.completed, "{a:?}");
    assert_eq!(
        (a.steps, a.t50, a.t90, a.t100, a.replans, &a.distance_per_robot, &a.trajectories),
        (b.steps, b.t50, b.t90, b.t100, b.replans, &b.distance_per_robot, &b.trajectories)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_fleet_finishes_without_a_robot_that_died_and_one_that_froze() {
    use client_sim::fleet::{Fault, FaultKind};
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("faults.db")).await;
    let mut config = RunConfig::new(bundled_map("nav2_depot"), 3, "burgard");
    config.server = Some(exec.url.clone());
    config.cell_size = Some(0.2);
    config.seed = 3;
    // Real-time lease and stall of 1 s; 5 ms per step make sure the run
    // lasts seconds past the faults whatever the machine's speed.
    config.pace = Some(std::time::Duration::from_millis(5));
    config.lease_s = Some(1.0);
    config.stall_s = Some(1.0);
    config.faults =
        vec![Fault { robot: 1, kind: FaultKind::Dies(20) }, Fault { robot: 2, kind: FaultKind::Freezes(40) }];
    let report = client_sim::run(&config).await.unwrap();
    assert!(report.completed, "{report:?}");
    assert_eq!(report.coverage, 1.0);
    assert!(report.steps > 400, "long enough for the lease to run out: {report:?}");
    let faults = report.fault_record.expect("a run with faults reports them");
    assert_eq!(faults.lost_robots, vec!["robot-1".to_owned()], "{faults:?}");
    assert!(faults.stalled_tasks >= 1, "the frozen robot's tasks fail for lack of progress: {faults:?}");
    assert!(faults.tasks_by_state.get("released").copied().unwrap_or(0) >= 1, "{faults:?}");
    exec.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_exploring_the_executive_brings_every_robot_home() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("home.db");
    let exec = TestExecutive::start(&db).await;
    let mut config = RunConfig::new(bundled_map("nav2_depot"), 3, "burgard");
    config.server = Some(exec.url.clone());
    config.cell_size = Some(0.2);
    config.seed = 3;
    config.return_home = true;
    let report = client_sim::run(&config).await.unwrap();
    assert!(report.completed, "{report:?}");
    assert!(report.home_steps.is_some(), "the robots did not all get home: {}", report.ended);
    for trajectory in &report.trajectories {
        assert_eq!(trajectory.first(), trajectory.last(), "a robot ended away from its start");
    }
    exec.stop().await;

    let pool = sqlx::SqlitePool::connect(&format!("sqlite://{}", db.display())).await.unwrap();
    let home: Vec<(String, String)> =
        sqlx::query_as("SELECT state, created_by FROM tasks WHERE kind = 'home'").fetch_all(&pool).await.unwrap();
    assert!(!home.is_empty(), "no home task was given");
    assert!(home.iter().all(|(state, by)| state == "reached" && by == "executive"), "{home:?}");
    let state: String = sqlx::query_scalar("SELECT state FROM missions").fetch_one(&pool).await.unwrap();
    assert_eq!(state, "completed");
}
