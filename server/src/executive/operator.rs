//! What operators do to a mission (Simmons et al. 2000, §4.2: a human may
//! override the executive): each action is prepared and checked by the
//! mission, made durable, logged with its actor, and the mission replanned
//! around it.

use std::sync::atomic::Ordering;

use exploration::math::Point2;
use exploration::policy::PolicyConfig;

use super::mission::Mission;
use super::planner::MissionCell;
use super::{Executive, MissionSummary, RobotSummary};
use crate::domain::{MissionId, OperatorNote, Override, Region, RobotId, Timestamp};
use crate::error::Error;
use crate::store::Changeset;

impl Executive {
    /// Changes a running mission's policy; the next replanning uses it.
    pub async fn set_policy(
        &self,
        mission_id: MissionId,
        policy: PolicyConfig,
        actor: &str,
        reason: &str,
    ) -> Result<MissionSummary, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mut mission = handle.lock().await;
        let changes = mission.prepare_policy(policy, actor, reason, Timestamp::now());
        self.operate(&handle, &mut mission, changes).await?;
        tracing::info!(mission = mission_id, policy = mission.record().spec.policy.name(), actor = %actor, "policy changed");
        Ok(Self::summary(&mission))
    }

    /// Overrides a robot's task for an operator (Simmons et al. 2000, §4.2);
    /// the others are replanned to cover for it.
    pub async fn override_robot(
        &self,
        robot_id: RobotId,
        action: Override,
        note: OperatorNote,
    ) -> Result<RobotSummary, Error> {
        let handle = self.mission_of_robot(robot_id).await?;
        let mut mission = handle.lock().await;
        let changes = mission.prepare_override(robot_id, action, &note, Timestamp::now(), &self.next_task_id)?;
        self.operate(&handle, &mut mission, changes).await?;
        tracing::info!(mission = mission.record().id, robot = robot_id, ?action, actor = %note.actor, "override");
        let record = mission.robot(robot_id)?;
        Ok(RobotSummary {
            record: record.clone(),
            target: mission.target_of(record),
            task_kind: mission.task_kind_of(record),
            blacklisted: mission.blacklisted(robot_id),
        })
    }

    /// Pauses (`pause`) or resumes a mission.
    pub async fn pause_mission(
        &self,
        mission_id: MissionId,
        pause: bool,
        note: OperatorNote,
    ) -> Result<MissionSummary, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mut mission = handle.lock().await;
        let changes = mission.prepare_pause(pause, &note, Timestamp::now())?;
        self.operate(&handle, &mut mission, changes).await?;
        tracing::info!(mission = mission_id, pause, actor = %note.actor, "mission paused or resumed");
        Ok(Self::summary(&mission))
    }

    /// Deletes a completed or paused mission: once the deletion is durable
    /// the mission is gone from every answer, its robots' tokens no longer
    /// admit them and its streams end; the slot and cells it took count no
    /// more against the executive's limits. Its rows are removed afterwards
    /// by the sweeps, a batch at a time ([`Self::sweep`]).
    pub async fn delete_mission(&self, mission_id: MissionId, note: OperatorNote) -> Result<(), Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mut mission = handle.lock().await;
        let changes = mission.prepare_delete(Timestamp::now())?;
        // A second deletion that waited for the lock is refused here, with
        // NOT_FOUND, like every write to a deleted mission.
        self.commit(&mut mission, changes).await?;
        mission.mark_deleted();
        let robots: Vec<RobotId> = mission.robots().map(|r| r.id).collect();
        drop(mission);
        // One removal per robot: the map holds every mission's robots, and
        // auth waits while it is locked.
        let mut tokens = self.tokens.write().unwrap_or_else(|e| e.into_inner());
        for robot in robots {
            tokens.remove(&robot);
        }
        drop(tokens);
        match &self.ownership {
            Some(ownership) => self.stop_holding(ownership, mission_id),
            None => self.forget_mission(mission_id),
        }
        tracing::info!(mission = mission_id, actor = %note.actor, reason = %note.reason, "mission deleted");
        Ok(())
    }

    /// Forbids a region of a mission: no target is assigned inside.
    pub async fn forbid_region(
        &self,
        mission_id: MissionId,
        min: Point2,
        max: Point2,
        note: OperatorNote,
    ) -> Result<Region, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mut mission = handle.lock().await;
        // Reserved atomically: calls on other missions run at the same time.
        // A refused or failed call leaves a gap, never a repeat.
        let id = self.next_region_id.fetch_add(1, Ordering::Relaxed) + 1;
        let (changes, region) = mission.prepare_forbid(id, min, max, &note, Timestamp::now())?;
        self.operate(&handle, &mut mission, changes).await?;
        tracing::info!(mission = mission_id, region = id, actor = %note.actor, "region forbidden");
        Ok(region)
    }

    /// Gives a mission its rooms and corridors (Wurm et al. 2008, §VI) as
    /// run-length pairs over its map (see [`exploration_proto::label_runs`]),
    /// or, with none, sends it back to the online segmentation.
    pub async fn set_given_segmentation(
        &self,
        mission_id: MissionId,
        label_runs: &[u8],
        note: OperatorNote,
    ) -> Result<MissionSummary, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mut mission = handle.lock().await;
        let rooms = if label_runs.is_empty() {
            None
        } else {
            let frame = &mission.record().spec.frame;
            let labels = exploration_proto::label_runs::decode(label_runs, frame.len())
                .map_err(|e| Error::InvalidArgument(format!("label_runs {e} ({} × {})", frame.width, frame.height)))?;
            Some(labels)
        };
        let changes = mission.prepare_rooms(rooms, &note, Timestamp::now())?;
        self.operate(&handle, &mut mission, changes).await?;
        tracing::info!(mission = mission_id, actor = %note.actor, given = mission.has_rooms(), "segmentation set");
        Ok(Self::summary(&mission))
    }

    /// Allows a forbidden region again.
    pub async fn allow_region(
        &self,
        mission_id: MissionId,
        region: u64,
        note: OperatorNote,
    ) -> Result<MissionSummary, Error> {
        let handle = self.mission_handle(mission_id).await?;
        let mut mission = handle.lock().await;
        let changes = mission.prepare_allow(region, &note, Timestamp::now())?;
        self.operate(&handle, &mut mission, changes).await?;
        tracing::info!(mission = mission_id, region, actor = %note.actor, "region allowed");
        Ok(Self::summary(&mission))
    }

    /// Commits an operator's changeset, then replans the mission around it.
    async fn operate(&self, handle: &MissionCell, mission: &mut Mission, changes: Changeset) -> Result<(), Error> {
        self.commit(mission, changes).await?;
        self.planner.after_change(handle, mission).await;
        Ok(())
    }
}
