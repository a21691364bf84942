//! The API through a real executive on port 0 with a real SQLite file: bad
//! input gets a precise status and changes nothing; good input is applied
//! exactly once; health and reflection answer as standard clients expect.

mod common;

use common::{TestExecutive, create_mission, patch, register, update};
use exploration_proto::v1 as pb;
use tonic::Code;

/// The mission's counters and the robot's sequence number, to show a refused
/// request changed nothing.
async fn snapshot(exec: &TestExecutive, mission_id: u64) -> (u64, u64, Vec<u64>, Vec<u8>) {
    let mission = exec.missions().get_mission(pb::GetMissionRequest { mission_id }).await.unwrap().into_inner();
    let robots = exec.missions().list_robots(pb::ListRobotsRequest { mission_id }).await.unwrap().into_inner().robots;
    let map = exec.missions().get_map(pb::GetMapRequest { mission_id }).await.unwrap().into_inner();
    (mission.map_updates, mission.known_cells, robots.iter().map(|r| r.last_map_seq).collect(), map.cells)
}

/// A mission whose robots have sent no map yet knows nothing: it cannot be
/// complete. (A load run saw fresh missions reported COMPLETED to their
/// robots: the plan made when the first robot joined found no frontier and
/// no robot that could explore anything, and took that for the end.)
#[tokio::test]
async fn a_mission_that_knows_nothing_yet_is_not_complete() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let mut missions = exec.missions();
    let mission = missions
        .create_mission(pb::CreateMissionRequest {
            name: "planned off the request path".into(),
            frame: Some(common::frame(40, 30)),
            policy: Some(pb::PolicySpec { name: "minpos".into(), params: Default::default() }),
            lockstep: false,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let mut fleet = exec.fleet();
    let robot = register(&mut fleet, mission.id, "r", 0.55, 0.55).await;
    // The robot joining asks for a plan; wait until it was made.
    let planned = async {
        loop {
            let got =
                missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
            if got.replans > 0 {
                return got;
            }
            tokio::task::yield_now().await;
        }
    };
    let got = tokio::time::timeout(std::time::Duration::from_secs(30), planned).await.expect("a plan within 30 s");
    assert_eq!(got.state, pb::MissionState::Active as i32, "{got:?}");
    let assignment = fleet.get_assignment(pb::GetAssignmentRequest { robot_id: robot.id }).await.unwrap().into_inner();
    assert_eq!(assignment.mission_state, pb::MissionState::Active as i32, "{assignment:?}");
    exec.stop().await;
}

#[tokio::test]
async fn bad_map_updates_get_precise_statuses_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = create_mission(&mut missions, 40, 30, "nearest").await;
    let robot = register(&mut fleet, mission.id, "r1", 1.0, 1.0).await;

    // A good update first.
    let ok = fleet.update_map(update(robot.id, 1, 1.0, 1.0, vec![patch(5, 5, 4, 3, 0.1)])).await.unwrap().into_inner();
    assert_eq!(ok.applied_seq, 1);
    let before = snapshot(&exec, mission.id).await;
    assert_eq!(before.0, 1);
    assert_eq!(before.1, 12);

    let mut wrong_count = patch(0, 0, 3, 3, 0.1);
    wrong_count.values.pop();
    let mut nan = patch(0, 0, 2, 2, 0.1);
    nan.values[3] = f32::NAN;
    let mut above_one = patch(0, 0, 2, 2, 0.1);
    above_one.values[1] = 1.5;
    let mut negative = patch(0, 0, 2, 2, 0.1);
    negative.values[0] = -0.1;
    let mut no_encoding = patch(0, 0, 2, 2, 0.1);
    no_encoding.encoding = 0;
    let mut short_mask = patch(0, 0, 2, 2, 0.1);
    short_mask.unknown = vec![1];
    let occupancy = |bytes: Vec<u8>| pb::MapPatch {
        width: 2,
        height: 2,
        encoding: pb::CellEncoding::OccupancyPercent as i32,
        occupancy: bytes,
        ..Default::default()
    };
    let mut both = occupancy(vec![0; 4]);
    both.values = vec![0.1; 4];
    let cases: Vec<(&str, pb::UpdateMapRequest, Code, &str)> = vec![
        (
            "patch past the right edge",
            update(robot.id, 6, 1.0, 1.0, vec![patch(38, 0, 4, 2, 0.1)]),
            Code::InvalidArgument,
            "outside the 40×30 mission grid",
        ),
        (
            "patch past the top",
            update(robot.id, 6, 1.0, 1.0, vec![patch(0, 29, 1, 2, 0.1)]),
            Code::InvalidArgument,
            "outside",
        ),
        (
            "patch far outside",
            update(robot.id, 6, 1.0, 1.0, vec![patch(4_000_000_000, 0, 1, 1, 0.1)]),
            Code::InvalidArgument,
            "outside",
        ),
        ("empty patch", update(robot.id, 6, 1.0, 1.0, vec![patch(0, 0, 0, 2, 0.1)]), Code::InvalidArgument, "empty"),
        (
            "cell count mismatch",
            update(robot.id, 6, 1.0, 1.0, vec![wrong_count]),
            Code::InvalidArgument,
            "carries 8 values",
        ),
        ("NaN probability", update(robot.id, 6, 1.0, 1.0, vec![nan]), Code::InvalidArgument, "not a finite number"),
        ("probability above 1", update(robot.id, 6, 1.0, 1.0, vec![above_one]), Code::InvalidArgument, "[0, 1]"),
        ("negative probability", update(robot.id, 6, 1.0, 1.0, vec![negative]), Code::InvalidArgument, "[0, 1]"),
        (
            "no encoding",
            update(robot.id, 6, 1.0, 1.0, vec![no_encoding]),
            Code::InvalidArgument,
            "send PROBABILITY, LOG_ODDS or OCCUPANCY_PERCENT",
        ),
        (
            "occupancy byte neither percent nor unknown",
            update(robot.id, 6, 1.0, 1.0, vec![occupancy(vec![0, 100, 255, 200])]),
            Code::InvalidArgument,
            "occupancy byte 3 of the patch is 200",
        ),
        (
            "occupancy bytes short",
            update(robot.id, 6, 1.0, 1.0, vec![occupancy(vec![0, 100])]),
            Code::InvalidArgument,
            "carries 2 values",
        ),
        (
            "occupancy bytes and float values",
            update(robot.id, 6, 1.0, 1.0, vec![both]),
            Code::InvalidArgument,
            "leave `values` and `unknown` empty",
        ),
        (
            "unknown mask of the wrong length",
            update(robot.id, 6, 1.0, 1.0, vec![short_mask]),
            Code::InvalidArgument,
            "unknown mask",
        ),
        (
            "pose off the map",
            update(robot.id, 6, 50.0, 1.0, vec![patch(0, 0, 1, 1, 0.1)]),
            Code::InvalidArgument,
            "outside the mission map",
        ),
        (
            "pose missing",
            pb::UpdateMapRequest { pose: None, ..update(robot.id, 6, 1.0, 1.0, vec![]) },
            Code::InvalidArgument,
            "pose is required",
        ),
        (
            "repeated sequence number",
            update(robot.id, 5, 1.0, 1.0, vec![patch(0, 0, 2, 2, 0.9)]),
            Code::AlreadyExists,
            "already applied",
        ),
        (
            "sequence number zero",
            update(robot.id, 0, 1.0, 1.0, vec![patch(0, 0, 2, 2, 0.9)]),
            Code::InvalidArgument,
            "at least 1",
        ),
        (
            "unknown robot",
            update(999, 6, 1.0, 1.0, vec![patch(0, 0, 2, 2, 0.9)]),
            Code::NotFound,
            "robot 999 does not exist",
        ),
        ("no robot", update(0, 6, 1.0, 1.0, vec![]), Code::InvalidArgument, "robot_id is required"),
    ];
    // A second good update so that a stale number below the last exists.
    fleet.update_map(update(robot.id, 5, 1.0, 1.0, vec![patch(5, 5, 1, 1, 0.1)])).await.unwrap();
    let before = snapshot(&exec, mission.id).await;
    for (what, request, code, message) in cases {
        let status = fleet.update_map(request).await.unwrap_err();
        assert_eq!(status.code(), code, "{what}: {status:?}");
        assert!(status.message().contains(message), "{what}: {:?} lacks {message:?}", status.message());
        assert_eq!(snapshot(&exec, mission.id).await, before, "{what} changed the mission");
    }
    let stale = fleet.update_map(update(robot.id, 3, 1.0, 1.0, vec![patch(0, 0, 2, 2, 0.9)])).await.unwrap_err();
    assert_eq!(stale.code(), Code::FailedPrecondition, "{stale:?}");
    assert!(stale.message().contains("stale"), "{stale:?}");
    assert_eq!(snapshot(&exec, mission.id).await, before);
    exec.stop().await;
}

#[tokio::test]
async fn bad_missions_and_robots_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let mut missions = exec.missions();
    let create = |frame: Option<pb::MapFrame>, policy: &str, params: &[(&str, f64)]| pb::CreateMissionRequest {
        name: "m".into(),
        frame,
        policy: Some(pb::PolicySpec {
            name: policy.into(),
            params: params.iter().map(|(k, v)| ((*k).to_owned(), *v)).collect(),
        }),
        replan: None,
        scoped_by_communication: false,
        ..Default::default()
    };
    let cases = [
        ("zero width", create(Some(common::frame(0, 10)), "burgard", &[]), "frame.width is 0"),
        ("zero height", create(Some(common::frame(10, 0)), "burgard", &[]), "frame.height is 0"),
        ("absurd size", create(Some(common::frame(20_000, 20_000)), "burgard", &[]), "at most 25000000"),
        ("absurd side", create(Some(common::frame(1_000_000, 1)), "burgard", &[]), "frame.width"),
        ("no frame", create(None, "burgard", &[]), "frame is required"),
        (
            "unknown policy",
            create(Some(common::frame(10, 10)), "teleport", &[]),
            "valid policies: nearest, greedy, burgard, burgard-joint, simmons, minpos, segmentation, hungarian, colares",
        ),
        (
            "parameter out of range",
            create(Some(common::frame(10, 10)), "burgard", &[("beta", -1.0)]),
            "must lie in [0, 1000]",
        ),
        ("unknown parameter", create(Some(common::frame(10, 10)), "burgard", &[("gamma", 1.0)]), "its parameters:"),
    ];
    for (what, request, message) in cases {
        let status = missions.create_mission(request).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{what}: {status:?}");
        assert!(status.message().contains(message), "{what}: {:?} lacks {message:?}", status.message());
    }
    let mut frame = common::frame(10, 10);
    frame.resolution = f64::NAN;
    let status = missions.create_mission(create(Some(frame), "burgard", &[])).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    let listed = missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner();
    assert!(listed.missions.is_empty(), "a refused mission was created");

    let status = missions.get_mission(pb::GetMissionRequest { mission_id: 7 }).await.unwrap_err();
    assert_eq!(status.code(), Code::NotFound);
    assert!(status.message().contains("mission 7 does not exist"));

    let mission = create_mission(&mut missions, 40, 30, "burgard").await;
    let mut fleet = exec.fleet();
    let register = |mission_id: u64, name: &str, range: f64, x: f64| pb::RegisterRobotRequest {
        mission_id,
        name: name.into(),
        capabilities: Some(pb::RobotCapabilities {
            sensor_range_m: range,
            field_of_view_rad: 3.0,
            speed_mps: 1.0,
            footprint_radius_m: 0.1,
        }),
        pose: Some(pb::Pose { x, y: 1.0, theta: 0.0 }),
    };
    for (what, request, code) in [
        ("unknown mission", register(99, "a", 2.0, 1.0), Code::NotFound),
        ("no name", register(mission.id, " ", 2.0, 1.0), Code::InvalidArgument),
        ("zero sensor range", register(mission.id, "a", 0.0, 1.0), Code::InvalidArgument),
        ("NaN sensor range", register(mission.id, "a", f64::NAN, 1.0), Code::InvalidArgument),
        ("pose off the map", register(mission.id, "a", 2.0, -3.0), Code::InvalidArgument),
    ] {
        let status = fleet.register_robot(request).await.unwrap_err();
        assert_eq!(status.code(), code, "{what}: {status:?}");
    }
    let robots = missions.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert!(robots.robots.is_empty());

    // Registering twice under one name resumes the same robot.
    let first = fleet.register_robot(register(mission.id, "a", 2.0, 1.0)).await.unwrap().into_inner();
    let again = fleet.register_robot(register(mission.id, "a", 3.0, 1.0)).await.unwrap().into_inner();
    assert!(!first.resumed);
    assert!(again.resumed);
    assert_eq!(first.robot.unwrap().id, again.robot.as_ref().unwrap().id);
    assert_eq!(again.robot.unwrap().capabilities.unwrap().sensor_range_m, 3.0);
    exec.stop().await;
}

#[tokio::test]
async fn an_update_is_applied_once_and_replans_push_assignments() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mission = create_mission(&mut missions, 40, 30, "nearest").await;
    let robot = register(&mut fleet, mission.id, "r1", 0.55, 0.55).await;
    let mut stream =
        fleet.watch_assignment(pb::WatchAssignmentRequest { robot_id: robot.id }).await.unwrap().into_inner();
    let first = stream.message().await.unwrap().unwrap();
    assert_eq!(first.task_id, 0, "no map, no task");

    // The robot sees a free 10×10 room corner around itself; the rest is unknown.
    let response =
        fleet.update_map(update(robot.id, 1, 0.55, 0.55, vec![patch(0, 0, 10, 10, 0.05)])).await.unwrap().into_inner();
    let assignment = response.assignment.unwrap();
    assert_ne!(assignment.task_id, 0, "a frontier exists: the robot has a task");
    let target = assignment.target.unwrap();
    assert!(target.x < 1.01 && target.y < 1.01, "a frontier cell of the room: {target:?}");
    let pushed = stream.message().await.unwrap().unwrap();
    assert_eq!(pushed.version, assignment.version);
    assert_eq!(pushed.task_id, assignment.task_id);

    // The robot arrives: the task is reached and a new one is pushed.
    let arrived = fleet
        .heartbeat(pb::HeartbeatRequest {
            robot_id: robot.id,
            pose: Some(pb::Pose { x: target.x, y: target.y, theta: 0.0 }),
            state: pb::RobotState::Arrived as i32,
            task_id: assignment.task_id,
            reason: String::new(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner()
        .assignment
        .unwrap();
    assert!(arrived.version > assignment.version);
    let tasks = missions
        .list_tasks(pb::ListTasksRequest { mission_id: mission.id, robot_id: robot.id, limit: 0, ..Default::default() })
        .await
        .unwrap()
        .into_inner()
        .tasks;
    let reached = tasks.iter().find(|t| t.id == assignment.task_id).unwrap();
    assert_eq!(reached.state, pb::TaskState::Reached as i32);
    let causes: Vec<_> = reached.transitions.iter().map(|t| (t.to, t.actor.as_str())).collect();
    assert_eq!(causes, vec![(pb::TaskState::Assigned as i32, "policy"), (pb::TaskState::Reached as i32, "robot")]);
    let mission_after =
        missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(mission_after.map_updates, 1);
    assert!(mission_after.replans >= 2);
    exec.stop().await;
}

#[tokio::test]
async fn health_reflection_and_the_policy_list_answer() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let mut health = tonic_health::pb::health_client::HealthClient::new(exec.channel());
    for service in ["", "exploration.v1.Missions", "exploration.v1.Fleet"] {
        let answer =
            health.check(tonic_health::pb::HealthCheckRequest { service: service.into() }).await.unwrap().into_inner();
        assert_eq!(
            answer.status,
            tonic_health::pb::health_check_response::ServingStatus::Serving as i32,
            "{service:?}"
        );
    }

    use tokio_stream::StreamExt;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    let mut reflection = ServerReflectionClient::new(exec.channel());
    let request = tonic_reflection::pb::v1::ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut responses = reflection.server_reflection_info(tokio_stream::iter([request])).await.unwrap().into_inner();
    let response = responses.next().await.unwrap().unwrap();
    let Some(MessageResponse::ListServicesResponse(list)) = response.message_response else {
        panic!("unexpected reflection answer {response:?}");
    };
    let names: Vec<_> = list.service.iter().map(|s| s.name.as_str()).collect();
    for expected in ["exploration.v1.Missions", "exploration.v1.Fleet", "grpc.health.v1.Health"] {
        assert!(names.contains(&expected), "{names:?} lacks {expected}");
    }

    let policies = exec.missions().list_policies(pb::ListPoliciesRequest {}).await.unwrap().into_inner().policies;
    let burgard = policies.iter().find(|p| p.name == "burgard").unwrap();
    let beta = burgard.params.iter().find(|p| p.name == "beta").unwrap();
    assert_eq!(beta.default_value, 1.0);
    // What a client needs to drive a policy comes from its descriptor.
    let flags = |name: &str| {
        let p = policies.iter().find(|p| p.name == name).unwrap();
        (p.uses_bids, p.keeps_segmentation)
    };
    assert_eq!(flags("simmons"), (true, false));
    assert_eq!(flags("segmentation"), (false, true));
    assert_eq!(flags("burgard"), (false, false));
    exec.stop().await;
}

/// A map whose every third cell is frontier (the largest mission's would be
/// 8 million cells) lists every frontier cell in `frontier_mask`, and only
/// the first 100 000 as points: as points alone, that map made a message of
/// 190 MB, which no client reads (the executive built it all the same).
#[tokio::test]
async fn the_map_of_a_fragmented_frontier_has_every_cell_in_its_mask_and_the_first_as_points() {
    let dir = tempfile::tempdir().unwrap();
    let exec = TestExecutive::start(&dir.path().join("x.db")).await;
    let (mut missions, mut fleet) = (exec.missions(), exec.fleet());
    let (width, height) = (1000, 600);
    let mission = create_mission(&mut missions, width, height, "nearest").await;
    let robot = register(&mut fleet, mission.id, "scout", 0.15, 0.05).await;
    fleet.update_map(update(robot.id, 1, 0.15, 0.05, vec![common::fragmented_map(width, height)])).await.unwrap();

    let map = missions.get_map(pb::GetMapRequest { mission_id: mission.id }).await.unwrap().into_inner();
    let mission = missions.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    // Every free cell (class 1) has an unknown one (class 0) to its left or below.
    let is_frontier = |x: u32, y: u32| common::fragmented_class(x, y) == 1;
    let cells: Vec<(u32, u32)> = (0..height).flat_map(|y| (0..width).map(move |x| (x, y))).collect();
    assert_eq!(map.frontier_mask.len(), cells.len().div_ceil(8));
    for (k, &(x, y)) in cells.iter().enumerate() {
        assert_eq!(map.frontier_mask[k / 8] >> (k % 8) & 1 == 1, is_frontier(x, y), "cell ({x}, {y})");
    }
    let frontier: Vec<(u32, u32)> = cells.iter().copied().filter(|&(x, y)| is_frontier(x, y)).collect();
    assert_eq!(mission.frontier_cells, frontier.len() as u64);
    assert!(frontier.len() > 150_000, "{}", frontier.len());
    // The points: the first 100 000 frontier cells in row order, at their centres.
    let frame = map.frame.unwrap();
    let origin = frame.origin.unwrap();
    let centre = |(x, y): (u32, u32)| {
        (origin.x + (f64::from(x) + 0.5) * frame.resolution, origin.y + (f64::from(y) + 0.5) * frame.resolution)
    };
    assert_eq!(map.frontier.len(), 100_000);
    for (point, &cell) in map.frontier.iter().zip(&frontier) {
        let (x, y) = centre(cell);
        assert!((point.x - x).abs() < 1e-9 && (point.y - y).abs() < 1e-9, "{point:?} is not cell {cell:?}");
    }
    exec.stop().await;
}
