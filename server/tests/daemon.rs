//! The `coordinator` daemon stops gracefully on SIGTERM: it ends open
//! assignment streams, finishes, and exits with success.

use std::process::{Command, Stdio};
use std::time::Duration;

use exploration_proto::v1 as pb;

#[tokio::test]
async fn sigterm_drains_streams_and_exits_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut child = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["--listen", &format!("127.0.0.1:{port}"), "--db"])
        .arg(dir.path().join("d.db"))
        .args(["--log-format", "json"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let url = format!("http://127.0.0.1:{port}");
    // Readiness: poll the health service of a real process.
    let channel = loop {
        if let Ok(c) = tonic::transport::Endpoint::from_shared(url.clone()).unwrap().connect().await {
            break c;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    let mut missions = pb::missions_client::MissionsClient::new(channel.clone());
    let mut fleet = pb::fleet_client::FleetClient::new(channel);
    let mission = missions
        .create_mission(pb::CreateMissionRequest {
            name: "m".into(),
            frame: Some(pb::MapFrame { resolution: 0.1, origin: None, width: 10, height: 10 }),
            policy: None,
            replan: None,
            scoped_by_communication: false,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(mission.policy.unwrap().name, "burgard", "the default policy");
    let robot = fleet
        .register_robot(pb::RegisterRobotRequest {
            mission_id: mission.id,
            name: "r".into(),
            capabilities: Some(pb::RobotCapabilities {
                sensor_range_m: 1.0,
                field_of_view_rad: 6.0,
                speed_mps: 1.0,
                footprint_radius_m: 0.0,
            }),
            pose: Some(pb::Pose { x: 0.5, y: 0.5, theta: 0.0 }),
        })
        .await
        .unwrap()
        .into_inner()
        .robot
        .unwrap();
    let mut stream =
        fleet.watch_assignment(pb::WatchAssignmentRequest { robot_id: robot.id }).await.unwrap().into_inner();
    stream.message().await.unwrap().unwrap();

    let status = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(status.success());
    // The stream ends instead of holding the shutdown up.
    assert!(!matches!(stream.message().await, Ok(Some(_))));
    let exit = tokio::task::spawn_blocking(move || {
        let exit = child.wait().unwrap();
        let mut logs = String::new();
        std::io::Read::read_to_string(child.stdout.as_mut().unwrap(), &mut logs).unwrap();
        (exit, logs)
    })
    .await
    .unwrap();
    assert!(exit.0.success(), "{:?}", exit.0);
    // Structured logs: one JSON object per line, the shutdown among them.
    let lines: Vec<serde_json::Value> = exit.1.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert!(lines.iter().any(|l| l["fields"]["message"] == "SIGTERM received"), "{lines:?}");
    assert!(lines.iter().any(|l| l["fields"]["message"] == "executive stopped"), "{lines:?}");
}
