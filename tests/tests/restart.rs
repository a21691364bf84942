//! The executive picks every mission up where it was after a restart on the
//! same database, and a graceful stop ends open assignment streams.

mod common;

use common::{TestExecutive, create_mission, patch, register, update};
use exploration_proto::v1 as pb;
use tonic::Code;

#[tokio::test]
async fn a_restart_on_the_same_file_restores_map_robots_and_tasks() {
    let dir = tempfile::tempdir().unwrap();
    a_restart_restores_map_robots_and_tasks(dir.path().join("x.db").into()).await;
}

/// The same on PostgreSQL (where `EXPLORATION_POSTGRES_URL` names a server).
#[tokio::test]
async fn a_restart_on_the_same_postgres_database_restores_map_robots_and_tasks() {
    if let Some(url) = common::postgres_database("restart").await {
        a_restart_restores_map_robots_and_tasks(coordinator::Location::Postgres(url)).await;
    }
}

async fn a_restart_restores_map_robots_and_tasks(db: coordinator::Location) {
    let exec = TestExecutive::start(db.clone()).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = create_mission(&mut missions, 60, 40, "burgard").await;
    let a = register(&mut fleet, mission.id, "a", 0.55, 0.55).await;
    let b = register(&mut fleet, mission.id, "b", 2.05, 0.55).await;
    fleet.update_map(update(a.id, 1, 0.55, 0.55, vec![patch(0, 0, 20, 10, 0.05)])).await.unwrap();
    let mut wall = patch(20, 0, 1, 10, 0.95);
    wall.values[3] = 0.9;
    let last_b = fleet
        .update_map(update(b.id, 1, 2.05, 0.55, vec![patch(15, 0, 5, 12, 0.05), wall]))
        .await
        .unwrap()
        .into_inner()
        .assignment
        .unwrap();
    let last_a = fleet.get_assignment(pb::GetAssignmentRequest { robot_id: a.id }).await.unwrap().into_inner();
    assert_ne!(last_a.task_id, 0);
    assert_ne!(last_b.task_id, 0);
    let map_before = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    let mission_before =
        missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();

    // A robot is watching when the executive stops: the stop must not hang on it.
    let mut stream = fleet.watch_assignment(pb::WatchAssignmentRequest { robot_id: a.id }).await.unwrap().into_inner();
    assert_eq!(stream.message().await.unwrap().unwrap().version, last_a.version);
    exec.stop().await;
    assert!(!matches!(stream.message().await, Ok(Some(_))), "the stream ended with the executive");

    let exec = TestExecutive::start(db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission_after =
        missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(mission_after.map_updates, mission_before.map_updates);
    assert_eq!(mission_after.known_cells, mission_before.known_cells);
    assert_eq!(mission_after.frontier_cells, mission_before.frontier_cells);
    assert_eq!(mission_after.replans, mission_before.replans);
    let map_after = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(map_after.cells, map_before.cells, "the fused map is rebuilt cell for cell");
    // Assignments are where they were, with their versions.
    let a_after = fleet.get_assignment(pb::GetAssignmentRequest { robot_id: a.id }).await.unwrap().into_inner();
    assert_eq!((a_after.task_id, a_after.version), (last_a.task_id, last_a.version));
    // Sequence numbers survive: the old one is recognised, the next one applies.
    let repeat = fleet.update_map(update(b.id, 1, 2.05, 0.55, vec![patch(15, 0, 5, 12, 0.05)])).await.unwrap_err();
    assert_eq!(repeat.code(), Code::AlreadyExists);
    let next =
        fleet.update_map(update(b.id, 2, 2.05, 0.55, vec![patch(30, 10, 2, 2, 0.05)])).await.unwrap().into_inner();
    assert_eq!(next.applied_seq, 2);
    // A second mission gets the next identity; task identities keep growing.
    let other = create_mission(&mut missions, 10, 10, "nearest").await;
    assert_eq!(other.id, mission.id + 1);
    let tasks = missions
        .list_tasks(pb::ListTasksRequest { mission_id: mission.id, robot_id: 0, limit: 0, ..Default::default() })
        .await
        .unwrap()
        .into_inner()
        .tasks;
    let mut ids: Vec<u64> = tasks.iter().map(|t| t.id).collect();
    let before = ids.len();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), before, "task identities are unique across the restart");
    exec.stop().await;
}

/// A patch log folded into a map snapshot (as the compactor does while the
/// executive runs) restarts to the same fused map, cell for cell, and the
/// robots' later updates apply on top of it.
#[tokio::test]
async fn a_folded_patch_log_restarts_to_the_same_map() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("x.db");
    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = create_mission(&mut missions, 60, 40, "minpos").await;
    let mut robots = Vec::new();
    for (name, x) in [("a", 0.55), ("b", 2.05), ("c", 3.55)] {
        robots.push(register(&mut fleet, mission.id, name, x, 0.55).await.id);
    }
    // Overlapping patches that change their minds, so that the fused values
    // depend on every patch and on the order they came in.
    for seq in 1..=12u64 {
        let robot = robots[seq as usize % 3];
        let x = (seq as u32 * 7) % 40;
        let mut p = patch(x, (seq as u32 * 3) % 25, 20, 15, 0.05 + 0.07 * seq as f32);
        for (k, v) in p.values.iter_mut().enumerate() {
            *v = (*v + 0.013 * (k % 11) as f32).min(1.0);
        }
        fleet.update_map(update(robot, seq, 0.55, 0.55, vec![p])).await.unwrap();
    }
    let map_before = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    exec.stop().await;

    let store = coordinator::SqliteStore::open(&db, coordinator::Durability::Full).await.unwrap();
    let stored = coordinator::store::Store::missions(&store).await.unwrap();
    assert_eq!(coordinator::store::compact::fold(&store, &stored[0], 9).await.unwrap(), 9);
    assert_eq!(coordinator::store::Store::unfolded_patches(&store, mission.id).await.unwrap(), 3);
    store.close().await;
    drop(store);

    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let map_after = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(map_after.cells, map_before.cells, "the snapshot and the rest of the log make the same map");
    let next = fleet.update_map(update(robots[0], 13, 0.55, 0.55, vec![patch(0, 0, 3, 3, 0.95)])).await.unwrap();
    assert_eq!(next.into_inner().applied_seq, 13);
    let map_updated = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_ne!(map_updated.cells, map_before.cells);
    exec.stop().await;

    let exec = TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let map_again = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(map_again.cells, map_updated.cells);
    exec.stop().await;
}
