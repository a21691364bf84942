//! `coordctl backup FILE` takes a consistent copy while a fleet explores; a
//! coordinator started on the copy holds the mission as it was and resumes it.

mod common;

use std::time::Duration;

use client_sim::RunConfig;
use common::{TestExecutive, bundled_map};
use exploration_proto::v1 as pb;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backup_taken_while_a_fleet_explores_restores_and_resumes() {
    use sqlx::Connection;
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("live.db")).await;
    let mut config = RunConfig::new(bundled_map("mrpb_maze"), 3, "nearest");
    config.server = Some(exec.url.clone());
    config.cell_size = Some(0.25);
    config.seed = 3;
    let fleet = tokio::spawn(async move { client_sim::run(&config).await });

    let mut missions = exec.missions();
    loop {
        let listed = missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner();
        if listed.missions.first().is_some_and(|m| m.map_updates >= 60) {
            break;
        }
        assert!(!fleet.is_finished(), "the fleet finished before the backup");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let copy = dir.path().join("copy.db");
    let coordctl = std::process::Command::new(common::binary("coordctl"))
        .args(["--server", &exec.url, "backup"])
        .arg(&copy)
        .output();
    let coordctl = tokio::task::spawn_blocking(move || coordctl).await.unwrap().unwrap();
    assert!(coordctl.status.success(), "{}", String::from_utf8_lossy(&coordctl.stderr));
    let report = fleet.await.unwrap().unwrap();
    assert!(report.completed, "the fleet went on undisturbed: {report:?}");
    let final_updates =
        missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner().missions[0].map_updates;
    exec.stop().await;

    // The copy is a sound database, taken mid-mission.
    let mut raw = sqlx::SqliteConnection::connect(&format!("sqlite:{}", copy.display())).await.unwrap();
    let check: String = sqlx::query_scalar("PRAGMA integrity_check").fetch_one(&mut raw).await.unwrap();
    assert_eq!(check, "ok");
    raw.close().await.unwrap();
    let restored = TestExecutive::start(&copy).await;
    let mut missions = restored.missions();
    let mission =
        missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner().missions.remove(0);
    assert!(
        mission.map_updates >= 60 && mission.map_updates < final_updates,
        "{} of {final_updates}",
        mission.map_updates
    );
    assert_eq!(mission.state(), pb::MissionState::Active);

    // Its robots come back by name and finish the map: the mission resumes.
    let robots =
        missions.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner().robots;
    let frame = mission.frame.unwrap();
    let mut fleet = restored.fleet();
    for robot in &robots {
        let again = pb::RegisterRobotRequest {
            mission_id: mission.id,
            name: robot.name.clone(),
            capabilities: robot.capabilities,
            pose: robot.pose,
        };
        let answer = fleet.register_robot(again).await.unwrap().into_inner();
        assert!(answer.resumed, "{} resumes", robot.name);
    }
    let pose = robots[0].pose.unwrap();
    let everything = common::patch(0, 0, frame.width, frame.height, 0.05);
    let done = common::update(robots[0].id, robots[0].last_map_seq + 1, pose.x, pose.y, vec![everything]);
    let answer = fleet.update_map(done).await.unwrap().into_inner();
    assert_eq!(answer.frontier_cells, 0);
    let after = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(after.state(), pb::MissionState::Completed);
    assert_eq!(after.map_updates, mission.map_updates + 1);
    restored.stop().await;
}
