//! Every policy of the papers behind one interface, selectable per mission
//! and switchable while it runs, through the real service.

mod common;

use client_sim::RunConfig;
use common::{TestExecutive, bundled_map, create_mission, patch, register, update};
use exploration_proto::v1 as pb;
use tonic::Code;

const POLICIES: [&str; 11] = [
    "nearest",
    "greedy",
    "burgard",
    "burgard-joint",
    "simmons",
    "minpos",
    "segmentation",
    "hungarian",
    "colares",
    "unassigned",
    "tours",
];

#[tokio::test]
async fn the_api_lists_every_policy_and_switches_them_on_a_running_mission() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let mut missions = exec.missions();
    let listed = missions.list_policies(pb::ListPoliciesRequest {}).await.unwrap().into_inner().policies;
    let names: Vec<&str> = listed.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, POLICIES);
    for p in &listed {
        assert!(!p.description.is_empty());
        for param in &p.params {
            assert!(param.min <= param.default_value && param.default_value <= param.max, "{}.{}", p.name, param.name);
        }
    }

    let mission = create_mission(&mut missions, 60, 40, "burgard").await;
    let mut fleet = exec.fleet();
    let robot = register(&mut fleet, mission.id, "r", 0.55, 0.55).await;
    fleet.update_map(update(robot.id, 1, 0.55, 0.55, vec![patch(0, 0, 20, 15, 0.05)])).await.unwrap();
    let before = fleet.get_assignment(pb::GetAssignmentRequest { robot_id: robot.id }).await.unwrap().into_inner();
    assert_eq!(before.policy, "burgard");

    let set = |name: &str, params: &[(&str, f64)]| pb::SetPolicyRequest {
        mission_id: mission.id,
        policy: Some(pb::PolicySpec {
            name: name.into(),
            params: params.iter().map(|(k, v)| ((*k).to_owned(), *v)).collect(),
        }),
        actor: "alice".into(),
        reason: "trying minpos".into(),
    };
    // Bad changes are refused and change nothing.
    for (request, needle) in [
        (set("teleport", &[]), "valid policies: nearest, greedy"),
        (set("minpos", &[("switch_margin", -2.0)]), "must lie in"),
        (set("minpos", &[("beta", 1.0)]), "its parameters: min_frontier_size, switch_margin"),
    ] {
        let status = missions.set_policy(request).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument);
        assert!(status.message().contains(needle), "{}", status.message());
    }
    let status = missions.set_policy(pb::SetPolicyRequest { mission_id: 99, ..set("minpos", &[]) }).await.unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert!(common::events(&mut missions, mission.id).await.is_empty());

    let changed = missions.set_policy(set("minpos", &[("switch_margin", 2.0)])).await.unwrap().into_inner();
    let policy = changed.policy.unwrap();
    assert_eq!(policy.name, "minpos");
    assert_eq!(policy.params["switch_margin"], 2.0);
    // The next replanning uses it: the robot's assignment now comes from minpos.
    let after = fleet.get_assignment(pb::GetAssignmentRequest { robot_id: robot.id }).await.unwrap().into_inner();
    assert_eq!(after.policy, "minpos");
    assert!(after.version > before.version || after.task_id == before.task_id);
    let events = common::events(&mut missions, mission.id).await;
    assert_eq!(events.len(), 1);
    assert_eq!(events[0].kind, "policy_changed");
    assert_eq!(events[0].actor, "alice");
    assert!(events[0].detail.starts_with("burgard -> minpos"), "{}", events[0].detail);
    assert!(events[0].detail.contains("trying minpos"), "{}", events[0].detail);

    // The change survives a restart.
    exec.stop().await;
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let reloaded =
        exec.missions().get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(reloaded.policy.unwrap().name, "minpos");
    exec.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_segmentation_is_kept_and_served() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("seg.db")).await;
    let mut config = RunConfig::new(bundled_map("nav2_depot"), 2, "segmentation");
    config.server = Some(exec.url.clone());
    config.cell_size = Some(0.25);
    config.max_steps = 60;
    let report = client_sim::run(&config).await.unwrap();
    let ask = |mission_id: u64, include_labels: bool, label_runs: bool| {
        let mut missions = exec.missions();
        async move {
            let request = pb::GetSegmentationRequest { mission_id, include_labels, label_runs };
            missions.get_segmentation(request).await.unwrap().into_inner()
        }
    };
    let segmentation = ask(report.mission_id, true, false).await;
    assert!(segmentation.computed_at.is_some());
    assert!(!segmentation.segments.is_empty());
    let frame = segmentation.frame.unwrap();
    assert_eq!(segmentation.labels.len(), (frame.width * frame.height * 4) as usize);
    let labelled = segmentation.labels.chunks_exact(4).filter(|c| *c != [0, 0, 0, 0]).count() as u64;
    assert_eq!(labelled, segmentation.segments.iter().map(|s| s.cells).sum::<u64>());
    // As runs: the same labels in a fraction of the bytes.
    let runs = ask(report.mission_id, true, true).await;
    assert!(runs.labels.is_empty());
    let cells = (frame.width * frame.height) as usize;
    assert_eq!(runs.labels_per_cell(cells).unwrap(), segmentation.labels_per_cell(cells).unwrap());
    assert!(runs.label_runs.len() * 10 < segmentation.labels.len(), "{} bytes of runs", runs.label_runs.len());
    // Without labels, only the summary; a mission never segmented has none.
    let plain = ask(report.mission_id, false, true).await;
    assert!(plain.labels.is_empty() && plain.label_runs.is_empty());
    let other = create_mission(&mut exec.missions(), 10, 10, "burgard").await;
    let none = ask(other.id, false, false).await;
    assert!(none.computed_at.is_none() && none.segments.is_empty());
    exec.stop().await;
}

/// Wurm et al. 2008, §VI: a mission given its rooms plans on them. Through
/// the real service: fleet-sim gives a generated office its own rooms; the
/// segmentation served is those rooms as far as they are known (no critical
/// points, one segment per room); bad label runs are refused and change
/// nothing; the rooms survive a restart and can be taken back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_given_segmentation_is_planned_on_kept_and_taken_back() {
    use client_sim::fleet::WorldSpec;
    use client_sim::generate::Generator;
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("given.db");
    let exec = TestExecutive::start(&db).await;
    let world = WorldSpec::Generated { generator: Generator::Office, width_m: 25.0, height_m: 20.0 };
    let mut config = RunConfig::on(world.clone(), 2, "segmentation");
    config.server = Some(exec.url.clone());
    config.cell_size = Some(0.25);
    config.max_steps = 80;
    config.given_segmentation = true;
    let report = client_sim::run(&config).await.unwrap();
    let rooms = world.build(config.cell_size, config.start, config.seed).unwrap().given_rooms();
    let mut missions = exec.missions();
    let get = |mut missions: pb::missions_client::MissionsClient<_>| async move {
        missions.get_mission(pb::GetMissionRequest { mission_id: report.mission_id }).await.unwrap().into_inner()
    };
    assert!(get(exec.missions()).await.given_segmentation);
    let served = missions
        .get_segmentation(pb::GetSegmentationRequest {
            mission_id: report.mission_id,
            include_labels: true,
            label_runs: false,
        })
        .await
        .unwrap()
        .into_inner();
    assert!(served.critical_points.is_empty(), "given rooms are not cut at critical points");
    let labels: Vec<u32> =
        served.labels.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    assert_eq!(labels.len(), rooms.len());
    // One segment per given room: the served labels and the rooms match one to one.
    let mut pairs: Vec<(u32, u32)> =
        labels.iter().zip(&rooms).filter(|(l, _)| **l != 0).map(|(l, r)| (*l, *r)).collect();
    pairs.sort_unstable();
    pairs.dedup();
    assert!(pairs.len() >= 2, "the robots saw more than one room in 80 steps: {pairs:?}");
    assert!(pairs.windows(2).all(|w| w[0].0 != w[1].0), "a segment spans two rooms: {pairs:?}");
    let mut by_room: Vec<u32> = pairs.iter().map(|p| p.1).collect();
    by_room.sort_unstable();
    assert!(by_room.windows(2).all(|w| w[0] != w[1]), "a room split into segments: {pairs:?}");
    let events = common::events(&mut missions, report.mission_id).await;
    assert!(events.iter().any(|e| e.kind == "segmentation_given" && e.actor == "fleet-sim"), "{events:?}");

    // Bad runs are refused, naming the field, and change nothing.
    let set = |mission_id: u64, label_runs: Vec<u8>| pb::SetGivenSegmentationRequest {
        mission_id,
        label_runs,
        actor: "alice".into(),
        reason: String::new(),
    };
    let cells = rooms.len() as u32;
    let pair = |label: u32, run: u32| [label.to_le_bytes(), run.to_le_bytes()].concat();
    for (request, code) in [
        (set(report.mission_id, vec![1, 2, 3]), Code::InvalidArgument),
        (set(report.mission_id, pair(1, cells - 1)), Code::InvalidArgument),
        (set(report.mission_id, [pair(1, u32::MAX), pair(2, u32::MAX)].concat()), Code::InvalidArgument),
        (set(report.mission_id + 100, pair(1, cells)), Code::NotFound),
        (set(0, pair(1, cells)), Code::InvalidArgument),
    ] {
        let status = missions.set_given_segmentation(request).await.unwrap_err();
        assert_eq!(status.code(), code, "{status:?}");
        if code == Code::InvalidArgument {
            assert!(status.message().contains("label_runs") || status.message().contains("mission_id"), "{status:?}");
        }
    }
    let before = served.segments.len();
    exec.stop().await;

    // Kept across a restart; then taken back.
    let exec = TestExecutive::start(&db).await;
    assert!(get(exec.missions()).await.given_segmentation);
    let mut missions = exec.missions();
    let stored = missions
        .get_segmentation(pb::GetSegmentationRequest { mission_id: report.mission_id, ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(stored.segments.len(), before);
    let back = missions.set_given_segmentation(set(report.mission_id, Vec::new())).await.unwrap().into_inner();
    assert!(!back.given_segmentation);
    exec.stop().await;
    let exec = TestExecutive::start(&db).await;
    assert!(!get(exec.missions()).await.given_segmentation);
    exec.stop().await;
}

/// An operator gives a mission the rooms of its finished map with
/// `coordctl rooms`, as the README shows; a map of another area is refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn coordctl_gives_a_mission_the_rooms_of_its_finished_map() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("rooms.db")).await;
    let url = exec.url.clone();
    let coordctl = move |args: &[&str]| {
        let output = std::process::Command::new(common::binary("coordctl"))
            .args(["--server", &url, "--json", "--as", "alice"])
            .args(args)
            .env("RUST_LOG", "warn")
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
        (output.status.success(), stdout, String::from_utf8_lossy(&output.stderr).into_owned())
    };
    let depot = bundled_map("nav2_depot").display().to_string();
    let warehouse = bundled_map("nav2_warehouse").display().to_string();
    let run = |args: Vec<String>| {
        let coordctl = coordctl.clone();
        tokio::task::spawn_blocking(move || coordctl(&args.iter().map(String::as_str).collect::<Vec<_>>()))
    };
    let (ok, created, err) = run(vec![
        "missions".into(),
        "create".into(),
        "--map".into(),
        depot.clone(),
        "--policy".into(),
        "segmentation".into(),
    ])
    .await
    .unwrap();
    assert!(ok, "{err}");
    let id = serde_json::from_str::<serde_json::Value>(&created).unwrap()["id"].as_u64().unwrap().to_string();
    let (ok, given, err) = run(vec!["rooms".into(), id.clone(), depot]).await.unwrap();
    assert!(ok, "{err}");
    assert_eq!(serde_json::from_str::<serde_json::Value>(&given).unwrap()["given_segmentation"], true, "{given}");
    let (ok, _, err) = run(vec!["rooms".into(), id.clone(), warehouse]).await.unwrap();
    assert!(!ok && err.contains("the mission's map is"), "{err}");
    let events = common::events(&mut exec.missions(), id.parse().unwrap()).await;
    assert_eq!(events.iter().filter(|e| e.kind == "segmentation_given" && e.actor == "alice").count(), 1, "{events:?}");
    let (ok, online, err) = run(vec!["rooms".into(), id, "--online".into()]).await.unwrap();
    assert!(ok, "{err}");
    assert_eq!(serde_json::from_str::<serde_json::Value>(&online).unwrap()["given_segmentation"], false, "{online}");
    exec.stop().await;
}

/// Every policy completes missions on the bundled maps with 1, 3 and 8
/// robots (coarse cells keep the debug build quick; the full matrix at
/// 0.1 m is `experiments/policy-matrix.toml`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_policy_completes_the_bundled_maps_with_1_3_and_8_robots() {
    let mut failures = Vec::new();
    for (k, policy) in POLICIES.iter().enumerate() {
        for (j, robots) in [1usize, 3, 8].into_iter().enumerate() {
            let map = ["mrpb_maze", "nav2_depot", "mrpb_shopping_mall", "nav2_warehouse"][(k + j) % 4];
            let mut config = RunConfig::new(bundled_map(map), robots, policy);
            config.cell_size = Some(0.4);
            config.seed = (k * 3 + j) as u64;
            let report = client_sim::run(&config).await.unwrap();
            if !report.completed {
                failures.push(format!("{policy} × {robots} on {map}: {}", report.ended));
            }
            assert_eq!(report.updates_acknowledged, report.map_updates);
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
