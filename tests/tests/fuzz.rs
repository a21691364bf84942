//! Property-based fuzzing, for a fixed number of seeded cases in CI: the
//! request conversions, map fusion and bids with arbitrary values, and
//! sequences of API calls against a real executive. Nothing may panic, no
//! call may fail with INTERNAL or UNKNOWN, and every acknowledged write must
//! be in the store after a restart.
//!
//! `cargo test -p e2e --test fuzz` runs the CI budget; `FUZZ_CASES=N` runs
//! more (the figures in the trust issue's note come from that).

mod common;

use std::collections::BTreeMap;

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, RngSeed, TestRunner};

use coordinator::domain::{Heartbeat, MapUpdate, MissionSpec, RobotSpec};
use coordinator::service::convert;
use exploration::fusion::{MapFusion, Patch};
use exploration::grid::{CellRect, GridFrame};
use exploration::math::Point2;
use exploration_proto::v1 as pb;
use tonic::Code;

/// Cases per property: the CI budget, or `FUZZ_CASES`.
fn cases(ci: u32) -> u32 {
    std::env::var("FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(ci)
}

/// A seeded runner: the same cases on every run.
fn runner(cases: u32, seed: u64) -> TestRunner {
    TestRunner::new(Config {
        cases,
        failure_persistence: None,
        rng_seed: RngSeed::Fixed(seed),
        rng_algorithm: RngAlgorithm::ChaCha,
        ..Config::default()
    })
}

/// Floats the network can send: ordinary, huge, tiny, and not numbers at all.
fn wild_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        4 => -50.0..50.0f64,
        1 => any::<f64>(),
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(f64::NEG_INFINITY),
        1 => Just(1e308),
        1 => Just(-1e12),
        1 => Just(0.0),
    ]
}

fn wild_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => 0.0..1.0f32,
        1 => any::<f32>(),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(-3.0f32),
    ]
}

fn wild_u32() -> impl Strategy<Value = u32> {
    prop_oneof![4 => 0..64u32, 1 => any::<u32>(), 1 => Just(u32::MAX), 1 => Just(1 << 31)]
}

fn wild_text() -> impl Strategy<Value = String> {
    prop_oneof![
        3 => "[a-z0-9-]{0,12}",
        1 => "\\PC{0,40}",
        1 => Just("line\nbreak".to_owned()),
        1 => Just("nul\0".to_owned()),
        1 => Just("x".repeat(200)),
    ]
}

fn point() -> impl Strategy<Value = Option<pb::Point>> {
    proptest::option::weighted(0.9, (wild_f64(), wild_f64()).prop_map(|(x, y)| pb::Point { x, y }))
}

fn pose() -> impl Strategy<Value = Option<pb::Pose>> {
    proptest::option::weighted(
        0.9,
        (wild_f64(), wild_f64(), wild_f64()).prop_map(|(x, y, theta)| pb::Pose { x, y, theta }),
    )
}

fn map_patch() -> impl Strategy<Value = pb::MapPatch> {
    (wild_u32(), wild_u32(), 0..12u32, 0..12u32, -1..5i32, any::<bool>(), any::<bool>(), any::<bool>()).prop_flat_map(
        |(x, y, width, height, encoding, extra_value, with_mask, with_occupancy)| {
            let n = (width * height) as usize + usize::from(extra_value);
            (
                Just((x, y, width, height, encoding)),
                proptest::collection::vec(wild_f32(), n),
                proptest::collection::vec(0..3u8, if with_mask { n } else { 0 }),
                // Mostly percentages and unknown, sometimes any byte.
                proptest::collection::vec(
                    prop_oneof![4 => 0..=100u8, 1 => Just(255u8), 1 => any::<u8>()],
                    if with_occupancy { n } else { 0 },
                ),
            )
                .prop_map(|((x, y, width, height, encoding), values, unknown, occupancy)| pb::MapPatch {
                    x,
                    y,
                    width,
                    height,
                    encoding,
                    values,
                    unknown,
                    occupancy,
                })
        },
    )
}

fn frame() -> impl Strategy<Value = Option<pb::MapFrame>> {
    proptest::option::weighted(
        0.9,
        (wild_f64(), point(), wild_u32(), wild_u32()).prop_map(|(resolution, origin, width, height)| pb::MapFrame {
            resolution,
            origin,
            width,
            height,
        }),
    )
}

fn rect() -> impl Strategy<Value = pb::Rect> {
    (wild_f64(), wild_f64(), wild_f64(), wild_f64()).prop_map(|(min_x, min_y, max_x, max_y)| pb::Rect {
        min_x,
        min_y,
        max_x,
        max_y,
    })
}

fn bid() -> impl Strategy<Value = pb::Bid> {
    (point(), wild_f64(), wild_f64(), proptest::option::of(rect())).prop_map(
        |(target, path_cost, information_gain, gain_region)| pb::Bid {
            target,
            path_cost,
            information_gain,
            gain_region,
        },
    )
}

/// Every request conversion, on arbitrary requests: an answer, never a panic;
/// what passes meets the limits.
#[test]
fn request_conversions_never_panic() {
    let create = (
        wild_text(),
        frame(),
        proptest::option::of(("[a-z-]{0,14}", proptest::collection::btree_map("[a-z_]{1,12}", wild_f64(), 0..4))),
    )
        .prop_map(|(name, frame, policy)| pb::CreateMissionRequest {
            name,
            frame,
            policy: policy.map(|(name, params)| pb::PolicySpec { name, params: params.into_iter().collect() }),
            ..Default::default()
        });
    let mut runner = runner(cases(2_000), 1);
    runner
        .run(&create, |request| {
            if let Ok(spec) = MissionSpec::try_from(request) {
                prop_assert!(spec.frame.len() as u64 <= convert::MAX_GRID_CELLS);
                prop_assert!(spec.frame.resolution.is_finite() && spec.frame.origin.x.is_finite());
                prop_assert!(!spec.name.chars().any(char::is_control));
            }
            Ok(())
        })
        .unwrap();

    let register =
        (wild_text(), pose(), proptest::option::weighted(0.9, (wild_f64(), wild_f64(), wild_f64(), wild_f64())))
            .prop_map(|(name, pose, caps)| pb::RegisterRobotRequest {
                mission_id: 1,
                name,
                pose,
                capabilities: caps.map(|(a, b, c, d)| pb::RobotCapabilities {
                    sensor_range_m: a,
                    field_of_view_rad: b,
                    speed_mps: c,
                    footprint_radius_m: d,
                }),
            });
    runner
        .run(&register, |request| {
            if let Ok(spec) = RobotSpec::try_from(request) {
                prop_assert!(spec.pose.position.x.is_finite() && spec.capabilities.speed_mps > 0.0);
            }
            Ok(())
        })
        .unwrap();

    let update = (
        any::<u64>(),
        pose(),
        proptest::collection::vec(map_patch(), 0..4),
        any::<bool>(),
        proptest::collection::vec(any::<u64>(), 0..8),
    )
        .prop_map(|(seq, pose, patches, peers_reported, peers)| pb::UpdateMapRequest {
            robot_id: 1,
            seq,
            pose,
            patches,
            peers_reported,
            peers,
        });
    runner
        .run(&update, |request| {
            if let Ok(update) = MapUpdate::try_from(request) {
                for patch in &update.patches {
                    prop_assert_eq!(patch.log_odds().len() as u64, patch.rect().area());
                    prop_assert!(patch.log_odds().iter().all(|v| v.is_nan() || v.is_finite()));
                }
            }
            Ok(())
        })
        .unwrap();

    let heartbeat = (pose(), -1..6i32, any::<u64>(), wild_text()).prop_map(|(pose, state, task_id, reason)| {
        pb::HeartbeatRequest { robot_id: 1, pose, state, task_id, reason, ..Default::default() }
    });
    runner
        .run(&heartbeat, |request| {
            let _ = Heartbeat::try_from(request);
            Ok(())
        })
        .unwrap();

    let bids = proptest::collection::vec(bid(), 0..6);
    runner
        .run(&bids, |bids| {
            if let Ok(bids) = convert::bids(bids) {
                prop_assert!(bids.iter().all(|b| b.target.x.is_finite() && b.path_cost >= 0.0));
            }
            Ok(())
        })
        .unwrap();

    let areas = proptest::option::of(rect());
    runner
        .run(&areas, |area| {
            if let Ok((min, max)) = convert::area(area, "area") {
                prop_assert!(min.x < max.x && min.y < max.y);
            }
            Ok(())
        })
        .unwrap();
}

/// Patches of arbitrary values and places, applied to a grid: refused or
/// applied, never a panic, and the fused grid stays a grid of known classes.
#[test]
fn map_fusion_of_arbitrary_patches() {
    let frame = GridFrame::new(0.1, Point2::new(-1.0, 2.0), 40, 30);
    let patches = proptest::collection::vec((0..4u64, map_patch()), 1..12);
    runner(cases(500), 2)
        .run(&patches, |patches| {
            let mut fusion = MapFusion::new(frame);
            for (layer, p) in patches {
                let Ok(patch) = convert::PatchInput::try_from(p) else { continue };
                let before = fusion.grid().cells().to_vec();
                match fusion.apply(layer, &patch.0) {
                    Ok(change) => prop_assert!(change.changed_cells <= patch.0.rect().area()),
                    Err(_) => prop_assert_eq!(fusion.grid().cells(), &before[..], "a refused patch changes nothing"),
                }
            }
            let valid = |v: u8| v == exploration::grid::UNKNOWN || v <= 100;
            prop_assert!(fusion.grid().cells().iter().all(|&v| valid(v)));
            Ok(())
        })
        .unwrap();
    // Stored patches of any bytes: refused or rebuilt, never a panic.
    let stored = (0..8u32, 0..8u32, proptest::collection::vec(any::<f32>(), 0..80));
    runner(cases(500), 3)
        .run(&stored, |(w, h, values)| {
            if let Ok(patch) = Patch::from_stored(CellRect::new(0, 0, w, h), values) {
                let mut fusion = MapFusion::new(frame);
                let _ = fusion.apply(1, &patch);
            }
            Ok(())
        })
        .unwrap();
}

/// One call of a sequence against the real executive.
#[derive(Debug, Clone)]
enum Call {
    Create(Option<pb::MapFrame>, u8, bool),
    Register(usize, String, Option<pb::Pose>),
    Update(usize, i64, Option<pb::Pose>, Vec<pb::MapPatch>),
    Heartbeat(usize, i32, i64, Option<pb::Pose>),
    Bids(usize, Vec<pb::Bid>),
    Forbid(usize, Option<pb::Rect>),
    Pause(usize, bool),
    /// Deletes a mission (after pausing it, when `pause_first`).
    Delete(usize, bool),
    Policy(usize, u8),
    Override(usize, u8, Option<pb::Point>),
    /// Rooms for a mission: 0 raw label runs from the numbers, 1 runs that
    /// cover its map (one per number), 2 none (back to online).
    Rooms(usize, u8, Vec<u32>),
}

/// The catalogued policy `k` (modulo their number).
fn policy_name(k: u8) -> String {
    let catalogue = exploration::policy::catalogue();
    catalogue[k as usize % catalogue.len()].name.to_owned()
}

fn call() -> impl Strategy<Value = Call> {
    let small_frame = (0.05..0.5f64, 1..60u32, 1..60u32).prop_map(|(resolution, width, height)| {
        Some(pb::MapFrame { resolution, origin: Some(pb::Point { x: 0.0, y: 0.0 }), width, height })
    });
    let near = (0.0..4.0f64, 0.0..4.0f64).prop_map(|(x, y)| Some(pb::Pose { x, y, theta: 0.0 }));
    let pose = prop_oneof![3 => near, 1 => pose()];
    prop_oneof![
        1 => (prop_oneof![4 => small_frame, 1 => frame()], any::<u8>(), any::<bool>())
            .prop_map(|(f, p, l)| Call::Create(f, p, l)),
        2 => (0..4usize, prop_oneof![3 => "r[0-3]", 1 => wild_text()], pose.clone()).prop_map(|(m, n, p)| Call::Register(m, n, p)),
        5 => (0..8usize, -2..4i64, pose.clone(), proptest::collection::vec(map_patch(), 0..3)).prop_map(|(r, s, p, q)| Call::Update(r, s, p, q)),
        2 => (0..8usize, -1..6i32, -1..3i64, pose).prop_map(|(r, s, t, p)| Call::Heartbeat(r, s, t, p)),
        1 => (0..8usize, proptest::collection::vec(bid(), 0..4)).prop_map(|(r, b)| Call::Bids(r, b)),
        1 => (0..4usize, proptest::option::of(rect())).prop_map(|(m, r)| Call::Forbid(m, r)),
        1 => (0..4usize, any::<bool>()).prop_map(|(m, p)| Call::Pause(m, p)),
        1 => (0..4usize, any::<bool>()).prop_map(|(m, p)| Call::Delete(m, p)),
        1 => (0..4usize, any::<u8>()).prop_map(|(m, p)| Call::Policy(m, p)),
        1 => (0..8usize, 0..7u8, point()).prop_map(|(r, a, p)| Call::Override(r, a, p)),
        1 => (0..4usize, 0..3u8, proptest::collection::vec(wild_u32(), 0..6)).prop_map(|(m, k, l)| Call::Rooms(m, k, l)),
    ]
}

/// What the executive acknowledged, to be found in the store afterwards.
#[derive(Debug, Default)]
struct Acknowledged {
    missions: Vec<u64>,
    /// Robot id → (mission id, highest acknowledged map seq).
    robots: BTreeMap<u64, (u64, u64)>,
    /// Mission id → acknowledged map updates.
    map_updates: BTreeMap<u64, u64>,
    /// Mission id → whether its rooms were last given (acknowledged).
    rooms: BTreeMap<u64, bool>,
}

/// A status the executive may answer: anything but a failure of its own.
fn expected(status: &tonic::Status) -> Result<(), TestCaseError> {
    prop_assert!(
        !matches!(status.code(), Code::Internal | Code::Unknown | Code::Unavailable),
        "the executive failed on its own: {status:?}"
    );
    Ok(())
}

async fn play(calls: Vec<Call>) -> Result<(), TestCaseError> {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("fuzz.db");
    let exec = common::TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let mut fleet = exec.fleet();
    let mut seen = Acknowledged::default();
    let robot_ids: Vec<u64> = Vec::new();
    let mut robot_ids = robot_ids;
    let mission_of =
        |seen: &Acknowledged, i: usize| seen.missions.get(i % seen.missions.len().max(1)).copied().unwrap_or(1);
    let robot_of = |ids: &[u64], i: usize| ids.get(i % ids.len().max(1)).copied().unwrap_or(1);
    for call in calls {
        match call {
            Call::Create(frame, p, lockstep) => {
                let policy = Some(pb::PolicySpec { name: policy_name(p), params: Default::default() });
                let request =
                    pb::CreateMissionRequest { name: "fuzz".into(), frame, policy, lockstep, ..Default::default() };
                match missions.create_mission(request).await {
                    Ok(m) => {
                        let m = m.into_inner();
                        seen.missions.push(m.id);
                        seen.map_updates.insert(m.id, 0);
                    }
                    Err(s) => expected(&s)?,
                }
            }
            Call::Register(m, name, pose) => {
                let mission_id = mission_of(&seen, m);
                let mut request = common::registration(mission_id, &name, 0.0, 0.0);
                request.pose = pose;
                match fleet.register_robot(request).await {
                    Ok(r) => {
                        let robot = r.into_inner().robot.unwrap();
                        if !robot_ids.contains(&robot.id) {
                            robot_ids.push(robot.id);
                        }
                        seen.robots.entry(robot.id).or_insert((mission_id, robot.last_map_seq));
                    }
                    Err(s) => expected(&s)?,
                }
            }
            Call::Update(r, step, pose, patches) => {
                let robot_id = robot_of(&robot_ids, r);
                let last = seen.robots.get(&robot_id).map_or(0, |r| r.1);
                let seq = (last as i64 + step).max(0) as u64;
                let request = pb::UpdateMapRequest { robot_id, seq, pose, patches, ..Default::default() };
                match fleet.update_map(request).await {
                    Ok(answer) => {
                        let (mission_id, high) = seen.robots.get_mut(&robot_id).expect("an acknowledged robot");
                        prop_assert!(answer.into_inner().applied_seq > *high, "each seq is applied once");
                        *high = seq;
                        *seen.map_updates.entry(*mission_id).or_default() += 1;
                    }
                    Err(s) => expected(&s)?,
                }
            }
            Call::Heartbeat(r, state, task, pose) => {
                let robot_id = robot_of(&robot_ids, r);
                let task_id = match task {
                    -1 => 0,
                    t => fleet
                        .get_assignment(pb::GetAssignmentRequest { robot_id })
                        .await
                        .map_or(t as u64, |a| a.into_inner().task_id + t as u64),
                };
                let request = pb::HeartbeatRequest { robot_id, pose, state, task_id, ..Default::default() };
                if let Err(s) = fleet.heartbeat(request).await {
                    expected(&s)?;
                }
            }
            Call::Bids(r, bids) => {
                let robot_id = robot_of(&robot_ids, r);
                if let Err(s) = fleet.submit_bids(pb::SubmitBidsRequest { robot_id, bids }).await {
                    expected(&s)?;
                }
            }
            Call::Forbid(m, area) => {
                let request = pb::ForbidRegionRequest { mission_id: mission_of(&seen, m), area, ..Default::default() };
                if let Err(s) = missions.forbid_region(request).await {
                    expected(&s)?;
                }
            }
            Call::Pause(m, pause) => {
                let request = pb::MissionControlRequest { mission_id: mission_of(&seen, m), ..Default::default() };
                let answer =
                    if pause { missions.pause_mission(request).await } else { missions.resume_mission(request).await };
                if let Err(s) = answer {
                    expected(&s)?;
                }
            }
            Call::Delete(m, pause_first) => {
                let request = pb::MissionControlRequest { mission_id: mission_of(&seen, m), ..Default::default() };
                if pause_first && let Err(s) = missions.pause_mission(request.clone()).await {
                    expected(&s)?;
                }
                match missions.delete_mission(request.clone()).await {
                    Ok(_) => seen.missions.retain(|&id| id != request.mission_id),
                    Err(s) => expected(&s)?,
                }
            }
            Call::Policy(m, p) => {
                let request = pb::SetPolicyRequest {
                    mission_id: mission_of(&seen, m),
                    policy: Some(pb::PolicySpec { name: policy_name(p), params: Default::default() }),
                    ..Default::default()
                };
                if let Err(s) = missions.set_policy(request).await {
                    expected(&s)?;
                }
            }
            Call::Rooms(m, kind, numbers) => {
                let mission_id = mission_of(&seen, m);
                let pair = |label: u32, run: u32| [label.to_le_bytes(), run.to_le_bytes()].concat();
                let label_runs: Vec<u8> = match kind {
                    0 => numbers.iter().flat_map(|n| n.to_le_bytes()).collect(),
                    1 => match missions.get_mission(pb::GetMissionRequest { mission_id }).await {
                        Ok(mission) => {
                            let frame = mission.into_inner().frame.unwrap_or_default();
                            let cells = u64::from(frame.width) * u64::from(frame.height);
                            let parts = numbers.len().max(1) as u64;
                            (0..parts)
                                .map(|k| {
                                    let run = cells * (k + 1) / parts - cells * k / parts;
                                    pair(numbers.get(k as usize).copied().unwrap_or(1), run as u32)
                                })
                                .collect::<Vec<_>>()
                                .concat()
                        }
                        Err(_) => Vec::new(),
                    },
                    _ => Vec::new(),
                };
                let given = !label_runs.is_empty();
                let request = pb::SetGivenSegmentationRequest { mission_id, label_runs, ..Default::default() };
                match missions.set_given_segmentation(request).await {
                    Ok(answer) => {
                        prop_assert_eq!(answer.into_inner().given_segmentation, given);
                        seen.rooms.insert(mission_id, given);
                    }
                    Err(s) => expected(&s)?,
                }
            }
            Call::Override(r, action, at) => {
                use pb::override_robot_request::{Action, Cancel, Hold, Home, Release};
                let action = match action {
                    0 => at.map(Action::Goto),
                    1 => at.map(Action::PinFrontier),
                    2 => Some(Action::Hold(Hold {})),
                    3 => Some(Action::Home(Home {})),
                    4 => Some(Action::Release(Release {})),
                    5 => Some(Action::Cancel(Cancel {})),
                    _ => at.map(|p| {
                        Action::ExploreRegion(pb::Rect { min_x: p.x, min_y: p.y, max_x: p.x + 1.0, max_y: p.y + 1.0 })
                    }),
                };
                let request =
                    pb::OverrideRobotRequest { robot_id: robot_of(&robot_ids, r), action, ..Default::default() };
                if let Err(s) = missions.override_robot(request).await {
                    expected(&s)?;
                }
            }
        }
    }
    exec.stop().await;

    // Every acknowledged write is in the store, as the restarted executive sees it.
    let exec = common::TestExecutive::start(&db).await;
    let mut missions = exec.missions();
    let stored = missions.list_missions(pb::ListMissionsRequest::default()).await.unwrap().into_inner().missions;
    prop_assert_eq!(stored.iter().map(|m| m.id).collect::<Vec<_>>(), seen.missions.clone());
    for mission in &stored {
        prop_assert_eq!(mission.map_updates, seen.map_updates[&mission.id]);
        prop_assert_eq!(mission.given_segmentation, seen.rooms.get(&mission.id).copied().unwrap_or(false));
        let robots = missions.list_robots(pb::ListRobotsRequest { mission_id: mission.id }).await.unwrap().into_inner();
        for robot in robots.robots {
            prop_assert_eq!(robot.last_map_seq, seen.robots[&robot.id].1);
        }
    }
    exec.stop().await;
    Ok(())
}

/// Sequences of API calls, good and bad, against a real executive with a
/// real database file, then a restart: nothing panics or fails internally,
/// and everything acknowledged is stored.
#[test]
fn api_call_sequences_keep_every_acknowledged_write() {
    // The nested strategies and their value trees are deep in a debug build:
    // a thread with room for them.
    std::thread::Builder::new().stack_size(64 << 20).spawn(api_call_sequences).unwrap().join().unwrap();
}

fn api_call_sequences() {
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let calls = ((small_create(), 1..3usize).prop_map(|(c, n)| vec![c; n]), proptest::collection::vec(call(), 1..40))
        .prop_map(|(mut first, rest)| {
            first.extend(rest);
            first
        });
    runner(cases(24), 4).run(&calls, |calls| runtime.block_on(Box::pin(play(calls)))).unwrap();
}

/// A mission every sequence starts with, so that the others have something to act on.
fn small_create() -> impl Strategy<Value = Call> {
    (1..40u32, 1..40u32, any::<u8>(), any::<bool>()).prop_map(|(w, h, p, lockstep)| {
        let frame = pb::MapFrame { resolution: 0.1, origin: None, width: w.max(10), height: h.max(10) };
        Call::Create(Some(frame), p, lockstep)
    })
}
