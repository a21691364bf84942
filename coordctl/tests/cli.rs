//! `coordctl` as an operator runs it, against a real executive on port 0
//! with a real SQLite file and an operator token.

use std::process::Output;

use serde_json::Value;
use tokio_util::sync::CancellationToken;

use exploration_proto::Bearer;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;

/// Alice's operator token.
const TOKEN: &str = "alice-ops-token-0123";

/// coordctl with `args` against `url`, with the operator token unless
/// `token` says otherwise.
fn command(url: &str, token: Option<&str>, args: &[&str]) -> std::process::Command {
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_coordctl"));
    command.env_remove("COORDINATOR_TOKEN").env("COORDINATOR_URL", url).arg("--as").arg("someone-else").args(args);
    if let Some(token) = token {
        command.env("COORDINATOR_TOKEN", token);
    }
    command
}

/// Runs coordctl with `args` against `url` (with the operator token unless
/// `token` says otherwise), off the async runtime.
async fn coordctl(url: &str, token: Option<&str>, args: &[&str]) -> Output {
    let mut command = command(url, token, args);
    tokio::task::spawn_blocking(move || command.output().unwrap()).await.unwrap()
}

/// Which of coordctl's outputs nobody reads.
enum Unread {
    Stdout,
    Stderr,
}

/// Runs coordctl as [`coordctl`] does, with one output a pipe whose reader
/// has gone (`coordctl events 1 | head` once `head` has its ten lines).
async fn coordctl_unread(url: &str, args: &[&str], unread: Unread) -> Output {
    let mut command = command(url, Some(TOKEN), args);
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    match unread {
        Unread::Stdout => command.stdout(writer),
        Unread::Stderr => command.stderr(writer),
    };
    tokio::task::spawn_blocking(move || command.output().unwrap()).await.unwrap()
}

fn json(output: &Output) -> Value {
    assert!(output.status.success(), "coordctl failed: {}", String::from_utf8_lossy(&output.stderr));
    serde_json::from_slice(&output.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&output.stdout)))
}

/// `coordctl robots` until the first robot explores: the mission is planned
/// off the request path, so the policy's task follows the answers.
async fn until_exploring(url: &str, mission: &str) -> Value {
    for _ in 0..100 {
        let robots = json(&coordctl(url, Some(TOKEN), &["--json", "robots", mission]).await);
        if robots[0]["task_kind"] == "explore" {
            return robots;
        }
    }
    panic!("the planner gave the robot no task");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_lists_overrides_forbids_and_exports_the_map() {
    let dir = tempfile::tempdir().unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let mut config = coordinator::Config::new(dir.path().join("ctl.db"));
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, format!("alice operator {}\n", coordinator::auth::sha256_hex(TOKEN))).unwrap();
    config.operator_tokens_file = Some(tokens);
    let stop = CancellationToken::new();
    let server = tokio::spawn(coordinator::run(listener, stop.clone().cancelled_owned(), config));

    // An operator creates the mission; a robot joins and maps a room.
    let created = json(
        &coordctl(
            &url,
            Some(TOKEN),
            &[
                "--json",
                "mission",
                "create",
                "--width",
                "60",
                "--height",
                "20",
                "--resolution",
                "0.1",
                "--policy",
                "nearest",
            ],
        )
        .await,
    );
    assert_eq!(created["policy"]["name"], "nearest");
    let mission_id = created["id"].as_u64().unwrap();
    let channel = tonic::transport::Endpoint::from_shared(url.clone()).unwrap().connect().await.unwrap();
    let mut fleet = FleetClient::with_interceptor(channel, Bearer::new(Some(TOKEN)).unwrap());
    let robot = fleet
        .register_robot(pb::RegisterRobotRequest {
            mission_id,
            name: "scout".into(),
            capabilities: Some(pb::RobotCapabilities {
                sensor_range_m: 2.0,
                field_of_view_rad: std::f64::consts::TAU,
                speed_mps: 0.5,
                footprint_radius_m: 0.0,
            }),
            pose: Some(pb::Pose { x: 3.0, y: 1.0, theta: 0.0 }),
        })
        .await
        .unwrap()
        .into_inner()
        .robot
        .unwrap();
    let patch = pb::MapPatch {
        x: 20,
        y: 0,
        width: 20,
        height: 20,
        encoding: pb::CellEncoding::Probability as i32,
        values: vec![0.05; 400],
        unknown: vec![],
        occupancy: vec![],
    };
    let update = pb::UpdateMapRequest {
        robot_id: robot.id,
        seq: 1,
        pose: Some(pb::Pose { x: 3.0, y: 1.0, theta: 0.0 }),
        patches: vec![patch],
        ..Default::default()
    };
    fleet.update_map(update).await.unwrap();
    let mission = mission_id.to_string();

    let robots = until_exploring(&url, &mission).await;
    assert_eq!(robots[0]["name"], "scout");

    // Send it somewhere by name, with a reason; the history shows who and why.
    let moved = json(
        &coordctl(
            &url,
            Some(TOKEN),
            &["--json", "override", &mission, "scout", "goto", "3.5,1.5", "--reason", "look at the door"],
        )
        .await,
    );
    assert_eq!(moved[0]["task_kind"], "goto");
    let tasks =
        json(&coordctl(&url, Some(TOKEN), &["--json", "history", &mission, "--robot", "scout", "--history"]).await);
    assert_eq!(tasks[0]["kind"], "goto");
    assert_eq!(tasks[0]["created_by"], "operator:alice");
    assert_eq!(tasks[0]["note"], "look at the door");
    assert_eq!(tasks[1]["state"], "overridden");
    assert_eq!(tasks[1]["transitions"].as_array().unwrap().last().unwrap()["by"], "alice");
    let released = json(&coordctl(&url, Some(TOKEN), &["--json", "override", &mission, "scout", "release"]).await);
    assert_ne!(released[0]["task_kind"], "goto", "the override has ended");
    until_exploring(&url, &mission).await;
    // A refusal names the robot as the operator does, not only by its id.
    let cancel = coordctl(&url, Some(TOKEN), &["override", &mission, "scout", "cancel"]).await;
    let said = String::from_utf8_lossy(&cancel.stderr);
    assert_eq!(cancel.status.code(), Some(4), "{said}");
    assert!(said.contains("(scout) is on ") && said.contains("not on an override"), "{said}");

    // A forbidden region shows in the mission and in the exported map.
    let region =
        json(&coordctl(&url, Some(TOKEN), &["--json", "forbid", &mission, "-1,0,2.5,2", "--reason", "wet"]).await);
    assert_eq!(region[0]["area"]["min_x"], 0.0, "kept as the part on the map");
    let shown = json(&coordctl(&url, Some(TOKEN), &["--json", "missions", "show", &mission]).await);
    assert_eq!(shown["forbidden_regions"].as_array().unwrap().len(), 1);
    let png = dir.path().join("map.png");
    let wrote =
        coordctl(&url, Some(TOKEN), &["map", "export", &mission, "--png", png.to_str().unwrap(), "--px", "600"]).await;
    assert!(wrote.status.success(), "{}", String::from_utf8_lossy(&wrote.stderr));
    let picture = image::open(&png).unwrap().to_rgb8();
    assert_eq!((picture.width(), picture.height()), (600, 200), "10 pixels per cell");
    let red = picture.pixels().filter(|p| p.0 == [220, 0, 0]).count();
    assert!(red > 100, "the forbidden region is outlined: {red} red pixels");
    // --png writes a PNG whatever the file's name ("format could not be
    // determined" before), and a full disk says so.
    let unnamed = dir.path().join("map-export");
    let wrote = coordctl(&url, Some(TOKEN), &["map", "export", &mission, "--png", unnamed.to_str().unwrap()]).await;
    assert!(wrote.status.success(), "{}", String::from_utf8_lossy(&wrote.stderr));
    assert!(std::fs::read(&unnamed).unwrap().starts_with(b"\x89PNG"));
    let full = coordctl(&url, Some(TOKEN), &["map", "export", &mission, "--png", "/dev/full"]).await;
    assert!(String::from_utf8_lossy(&full.stderr).contains("No space left on device"));

    // A big mission's whole map (9 million cells) is more than gRPC's
    // default 4 MiB message: coordctl still exports it.
    let big = json(
        &coordctl(&url, Some(TOKEN), &["--json", "mission", "create", "--width", "3000", "--height", "3000"]).await,
    );
    let big_png = dir.path().join("big.png");
    let big_id = big["id"].to_string();
    let wrote = coordctl(&url, Some(TOKEN), &["map", "export", &big_id, "--png", big_png.to_str().unwrap()]).await;
    assert!(wrote.status.success(), "{}", String::from_utf8_lossy(&wrote.stderr));

    // Refusals carry the server's reason and a documented exit code.
    let unknown = coordctl(&url, Some(TOKEN), &["override", &mission, "nobody", "hold"]).await;
    assert_eq!(unknown.status.code(), Some(3));
    assert!(String::from_utf8_lossy(&unknown.stderr).contains("no robot `nobody`"));
    let anonymous = coordctl(&url, None, &["robots", &mission]).await;
    assert_eq!(anonymous.status.code(), Some(5));
    assert!(String::from_utf8_lossy(&anonymous.stderr).contains("bearer token"));
    assert_eq!(coordctl(&url, Some(TOKEN), &["mission", "pause", &mission]).await.status.code(), Some(0));
    let twice = coordctl(&url, Some(TOKEN), &["mission", "pause", &mission]).await;
    assert_eq!(twice.status.code(), Some(4), "{}", String::from_utf8_lossy(&twice.stderr));
    assert_eq!(coordctl(&url, Some(TOKEN), &["override", &mission, "scout", "goto", "1"]).await.status.code(), Some(2));
    assert_eq!(coordctl(&url, Some(TOKEN), &["watch", &mission, "--count", "0"]).await.status.code(), Some(2));

    // More events than one page of ListEvents (1 000): coordctl reads them all.
    let mut missions = exploration_proto::v1::missions_client::MissionsClient::with_interceptor(
        tonic::transport::Endpoint::from_shared(url.clone()).unwrap().connect().await.unwrap(),
        Bearer::new(Some(TOKEN)).unwrap(),
    );
    let control = pb::MissionControlRequest { mission_id, actor: "drill".into(), reason: String::new() };
    for _ in 0..501 {
        missions.resume_mission(control.clone()).await.unwrap();
        missions.pause_mission(control.clone()).await.unwrap();
    }
    let events = json(&coordctl(&url, Some(TOKEN), &["--json", "events", &mission]).await);
    let ids: Vec<u64> = events.as_array().unwrap().iter().map(|e| e["id"].as_u64().unwrap()).collect();
    assert!(ids.len() > 1_002, "every event, not the first page: {}", ids.len());
    assert!(ids.windows(2).all(|w| w[0] < w[1]), "oldest first, none twice");

    // A reader that leaves early is no failure, and an error message nobody
    // reads changes nothing but the message: no panic either way.
    let head = coordctl_unread(&url, &["events", &mission], Unread::Stdout).await;
    assert_eq!(head.status.code(), Some(0), "{}", String::from_utf8_lossy(&head.stderr));
    assert!(head.stderr.is_empty(), "{}", String::from_utf8_lossy(&head.stderr));
    let unheard = coordctl_unread(&url, &["override", &mission, "nobody", "hold"], Unread::Stderr).await;
    assert_eq!(unheard.status.code(), Some(3));

    stop.cancel();
    server.await.unwrap().unwrap();
}

/// An executive that cannot be reached is reported with why (the
/// connection refused), not only gRPC's "tcp connect error".
#[test]
fn an_unreachable_executive_is_reported_with_the_reason() {
    let closed = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", closed.local_addr().unwrap());
    drop(closed);
    let output = command(&url, Some(TOKEN), &["missions"]).output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(stderr.starts_with("coordctl: Unavailable: "), "{stderr}");
    assert!(stderr.contains("Connection refused"), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
}

/// Addresses the transport would dial somewhere else than meant (another
/// scheme read as http, a port it cannot read read as 80, nothing at all
/// read as a dead address) are refused before any call, as usage errors.
#[test]
fn addresses_that_would_be_misread_are_refused_before_any_call() {
    for (url, problem) in [
        ("htp://x", "must start with http:// or https://"),
        ("http://127.0.0.1:99999", "has a port outside 1 to 65535"),
        (" , ", "give at least one address"),
    ] {
        let output = command(url, Some(TOKEN), &["missions"]).output().unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{url}: {stderr}");
        assert!(stderr.starts_with("coordctl: --server: ") && stderr.contains(problem), "{url}: {stderr}");
    }
}
