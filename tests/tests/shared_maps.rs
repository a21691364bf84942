//! Every map of the shared collection, explored by a small fleet through the
//! real service. The collection is not redistributable: this runs only when
//! `EXPLORATION_SHARED_MAPS` names its folder (`.ci/run` sets it), and says
//! SKIPPED otherwise.

mod common;

use client_sim::RunConfig;

const MAPS: [&str; 10] = [
    "stage_hospital",
    "stage_autolab",
    "stage_simple_rooms",
    "ipa_freiburg79",
    "ipa_intel_lab",
    "ipa_nlb",
    "nav2_warehouse",
    "nav2_depot",
    "mrpb_shopping_mall",
    "mrpb_maze",
];

/// Every policy on every shared map, the team size cycling through 1, 3
/// and 8 so that each policy meets each size on several maps. The full
/// matrix (every size everywhere, 0.1 m cells) is `experiments/policy-matrix.toml`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_policy_explores_every_shared_map() {
    let Some(dir) = common::shared_maps("every_policy_explores_every_shared_map") else {
        return;
    };
    // Every catalogued policy but `unassigned` (Wurm's baseline: `nearest`
    // with taken cells removed), left out to keep this test short.
    let policies: Vec<&str> =
        exploration::policy::catalogue().iter().map(|d| d.name).filter(|&name| name != "unassigned").collect();
    let mut failures = Vec::new();
    for (i, map) in MAPS.iter().enumerate() {
        for (k, policy) in policies.iter().enumerate() {
            let robots = [1, 3, 8][(i + k) % 3];
            let mut config = RunConfig::new(dir.join(format!("{map}.yaml")), robots, policy);
            // Coarse cells keep the debug-build test short.
            config.cell_size = Some(0.4);
            config.seed = 1;
            let report = client_sim::run(&config).await.unwrap();
            eprintln!(
                "{map}: {policy} × {robots}: {} steps, coverage {:.4}, {:.1} s",
                report.steps, report.coverage, report.wall_time_s
            );
            if !report.completed {
                failures.push(format!("{map}: {policy} × {robots}: {}", report.ended));
            }
            assert_eq!(report.updates_acknowledged, report.map_updates, "{map}");
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
