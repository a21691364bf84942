//! The planner: where and when plans are made.
//!
//! A map update, a heartbeat or bids are committed, applied and answered at
//! once, at a cost that grows with the request, not the map. When they make
//! a replanning due, the mission's planner task is woken. It coalesces
//! wake-ups (every trigger that arrives while a plan is made is served by
//! the next one), takes a snapshot under the mission's lock, makes the plan
//! off the lock on the planning threads (missions in parallel, up to the
//! background budget: one core fewer than all by default, so that requests
//! keep a core while every mission plans; plans a robot waits for take
//! the turns first, see `turns`), and commits it only while it
//! still fits the mission: if something that demands a new plan happened meanwhile (a task
//! ended, a robot joined or left, the policy changed), it plans again. A
//! plan is committed as a map update is: queued and applied under the
//! lock, which is released while the disk works; the robots are told their
//! new tasks once it is durable.
//!
//! A mission in lockstep (simulations) is planned inside the request that
//! made the plan due, under the mission's lock, so that the same requests in
//! the same order give the same plans.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};

use prometheus_client::metrics::gauge::Gauge;
use tokio::sync::{Mutex, MutexGuard, Notify};
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

use super::mission::{JobOutcome, Mission, PlanBasis};
use super::writer::{Queued, Writer};
use crate::clock::Clock;
use crate::domain::Timestamp;
use crate::error::Error;
use crate::metrics::Metrics;

mod budget;
mod turns;

use budget::PlannerBudget;
use exploration::workers::{Pace, Unpaced};
use turns::{Turn, Turns};

/// How many times a plan that no longer fits is made again before the
/// planner waits for the next trigger (a mission whose team changes faster
/// than it can be planned is planned at the rate it can be).
const ATTEMPTS: usize = 3;

/// One mission as the executive holds it: its state behind a lock, and the
/// wake-up of its planner.
#[derive(Debug)]
pub(crate) struct MissionCell {
    state: Mutex<Mission>,
    wake: Notify,
    /// Requests waiting for the lock, to bound the work queued per mission.
    queued: AtomicUsize,
    /// Whether a robot waits for the next plan (a demand: a task ended, a
    /// robot joined, ...), as of the last change: such plans take the
    /// planning turns first.
    demanded: Arc<AtomicBool>,
    /// Its grid's cells, counted against the executive's limit.
    cells: u64,
    /// Cancelled when this executive no longer acts for the mission
    /// (another replica took it): its planner stops.
    retired: tokio_util::sync::CancellationToken,
}

impl MissionCell {
    pub(crate) fn new(mission: Mission) -> Self {
        let cells = mission.record().spec.frame.len() as u64;
        Self {
            state: Mutex::new(mission),
            wake: Notify::new(),
            queued: AtomicUsize::new(0),
            demanded: Arc::new(AtomicBool::new(false)),
            cells,
            retired: tokio_util::sync::CancellationToken::new(),
        }
    }

    /// Its grid's cells.
    pub(crate) fn cells(&self) -> u64 {
        self.cells
    }

    /// This executive no longer acts for the mission.
    pub(crate) fn retire(&self) {
        self.retired.cancel();
    }

    /// The mission, for reading or for work that is not a robot's request.
    pub(crate) async fn lock(&self) -> MutexGuard<'_, Mission> {
        self.state.lock().await
    }

    /// The mission, for a request, unless `limit` requests already wait for
    /// it: then the request is refused at once instead of queueing without
    /// bound.
    pub(crate) async fn lock_for_request(&self, limit: usize) -> Result<MutexGuard<'_, Mission>, Error> {
        let waiting = self.queued.fetch_add(1, Ordering::AcqRel);
        if waiting >= limit {
            self.queued.fetch_sub(1, Ordering::AcqRel);
            return Err(Error::Overloaded(format!(
                "{waiting} requests already wait for this mission; retry after a short pause"
            )));
        }
        let guard = self.state.lock().await;
        self.queued.fetch_sub(1, Ordering::AcqRel);
        Ok(guard)
    }
}

/// A job for the planning threads.
type Job = Box<dyn FnOnce() + Send>;

/// What holds the planning threads back: a CPU budget, or nothing.
pub(crate) type SharedPace = Arc<dyn Pace + Send + Sync>;

/// How the planner plans.
#[derive(Debug, Clone, Default)]
pub(crate) struct PlannerSettings {
    /// Threads one plan may use.
    pub(crate) threads: usize,
    /// Plans made off the request path at once (see [`background_budget`]).
    pub(crate) background: usize,
    /// Least time between two plans of a mission for map news alone.
    pub(crate) min_gap: std::time::Duration,
    /// CPU the planning threads may use on average, in cores.
    pub(crate) cpu: Option<f64>,
}

impl From<&super::ExecutiveSettings> for PlannerSettings {
    fn from(s: &super::ExecutiveSettings) -> Self {
        Self {
            threads: s.planner_threads,
            background: s.background_planner_threads,
            min_gap: s.min_plan_interval,
            cpu: s.planner_cpu,
        }
    }
}

/// The threads plans run on, at the lowest scheduling priority: on a busy
/// machine the request path (the async workers, the store) goes first, and
/// plans take what is left.
#[derive(Debug)]
struct PlanThreads {
    jobs: std::sync::Mutex<std::sync::mpsc::Sender<Job>>,
}

impl PlanThreads {
    /// `threads` threads, each charging `pace` after each job (the part of
    /// a plan outside its parallel pieces).
    fn start(threads: usize, pace: &SharedPace) -> Self {
        let (jobs, queue) = std::sync::mpsc::channel::<Job>();
        let queue = Arc::new(std::sync::Mutex::new(queue));
        for k in 0..threads {
            let queue = Arc::clone(&queue);
            let pace = Arc::clone(pace);
            let spawned = std::thread::Builder::new().name(format!("planner-{k}")).spawn(move || {
                // Not allowed to lower itself (a sandbox): it plans at normal priority.
                if let Err(e) = thread_priority::set_current_thread_priority(thread_priority::ThreadPriority::Min) {
                    tracing::debug!(error = ?e, "planner thread keeps its priority");
                }
                loop {
                    let job = queue.lock().unwrap_or_else(|e| e.into_inner()).recv();
                    let Ok(job) = job else { return };
                    job();
                    pace.piece_done();
                }
            });
            if let Err(e) = spawned {
                tracing::error!(error = %e, "cannot start a planner thread");
            }
        }
        Self { jobs: std::sync::Mutex::new(jobs) }
    }

    /// Runs `work` on a planning thread.
    async fn run<T: Send + 'static>(&self, work: impl FnOnce() -> T + Send + 'static) -> Result<T, Error> {
        let (answer, outcome) = tokio::sync::oneshot::channel();
        let job: Job = Box::new(move || {
            let _ = answer.send(work());
        });
        let sent = self.jobs.lock().unwrap_or_else(|e| e.into_inner()).send(job);
        sent.map_err(|_| Error::Internal("the planner threads are gone".to_owned()))?;
        outcome.await.map_err(|_| Error::Internal("a planning job failed".to_owned()))
    }
}

/// Makes the plans of every mission.
#[derive(Debug)]
pub(crate) struct Planner {
    threads_pool: PlanThreads,
    /// Handed to every plan's searches.
    pace: SharedPace,
    writer: Writer,
    clock: Clock,
    /// Threads one plan may use.
    threads: usize,
    /// Plans made off the request path at once, and the threads one of
    /// them may use when it is the only one.
    background: usize,
    /// One turn per plan made off the request path at once, demanded
    /// plans first.
    turns: Turns,
    /// Plans being made now.
    running: AtomicUsize,
    task_ids: Arc<AtomicU64>,
    metrics: Arc<Metrics>,
    /// Least time between two plans of a mission for map news alone.
    min_gap: std::time::Duration,
    stop: CancellationToken,
    tasks: std::sync::Mutex<JoinSet<()>>,
}

impl Planner {
    pub(crate) fn new(
        writer: Writer,
        clock: Clock,
        settings: PlannerSettings,
        task_ids: Arc<AtomicU64>,
        metrics: Arc<Metrics>,
    ) -> Arc<Self> {
        let PlannerSettings { threads, background, min_gap, cpu } = settings;
        let background = background_budget(threads, background);
        let pace = pace_for(cpu, &metrics);
        Arc::new(Self {
            threads_pool: PlanThreads::start(threads.max(1), &pace),
            pace,
            writer,
            turns: Turns::new(background, clock.clone()),
            clock,
            threads: threads.max(1),
            background,
            running: AtomicUsize::new(0),
            task_ids,
            metrics,
            min_gap,
            stop: CancellationToken::new(),
            tasks: std::sync::Mutex::new(JoinSet::new()),
        })
    }

    /// Starts the planner task of a mission; it plans whenever woken.
    pub(crate) fn start(self: &Arc<Self>, cell: Arc<MissionCell>) {
        let planner = Arc::clone(self);
        let mut tasks = self.tasks.lock().unwrap_or_else(|e| e.into_inner());
        tasks.spawn(async move {
            loop {
                tokio::select! {
                    () = planner.stop.cancelled() => return,
                    () = cell.retired.cancelled() => return,
                    () = cell.wake.notified() => {}
                }
                planner.plan_off_path(&cell).await;
            }
        });
    }

    /// Stops every planner task and waits for them (plans being committed
    /// finish first).
    pub(crate) async fn shutdown(&self) {
        self.stop.cancel();
        let mut tasks = std::mem::take(&mut *self.tasks.lock().unwrap_or_else(|e| e.into_inner()));
        while let Some(done) = tasks.join_next().await {
            if let Err(e) = done
                && e.is_panic()
            {
                tracing::error!(error = %e, "a planner task panicked");
            }
        }
    }

    /// After a change was applied to `mission`: plans now when it is in
    /// lockstep, otherwise wakes its planner if a plan is due.
    pub(crate) async fn after_change(&self, cell: &MissionCell, mission: &mut Mission) {
        cell.demanded.store(mission.plan_demanded(), Ordering::Release);
        if mission.record().spec.lockstep {
            self.plan_inline(mission).await;
        } else if mission.replan_failed() || mission.replan_reason_off_path(self.clock.now(), self.min_gap).is_some() {
            self.metrics.planner_triggers.inc();
            cell.wake.notify_one();
        }
    }

    /// Plans `mission` now, under its lock. A plan that cannot be committed
    /// (a full disk) is logged and stays due.
    pub(crate) async fn plan_inline(&self, mission: &mut Mission) {
        if let Err(e) = self.plan_locked(mission).await {
            tracing::error!(mission = mission.record().id, error = %e, "replanning failed; it stays due");
            mission.note_replan_failed();
        }
    }

    async fn plan_locked(&self, mission: &mut Mission) -> Result<(), Error> {
        let now = self.clock.now();
        let Some(reason) = mission.replan_reason(now) else {
            return Ok(());
        };
        let basis = mission.plan_basis();
        let job = mission.planning_job(self.threads).paced_by(Arc::clone(&self.pace));
        let started = std::time::Instant::now();
        let outcome = self.threads_pool.run(move || job.run()).await?;
        self.metrics.observe_plan(mission.record().spec.policy.name(), started.elapsed());
        self.commit_plan(mission, &MadePlan { outcome: &outcome, reason: &reason, now, basis: &basis }).await
    }

    /// Commits a plan under the mission's lock: written, then applied.
    async fn commit_plan(&self, mission: &mut Mission, plan: &MadePlan<'_>) -> Result<(), Error> {
        let changes = mission.prepare_plan(plan.outcome, plan.reason, Timestamp::now(), &self.task_ids);
        let changes = self.writer.write(mission, changes).await?;
        let reassigned = changes.new_tasks.len();
        let demands = mission.demands();
        mission.apply(changes);
        plan.mark_committed(mission, demands, reassigned);
        Ok(())
    }

    /// Queues a plan and applies it at once, as a map update is (see
    /// `writer`): the mission is released while the disk works, and the
    /// robots are told their new tasks once the plan is durable
    /// ([`Writer::durable`]). Written under the lock, a plan held every
    /// request of its mission behind the disk: in a stall of the disk, fifty
    /// robots' calls filled the mission's queue and were shed.
    async fn queue_plan(&self, mission: &mut Mission, plan: &MadePlan<'_>) -> Result<Queued, Error> {
        let changes = mission.prepare_plan(plan.outcome, plan.reason, Timestamp::now(), &self.task_ids);
        let reassigned = changes.new_tasks.len();
        let demands = mission.demands();
        let queued = self.writer.queue_and_apply(mission, changes).await?;
        plan.mark_committed(mission, demands, reassigned);
        Ok(queued)
    }

    /// A planning turn, counted in `planner_busy` while it is waited for and
    /// while it is held.
    async fn take_turn(&self, cell: &MissionCell) -> Option<Busy<'_>> {
        let mut busy = Busy::new(&self.metrics.planner_busy);
        busy.turn = Some(self.turns.take(Arc::clone(&cell.demanded)).await?);
        Some(busy)
    }

    /// Plans a mission off the request path (see the module).
    async fn plan_off_path(&self, cell: &MissionCell) {
        for _ in 0..ATTEMPTS {
            // The turn first, then the snapshot: a plan waits its turn
            // behind other missions' plans, and a snapshot taken before
            // the wait missed what arrived during it, such as the robot
            // whose arrival woke the planner, which then waited a second turn.
            let Some(turn) = self.take_turn(cell).await else { return };
            let (job, basis, reason, now, policy) = {
                let mission = cell.lock().await;
                let now = self.clock.now();
                let Some(reason) = mission.replan_reason_off_path(now, self.min_gap) else { return };
                let threads = if self.running.load(Ordering::Acquire) > 0 { 1 } else { self.background };
                let policy = mission.record().spec.policy.name();
                let job = mission.planning_job(threads).paced_by(Arc::clone(&self.pace));
                (job, mission.plan_basis(), reason, now, policy)
            };
            self.running.fetch_add(1, Ordering::AcqRel);
            let started = std::time::Instant::now();
            let outcome = self.threads_pool.run(move || job.run()).await;
            self.running.fetch_sub(1, Ordering::AcqRel);
            // The turn is for the planning threads: another mission may
            // plan while this plan waits for the mission and the disk.
            drop(turn);
            self.metrics.observe_plan(policy, started.elapsed());
            let outcome = match outcome {
                Ok(outcome) => outcome,
                Err(e) => {
                    tracing::error!(error = %e, "a planning job failed");
                    cell.lock().await.note_replan_failed();
                    return;
                }
            };
            let queued = {
                let mut mission = cell.lock().await;
                if !mission.plan_still_fits(&basis) {
                    self.metrics.stale_plans.inc();
                    continue;
                }
                let plan = MadePlan { outcome: &outcome, reason: &reason, now, basis: &basis };
                let queued = self.queue_plan(&mut mission, &plan).await;
                // The demands it served are reset; those it left (a robot
                // whose target was explored meanwhile) are not.
                cell.demanded.store(mission.plan_demanded(), Ordering::Release);
                match queued {
                    Ok(queued) => queued,
                    Err(e) => {
                        tracing::error!(mission = mission.record().id, error = %e, "replanning failed; it stays due");
                        mission.note_replan_failed();
                        return;
                    }
                }
            };
            // Not durable: the mission was reloaded from the store (which
            // leaves a replanning due) and the robots were told nothing.
            if let Err(e) = self.writer.durable(queued, cell).await {
                tracing::error!(error = %e, "a replanning could not be written; the mission was reloaded");
                return;
            }
            // Demands that arrived meanwhile are served by the next round.
            if cell.lock().await.replan_reason_off_path(self.clock.now(), self.min_gap).is_none() {
                return;
            }
        }
    }
}

/// A plan counted in `planner_busy` from the moment it waits for a turn
/// until it gives the turn back.
struct Busy<'a> {
    gauge: &'a Gauge,
    turn: Option<Turn>,
}

impl<'a> Busy<'a> {
    fn new(gauge: &'a Gauge) -> Self {
        gauge.inc();
        Self { gauge, turn: None }
    }
}

impl Drop for Busy<'_> {
    fn drop(&mut self) {
        self.turn = None;
        self.gauge.dec();
    }
}

/// A plan made, with why and on what, ready to be committed.
struct MadePlan<'a> {
    outcome: &'a JobOutcome,
    reason: &'a str,
    /// When its snapshot was taken.
    now: tokio::time::Instant,
    basis: &'a PlanBasis,
}

impl MadePlan<'_> {
    /// Once its changes are applied: the triggers it served are reset.
    fn mark_committed(&self, mission: &mut Mission, demands_before: u64, reassigned: usize) {
        mission.mark_replanned(self.now, self.basis, demands_before);
        mission.demand_for_robots_left_idle(self.outcome);
        let (id, replans, reason) = (mission.record().id, mission.record().replans, self.reason);
        tracing::debug!(mission = id, %reason, reassigned, replans, "replanned");
    }
}

/// The planning threads' pace for a budget of `cpu` cores: none without
/// one, or with one out of range (a library caller's NaN or zero).
fn pace_for(cpu: Option<f64>, metrics: &Metrics) -> SharedPace {
    match cpu {
        Some(cores) if cores.is_finite() && cores >= budget::LEAST_CORES => {
            Arc::new(PlannerBudget::new(cores, metrics.planner_paced_seconds.clone()))
        }
        Some(cores) => {
            tracing::warn!(cores, least = budget::LEAST_CORES, "planner CPU budget out of range: none kept");
            Arc::new(Unpaced)
        }
        None => Arc::new(Unpaced),
    }
}

/// Plans made off the request path at once (and threads for one alone): at
/// least one, and no more threads than one plan may use.
fn background_budget(threads: usize, background: usize) -> usize {
    background.clamp(1, threads.max(1))
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::sync::atomic::AtomicU64;

    use exploration::math::Point2;
    use exploration::policy::Capabilities;

    use super::{MissionCell, Planner, PlannerSettings, background_budget};
    use crate::ExecutiveSettings;
    use crate::clock::Clock;
    use crate::domain::{Pose, RobotSpec, Timestamp};
    use crate::executive::mission::Mission;
    use crate::executive::mission::testing::{left_half_known, nearest_spec};
    use crate::executive::writer::Writer;
    use crate::metrics::Metrics;
    use crate::store::{SqliteStore, Store};

    /// One planning thread, unpaced.
    fn one_thread() -> PlannerSettings {
        PlannerSettings { threads: 1, background: 1, ..PlannerSettings::default() }
    }

    /// A plan waits its turn before it takes its snapshot, so that what
    /// arrives during the wait (here a robot joining) is in the plan. Taken
    /// before the wait, the snapshot left the robot out of it (this test
    /// fails so).
    #[tokio::test(flavor = "current_thread")]
    async fn a_plan_takes_its_snapshot_after_waiting_its_turn() {
        let dir = tempfile::tempdir().unwrap();
        let store = SqliteStore::open(&dir.path().join("p.db"), crate::Durability::Full).await.unwrap();
        let record = store.create_mission(&nearest_spec("turns"), Timestamp(1)).await.unwrap();
        let mut robots = Vec::new();
        for (name, x) in [("a", 0.5), ("b", 1.0), ("c", 1.5)] {
            let capabilities =
                Capabilities { sensor_range_m: 1.0, field_of_view_rad: 6.0, speed_mps: 0.5, footprint_radius_m: 0.0 };
            let pose = Pose { position: Point2::new(x, 0.5), heading: 0.0 };
            let spec = RobotSpec { name: name.into(), capabilities, pose };
            robots.push(store.create_robot(record.id, &spec, &|_| "0".repeat(64), Timestamp(1), None).await.unwrap());
        }
        let now = tokio::time::Instant::now();
        let mut mission = Mission::new(record, now);
        for robot in &robots[..2] {
            mission.insert_robot(robot.clone(), now);
        }
        mission.apply(left_half_known(robots[0].id));

        let store: Arc<dyn Store> = Arc::new(store);
        let metrics = Arc::new(Metrics::new());
        let ids = Arc::new(AtomicU64::new(0));
        let writer = Writer::new(store, Clock::default(), Arc::clone(&metrics));
        let planner = Planner::new(writer, Clock::default(), one_thread(), ids, Arc::clone(&metrics));
        let cell = Arc::new(MissionCell::new(mission));
        // Another mission's plan holds the only turn.
        let turn = planner.turns.try_take().unwrap();
        planner.start(Arc::clone(&cell));
        cell.wake.notify_one();
        for _ in 0..10 {
            tokio::task::yield_now().await;
        }
        // The planner is waiting its turn; a robot joins meanwhile.
        assert_eq!(metrics.planner_busy.get(), 1, "a plan waits for a turn");
        cell.lock().await.insert_robot(robots[2].clone(), now);
        drop(turn);
        // The plan is committed through the store's writer thread.
        while cell.lock().await.record().replans == 0 {
            tokio::task::yield_now().await;
        }
        assert_eq!(metrics.stale_plans.get(), 0, "the plan was made once");
        assert_eq!(metrics.planner_busy.get(), 0, "and gave its turn back");
        let mission = cell.lock().await;
        for robot in &robots {
            assert!(mission.robot(robot.id).unwrap().current_task.is_some(), "{} has a task", robot.name);
        }
        drop(mission);
        planner.shutdown().await;
    }

    /// While a plan waits for the disk (here another connection holds
    /// SQLite's write lock), its mission is free for requests and already
    /// holds the plan, but no robot is told a new task until the plan is
    /// durable; and the only planning turn is free for another mission's
    /// plan. Written under the lock, the plan kept the mission held until
    /// the disk answered, and a plan waiting for the disk kept its turn
    /// (this test then never sees both plans).
    #[tokio::test(flavor = "current_thread")]
    async fn plans_waiting_for_the_disk_leave_missions_and_turns_free_and_tell_nobody() {
        use sqlx::Connection;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.db");
        let store = SqliteStore::open(&path, crate::Durability::Full).await.unwrap();
        let mut cells = Vec::new();
        for name in ["held", "next"] {
            let record = store.create_mission(&nearest_spec(name), Timestamp(1)).await.unwrap();
            let capabilities =
                Capabilities { sensor_range_m: 1.0, field_of_view_rad: 6.0, speed_mps: 0.5, footprint_radius_m: 0.0 };
            let pose = Pose { position: Point2::new(0.5, 0.5), heading: 0.0 };
            let spec = RobotSpec { name: "a".into(), capabilities, pose };
            let robot = store.create_robot(record.id, &spec, &|_| "0".repeat(64), Timestamp(1), None).await.unwrap();
            let now = tokio::time::Instant::now();
            let mut mission = Mission::new(record, now);
            mission.insert_robot(robot.clone(), now);
            mission.apply(left_half_known(robot.id));
            cells.push((Arc::new(MissionCell::new(mission)), robot.id));
        }

        let store: Arc<dyn Store> = Arc::new(store);
        let metrics = Arc::new(Metrics::new());
        let writer = Writer::new(store, Clock::default(), Arc::clone(&metrics));
        let ids = Arc::new(AtomicU64::new(0));
        // One plan at a time.
        let planner = Planner::new(writer, Clock::default(), one_thread(), ids, metrics);
        let mut generations = Vec::new();
        for (cell, _) in &cells {
            generations.push(cell.lock().await.generation());
        }
        let mut other = sqlx::SqliteConnection::connect(&format!("sqlite://{}", path.display())).await.unwrap();
        sqlx::query("BEGIN IMMEDIATE").execute(&mut other).await.unwrap();
        for (cell, _) in &cells {
            planner.start(Arc::clone(cell));
            cell.wake.notify_one();
        }
        // A guard, not a measurement: the disk stays held until both plans
        // are seen. A plan that kept its turn lets the other plan only once
        // its write has failed (SQLite's busy timeout), which reloads its
        // mission: the generation below tells.
        let seen = tokio::time::timeout(std::time::Duration::from_secs(30), async {
            for (cell, _) in &cells {
                while cell.lock().await.record().replans == 0 {
                    tokio::task::yield_now().await;
                }
            }
        })
        .await;
        let mut held = Vec::new();
        for (cell, robot) in &cells {
            let mission = cell.lock().await;
            let planned = mission.robot(*robot).unwrap().current_task.is_some();
            let told = mission.assignment_told(*robot).unwrap().task.is_some();
            held.push((mission.generation(), planned, told));
        }
        // Released before anything is asserted, so that a failure fails
        // the test instead of leaving the planner waiting on the disk.
        sqlx::query("ROLLBACK").execute(&mut other).await.unwrap();
        seen.expect("both plans are applied while the disk is held");
        let expected: Vec<_> = generations.iter().map(|&generation| (generation, true, false)).collect();
        assert_eq!(held, expected, "(generation, planned, told): both plans applied, no write failed, nobody told");
        for (cell, robot) in &cells {
            while cell.lock().await.assignment_told(*robot).unwrap().task.is_none() {
                tokio::task::yield_now().await;
            }
        }
        planner.shutdown().await;
    }

    /// A budget out of range keeps none: with zero cores, the first piece
    /// of work would wait forever (or panic converting infinity).
    #[test]
    fn a_budget_out_of_range_holds_nothing_back() {
        let metrics = Metrics::new();
        for cores in [f64::NAN, 0.0, -1.0, f64::INFINITY, 1e-9] {
            let pace = super::pace_for(Some(cores), &metrics);
            let spin = std::time::Instant::now();
            while spin.elapsed() < std::time::Duration::from_millis(10) {
                std::hint::black_box(spin.elapsed());
            }
            pace.piece_done();
        }
        assert_eq!(metrics.planner_paced_seconds.get(), 0.0);
        // In range, the same work is held back.
        let pace = super::pace_for(Some(1.0), &metrics);
        let spin = std::time::Instant::now();
        while spin.elapsed() < std::time::Duration::from_millis(5) {
            std::hint::black_box(spin.elapsed());
        }
        pace.piece_done();
        assert!(metrics.planner_paced_seconds.get() > 0.0);
    }

    #[test]
    fn background_plans_leave_the_requests_a_core_when_there_is_more_than_one() {
        let settings = ExecutiveSettings::default();
        let cores = settings.planner_threads;
        let budget = background_budget(settings.planner_threads, settings.background_planner_threads);
        assert_eq!(budget, (cores - 1).max(1), "{cores} cores");
        assert_eq!(background_budget(2, 1), 1);
        assert_eq!(background_budget(8, 7), 7);
        // Never none, never more than one plan may use.
        assert_eq!(background_budget(2, 0), 1);
        assert_eq!(background_budget(2, 9), 2);
        assert_eq!(background_budget(0, 0), 1);
    }
}
