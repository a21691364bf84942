//! Chaos: twenty missions on different maps and policies explore through one
//! `coordinator` process that is killed with SIGKILL at seeded random moments
//! and started again on the same database. Every mission completes, no
//! acknowledged map update is lost or applied twice, and the database passes
//! SQLite's integrity check.

mod common;

use std::time::Duration;

use client_sim::RunConfig;
use client_sim::fleet::WorldSpec;
use client_sim::generate::Generator;
use common::{bundled_map, spawn_coordinator, wait_until_serving};
use exploration::rng::SplitMix64;
use exploration_proto::v1 as pb;

/// The twenty missions: maps and generated worlds, every policy.
fn missions(url: &str) -> Vec<RunConfig> {
    let policies =
        ["nearest", "greedy", "burgard", "burgard-joint", "simmons", "minpos", "segmentation", "hungarian", "colares"];
    let worlds = [
        WorldSpec::Map(bundled_map("mrpb_maze")),
        WorldSpec::Map(bundled_map("nav2_depot")),
        WorldSpec::Map(bundled_map("mrpb_shopping_mall")),
        WorldSpec::Map(bundled_map("nav2_warehouse")),
        WorldSpec::Generated { generator: Generator::Office, width_m: 16.0, height_m: 12.0 },
        WorldSpec::Generated { generator: Generator::Unstructured { density: 0.15 }, width_m: 14.0, height_m: 14.0 },
        WorldSpec::Generated { generator: Generator::Corridor, width_m: 16.0, height_m: 16.0 },
    ];
    (0..20)
        .map(|i| {
            let mut config = RunConfig::on(worlds[i % worlds.len()].clone(), 2 + i % 3, policies[i % policies.len()]);
            config.server = Some(url.to_owned());
            config.cell_size = Some(if i % worlds.len() < 4 { 0.5 } else { 0.4 });
            config.seed = i as u64 + 1;
            config.retry_budget = Duration::from_secs(120);
            config
        })
        .collect()
}

/// Acknowledged map updates over every mission, as the executive reports them.
async fn progress(url: &str) -> Option<u64> {
    let channel = tonic::transport::Endpoint::from_shared(url.to_owned()).unwrap().connect().await.ok()?;
    let mut client = pb::missions_client::MissionsClient::new(channel);
    let listed = client.list_missions(pb::ListMissionsRequest::default()).await.ok()?.into_inner();
    Some(listed.missions.iter().map(|m| m.map_updates).sum())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twenty_missions_survive_sigkill_at_random_moments() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("chaos.db");
    let port = common::free_port();
    let url = format!("http://127.0.0.1:{port}");
    let mut child = spawn_coordinator(port, &db, "error");
    wait_until_serving(&url, Duration::from_secs(30)).await;

    // Five fleets at a time, twenty in all.
    let configs = missions(&url);
    let fleets = tokio::spawn(async move {
        let mut reports = Vec::new();
        for batch in configs.chunks(5) {
            let runs: Vec<_> = batch
                .iter()
                .cloned()
                .map(|config| tokio::spawn(async move { (client_sim::run(&config).await, config) }))
                .collect();
            for run in runs {
                reports.push(run.await.unwrap());
            }
        }
        reports
    });

    // Kill whenever progress passes the next seeded random mark.
    let mut rng = SplitMix64::new(2026);
    let mut kills = 0;
    let mut mark = 50 + rng.below(400);
    while !fleets.is_finished() {
        if progress(&url).await.is_some_and(|done| done >= mark) {
            child.kill().unwrap();
            child.wait().unwrap();
            kills += 1;
            mark += 100 + rng.below(600);
            child = spawn_coordinator(port, &db, "error");
            wait_until_serving(&url, Duration::from_secs(30)).await;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let reports = fleets.await.unwrap();
    child.kill().unwrap();
    child.wait().unwrap();

    assert!(kills >= 10, "the executive was killed {kills} times");
    let mut completed = 0;
    for (report, config) in &reports {
        let report = report.as_ref().unwrap_or_else(|e| panic!("{} / {}: {e}", config.policy, config.seed));
        assert!(
            report.completed,
            "{} seed {}: ended {} after {} steps at coverage {:.3}",
            config.policy, config.seed, report.ended, report.steps, report.coverage
        );
        assert_eq!(
            report.updates_acknowledged, report.map_updates,
            "{} seed {}: every acknowledged update applied exactly once",
            config.policy, config.seed
        );
        completed += 1;
    }
    assert_eq!(completed, 20);

    use sqlx::Connection;
    let mut raw = sqlx::SqliteConnection::connect(&format!("sqlite:{}", db.display())).await.unwrap();
    let check: String = sqlx::query_scalar("PRAGMA integrity_check").fetch_one(&mut raw).await.unwrap();
    assert_eq!(check, "ok");
    eprintln!("chaos: 20 of 20 missions completed through {kills} SIGKILLs; 0 acknowledged updates lost");
}
