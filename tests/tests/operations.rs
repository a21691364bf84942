//! Operating a fleet through a real executive (port 0, SQLite file, bearer
//! tokens): leases and stalls, blacklists, completion with its leftovers and
//! the return home, every operator override, forbidden regions, pause and
//! resume, and the permission checks.
//!
//! Time is the executive's manual clock, moved on by hand: no test sleeps
//! through a lease. Waiting for the executive's reaction follows its
//! WatchMission stream.

mod common;

use std::sync::Arc;
use std::time::Duration;

use prost::Message as _;
use sqlx::Connection as _;
use tonic::Code;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

use common::{TestExecutive, patch};
use coordinator::{Clock, ManualClock};
use exploration_proto::Bearer;
use exploration_proto::v1 as pb;
use exploration_proto::v1::fleet_client::FleetClient;
use exploration_proto::v1::missions_client::MissionsClient;
use exploration_proto::v1::override_robot_request::{Action, Cancel, Hold, Release};

/// Alice's operator token; Kim holds a viewer's.
const OPERATOR: &str = "alice-operator-secret";
const VIEWER: &str = "kim-viewer-secret-0000";

type Missions = MissionsClient<InterceptedService<Channel, Bearer>>;
type Fleet = FleetClient<InterceptedService<Channel, Bearer>>;

/// An executive that requires named tokens and keeps time by hand.
struct Site {
    exec: TestExecutive,
    clock: Arc<ManualClock>,
    tokens: std::path::PathBuf,
    dir: tempfile::TempDir,
}

/// A line of the tokens file.
fn token_line(name: &str, role: &str, token: &str) -> String {
    format!("{name} {role} {}\n", coordinator::auth::sha256_hex(token))
}

impl Site {
    async fn start() -> Self {
        Self::start_in(tempfile::tempdir().unwrap(), |_| {}).await
    }

    /// The executive stopped, and started again on its database.
    async fn restart(self) -> Self {
        self.exec.stop().await;
        Self::start_in(self.dir, |_| {}).await
    }

    /// An executive on `dir`'s database, its settings changed by `tune`.
    async fn start_in(dir: tempfile::TempDir, tune: impl FnOnce(&mut coordinator::ExecutiveSettings)) -> Self {
        let (clock, handle) = Clock::manual();
        let tokens = dir.path().join("tokens");
        std::fs::write(&tokens, token_line("alice", "operator", OPERATOR) + &token_line("kim", "viewer", VIEWER))
            .unwrap();
        let mut config = coordinator::Config::new(dir.path().join("ops.db"));
        config.operator_tokens_file = Some(tokens.clone());
        config.executive.clock = clock;
        tune(&mut config.executive);
        Self { exec: TestExecutive::start_with(config).await, clock: handle, tokens, dir }
    }

    fn missions(&self, token: Option<&str>) -> Missions {
        MissionsClient::with_interceptor(self.exec.channel(), Bearer::new(token).unwrap())
    }

    fn fleet(&self, token: Option<&str>) -> Fleet {
        FleetClient::with_interceptor(self.exec.channel(), Bearer::new(token).unwrap())
    }

    fn operator(&self) -> Missions {
        self.missions(Some(OPERATOR))
    }

    /// A 6 m × 2 m mission (0.1 m cells) for `policy` with the given lease
    /// and stall times.
    async fn mission(&self, policy: &str, lease_s: f64, stall_s: f64) -> pb::Mission {
        let request = pb::CreateMissionRequest {
            name: "ops".into(),
            frame: Some(common::frame(60, 20)),
            policy: Some(pb::PolicySpec { name: policy.into(), params: Default::default() }),
            lifecycle: Some(pb::LifecycleSettings { lease_s, stall_s, rendezvous: None }),
            lockstep: true,
            ..Default::default()
        };
        self.operator().create_mission(request).await.unwrap().into_inner()
    }

    /// Registers a robot at (x, y) with the operator's token; returns it and
    /// a client that speaks with the robot's own token.
    async fn robot(&self, mission_id: u64, name: &str, x: f64, y: f64) -> (pb::Robot, Fleet) {
        let request = common::registration(mission_id, name, x, y);
        let response = self.fleet(Some(OPERATOR)).register_robot(request).await.unwrap().into_inner();
        assert!(response.token.starts_with("rbt_"), "a robot token is issued: {:?}", response.token);
        (response.robot.unwrap(), self.fleet(Some(&response.token)))
    }

    /// Waits (at most 20 s of real time) for a view of the mission that
    /// satisfies `done`, and returns it.
    async fn until(&self, mission_id: u64, what: &str, done: impl Fn(&pb::MissionView) -> bool) -> pb::MissionView {
        let mut views =
            self.operator().watch_mission(pb::WatchMissionRequest { mission_id }).await.unwrap().into_inner();
        let wait = async {
            let mut last = None;
            loop {
                match views.message().await {
                    Ok(Some(view)) if done(&view) => return view,
                    Ok(Some(view)) => last = Some(view),
                    other => panic!("the watch ended before {what}: {other:?}; last view {last:#?}"),
                }
            }
        };
        tokio::time::timeout(Duration::from_secs(20), wait)
            .await
            .unwrap_or_else(|_| panic!("the executive never showed {what}"))
    }

    async fn tasks(&self, mission_id: u64, robot_id: u64) -> Vec<pb::Task> {
        let request = pb::ListTasksRequest { mission_id, robot_id, ..Default::default() };
        self.operator().list_tasks(request).await.unwrap().into_inner().tasks
    }

    async fn events(&self, mission_id: u64) -> Vec<pb::MissionEvent> {
        self.operator()
            .list_events(pb::ListEventsRequest { mission_id, ..Default::default() })
            .await
            .unwrap()
            .into_inner()
            .events
    }
}

/// The free band x ∈ [2, 4) m of the 6 × 2 m mission: two frontiers, at
/// x = 2 m and at x = 4 m.
fn middle_known(robot_id: u64, seq: u64, x: f64, y: f64) -> pb::UpdateMapRequest {
    common::update(robot_id, seq, x, y, vec![patch(20, 0, 20, 20, 0.05)])
}

fn heartbeat(robot_id: u64, x: f64, y: f64, state: pb::RobotState, task_id: u64) -> pb::HeartbeatRequest {
    pb::HeartbeatRequest {
        robot_id,
        pose: Some(pb::Pose { x, y, theta: 0.0 }),
        state: state as i32,
        task_id,
        ..Default::default()
    }
}

fn robot(view: &pb::MissionView, id: u64) -> &pb::Robot {
    view.robots.iter().find(|r| r.id == id).expect("the robot is in the view")
}

fn target_x(robot: &pb::Robot) -> f64 {
    robot.target.expect("the robot has a target").x
}

#[tokio::test]
async fn a_silent_robot_loses_its_task_and_comes_back_when_it_reports() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 10.0, 1000.0).await;
    let (a, mut fleet_a) = site.robot(mission.id, "a", 2.5, 1.0).await;
    let (b, mut fleet_b) = site.robot(mission.id, "b", 3.5, 1.0).await;
    fleet_a.update_map(middle_known(a.id, 1, 2.5, 1.0)).await.unwrap();
    let view = site.until(mission.id, "both robots assigned", |v| v.robots.iter().all(|r| r.task_id != 0)).await;
    let task_of_a = robot(&view, a.id).task_id;

    // b keeps reporting; a falls silent past the 10 s lease.
    site.clock.advance(Duration::from_secs(6));
    fleet_b.heartbeat(heartbeat(b.id, 3.5, 1.0, pb::RobotState::Moving, 0)).await.unwrap();
    site.clock.advance(Duration::from_secs(6));
    let view = site.until(mission.id, "robot a lost", |v| robot(v, a.id).lost).await;
    assert_eq!(robot(&view, a.id).task_id, 0, "a lost robot keeps no task");
    assert!(!robot(&view, b.id).lost, "a robot that reported within its lease is not lost");

    let released = site.tasks(mission.id, a.id).await.into_iter().find(|t| t.id == task_of_a).unwrap();
    assert_eq!(released.state(), pb::TaskState::Released);
    let last = released.transitions.last().unwrap();
    assert_eq!(last.actor, "lease");
    assert!(last.cause.contains("lease 10 s"), "{}", last.cause);
    // Named as operators know it, and by id for scripts.
    let lost = format!("robot {} (a): no report", a.id);
    assert!(site.events(mission.id).await.iter().any(|e| e.kind == "robot_lost" && e.detail.starts_with(&lost)));
    // Its lost state is kept in the store and survives the listing.
    let listed = site.operator().list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap();
    assert!(listed.into_inner().robots.iter().any(|r| r.id == a.id && r.lost));

    // A report brings it back into the pool, and it gets work again.
    fleet_a.heartbeat(heartbeat(a.id, 2.5, 1.0, pb::RobotState::Idle, 0)).await.unwrap();
    let view =
        site.until(mission.id, "robot a back at work", |v| !robot(v, a.id).lost && robot(v, a.id).task_id != 0).await;
    assert_ne!(robot(&view, a.id).task_id, task_of_a, "a rejoining robot gets a new task");
}

#[tokio::test]
async fn a_robot_that_makes_no_progress_fails_its_task_and_the_target_is_blacklisted_until_the_map_changes() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 1000.0, 5.0).await;
    let (a, mut fleet_a) = site.robot(mission.id, "a", 2.6, 1.0).await;
    fleet_a.update_map(middle_known(a.id, 1, 2.6, 1.0)).await.unwrap();
    let view = site.until(mission.id, "a assigned", |v| robot(v, a.id).task_id != 0).await;
    let stuck = robot(&view, a.id).clone();
    assert!(target_x(&stuck) < 2.5, "nearest sends a to the left frontier first: {:?}", stuck.target);

    // It reports, but never gets closer.
    fleet_a.heartbeat(heartbeat(a.id, 2.6, 1.0, pb::RobotState::Moving, stuck.task_id)).await.unwrap();
    site.clock.advance(Duration::from_secs(3));
    fleet_a.heartbeat(heartbeat(a.id, 2.6, 1.0, pb::RobotState::Moving, stuck.task_id)).await.unwrap();
    site.clock.advance(Duration::from_secs(3));
    fleet_a.heartbeat(heartbeat(a.id, 2.6, 1.0, pb::RobotState::Moving, stuck.task_id)).await.unwrap();
    let view = site
        .until(mission.id, "the stalled task failed", |v| {
            robot(v, a.id).blacklisted == 1 && robot(v, a.id).task_id != stuck.task_id && robot(v, a.id).task_id != 0
        })
        .await;
    // The blacklist covers the target's neighbourhood (0.5 m), not the
    // whole frontier.
    let (old, new) = (stuck.target.unwrap(), robot(&view, a.id).target.unwrap());
    assert!(((old.x - new.x).powi(2) + (old.y - new.y).powi(2)).sqrt() > 0.5, "{old:?} blacklisted, yet {new:?}");
    let failed = site.tasks(mission.id, a.id).await.into_iter().find(|t| t.id == stuck.task_id).unwrap();
    assert_eq!(failed.state(), pb::TaskState::Failed);
    assert!(failed.transitions.last().unwrap().cause.contains("no progress"), "{:?}", failed.transitions);

    // More of the map around the blacklisted target becomes known: the entry
    // expires, and the left side may be chosen again.
    fleet_a.update_map(common::update(a.id, 2, 2.6, 1.0, vec![patch(14, 0, 6, 20, 0.05)])).await.unwrap();
    site.until(mission.id, "the blacklist entry expired", |v| robot(v, a.id).blacklisted == 0).await;
}

#[tokio::test]
async fn completion_names_what_was_left_and_sends_robots_home() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 10.0, 1000.0).await;
    let (a, mut fleet_a) = site.robot(mission.id, "a", 2.5, 0.5).await;
    fleet_a.update_map(middle_known(a.id, 1, 2.5, 0.5)).await.unwrap();
    site.until(mission.id, "a assigned", |v| robot(v, a.id).task_id != 0).await;
    // The robot drives to the middle; then both frontiers are forbidden.
    fleet_a.heartbeat(heartbeat(a.id, 3.0, 1.5, pb::RobotState::Moving, 0)).await.unwrap();
    let mut operator = site.operator();
    for area in [(1.5, 0.0, 2.1, 2.0), (3.9, 0.0, 4.5, 2.0)] {
        let area = pb::Rect { min_x: area.0, min_y: area.1, max_x: area.2, max_y: area.3 };
        let request = pb::ForbidRegionRequest {
            mission_id: mission.id,
            area: Some(area),
            actor: "alice".into(),
            reason: "closed".into(),
        };
        operator.forbid_region(request).await.unwrap();
    }
    let view = site
        .until(mission.id, "completion", |v| v.mission.as_ref().unwrap().state() == pb::MissionState::Completed)
        .await;
    let done = view.mission.as_ref().unwrap();
    assert!(!done.leftovers.is_empty(), "the forbidden frontier is reported as left over");
    assert!(done.leftovers.iter().all(|l| l.reason() == pb::LeftoverReason::Forbidden), "{:?}", done.leftovers);
    assert_eq!(done.leftovers.iter().map(|l| l.cells).sum::<u64>(), 40, "both frontier columns of 20 cells");

    let home = site.until(mission.id, "a sent home", |v| robot(v, a.id).task_kind() == pb::TaskKind::Home).await;
    let target = robot(&home, a.id).target.unwrap();
    assert!((target.x - 2.5).abs() < 0.1 && (target.y - 0.5).abs() < 0.1, "home is the start pose: {target:?}");
    // Leftovers are stored with the mission.
    let stored = site.operator().get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap();
    assert_eq!(stored.into_inner().leftovers.len(), done.leftovers.len());

    // The robot goes silent on its way home: losing it (and the replanning
    // its released task starts) does not reopen the mission.
    site.clock.advance(Duration::from_secs(11));
    let view = site.until(mission.id, "a lost", |v| robot(v, a.id).lost).await;
    let after = site.operator().get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap();
    let after = after.into_inner();
    assert!(after.replans > done.replans, "a replanning followed the loss");
    assert_eq!(after.state(), pb::MissionState::Completed, "{view:?}");
    assert_eq!(after.leftovers.len(), done.leftovers.len());
}

/// A 120 × 120 map of one-cell pockets, each a free cell walled in but for
/// an unknown cell at its left, and a walled room of 30 × 30 cells at the
/// origin for the robot: 1 500 frontier clusters no robot can reach.
fn pockets() -> pb::MapPatch {
    let class = |x: u32, y: u32| -> u8 {
        if x < 30 && y < 30 {
            return if x.is_multiple_of(29) || y.is_multiple_of(29) { 100 } else { 0 };
        }
        match (x % 3, y % 3) {
            (1, 1) => 0,
            (0, 1) => 255,
            _ => 100,
        }
    };
    let occupancy = (0..120).flat_map(|y| (0..120).map(move |x| class(x, y))).collect();
    pb::MapPatch {
        width: 120,
        height: 120,
        encoding: pb::CellEncoding::OccupancyPercent as i32,
        values: vec![],
        occupancy,
        ..patch(0, 0, 120, 120, 0.5)
    }
}

/// Every GetMission, ListMissions and WatchMission carries the leftovers: a
/// map a robot wrote must not make them unbounded (a 25-million-cell
/// mission of such pockets had 2.8 million, 75 MB a mission).
#[tokio::test]
async fn a_mission_left_with_countless_pockets_lists_the_largest_and_counts_the_rest() {
    let site = Site::start().await;
    let request = pb::CreateMissionRequest {
        name: "pockets".into(),
        frame: Some(common::frame(120, 120)),
        policy: Some(pb::PolicySpec { name: "nearest".into(), params: Default::default() }),
        lockstep: true,
        ..Default::default()
    };
    let mission = site.operator().create_mission(request).await.unwrap().into_inner();
    let (a, mut fleet_a) = site.robot(mission.id, "a", 1.5, 1.5).await;
    // One pocket a cell larger than the others, with its own unknown cell
    // at its left: it is listed first.
    let mut map = pockets();
    map.occupancy[117 * 120 + 118] = 0;
    map.occupancy[117 * 120 + 117] = 255;
    fleet_a.update_map(common::update(a.id, 1, 1.5, 1.5, vec![map])).await.unwrap();
    let view = site
        .until(mission.id, "completion", |v| v.mission.as_ref().unwrap().state() == pb::MissionState::Completed)
        .await;
    let done = view.mission.unwrap();
    assert_eq!(done.leftovers.len(), 1_000);
    assert_eq!((done.unlisted_leftovers, done.unlisted_leftover_cells), (500, 500));
    assert_eq!(done.leftovers[0].cells, 2, "{:?}", done.leftovers[0]);
    assert!(done.leftovers[1..].iter().all(|l| l.cells == 1));
    assert!(done.leftovers.iter().all(|l| l.reason() == pb::LeftoverReason::Disconnected));
    let listed = site.operator().list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner();
    assert_eq!(listed.missions, vec![done.clone()]);
    // Kept so across a restart.
    let site = site.restart().await;
    let stored = site.operator().get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap();
    let stored = stored.into_inner();
    assert_eq!((stored.leftovers, stored.unlisted_leftovers), (done.leftovers, 500));
}

#[tokio::test]
async fn operator_overrides_take_a_robot_out_of_the_pool_and_give_it_back() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 1000.0, 1000.0).await;
    let (a, mut fleet_a) = site.robot(mission.id, "a", 2.5, 1.0).await;
    let (b, _fleet_b) = site.robot(mission.id, "b", 3.5, 1.0).await;
    fleet_a.update_map(middle_known(a.id, 1, 2.5, 1.0)).await.unwrap();
    site.until(mission.id, "both assigned", |v| v.robots.iter().all(|r| r.task_id != 0)).await;
    let mut operator = site.operator();
    let mut act = async |robot_id: u64, action: Action| {
        // The request claims another name: the record names the token's holder.
        let request = pb::OverrideRobotRequest {
            robot_id,
            action: Some(action),
            actor: "mallory".into(),
            reason: "checking".into(),
        };
        operator.override_robot(request).await.unwrap().into_inner()
    };

    // Goto: done on arrival, then back to the pool.
    let robot_a = act(a.id, Action::Goto(pb::Point { x: 3.0, y: 1.5 })).await;
    assert_eq!(robot_a.task_kind(), pb::TaskKind::Goto);
    let goto_task = robot_a.task_id;
    let assignment = fleet_a.get_assignment(pb::GetAssignmentRequest { robot_id: a.id }).await.unwrap().into_inner();
    assert_eq!((assignment.task_id, assignment.kind()), (goto_task, pb::TaskKind::Goto));
    fleet_a.heartbeat(heartbeat(a.id, 3.05, 1.55, pb::RobotState::Arrived, goto_task)).await.unwrap();
    site.until(mission.id, "a back to exploring", |v| robot(v, a.id).task_kind() == pb::TaskKind::Explore).await;
    let goto = site.tasks(mission.id, a.id).await.into_iter().find(|t| t.id == goto_task).unwrap();
    assert_eq!(goto.state(), pb::TaskState::Reached);
    assert_eq!(goto.created_by, "operator:alice");
    assert_eq!(goto.note, "checking");
    assert_eq!(goto.transitions[0].by, "alice");

    // Hold: kept through replannings until released.
    let held = act(a.id, Action::Hold(Hold {})).await;
    assert_eq!(held.task_kind(), pb::TaskKind::Hold);
    let replans = site.operator().get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap();
    let replans = replans.into_inner().replans;
    fleet_a.update_map(common::update(a.id, 2, 3.0, 1.5, vec![patch(18, 0, 2, 20, 0.05)])).await.unwrap();
    let view = site.until(mission.id, "a replanning", |v| v.mission.as_ref().unwrap().replans > replans).await;
    assert_eq!(robot(&view, a.id).task_id, held.task_id, "a replanning does not touch an override");
    let released = act(a.id, Action::Release(Release {})).await;
    assert_ne!(released.task_id, held.task_id);
    site.until(mission.id, "a exploring after release", |v| robot(v, a.id).task_kind() == pb::TaskKind::Explore).await;

    // Pin: a has the frontier at x = 4 m; b is kept away from it.
    let pinned = act(a.id, Action::PinFrontier(pb::Point { x: 4.0, y: 1.0 })).await;
    assert_eq!(pinned.task_kind(), pb::TaskKind::Pin);
    assert!((target_x(&pinned) - 4.0).abs() < 0.2, "{:?}", pinned.target);
    site.until(mission.id, "b kept away from the pinned frontier", |v| {
        robot(v, b.id).target.is_some_and(|t| (t.x - 4.0).abs() > 1.0)
    })
    .await;

    // Cancel: back to the pool at once.
    let cancelled = act(a.id, Action::Cancel(Cancel {})).await;
    assert_ne!(cancelled.task_kind(), pb::TaskKind::Pin);
    let history = site.tasks(mission.id, a.id).await;
    let pin = history.iter().find(|t| t.id == pinned.task_id).unwrap();
    assert_eq!(pin.state(), pb::TaskState::Cancelled);
    let events = site.events(mission.id).await;
    assert_eq!(events.iter().filter(|e| e.kind == "override").count(), 5, "{events:#?}");
    assert!(events.iter().all(|e| e.kind != "override" || e.actor == "alice"));

    // Overrides of unknown robots are refused precisely.
    let request = pb::OverrideRobotRequest { robot_id: 999, action: Some(Action::Hold(Hold {})), ..Default::default() };
    let refused = site.operator().override_robot(request).await.unwrap_err();
    assert_eq!(refused.code(), Code::NotFound, "{refused:?}");
}

#[tokio::test]
async fn forbidden_regions_get_no_targets_until_allowed() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 1000.0, 1000.0).await;
    let (a, mut fleet_a) = site.robot(mission.id, "a", 2.5, 1.0).await;
    let mut operator = site.operator();
    let area = pb::Rect { min_x: 1.0, min_y: 0.0, max_x: 2.5, max_y: 2.0 };
    let request =
        pb::ForbidRegionRequest { mission_id: mission.id, area: Some(area), actor: "bob".into(), reason: "wet".into() };
    let region = operator.forbid_region(request).await.unwrap().into_inner();
    fleet_a.update_map(middle_known(a.id, 1, 2.5, 1.0)).await.unwrap();
    let view = site.until(mission.id, "a assigned", |v| robot(v, a.id).task_id != 0).await;
    assert!(target_x(robot(&view, a.id)) > 3.5, "the nearer frontier is forbidden: {:?}", robot(&view, a.id).target);
    assert_eq!(view.mission.as_ref().unwrap().forbidden_regions.len(), 1);

    let bad = pb::ForbidRegionRequest {
        mission_id: mission.id,
        area: Some(pb::Rect { min_x: 3.0, min_y: 0.0, max_x: 2.0, max_y: 1.0 }),
        ..Default::default()
    };
    assert_eq!(operator.forbid_region(bad).await.unwrap_err().code(), Code::InvalidArgument);
    let unknown = pb::AllowRegionRequest { mission_id: mission.id, region_id: 77, ..Default::default() };
    assert_eq!(operator.allow_region(unknown).await.unwrap_err().code(), Code::NotFound);

    let allow = pb::AllowRegionRequest {
        mission_id: mission.id,
        region_id: region.id,
        actor: "bob".into(),
        reason: "dry".into(),
    };
    let allowed = operator.allow_region(allow).await.unwrap().into_inner();
    assert!(allowed.forbidden_regions.is_empty());
    let kinds: Vec<String> = site.events(mission.id).await.into_iter().map(|e| e.kind).collect();
    assert!(kinds.contains(&"region_forbidden".into()) && kinds.contains(&"region_allowed".into()), "{kinds:?}");
}

/// Each replanning checks every frontier cell against every region, and
/// every answer about the mission lists them: a mission holds at most
/// 1 000, and the next is refused without a trace until one is allowed.
#[tokio::test]
async fn a_mission_holds_at_most_a_thousand_forbidden_regions() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 1000.0, 1000.0).await;
    let mut operator = site.operator();
    let forbid = |i: u32| pb::ForbidRegionRequest {
        mission_id: mission.id,
        area: Some(pb::Rect {
            min_x: 0.1 * f64::from(i % 59),
            min_y: 0.0,
            max_x: 0.1 * f64::from(i % 59 + 1),
            max_y: 0.5,
        }),
        actor: "bob".into(),
        reason: format!("cone {i}"),
    };
    let mut first = None;
    for i in 0..1_000 {
        let region = operator.forbid_region(forbid(i)).await.unwrap().into_inner();
        first.get_or_insert(region.id);
    }
    let refused = operator.forbid_region(forbid(1_000)).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("already has 1000 forbidden regions"), "{refused:?}");
    let held = operator.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!(held.forbidden_regions.len(), 1_000);
    assert!(!held.forbidden_regions.iter().any(|r| r.reason == "cone 1000"));
    let allow = pb::AllowRegionRequest { mission_id: mission.id, region_id: first.unwrap(), ..Default::default() };
    operator.allow_region(allow).await.unwrap();
    operator.forbid_region(forbid(1_000)).await.unwrap();
}

/// An operator can make a mission about 2 MB (1 000 regions, each with the
/// longest reason kept, in four-byte characters): three such missions were
/// one 6 MB answer. ListMissions answers in pages a client with gRPC's
/// default 4 MB limit reads, and coordctl follows them to list every
/// mission.
#[tokio::test]
async fn missions_are_listed_in_pages_a_client_with_default_limits_reads() {
    let site = Site::start().await;
    let mut operator = site.operator();
    let mut ids = Vec::new();
    for regions in [1_000, 1_000, 1_000, 0] {
        let mission = site.mission("nearest", 1000.0, 1000.0).await;
        let forbid = |i: u32| pb::ForbidRegionRequest {
            mission_id: mission.id,
            area: Some(pb::Rect { min_x: 0.1 * f64::from(i % 59), min_y: 0.0, max_x: 5.9, max_y: 0.5 }),
            actor: "\u{1F916}".repeat(128),
            reason: "\u{1F6A7}".repeat(500),
        };
        for i in 0..regions {
            operator.forbid_region(forbid(i)).await.unwrap();
        }
        ids.push(mission.id);
    }

    let mut pages = Vec::new();
    let mut after_id = 0;
    loop {
        let page = operator.list_missions(pb::ListMissionsRequest { after_id, limit: 0 }).await.unwrap().into_inner();
        assert!(page.encoded_len() <= 4 << 20, "a page of {} bytes", page.encoded_len());
        pages.push(page.missions.iter().map(|m| m.id).collect::<Vec<_>>());
        if page.next_after_id == 0 {
            break;
        }
        after_id = page.next_after_id;
    }
    assert_eq!(pages, vec![vec![ids[0]], vec![ids[1]], vec![ids[2], ids[3]]]);
    let by_count = operator.list_missions(pb::ListMissionsRequest { after_id: ids[2], limit: 1 }).await.unwrap();
    let by_count = by_count.into_inner();
    assert_eq!((by_count.missions.len(), by_count.missions[0].id, by_count.next_after_id), (1, ids[3], 0));
    let past_the_last = pb::ListMissionsRequest { after_id: u64::MAX, limit: u32::MAX };
    assert_eq!(operator.list_missions(past_the_last).await.unwrap().into_inner(), Default::default());

    let url = site.exec.url.clone();
    let coordctl = tokio::task::spawn_blocking(move || {
        std::process::Command::new(common::binary("coordctl"))
            .args(["--server", &url, "--token", OPERATOR, "--json", "missions"])
            .output()
            .unwrap()
    });
    let output = coordctl.await.unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let listed: Vec<serde_json::Value> = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(listed.iter().map(|m| m["id"].as_u64().unwrap()).collect::<Vec<_>>(), ids);
}

/// An executive holds a bounded number of missions, and a finished one
/// kept its place for ever. An operator deletes a paused or completed
/// mission: it is gone from every answer at once, its robot's token no
/// longer admits it, its place is free, and after a restart its rows are
/// purged while the other missions stay.
#[tokio::test]
async fn an_operator_deletes_a_stopped_mission_and_frees_its_place() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("ops.db");
    let site = Site::start_in(dir, |executive| executive.max_missions = 2).await;
    let gone = site.mission("nearest", 1000.0, 1000.0).await;
    let (robot, mut fleet) = site.robot(gone.id, "a", 2.5, 1.0).await;
    fleet.update_map(middle_known(robot.id, 1, 2.5, 1.0)).await.unwrap();
    site.until(gone.id, "a assigned", |v| v.robots.first().is_some_and(|r| r.task_id != 0)).await;
    let stays = site.mission("nearest", 1000.0, 1000.0).await;
    let mut operator = site.operator();
    let history = pb::MissionControlRequest { mission_id: stays.id, actor: "carol".into(), reason: "drill".into() };
    operator.pause_mission(history).await.unwrap();
    let third = || pb::CreateMissionRequest {
        name: "third".into(),
        frame: Some(common::frame(60, 20)),
        policy: Some(pb::PolicySpec { name: "nearest".into(), params: Default::default() }),
        ..Default::default()
    };
    let full = operator.create_mission(third()).await.unwrap_err();
    assert_eq!(full.code(), Code::ResourceExhausted, "{full:?}");

    let control = pb::MissionControlRequest { mission_id: gone.id, actor: "carol".into(), reason: "done".into() };
    let running = operator.delete_mission(control.clone()).await.unwrap_err();
    assert_eq!(running.code(), Code::FailedPrecondition, "{running:?}");
    assert!(running.message().contains("pause it"), "{running:?}");
    let denied = site.missions(Some(VIEWER)).delete_mission(control.clone()).await.unwrap_err();
    assert_eq!(denied.code(), Code::PermissionDenied, "{denied:?}");
    operator.get_mission(pb::GetMissionRequest { mission_id: gone.id }).await.unwrap();

    let mut watch = operator.watch_mission(pb::WatchMissionRequest { mission_id: gone.id }).await.unwrap().into_inner();
    watch.message().await.unwrap().unwrap();
    operator.pause_mission(control.clone()).await.unwrap();
    // Two operators at once: one deletes it, the other is told it is gone.
    let mut other = site.operator();
    let (first, second) = tokio::join!(operator.delete_mission(control.clone()), other.delete_mission(control.clone()));
    let codes = [&first, &second].map(|r| r.as_ref().map_or_else(|s| s.code(), |_| Code::Ok));
    assert!(codes == [Code::Ok, Code::NotFound] || codes == [Code::NotFound, Code::Ok], "{first:?} {second:?}");
    loop {
        match tokio::time::timeout(Duration::from_secs(20), watch.message()).await.expect("the watch went on") {
            Ok(Some(_)) => continue,
            Ok(None) => break,
            Err(status) => {
                assert_eq!(status.code(), Code::NotFound, "{status:?}");
                break;
            }
        }
    }
    let missing = operator.get_mission(pb::GetMissionRequest { mission_id: gone.id }).await.unwrap_err();
    assert_eq!(missing.code(), Code::NotFound, "{missing:?}");
    let again = operator.delete_mission(control).await.unwrap_err();
    assert_eq!(again.code(), Code::NotFound, "{again:?}");
    let refused = fleet.heartbeat(heartbeat(robot.id, 2.5, 1.0, pb::RobotState::Idle, 0)).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated, "{refused:?}");
    let created = operator.create_mission(third()).await.unwrap().into_inner();
    assert!(created.id > stays.id);
    let listed = operator.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner().missions;
    assert_eq!(listed.iter().map(|m| m.id).collect::<Vec<_>>(), vec![stays.id, created.id]);

    // After a restart it stays gone, and the sweeps purge its rows.
    let site = site.restart().await;
    site.clock.step(Duration::from_secs(1)).await;
    let listed = site.operator().list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner();
    assert_eq!(listed.missions.iter().map(|m| m.id).collect::<Vec<_>>(), vec![stays.id, created.id]);
    let mut raw = sqlx::SqliteConnection::connect(&format!("sqlite:{}", db.display())).await.unwrap();
    for count in [
        "SELECT COUNT(*) FROM robots WHERE mission_id = ?",
        "SELECT COUNT(*) FROM map_patches WHERE mission_id = ?",
        "SELECT COUNT(*) FROM tasks WHERE mission_id = ?",
        "SELECT COUNT(*) FROM mission_events WHERE mission_id = ?",
    ] {
        let rows: i64 = sqlx::query_scalar(count).bind(gone.id as i64).fetch_one(&mut raw).await.unwrap();
        assert_eq!(rows, 0, "{count}: the deleted mission's rows");
    }
    let purged: i64 = sqlx::query_scalar("SELECT purged FROM missions WHERE id = ?")
        .bind(gone.id as i64)
        .fetch_one(&mut raw)
        .await
        .unwrap();
    assert_eq!(purged, 1);
    let kept: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM mission_events WHERE mission_id = ?")
        .bind(stays.id as i64)
        .fetch_one(&mut raw)
        .await
        .unwrap();
    assert!(kept > 0, "the other mission's history stays");
}

#[tokio::test]
async fn a_paused_mission_holds_every_robot_until_resumed() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 1000.0, 1000.0).await;
    let (a, mut fleet_a) = site.robot(mission.id, "a", 2.5, 1.0).await;
    fleet_a.update_map(middle_known(a.id, 1, 2.5, 1.0)).await.unwrap();
    site.until(mission.id, "a assigned", |v| robot(v, a.id).task_id != 0).await;
    let mut operator = site.operator();
    let control = pb::MissionControlRequest { mission_id: mission.id, actor: "carol".into(), reason: "door".into() };
    let paused = operator.pause_mission(control.clone()).await.unwrap().into_inner();
    assert_eq!(paused.state(), pb::MissionState::Paused);
    let assignment = fleet_a.get_assignment(pb::GetAssignmentRequest { robot_id: a.id }).await.unwrap().into_inner();
    assert_eq!(assignment.mission_state(), pb::MissionState::Paused, "robots learn that they must hold");
    // While paused, new map knowledge does not start a replanning.
    let replans = paused.replans;
    fleet_a.update_map(common::update(a.id, 2, 2.5, 1.0, vec![patch(15, 0, 5, 20, 0.05)])).await.unwrap();
    let still = operator.get_mission(pb::GetMissionRequest { mission_id: mission.id }).await.unwrap().into_inner();
    assert_eq!((still.state(), still.replans), (pb::MissionState::Paused, replans));
    // Pausing twice is refused: the state says so.
    assert_eq!(operator.pause_mission(control.clone()).await.unwrap_err().code(), Code::FailedPrecondition);

    let resumed = operator.resume_mission(control).await.unwrap().into_inner();
    assert_eq!(resumed.state(), pb::MissionState::Active);
    site.until(mission.id, "a replanning after resume", |v| v.mission.as_ref().unwrap().replans > replans).await;
    let kinds: Vec<String> = site.events(mission.id).await.into_iter().map(|e| e.kind).collect();
    assert!(kinds.contains(&"mission_paused".into()) && kinds.contains(&"mission_resumed".into()), "{kinds:?}");
}

#[tokio::test]
async fn the_event_log_is_read_in_pages_that_add_up_to_the_whole() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 1000.0, 1000.0).await;
    let mut operator = site.operator();
    let control = pb::MissionControlRequest { mission_id: mission.id, actor: "carol".into(), reason: "drill".into() };
    for _ in 0..3 {
        operator.pause_mission(control.clone()).await.unwrap();
        operator.resume_mission(control.clone()).await.unwrap();
    }
    let whole = operator.list_events(pb::ListEventsRequest { mission_id: mission.id, ..Default::default() }).await;
    let whole = whole.unwrap().into_inner();
    assert!(whole.events.len() >= 6, "{:?}", whole.events);
    assert_eq!(whole.next_after_id, 0, "everything fits the default page");

    let (mut paged, mut after_id, mut pages) = (Vec::new(), 0, 0);
    loop {
        let request = pb::ListEventsRequest { mission_id: mission.id, limit: 2, after_id };
        let page = operator.list_events(request).await.unwrap().into_inner();
        assert!(page.events.len() <= 2, "a page holds at most its limit");
        paged.extend(page.events);
        pages += 1;
        if page.next_after_id == 0 {
            break;
        }
        assert_eq!(page.next_after_id, paged.last().unwrap().id, "the cursor is the page's last event");
        after_id = page.next_after_id;
    }
    assert_eq!(paged, whole.events, "the pages, in order, are the whole log");
    assert_eq!(pages, whole.events.len().div_ceil(2) + usize::from(whole.events.len() % 2 == 0));

    // Worst values: the largest limit is capped, not refused; a cursor past
    // every identity is an empty last page; an unknown mission is NOT_FOUND.
    let request = pb::ListEventsRequest { mission_id: mission.id, limit: u32::MAX, after_id: 0 };
    assert_eq!(operator.list_events(request).await.unwrap().into_inner(), whole);
    let request = pb::ListEventsRequest { mission_id: mission.id, limit: 2, after_id: u64::MAX };
    let past = operator.list_events(request).await.unwrap().into_inner();
    assert!(past.events.is_empty() && past.next_after_id == 0, "{past:?}");
    let request = pb::ListEventsRequest { mission_id: mission.id + 1000, ..Default::default() };
    assert_eq!(operator.list_events(request).await.unwrap_err().code(), Code::NotFound);
}

#[tokio::test]
async fn tokens_are_checked_and_refused_requests_change_nothing() {
    let site = Site::start().await;
    let mission = site.mission("nearest", 1000.0, 1000.0).await;
    let (a, mut fleet_a) = site.robot(mission.id, "a", 2.5, 1.0).await;
    let (b, _) = site.robot(mission.id, "b", 3.5, 1.0).await;
    let before = site.operator().list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap();
    let events_before = site.events(mission.id).await.len();

    // No token, a wrong token: unauthenticated.
    for token in [None, Some("guess"), Some("rbt_1_0000")] {
        let status = site.missions(token).list_missions(pb::ListMissionsRequest::default()).await.unwrap_err();
        assert_eq!(status.code(), Code::Unauthenticated, "{token:?}: {status:?}");
        assert!(status.message().contains("token"), "{}", status.message());
        let status = site.fleet(token).heartbeat(heartbeat(a.id, 9.0, 9.0, pb::RobotState::Idle, 0)).await;
        assert_eq!(status.unwrap_err().code(), Code::Unauthenticated);
    }
    // A robot's token reads, and speaks for its robot only.
    let robot_token = fleet_a.register_robot(pb::RegisterRobotRequest {
        mission_id: mission.id,
        name: "a".into(),
        capabilities: before.get_ref().robots[0].capabilities,
        pose: Some(pb::Pose { x: 2.5, y: 1.0, theta: 0.0 }),
    });
    let renewed = robot_token.await.unwrap().into_inner();
    assert!(renewed.resumed, "a robot may re-register itself with its own token");
    let mut as_a = site.missions(Some(&renewed.token));
    as_a.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap();
    let denied = [
        as_a.override_robot(pb::OverrideRobotRequest {
            robot_id: b.id,
            action: Some(Action::Hold(Hold {})),
            ..Default::default()
        })
        .await
        .unwrap_err(),
        as_a.pause_mission(pb::MissionControlRequest { mission_id: mission.id, ..Default::default() })
            .await
            .unwrap_err(),
        as_a.create_mission(pb::CreateMissionRequest { frame: Some(common::frame(10, 10)), ..Default::default() })
            .await
            .unwrap_err(),
        site.fleet(Some(&renewed.token))
            .heartbeat(heartbeat(b.id, 9.0, 9.0, pb::RobotState::Idle, 0))
            .await
            .unwrap_err(),
    ];
    for status in &denied {
        assert_eq!(status.code(), Code::PermissionDenied, "{status:?}");
    }
    // A viewer reads and changes nothing.
    let mut kim = site.missions(Some(VIEWER));
    kim.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap();
    let refused = kim.pause_mission(pb::MissionControlRequest { mission_id: mission.id, ..Default::default() }).await;
    assert_eq!(refused.unwrap_err().code(), Code::PermissionDenied);
    let refused = site.fleet(Some(VIEWER)).heartbeat(heartbeat(a.id, 9.0, 9.0, pb::RobotState::Idle, 0)).await;
    assert_eq!(refused.unwrap_err().code(), Code::PermissionDenied);
    // Revoked by taking its line out of the file: refused at once, no restart.
    std::fs::write(&site.tokens, token_line("alice", "operator", OPERATOR)).unwrap();
    let revoked = kim.list_missions(pb::ListMissionsRequest::default()).await.unwrap_err();
    assert_eq!(revoked.code(), Code::Unauthenticated);

    // The old token stopped working when the robot registered again.
    let status = fleet_a.heartbeat(heartbeat(a.id, 2.5, 1.0, pb::RobotState::Idle, 0)).await.unwrap_err();
    assert_eq!(status.code(), Code::Unauthenticated, "a replaced robot token is refused: {status:?}");

    // Nothing changed.
    let after = site.operator().list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap();
    let poses = |r: &pb::ListRobotsResponse| r.robots.iter().map(|r| (r.id, r.pose, r.task_id)).collect::<Vec<_>>();
    assert_eq!(poses(before.get_ref()), poses(after.get_ref()));
    assert_eq!(site.events(mission.id).await.len(), events_before);
    let missions = site.operator().list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner();
    assert_eq!(missions.missions.len(), 1);
    let paused = missions.missions[0].state();
    assert_eq!(paused, pb::MissionState::Active);
}
