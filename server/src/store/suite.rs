//! The store's behaviour, the same on every engine: each test runs on a
//! fresh SQLite file and on a fresh PostgreSQL database (where
//! `EXPLORATION_POSTGRES_URL` names a server; `.ci/run` starts one).

use std::sync::Arc;
use std::time::Duration;

use crate::domain::{
    Actor, Bid, BlacklistEntry, Leftover, LeftoverReason, Leftovers, LifecycleSettings, MOST_LEFTOVERS, MissionEvent,
    MissionId, MissionSpec, MissionState, Pose, Region, ReplanSettings, RobotSpec, RobotState, StoredSegmentation,
    TaskKind, TaskRecord, TaskState, Timestamp, Transition,
};
use crate::store::sqlite::Durability;
use crate::store::{
    Changeset, Claimant, FailureKind, Fence, Location, LoggedPatch, MapSnapshot, MissionCounters, Share, Store,
    StoreError, TaskChange, TaskFilter, compact,
};
use exploration::fusion::Patch;
use exploration::grid::{Cell, CellRect, GridFrame};
use exploration::math::Point2;
use exploration::policy::{Capabilities, PolicyConfig};
use exploration::segment::{CriticalPoint, Segment, Segmentation};

/// A fresh database for one test, on one engine.
pub(crate) enum TestDb {
    /// A file in a folder removed with it.
    Sqlite(tempfile::TempDir),
    /// A database of its own on the server.
    Postgres(String),
}

impl TestDb {
    pub(crate) fn sqlite() -> Self {
        Self::Sqlite(tempfile::tempdir().unwrap())
    }

    /// A fresh database named after `test` (see [`crate::store::postgres::test_database`]).
    pub(crate) async fn postgres(test: &str) -> Option<Self> {
        crate::store::postgres::test_database(&format!("store_{test}")).await.map(Self::Postgres)
    }

    fn location(&self) -> Location {
        match self {
            Self::Sqlite(dir) => Location::Sqlite(dir.path().join("store.db")),
            Self::Postgres(url) => Location::Postgres(url.clone()),
        }
    }

    pub(crate) async fn try_open(&self) -> Result<Arc<dyn Store>, StoreError> {
        self.location().open(Durability::Full, false, None).await
    }

    pub(crate) async fn open(&self) -> Arc<dyn Store> {
        self.try_open().await.unwrap()
    }
}

/// Each test, on a fresh SQLite file and on a fresh PostgreSQL database.
macro_rules! on_both_engines {
    ($($test:ident),* $(,)?) => {$(
        mod $test {
            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn sqlite() {
                super::$test(super::TestDb::sqlite()).await;
            }

            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn postgres() {
                if let Some(db) = super::TestDb::postgres(stringify!($test)).await {
                    super::$test(db).await;
                }
            }
        }
    )*};
}

on_both_engines!(
    a_changeset_round_trips,
    a_failed_changeset_writes_nothing,
    one_executive_per_database,
    a_group_commit_fails_only_the_bad_changeset,
    what_follows_a_refused_changeset_is_not_written,
    a_folded_patch_log_restores_the_same_map,
    patches_come_back_bit_for_bit_whichever_way_they_came,
    a_lease_passes_on_only_once_it_ran_out_and_fences_its_old_holder,
    a_mission_created_with_its_lease_is_never_unclaimed,
    replicas_are_counted_while_their_announcements_last,
);

pub(crate) const HASH: &str = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad";

/// A changeset holding one note event of `mission_id` at `at`.
pub(crate) fn note(mission_id: MissionId, at: i64, detail: String) -> Changeset {
    let event =
        MissionEvent { id: 0, mission_id, at: Timestamp(at), kind: "note".into(), detail, actor: "test".into() };
    Changeset { events: vec![event], ..Changeset::default() }
}

pub(crate) fn spec() -> MissionSpec {
    MissionSpec {
        name: "lab".into(),
        frame: GridFrame::new(0.1, Point2::new(-1.0, -2.0), 40, 30),
        policy: PolicyConfig::default_for("burgard").unwrap(),
        replan: ReplanSettings::default(),
        scoped_by_communication: true,
        lockstep: true,
        lifecycle: LifecycleSettings {
            lease: Duration::from_secs(7),
            stall: Duration::from_secs(11),
            rendezvous: Some(Point2::new(0.5, -1.5)),
        },
    }
}

/// A replica named `id`, reached at `http://{id}:1`.
fn claimant(id: &str) -> Claimant {
    Claimant { id: id.into(), address: format!("http://{id}:1") }
}

pub(crate) fn robot_spec(name: &str) -> RobotSpec {
    RobotSpec {
        name: name.into(),
        capabilities: Capabilities {
            sensor_range_m: 4.0,
            field_of_view_rad: 6.0,
            speed_mps: 0.5,
            footprint_radius_m: 0.2,
        },
        pose: Pose { position: Point2::new(0.5, 0.5), heading: 0.1 },
    }
}

async fn a_changeset_round_trips(db: TestDb) {
    let store = db.open().await;
    let mission = store.create_mission(&spec(), Timestamp(1_000)).await.unwrap();
    assert_eq!(mission.spec, spec());
    let mut robot =
        store.create_robot(mission.id, &robot_spec("r1"), &|_| HASH.to_owned(), Timestamp(2_000), None).await.unwrap();
    assert_eq!(robot.state, RobotState::Idle);
    assert_eq!(robot.home, Point2::new(0.5, 0.5));
    assert_eq!(store.robot_tokens().await.unwrap(), vec![(robot.id, HASH.to_owned())]);

    let rect = CellRect::new(3, 4, 2, 1);
    let patch = Patch::from_probabilities(rect, &[0.2, 0.9], &[false, true]).unwrap();
    let task = TaskRecord {
        id: 7,
        mission_id: mission.id,
        robot_id: robot.id,
        kind: TaskKind::Goto,
        target: Point2::new(1.0, 2.0),
        state: TaskState::Assigned,
        policy: "operator".into(),
        utility: 0.5,
        path_cost: 1.5,
        gain_region: Some(CellRect::new(1, 2, 3, 4)),
        created_by: "operator:ana".into(),
        note: "check the lab".into(),
        created_at: Timestamp(3_000),
        updated_at: Timestamp(3_000),
        transitions: vec![Transition {
            from: None,
            to: TaskState::Assigned,
            at: Timestamp(3_000),
            cause: "operator ana".into(),
            actor: Actor::Operator,
            by: "ana".into(),
        }],
    };
    let frame = spec().frame;
    let mut labels = vec![0u32; frame.len()];
    labels[5..40].fill(1);
    labels[100..130].fill(2);
    let rooms: crate::domain::Rooms = (0..mission.spec.frame.len() as u32).map(|i| i / 7).collect();
    let segmentation = StoredSegmentation {
        computed_at: Timestamp(3_000),
        segmentation: Segmentation {
            frame,
            labels,
            segments: vec![
                Segment { id: 1, cells: 35, bounds: CellRect::new(5, 0, 35, 1), frontier: vec![Cell::new(7, 0)] },
                Segment { id: 2, cells: 30, bounds: CellRect::new(20, 2, 20, 2), frontier: vec![] },
            ],
            critical_points: vec![CriticalPoint { cell: Cell::new(19, 1), clearance: 2.5 }],
        },
    };
    robot.current_task = Some(7);
    robot.last_map_seq = 5;
    robot.assignment_version = 1;
    robot.lost = true;
    // More than are listed: the JSON form with the tally.
    let leftovers = Leftovers::keep_largest(
        (0..MOST_LEFTOVERS + 2)
            .map(|i| Leftover {
                reason: LeftoverReason::TooNarrow,
                cells: 12 + i,
                // The last bit of a position survives the JSON it is kept in.
                position: Point2::new(11.850000000000001, 0.1 * i as f64),
            })
            .collect(),
    );
    assert_eq!((leftovers.unlisted_clusters, leftovers.unlisted_cells), (2, 25));
    let region = Region {
        id: 3,
        mission_id: mission.id,
        min: Point2::new(0.0, 0.0),
        max: Point2::new(1.0, 1.0),
        actor: "ana".into(),
        reason: "wet floor".into(),
        created_at: Timestamp(3_000),
    };
    let blacklisted = BlacklistEntry {
        robot_id: robot.id,
        cell: Cell::new(4, 5),
        cause: "unreachable".into(),
        created_at: Timestamp(3_000),
    };
    store
        .commit(Changeset {
            mission: Some(MissionCounters {
                id: mission.id,
                state: MissionState::Completed,
                replans: 1,
                map_updates: 1,
                paused: true,
                leftovers: leftovers.clone(),
            }),
            robots: vec![robot.clone()],
            new_tasks: vec![task.clone()],
            task_changes: vec![],
            patches: vec![LoggedPatch { robot_id: robot.id, seq: 5, patch: Arc::new(patch.clone()) }],
            policy: Some((mission.id, PolicyConfig::default_for("minpos").unwrap())),
            events: vec![MissionEvent {
                id: 0,
                mission_id: mission.id,
                at: Timestamp(3_000),
                kind: "policy_changed".into(),
                detail: "burgard -> minpos".into(),
                actor: "ops".into(),
            }],
            segmentation: Some((mission.id, segmentation.clone())),
            given_segmentation: Some((mission.id, Some(rooms.clone()))),
            blacklisted: vec![blacklisted.clone(), BlacklistEntry { cell: Cell::new(9, 9), ..blacklisted.clone() }],
            unblacklisted: vec![],
            forbidden: vec![region.clone(), Region { id: 4, ..region.clone() }],
            allowed: vec![],
            robot_tokens: vec![(robot.id, "0".repeat(64))],
            bids: Some((
                robot.id,
                vec![Bid {
                    target: Point2::new(0.5, 0.5),
                    path_cost: 1.0,
                    information_gain: 20.0,
                    gain_region: (Point2::new(0.0, 0.0), Point2::new(1.0, 1.0)),
                }],
            )),
            fence: None,
            snapshot: None,
            forget_folded: None,
            deleted: None,
            at: Some(Timestamp(3_000)),
        })
        .await
        .unwrap();
    store
        .commit(Changeset {
            task_changes: vec![TaskChange {
                task_id: 7,
                state: TaskState::Reached,
                transition: Transition {
                    from: Some(TaskState::Assigned),
                    to: TaskState::Reached,
                    at: Timestamp(4_000),
                    cause: "robot arrived".into(),
                    actor: Actor::Robot,
                    by: String::new(),
                },
            }],
            unblacklisted: vec![(robot.id, Cell::new(9, 9))],
            allowed: vec![4],
            ..Changeset::default()
        })
        .await
        .unwrap();
    store.close().await;

    // Reopen the database: everything is there.
    let store = db.open().await;
    let missions = store.missions().await.unwrap();
    assert_eq!(missions.len(), 1);
    assert_eq!(missions[0].replans, 1);
    assert_eq!(missions[0].spec.lifecycle, spec().lifecycle);
    assert!(missions[0].paused);
    assert_eq!(missions[0].state, MissionState::Completed);
    assert_eq!(missions[0].leftovers, leftovers);
    assert_eq!(store.blacklist(mission.id).await.unwrap(), vec![blacklisted]);
    assert_eq!(store.forbidden_regions(mission.id).await.unwrap(), vec![region]);
    assert_eq!(store.max_region_id().await.unwrap(), 4);
    assert_eq!(store.robot_tokens().await.unwrap(), vec![(robot.id, "0".repeat(64))]);
    assert_eq!(store.bids(robot.id).await.unwrap().len(), 1);
    let missions = store.missions().await.unwrap();
    assert_eq!(store.robots(&missions[0]).await.unwrap(), vec![robot.clone()]);
    let patches = store.stored_map(&missions[0], None).await.unwrap().patches;
    assert_eq!(patches.len(), 1);
    assert_eq!(patches[0].seq, 5);
    assert_eq!(patches[0].patch.rect(), rect);
    assert_eq!(patches[0].patch.log_odds()[0], patch.log_odds()[0]);
    assert!(patches[0].patch.log_odds()[1].is_nan());
    assert!(store.open_tasks(mission.id).await.unwrap().is_empty());
    let tasks =
        store.tasks(TaskFilter { robot_id: Some(robot.id), ..TaskFilter::mission(mission.id, 10) }).await.unwrap();
    assert_eq!(tasks.len(), 1);
    assert_eq!(tasks[0].state, TaskState::Reached);
    assert_eq!(
        (tasks[0].kind, tasks[0].created_by.as_str(), tasks[0].note.as_str()),
        (TaskKind::Goto, "operator:ana", "check the lab")
    );
    assert_eq!(tasks[0].transitions.len(), 2);
    assert_eq!(tasks[0].transitions[0].by, "ana");
    assert_eq!(tasks[0].transitions[1].actor, Actor::Robot);
    let filter = TaskFilter { kind: Some(TaskKind::Explore), ..TaskFilter::mission(mission.id, 10) };
    assert!(store.tasks(filter).await.unwrap().is_empty());
    let filter = TaskFilter { open_only: true, ..TaskFilter::mission(mission.id, 10) };
    assert!(store.tasks(filter).await.unwrap().is_empty());
    assert_eq!(tasks[0].gain_region, Some(CellRect::new(1, 2, 3, 4)));
    assert_eq!(missions[0].spec.policy.name(), "minpos");
    let events = store.events(mission.id, 0, u32::MAX).await.unwrap();
    assert_eq!(events.len(), 1);
    assert_eq!((events[0].kind.as_str(), events[0].actor.as_str()), ("policy_changed", "ops"));
    assert_eq!(store.segmentation(mission.id).await.unwrap(), Some(segmentation));
    assert_eq!(store.given_segmentation(mission.id).await.unwrap(), Some(rooms));
    let cleared = Changeset { given_segmentation: Some((mission.id, None)), ..Changeset::default() };
    store.commit(cleared).await.unwrap();
    assert_eq!(store.given_segmentation(mission.id).await.unwrap(), None);
    assert_eq!(store.max_task_id().await.unwrap(), 7);

    // Deleted, beside a mission that stays: hidden at once, its robot's
    // token void, then purged a batch at a time down to its own row.
    let kept = store.create_mission(&spec(), Timestamp(5_000)).await.unwrap();
    let keeper =
        store.create_robot(kept.id, &robot_spec("r1"), &|_| HASH.to_owned(), Timestamp(5_000), None).await.unwrap();
    let kept_patch = LoggedPatch { robot_id: keeper.id, seq: 1, patch: Arc::new(patch.clone()) };
    let kept_event = note(kept.id, 5_000, "stays".into());
    store.commit(Changeset { patches: vec![kept_patch], ..kept_event }).await.unwrap();
    store.commit(Changeset { deleted: Some(mission.id), ..Changeset::default() }).await.unwrap();
    assert_eq!(store.missions().await.unwrap().iter().map(|m| m.id).collect::<Vec<_>>(), vec![kept.id]);
    assert_eq!(store.mission(mission.id).await.unwrap(), None);
    assert_eq!(store.robot_tokens().await.unwrap(), vec![(keeper.id, HASH.to_owned())]);
    assert_eq!(store.unclaimed(Timestamp(6_000), Duration::ZERO).await.unwrap(), vec![kept.id]);
    let a = claimant("a");
    let claim = store.claim(mission.id, &a, Timestamp(6_000), Duration::from_secs(5), Duration::ZERO).await;
    assert_eq!(claim.unwrap(), None, "a deleted mission was claimed");
    let mut batches = 0;
    while store.purge_deleted(1).await.unwrap() {
        batches += 1;
        assert!(batches < 100, "the purge does not end");
    }
    // A patch, a task, an event, then the rest with the robot.
    assert_eq!(batches, 4);
    let deleted = &missions[0];
    assert!(store.robots(deleted).await.unwrap().is_empty());
    assert!(store.stored_map(deleted, None).await.unwrap().patches.is_empty());
    assert!(store.tasks(TaskFilter::mission(mission.id, 10)).await.unwrap().is_empty());
    assert!(store.events(mission.id, 0, u32::MAX).await.unwrap().is_empty());
    assert_eq!(store.segmentation(mission.id).await.unwrap(), None);
    assert!(store.blacklist(mission.id).await.unwrap().is_empty());
    assert!(store.forbidden_regions(mission.id).await.unwrap().is_empty());
    assert!(store.bids(robot.id).await.unwrap().is_empty());
    assert_eq!(store.robots(&kept).await.unwrap(), vec![keeper]);
    assert_eq!(store.stored_map(&kept, None).await.unwrap().patches.len(), 1);
    assert_eq!(store.events(kept.id, 0, u32::MAX).await.unwrap().len(), 1);
    // A fold the compactor made before the deletion leaves nothing behind.
    let late =
        MapSnapshot { mission_id: mission.id, through_patch_id: 1, folded: 1, bytes: vec![1; 64], raw_bytes: 64 };
    store.commit(Changeset { snapshot: Some(late), ..Changeset::default() }).await.unwrap();
    assert!(store.stored_map(deleted, None).await.unwrap().snapshot.is_none());
    // The deleted mission's identities are not given again.
    assert_eq!((store.max_task_id().await.unwrap(), store.max_region_id().await.unwrap()), (7, 4));
    let next = store.create_mission(&spec(), Timestamp(7_000)).await.unwrap();
    assert!(next.id > kept.id, "{} after {}", next.id, kept.id);
}

/// A patch sent as ROS's occupancy bytes is kept as those bytes, and one
/// sent as floats as its log-odds; both read back bit for bit, unknown
/// cells included, and the bytes with them.
async fn patches_come_back_bit_for_bit_whichever_way_they_came(db: TestDb) {
    let store = db.open().await;
    let mission = store.create_mission(&spec(), Timestamp(1_000)).await.unwrap();
    let robot =
        store.create_robot(mission.id, &robot_spec("r1"), &|_| HASH.to_owned(), Timestamp(2_000), None).await.unwrap();
    let rect = CellRect::new(0, 0, 34, 3);
    let bytes: Vec<u8> = (0..=100).chain([255]).collect();
    let floats: Vec<f32> = (0..102).map(|i| (i % 7) as f32 / 7.0).collect();
    let unknown: Vec<bool> = (0..102).map(|i| i % 5 == 0).collect();
    let sent = [
        Patch::from_occupancy_percent(rect, bytes.clone()).unwrap(),
        Patch::from_probabilities(rect, &floats, &unknown).unwrap(),
    ];
    for (seq, patch) in (1..).zip(&sent) {
        let logged = LoggedPatch { robot_id: robot.id, seq, patch: Arc::new(patch.clone()) };
        store.commit(Changeset { patches: vec![logged], ..Changeset::default() }).await.unwrap();
    }
    let read = store.stored_map(&mission, None).await.unwrap().patches;
    assert_eq!(read.len(), 2);
    for (logged, patch) in read.iter().zip(&sent) {
        let bits = |p: &Patch| p.log_odds().iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(logged.patch.rect(), rect);
        assert_eq!(bits(&logged.patch), bits(patch));
        assert_eq!(logged.patch.occupancy_percent(), patch.occupancy_percent());
    }
    assert_eq!(read[0].patch.occupancy_percent(), Some(&bytes[..]));
}

async fn a_failed_changeset_writes_nothing(db: TestDb) {
    let store = db.open().await;
    let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    let robot =
        store.create_robot(mission.id, &robot_spec("r1"), &|_| HASH.to_owned(), Timestamp(1), None).await.unwrap();
    let mut moved = robot.clone();
    moved.last_map_seq = 9;
    // A task for a robot that does not exist violates a foreign key.
    let bad_task = TaskRecord {
        id: 1,
        mission_id: mission.id,
        robot_id: 999,
        kind: TaskKind::Explore,
        target: Point2::origin(),
        state: TaskState::Assigned,
        policy: "burgard".into(),
        utility: 0.0,
        path_cost: 0.0,
        gain_region: None,
        created_by: "policy".into(),
        note: String::new(),
        created_at: Timestamp(1),
        updated_at: Timestamp(1),
        transitions: vec![],
    };
    let result =
        store.commit(Changeset { robots: vec![moved], new_tasks: vec![bad_task], ..Changeset::default() }).await;
    assert!(result.is_err());
    assert_eq!(store.robots(&mission).await.unwrap(), vec![robot]);
}

/// A second store on the same database is refused while the first is open, with
/// the holder named; closing the first lets the next one in.
async fn one_executive_per_database(db: TestDb) {
    let first = db.open().await;
    let err = db.try_open().await.unwrap_err();
    assert!(matches!(err, StoreError::Locked(_)), "{err}");
    assert!(err.to_string().contains(&format!("pid {}", std::process::id())), "{err}");
    first.close().await;
    drop(first);
    db.open().await;
}

/// Changesets that arrive together are written together; one that breaks a
/// constraint fails alone, and every other is durable.
async fn a_group_commit_fails_only_the_bad_changeset(db: TestDb) {
    let store = db.open().await;
    let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    let event = |i: u64| note(mission.id, i as i64, format!("event {i}"));
    // An event of a mission that does not exist breaks a foreign key.
    let bad = note(999, 0, "event 0".into());
    let mut commits = tokio::task::JoinSet::new();
    for i in 0..40 {
        let (store, changes) = (store.clone(), if i == 17 { bad.clone() } else { event(i) });
        commits.spawn(async move { store.commit(changes).await.is_ok() });
    }
    let outcomes = commits.join_all().await;
    assert_eq!(outcomes.iter().filter(|ok| !**ok).count(), 1, "only the bad changeset fails");
    store.close().await;
    let store = db.open().await;
    assert_eq!(store.events(mission.id, 0, u32::MAX).await.unwrap().len(), 39);
}

/// A changeset that follows one the store refused is not written, nor is
/// the one that follows it; changesets of other chains are, queued
/// together with them or after.
async fn what_follows_a_refused_changeset_is_not_written(db: TestDb) {
    let store = db.open().await;
    let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    let event = |i: i64, mission_id: MissionId| note(mission_id, i, format!("event {i}"));
    // Chain a: 1 is written, 2 breaks a foreign key, 3 and 4 follow it.
    // Chain b runs beside it; the empty changeset of chain a writes nothing
    // and passes its place on.
    let a1 = store.submit(event(1, mission.id), None).await.unwrap();
    let b1 = store.submit(event(10, mission.id), None).await.unwrap();
    let a2 = store.submit(event(2, 999), Some(a1.id)).await.unwrap();
    let empty = store.submit(Changeset::default(), Some(a2.id)).await.unwrap();
    assert_eq!(empty.id, a2.id, "an empty changeset stands where its predecessor stands");
    let a3 = store.submit(event(3, mission.id), Some(empty.id)).await.unwrap();
    let b2 = store.submit(event(11, mission.id), Some(b1.id)).await.unwrap();
    let a4 = store.submit(event(4, mission.id), Some(a3.id)).await.unwrap();
    let (a1, a2, a3, a4) = (a1.durable().await, a2.durable().await, a3.durable().await, a4.durable().await);
    assert!(a1.is_ok());
    assert!(matches!(a2, Err(StoreError::Database(_))), "{a2:?}");
    for abandoned in [a3, a4] {
        let Err(StoreError::Abandoned { kind, cause }) = abandoned else { panic!("{abandoned:?}") };
        assert_eq!(kind, FailureKind::Internal, "the kind of the first failure");
        assert!(cause.to_lowercase().contains("foreign key"), "{cause}");
    }
    assert!(b1.durable().await.is_ok() && b2.durable().await.is_ok(), "another chain is unaffected");
    assert!(empty.durable().await.is_ok());
    // A changeset that follows nothing starts afresh.
    store.commit(event(5, mission.id)).await.unwrap();
    store.close().await;
    let store = db.open().await;
    let mut written: Vec<i64> = store.events(mission.id, 0, u32::MAX).await.unwrap().iter().map(|e| e.at.0).collect();
    written.sort_unstable();
    assert_eq!(written, vec![1, 5, 10, 11]);
    // The latest ones, newest first, as the live view reads them.
    let latest: Vec<i64> = store.latest_events(mission.id, 2).await.unwrap().iter().map(|e| e.at.0).collect();
    assert_eq!(latest, vec![5, 11]);
    // Pages after a cursor, as ListEvents reads them, add up to the whole.
    let all: Vec<u64> = store.events(mission.id, 0, u32::MAX).await.unwrap().iter().map(|e| e.id).collect();
    let first: Vec<u64> = store.events(mission.id, 0, 3).await.unwrap().iter().map(|e| e.id).collect();
    let rest: Vec<u64> = store.events(mission.id, first[2], 3).await.unwrap().iter().map(|e| e.id).collect();
    assert_eq!([first, rest].concat(), all);
    assert!(all.is_sorted(), "oldest first");
    assert!(store.events(mission.id, u64::MAX, 3).await.unwrap().is_empty(), "a cursor past every identity");
}

/// The map of a mission's patches (as each robot sent them), applied in order.
fn fused(frame: &GridFrame, patches: &[LoggedPatch]) -> exploration::fusion::MapFusion {
    let mut fusion = exploration::fusion::MapFusion::new(*frame);
    for logged in patches {
        fusion.apply(logged.robot_id, &logged.patch).unwrap();
    }
    fusion
}

/// A fusion's state, bit for bit.
fn bits(fusion: &exploration::fusion::MapFusion) -> (Vec<u8>, Vec<u32>) {
    (fusion.grid().cells().to_vec(), fusion.parts().sum.iter().map(|v| v.to_bits()).collect())
}

/// Folding the log keeps the map exactly as it was, across a restart, and
/// removes the folded patches from the log; a fold older than the stored
/// snapshot changes nothing.
async fn a_folded_patch_log_restores_the_same_map(db: TestDb) {
    let store = db.open().await;
    let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    let frame = mission.spec.frame;
    let mut robots = Vec::new();
    for name in ["r1", "r2", "r3"] {
        robots.push(
            store.create_robot(mission.id, &robot_spec(name), &|_| HASH.to_owned(), Timestamp(1), None).await.unwrap(),
        );
    }
    // Overlapping patches whose values change, so that the sums depend on
    // the order they were added in.
    let mut rng = exploration::rng::SplitMix64::new(11);
    let mut sent = Vec::new();
    let mut log = |store: &Arc<dyn Store>, seq: u64, sent: &mut Vec<LoggedPatch>| {
        let robot = robots[rng.below(3) as usize].id;
        let (x, y) = (rng.below(30) as i32, rng.below(20) as i32);
        let rect = CellRect::new(x, y, 10, 10);
        let values: Vec<f32> = (0..100).map(|_| rng.below(1000) as f32 / 999.0).collect();
        let unknown: Vec<bool> = (0..100).map(|_| rng.below(5) == 0).collect();
        let patch = Patch::from_probabilities(rect, &values, &unknown).unwrap();
        let logged = LoggedPatch { robot_id: robot, seq, patch: Arc::new(patch) };
        sent.push(logged.clone());
        let store = store.clone();
        async move { store.commit(Changeset { patches: vec![logged], ..Changeset::default() }).await.unwrap() }
    };
    for seq in 1..=30 {
        log(&store, seq, &mut sent).await;
    }
    assert_eq!(compact::fold(&*store, &mission, 20).await.unwrap(), 20);
    assert_eq!(store.unfolded_patches(mission.id).await.unwrap(), 10);
    assert_eq!(store.folded_patches(mission.id).await.unwrap(), 20, "still in the file, never read again");
    let stored = store.stored_map(&mission, None).await.unwrap();
    assert_eq!(stored.snapshot.as_ref().map(|s| s.folded), Some(20));
    let names = |patches: &[LoggedPatch]| patches.iter().map(|p| (p.robot_id, p.seq)).collect::<Vec<_>>();
    assert_eq!(names(&stored.patches), names(&sent[20..]));
    assert_eq!(bits(&stored.fuse(&frame, 3).unwrap()), bits(&fused(&frame, &sent)));

    // Folded again, with patches logged after: still the same map.
    assert_eq!(compact::fold(&*store, &mission, 20).await.unwrap(), 10);
    assert_eq!(store.unfolded_patches(mission.id).await.unwrap(), 0);
    let never = tokio_util::sync::CancellationToken::new();
    assert_eq!(compact::forget(&*store, mission.id, Duration::ZERO, &never).await.unwrap(), 1);
    assert_eq!(store.folded_patches(mission.id).await.unwrap(), 0, "the folded patches are gone");
    for seq in 31..=35 {
        log(&store, seq, &mut sent).await;
    }
    let newer = store.stored_map(&mission, None).await.unwrap();
    assert_eq!(newer.snapshot.as_ref().map(|s| s.folded), Some(30));
    assert_eq!(bits(&newer.fuse(&frame, 3).unwrap()), bits(&fused(&frame, &sent)));

    // A stale fold (through an earlier patch) neither replaces the snapshot
    // nor removes anything.
    let stale = MapSnapshot { through_patch_id: 1, folded: 1, ..stored.snapshot.clone().unwrap() };
    store.commit(Changeset { snapshot: Some(stale), ..Changeset::default() }).await.unwrap();
    let after_stale = store.stored_map(&mission, None).await.unwrap();
    assert_eq!(after_stale.snapshot, newer.snapshot);
    assert_eq!(after_stale.patches.len(), 5);
    assert_eq!(compact::forget(&*store, mission.id, Duration::ZERO, &never).await.unwrap(), 0);
    assert_eq!(store.unfolded_patches(mission.id).await.unwrap(), 5, "forgetting never removes an unfolded patch");

    store.close().await;
    drop(store);
    let reopened = db.open().await;
    let missions = reopened.missions().await.unwrap();
    let restarted = reopened.stored_map(&missions[0], None).await.unwrap();
    assert_eq!(bits(&restarted.fuse(&frame, 3).unwrap()), bits(&fused(&frame, &sent)));
}

/// A mission's lease goes to one replica at a time; another may claim it
/// only once it ran out (and the grace passed), with the next fencing
/// token; from then on the old holder can write nothing for the mission,
/// however its changeset comes, while changesets of other missions in the
/// same group are written.
/// A replica's new mission is stored with its lease: token 1, held by its
/// creator, never listed as unclaimed, and not claimable by another.
async fn a_mission_created_with_its_lease_is_never_unclaimed(db: TestDb) {
    let store = db.open().await;
    let (a, b) = (claimant("a"), claimant("b"));
    let period = Duration::from_secs(5);
    let (mission, lease) = store.create_claimed_mission(&spec(), Timestamp(1_000), &a, period).await.unwrap();
    assert_eq!(mission.spec, spec());
    assert_eq!(
        (lease.mission_id, lease.owner.as_str(), lease.address.as_str(), lease.token, lease.expires_at),
        (mission.id, "a", "http://a:1", 1, Timestamp(6_000))
    );
    assert_eq!(store.lease(mission.id).await.unwrap(), Some(lease));
    assert!(store.unclaimed(Timestamp(1_000), Duration::ZERO).await.unwrap().is_empty());
    assert_eq!(store.claim(mission.id, &b, Timestamp(2_000), period, Duration::ZERO).await.unwrap(), None);
    assert_eq!(store.missions().await.unwrap(), vec![mission]);
}

async fn a_lease_passes_on_only_once_it_ran_out_and_fences_its_old_holder(db: TestDb) {
    let store = db.open().await;
    let mission = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    let other = store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    let (a, b) = (claimant("a"), claimant("b"));
    let (period, grace) = (Duration::from_secs(5), Duration::from_secs(1));
    assert_eq!(store.unclaimed(Timestamp(1_000), grace).await.unwrap(), vec![mission.id, other.id]);
    let first = store.claim(mission.id, &a, Timestamp(1_000), period, grace).await.unwrap().unwrap();
    assert_eq!((first.owner.as_str(), first.token, first.expires_at), ("a", 1, Timestamp(6_000)));
    assert_eq!(store.claim(mission.id, &b, Timestamp(6_500), period, grace).await.unwrap(), None, "within the grace");
    let fence_a = Fence { mission_id: mission.id, token: 1 };
    assert_eq!(store.renew(&[fence_a], Timestamp(5_000), period).await.unwrap(), vec![mission.id]);
    assert_eq!(store.claim(mission.id, &b, Timestamp(10_500), period, grace).await.unwrap(), None, "renewed");
    assert_eq!(store.unclaimed(Timestamp(10_500), grace).await.unwrap(), vec![other.id]);
    let taken = store.claim(mission.id, &b, Timestamp(11_001), period, grace).await.unwrap().unwrap();
    assert_eq!((taken.owner.as_str(), taken.address.as_str(), taken.token), ("b", "http://b:1", 2));
    assert_eq!(store.lease(mission.id).await.unwrap(), Some(taken.clone()));

    // The old holder: its renewal fails, its writes are refused whole.
    assert_eq!(store.renew(&[fence_a], Timestamp(11_100), period).await.unwrap(), Vec::<MissionId>::new());
    let fenced =
        |fence: Fence, detail: &str| Changeset { fence: Some(fence), ..note(fence.mission_id, 2, detail.into()) };
    let err = store.commit(fenced(fence_a, "stale")).await.unwrap_err();
    assert!(matches!(err, StoreError::Fenced { mission_id } if mission_id == mission.id), "{err}");
    assert_eq!(err.kind(), FailureKind::Fenced);
    let err = store
        .create_robot(mission.id, &robot_spec("late"), &|_| HASH.to_owned(), Timestamp(2), Some(fence_a))
        .await
        .unwrap_err();
    assert!(matches!(err, StoreError::Fenced { .. }), "{err}");
    assert!(store.robots(&mission).await.unwrap().is_empty(), "no robot registered by the old holder");
    // In one group with another mission's changeset: only the stale one fails.
    let fence_other = Fence {
        mission_id: other.id,
        token: store.claim(other.id, &a, Timestamp(11_100), period, grace).await.unwrap().unwrap().token,
    };
    let stale = store.submit(fenced(fence_a, "stale again"), None).await.unwrap();
    let fresh = store.submit(fenced(fence_other, "fresh"), None).await.unwrap();
    assert!(matches!(stale.durable().await, Err(StoreError::Fenced { .. })));
    fresh.durable().await.unwrap();
    // The new holder writes.
    store.commit(fenced(Fence { mission_id: mission.id, token: 2 }, "new holder")).await.unwrap();
    let details: Vec<String> = store.events(mission.id, 0, 10).await.unwrap().into_iter().map(|e| e.detail).collect();
    assert_eq!(details, vec!["new holder".to_owned()]);
    assert_eq!(store.events(other.id, 0, 10).await.unwrap().len(), 1);

    // A holder that restarts claims its own mission back at once, with a
    // new token that fences its former self; a released lease is anyone's.
    let again = store.claim(mission.id, &b, Timestamp(11_200), period, grace).await.unwrap().unwrap();
    assert_eq!(again.token, 3);
    store.release(Fence { mission_id: mission.id, token: 3 }).await.unwrap();
    assert_eq!(store.claim(mission.id, &a, Timestamp(11_300), period, grace).await.unwrap().map(|l| l.token), Some(4));
    // Identity blocks never repeat.
    let blocks = [
        store.reserve_id_block("a", Timestamp(1)).await.unwrap(),
        store.reserve_id_block("b", Timestamp(1)).await.unwrap(),
    ];
    assert!(blocks[0] >= 1 && blocks[1] > blocks[0], "{blocks:?}");
}

/// A replica's announcement counts it alive until it runs out or is
/// withdrawn; every mission counts towards the share, held or not.
async fn replicas_are_counted_while_their_announcements_last(db: TestDb) {
    let store = db.open().await;
    let (a, b) = (claimant("a"), claimant("b"));
    let period = Duration::from_secs(5);
    let alone = store.announce(&a, Timestamp(1_000), period).await.unwrap();
    assert_eq!(alone, Share { replicas: 1, missions: 0 });
    for _ in 0..5 {
        store.create_mission(&spec(), Timestamp(1)).await.unwrap();
    }
    let both = store.announce(&b, Timestamp(2_000), period).await.unwrap();
    assert_eq!(both, Share { replicas: 2, missions: 5 });
    assert_eq!(both.fair(), 3);
    // a's announcement ran out at 6 000: b is alone, and takes everything.
    let later = store.announce(&b, Timestamp(6_000), period).await.unwrap();
    assert_eq!((later.replicas, later.fair()), (1, 5));
    // Renewed, then withdrawn (a replica that stops).
    assert_eq!(store.announce(&a, Timestamp(6_500), period).await.unwrap().replicas, 2);
    assert_eq!(store.announce(&a, Timestamp(6_600), Duration::ZERO).await.unwrap().replicas, 1);
    assert_eq!(store.announce(&b, Timestamp(6_700), period).await.unwrap().replicas, 1);
}
