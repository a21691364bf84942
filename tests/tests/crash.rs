//! SIGKILL the `coordinator` binary in the middle of a fleet's run and start
//! it again on the same database: the fleet reconnects, the mission
//! completes, and no acknowledged map update is lost or applied twice.

mod common;

use std::time::Duration;

use client_sim::RunConfig;
use common::{bundled_map, spawn_coordinator, wait_until_serving};
use exploration_proto::v1 as pb;
use exploration_proto::v1::missions_client::MissionsClient;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_fleet_survives_a_killed_executive() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("crash.db");
    let port = common::free_port();
    let url = format!("http://127.0.0.1:{port}");
    let mut child = spawn_coordinator(port, &db, "warn");
    wait_until_serving(&url, Duration::from_secs(30)).await;

    let mut config = RunConfig::new(bundled_map("mrpb_maze"), 3, "burgard");
    config.server = Some(url.clone());
    config.cell_size = Some(0.25);
    config.seed = 5;
    config.retry_budget = Duration::from_secs(60);
    let fleet = tokio::spawn(async move { client_sim::run(&config).await });

    // Let the fleet get well into its mission, then kill the executive.
    let channel = tonic::transport::Endpoint::from_shared(url.clone()).unwrap().connect_lazy();
    let mut missions = MissionsClient::new(channel);
    let applied_before_kill = loop {
        let list = missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner();
        if let Some(m) = list.missions.first().filter(|m| m.map_updates >= 150) {
            break m.map_updates;
        }
        assert!(!fleet.is_finished(), "the fleet finished before the kill");
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    child.kill().unwrap();
    child.wait().unwrap();
    let mut child = spawn_coordinator(port, &db, "warn");
    wait_until_serving(&url, Duration::from_secs(30)).await;

    let report = fleet.await.unwrap().unwrap();
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(report.completed, "{report:?}");
    assert_eq!(report.coverage, 1.0);
    assert!(report.map_updates > applied_before_kill);
    assert_eq!(
        report.updates_acknowledged, report.map_updates,
        "every acknowledged update is applied exactly once across the crash"
    );
}
