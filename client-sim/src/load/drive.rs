//! What each robot does during the real-rate phase: drive towards its
//! target, send heartbeats and map patches when due (open-loop), and note
//! when an arrival is answered by its next task.

use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::watch;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use tonic::Code;

use exploration::math::Point2;
use exploration_proto::client::retry_pushback;
use exploration_proto::v1 as pb;

use super::report::{Recorder, TRIGGER_GRACE, Triggers};
use super::{Fleet, LoadConfig, Robot, footprint, pose_at};
use crate::world::World;

/// Keeps a robot's newest assignment from its stream, reconnecting.
pub(super) async fn follow(
    mut client: Fleet,
    robot_id: u64,
    tx: watch::Sender<Option<(pb::Assignment, Instant)>>,
    stop: CancellationToken,
) {
    loop {
        let answer = tokio::select! {
            () = stop.cancelled() => return,
            answer = client.watch_assignment(pb::WatchAssignmentRequest { robot_id }) => answer,
        };
        if let Ok(answer) = answer {
            let mut stream = answer.into_inner();
            loop {
                let message = tokio::select! {
                    () = stop.cancelled() => return,
                    message = stream.message() => message,
                };
                let Ok(Some(assignment)) = message else { break };
                let arrived = Instant::now();
                tx.send_if_modified(|now| {
                    let newer = now.as_ref().is_none_or(|(a, _)| assignment.version > a.version);
                    if newer {
                        *now = Some((assignment, arrived));
                    }
                    newer
                });
            }
        }
        tokio::select! {
            () = stop.cancelled() => return,
            () = tokio::time::sleep(Duration::from_millis(200)) => {}
        }
    }
}

/// Until when the executive asked a robot to hold one kind of call (the
/// retry hint of a refusal), shared by the robot and its calls in flight.
#[derive(Debug, Default)]
struct Hold(Mutex<Option<Instant>>);

impl Hold {
    /// Whether a call due at `due` must wait.
    fn holds(&self, due: Instant) -> bool {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).is_some_and(|until| due < until)
    }

    /// After `status` answered a call at `now`: hold until its hint, if it
    /// has one, has passed.
    fn after(&self, status: &tonic::Status, now: Instant) {
        if let Some(wait) = retry_pushback(status) {
            let mut until = self.0.lock().unwrap_or_else(|e| e.into_inner());
            *until = Some(until.map_or(now + wait, |u| u.max(now + wait)));
        }
    }
}

/// Map patches held back at most, the newest kept: a hint holds at most
/// 10 s, ten patches at the real rate.
const HELD_PATCHES: usize = 64;

/// Where a robot was at the map updates it held or had refused with a
/// hint: their footprints go with its next update, as a robot would send
/// what it saw meanwhile.
#[derive(Debug, Default)]
struct Unsent(Mutex<Vec<Point2>>);

impl Unsent {
    fn push(&self, at: Point2) {
        let mut unsent = self.0.lock().unwrap_or_else(|e| e.into_inner());
        if unsent.len() == HELD_PATCHES {
            unsent.remove(0);
        }
        unsent.push(at);
    }

    fn take(&self) -> Vec<Point2> {
        std::mem::take(&mut *self.0.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// Drives one robot until `until`: moves it, and sends its heartbeats and
/// map updates when they are due, each on its own task (open-loop).
pub(super) async fn drive(
    robot: Arc<Robot>,
    start: Point2,
    world: Arc<World>,
    config: LoadConfig,
    recorder: Arc<Recorder>,
    triggers: Arc<Mutex<Triggers>>,
    until: Instant,
) {
    let frame = world.frame;
    let heartbeat_every = Duration::from_secs_f64(1.0 / config.heartbeat_hz.max(1e-3));
    let map_every = Duration::from_secs_f64(1.0 / config.map_hz.max(1e-3));
    // Robots start out of phase, as real ones would.
    let offset = Duration::from_secs_f64((robot.id % 97) as f64 / 97.0 * heartbeat_every.as_secs_f64());
    let origin = Instant::now() + offset;
    let (mut next_heartbeat, mut next_map) = (origin, origin);
    let mut position = start;
    let mut heading = 0.0;
    let mut last_move = origin;
    // The task reached and when, until the next one arrives.
    let mut waiting: Option<(u64, Instant)> = None;
    let mut reported = None;
    let mut seen_completed = false;
    let mut requests = JoinSet::new();
    let mut assignment = robot.assignment.clone();
    let mut stream_followed = true;
    let (heartbeat_hold, map_hold) = (Arc::new(Hold::default()), Arc::new(Hold::default()));
    let unsent = Arc::new(Unsent::default());
    // An arrival whose heartbeat was not answered: reported again.
    let lost_arrival: Arc<Mutex<Option<u64>>> = Arc::default();
    loop {
        let due = next_heartbeat.min(next_map);
        if due >= until {
            break;
        }
        // Each assignment is looked at as it arrives: an arrival is answered
        // by the first next task, which a later plan may replace before the
        // robot's next call (at a tenth of the real rates, 5 s later).
        let assigned = tokio::select! {
            () = tokio::time::sleep_until(due.into()) => false,
            changed = assignment.changed(), if stream_followed => {
                stream_followed = changed.is_ok();
                true
            }
        };
        let current = assignment.borrow_and_update().clone();
        let target = current.as_ref().filter(|(a, _)| a.task_id != 0).and_then(|(a, _)| Some((a.task_id, a.target?)));
        let explores = current.as_ref().is_some_and(|(a, _)| {
            matches!(pb::TaskKind::try_from(a.kind), Ok(pb::TaskKind::Explore | pb::TaskKind::Pin | pb::TaskKind::Goto))
        });
        if let Some((a, arrived)) = &current {
            if !seen_completed && a.mission_state == pb::MissionState::Completed as i32 {
                seen_completed = true;
                let mut triggers = triggers.lock().unwrap_or_else(|e| e.into_inner());
                triggers.completed.entry(robot.mission).or_insert(*arrived);
            }
            // The answer to an arrival: the next task, or the mission's end.
            if let Some((task, reported)) = waiting {
                if explores && a.task_id != task {
                    let delay = arrived.saturating_duration_since(reported).max(Duration::from_micros(1));
                    let mut triggers = triggers.lock().unwrap_or_else(|e| e.into_inner());
                    triggers.answer(delay, reported, robot.mission, robot.id);
                    waiting = None;
                } else if a.mission_state == pb::MissionState::Completed as i32 {
                    triggers.lock().unwrap_or_else(|e| e.into_inner()).ended_by_completion += 1;
                    waiting = None;
                }
            }
        }
        if assigned {
            continue;
        }
        // Move towards the target at the robot's speed.
        let now = Instant::now();
        let dt = now.duration_since(last_move).as_secs_f64();
        last_move = now;
        let lost = lost_arrival.lock().unwrap_or_else(|e| e.into_inner()).take();
        if lost.is_some() && lost == reported {
            reported = None;
        }
        let mut arrived = None;
        if let Some((task, goal)) = target {
            let goal = Point2::new(goal.x, goal.y);
            let to_goal = goal - position;
            let step = config.speed_mps * dt;
            if to_goal.norm() <= step.max(frame.resolution) {
                position = goal;
                if reported != Some(task) {
                    arrived = Some(task);
                }
            } else {
                heading = to_goal.y.atan2(to_goal.x);
                position += to_goal * (step / to_goal.norm());
            }
        }
        if due == next_heartbeat {
            next_heartbeat += heartbeat_every;
            if config.honour_pushback && heartbeat_hold.holds(due) {
                recorder.held("Heartbeat");
                continue;
            }
            let (state, task_id) = match (arrived, target) {
                (Some(task), _) => (pb::RobotState::Arrived, task),
                (None, Some((task, _))) => (pb::RobotState::Moving, task),
                (None, None) => (pb::RobotState::Idle, 0),
            };
            if let Some(task) = arrived {
                reported = Some(task);
                // Arriving home or at a hold ends nothing the executive must
                // answer; an arrival reported again waits from the first report.
                if explores && waiting.is_none_or(|(t, _)| t != task) {
                    waiting = Some((task, due));
                }
            }
            let request = pb::HeartbeatRequest {
                robot_id: robot.id,
                pose: Some(pose_at(position, heading)),
                state: state as i32,
                task_id,
                ..Default::default()
            };
            let (mut client, recorder, hold) =
                (robot.client.clone(), Arc::clone(&recorder), Arc::clone(&heartbeat_hold));
            let lost_arrival = Arc::clone(&lost_arrival);
            requests.spawn(async move {
                let code = match client.heartbeat(request).await {
                    Ok(_) => Code::Ok,
                    Err(status) => {
                        hold.after(&status, Instant::now());
                        if state == pb::RobotState::Arrived {
                            *lost_arrival.lock().unwrap_or_else(|e| e.into_inner()) = Some(task_id);
                        }
                        status.code()
                    }
                };
                recorder.record("Heartbeat", due, code);
            });
        } else {
            next_map += map_every;
            if config.honour_pushback && map_hold.holds(due) {
                recorder.held("UpdateMap");
                unsent.push(position);
                continue;
            }
            let seq = robot.next_seq.fetch_add(1, Ordering::AcqRel);
            let patches = unsent
                .take()
                .into_iter()
                .chain([position])
                .map(|at| footprint(&world, at, config.sensor_range_m, config.cell_encoding))
                .collect();
            let request = pb::UpdateMapRequest {
                robot_id: robot.id,
                seq,
                pose: Some(pose_at(position, heading)),
                patches,
                ..Default::default()
            };
            let (robot, recorder, hold) = (Arc::clone(&robot), Arc::clone(&recorder), Arc::clone(&map_hold));
            let (unsent, honour) = (Arc::clone(&unsent), config.honour_pushback);
            requests.spawn(async move {
                let code = match robot.client.clone().update_map(request).await {
                    Ok(_) => {
                        robot.acked.fetch_add(1, Ordering::AcqRel);
                        robot.acked_seq.fetch_max(seq, Ordering::AcqRel);
                        Code::Ok
                    }
                    Err(status) => {
                        if honour && retry_pushback(&status).is_some() {
                            hold.after(&status, Instant::now());
                            unsent.push(position);
                        }
                        status.code()
                    }
                };
                recorder.record("UpdateMap", due, code);
            });
        }
        // Answered requests are collected as they come.
        while requests.try_join_next().is_some() {}
    }
    while requests.join_next().await.is_some() {}
    if let Some((_, reported)) = waiting {
        let mut triggers = triggers.lock().unwrap_or_else(|e| e.into_inner());
        if reported + TRIGGER_GRACE >= until {
            triggers.pending += 1;
        } else {
            triggers.unanswered += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn refused_for(ms: &str) -> tonic::Status {
        let mut status = tonic::Status::resource_exhausted("busy");
        status.metadata_mut().insert(exploration_proto::client::RETRY_PUSHBACK_METADATA, ms.parse().unwrap());
        status
    }

    #[test]
    fn a_hint_holds_calls_until_it_has_passed_and_the_longer_of_two_wins() {
        let hold = Hold::default();
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        assert!(!hold.holds(t0), "nothing is held before a refusal");
        hold.after(&tonic::Status::resource_exhausted("no hint"), t0);
        assert!(!hold.holds(t0), "a refusal without a hint holds nothing");
        hold.after(&refused_for("1000"), t0);
        assert!(hold.holds(t0 + ms(999)));
        assert!(!hold.holds(t0 + ms(1000)), "held until the hint, not beyond");
        // A shorter hint answered later does not shorten the hold.
        hold.after(&refused_for("100"), t0 + ms(500));
        assert!(hold.holds(t0 + ms(999)));
        hold.after(&refused_for("1000"), t0 + ms(500));
        assert!(hold.holds(t0 + ms(1499)) && !hold.holds(t0 + ms(1500)));
    }

    #[test]
    fn unsent_patches_are_kept_newest_first_up_to_the_cap() {
        let unsent = Unsent::default();
        for k in 0..HELD_PATCHES + 3 {
            unsent.push(Point2::new(k as f64, 0.0));
        }
        let kept = unsent.take();
        assert_eq!(kept.len(), HELD_PATCHES);
        assert_eq!(kept[0].x, 3.0, "the oldest go first");
        assert_eq!(kept[HELD_PATCHES - 1].x, (HELD_PATCHES + 2) as f64);
        assert!(unsent.take().is_empty(), "taken once");
    }
}
