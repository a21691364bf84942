//! A small mission the executive's unit tests share.

use std::sync::Arc;

use exploration::fusion::Patch;
use exploration::grid::{CellRect, GridFrame};
use exploration::math::Point2;
use exploration::policy::PolicyConfig;

use crate::domain::{LifecycleSettings, MissionSpec, ReplanSettings, RobotId};
use crate::store::{Changeset, LoggedPatch};

/// A 4 m × 2 m mission of 0.1 m cells under `nearest`, replanned off the
/// request path.
pub(crate) fn nearest_spec(name: &str) -> MissionSpec {
    MissionSpec {
        name: name.into(),
        frame: GridFrame::new(0.1, Point2::origin(), 40, 20),
        policy: PolicyConfig::default_for("nearest").unwrap(),
        replan: ReplanSettings::default(),
        scoped_by_communication: false,
        lockstep: false,
        lifecycle: LifecycleSettings::default(),
    }
}

/// The left half of [`nearest_spec`]'s map, free, as robot `robot`'s first update.
pub(crate) fn left_half_known(robot: RobotId) -> Changeset {
    let known = Patch::from_probabilities(CellRect::new(0, 0, 20, 20), &[0.1; 400], &[]).unwrap();
    Changeset { patches: vec![LoggedPatch { robot_id: robot, seq: 1, patch: Arc::new(known) }], ..Changeset::default() }
}
