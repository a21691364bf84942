//! The robot's body: what it senses (a range sensor, ray casting in the
//! true world), the map it keeps and shares with peers in range, the patch
//! of new cells it reports, and the way around a robot in its path.

use std::collections::HashMap;

use exploration::cost::{TraversalMap, shortest_path};
use exploration::grid::{Cell, CellClass, CellRect, GridFrame, OccupancyGrid};
use exploration_proto::v1 as pb;

use super::SimRobot;
use crate::world::World;

/// Probability a robot reports for a cell its sensor saw empty.
const P_FREE: f32 = 0.05;

/// Probability a robot reports for a cell that stopped a beam.
const P_OCCUPIED: f32 = 0.95;

/// How a robot's map stores a cell seen free (percent).
const KNOWN_FREE: u8 = 5;

/// How a robot's map stores a cell seen occupied (percent).
const KNOWN_OCCUPIED: u8 = 95;

/// What the whole team knows: the union of the robots' maps. Robots plan
/// their paths on it (the shared map of Burgard et al. 2005, §III), and the
/// fleet measures coverage with it.
#[derive(Debug, Clone)]
pub struct TeamMap {
    /// Known cells: free or occupied.
    pub grid: OccupancyGrid,
    /// Reachable free cells known.
    pub known_reachable: usize,
    /// Per cell: how many robots sensed it (for the overlap figure).
    pub sensed_by: Vec<u8>,
}

impl TeamMap {
    /// Nothing known yet.
    pub fn new(frame: GridFrame) -> Self {
        Self { grid: OccupancyGrid::unknown(frame), known_reachable: 0, sensed_by: vec![0; frame.len()] }
    }
}

/// The cells the robots stand on, counted: two robots squeezing past each
/// other share a cell for a step.
#[derive(Debug, Clone, Default)]
pub struct Occupancy(HashMap<Cell, u32>);

impl Occupancy {
    /// The robots' cells.
    pub fn of(cells: impl IntoIterator<Item = Cell>) -> Self {
        let mut occupancy = Self::default();
        for cell in cells {
            occupancy.enter(cell);
        }
        occupancy
    }

    /// Whether a robot stands on `cell`.
    pub fn is_taken(&self, cell: Cell) -> bool {
        self.0.contains_key(&cell)
    }

    /// A robot moves from `from` to `to`.
    pub fn step(&mut self, from: Cell, to: Cell) {
        if let Some(n) = self.0.get_mut(&from) {
            *n -= 1;
            if *n == 0 {
                self.0.remove(&from);
            }
        }
        self.enter(to);
    }

    fn enter(&mut self, cell: Cell) {
        *self.0.entry(cell).or_default() += 1;
    }
}

impl SimRobot {
    /// A path to the task's target around the cells other robots stand on,
    /// when there is one (then true); otherwise the robot keeps waiting on
    /// its path.
    pub(super) fn detour(&mut self, world: &World, team: &TeamMap, occupied: &Occupancy) -> bool {
        let Some(task) = self.task else { return false };
        let map = if self.limited { &self.own } else { &team.grid };
        let free = |c: Cell| !occupied.is_taken(c) || c == self.cell;
        let path = if self.capabilities.footprint_radius_m > 0.0 {
            let traversal = TraversalMap::free_space(map, self.capabilities.footprint_radius_m);
            shortest_path(&world.frame, self.cell, task.target, |c| traversal.passable(c) && free(c))
        } else {
            shortest_path(&world.frame, self.cell, task.target, |c| map.class(c) == CellClass::Free && free(c))
        };
        let Some(path) = path else { return false };
        self.path = path.into_iter().skip(1).collect();
        self.waited = 0;
        true
    }

    /// Senses from the current cell into its map, its log and the team's map.
    pub(super) fn sense(&mut self, world: &World, team: &mut TeamMap) {
        let frame = world.frame;
        let own = &mut self.own;
        let (log, dirty, known, seen) = (&mut self.log, &mut self.dirty, &mut self.known_reachable, &mut self.seen);
        self.sensor.scan(
            self.cell,
            self.heading,
            |c| world.is_blocked(c),
            |cell, hit| {
                if !frame.contains(cell) {
                    return;
                }
                let i = frame.index(cell);
                // Overlap counts robots that swept a cell, whatever they knew of it.
                if !seen[i] {
                    seen[i] = true;
                    team.sensed_by[i] = team.sensed_by[i].saturating_add(1);
                }
                if own.class(cell) != CellClass::Unknown {
                    return;
                }
                own.set(cell, if hit { KNOWN_OCCUPIED } else { KNOWN_FREE });
                log.push((i as u32, hit));
                *dirty = Some(dirty.map_or(CellRect::new(cell.x, cell.y, 1, 1), |r| r.including(cell)));
                if world.reachable[i] {
                    *known += 1;
                }
                if team.grid.class(cell) == CellClass::Unknown {
                    team.grid.set(cell, if hit { KNOWN_OCCUPIED } else { KNOWN_FREE });
                    if world.reachable[i] {
                        team.known_reachable += 1;
                    }
                }
            },
        );
    }

    /// Passes the measurements `to` was not sent yet, and marks them sent
    /// (Burgard et al. 2005, §III: a per-peer log). Forwarded measurements
    /// count too, so that robots that meet end up with their clusters' joint
    /// map, the map the executive plans their sub-team on; `to` integrates a
    /// measurement only once, into cells it does not know yet.
    pub fn share_with(&mut self, to: &mut SimRobot, to_index: usize, world: &World) {
        let frame = world.frame;
        let start = self.sent[to_index];
        for &(i, occupied) in &self.log[start..] {
            let cell = frame.cell(i as usize);
            if to.own.class(cell) == CellClass::Unknown {
                to.own.set(cell, if occupied { KNOWN_OCCUPIED } else { KNOWN_FREE });
                to.log.push((i, occupied));
                to.dirty = Some(to.dirty.map_or(CellRect::new(cell.x, cell.y, 1, 1), |r| r.including(cell)));
                if world.reachable[i as usize] {
                    to.known_reachable += 1;
                }
            }
        }
        self.sent[to_index] = self.log.len();
    }

    /// The cells changed since the last update, as a patch of its map:
    /// only its own measurements with unlimited communication (the executive
    /// fuses the robots'), all it knows with limited communication.
    pub(super) fn patch(&mut self) -> Option<pb::MapPatch> {
        let rect = self.dirty.take()?;
        let mut values = Vec::with_capacity(rect.area() as usize);
        let mut unknown = Vec::with_capacity(rect.area() as usize);
        for cell in rect.cells() {
            match self.own.value(cell) {
                KNOWN_FREE => {
                    values.push(P_FREE);
                    unknown.push(0);
                }
                KNOWN_OCCUPIED => {
                    values.push(P_OCCUPIED);
                    unknown.push(0);
                }
                _ => {
                    values.push(0.5);
                    unknown.push(1);
                }
            }
        }
        let any_unknown = unknown.iter().any(|&u| u != 0);
        Some(pb::MapPatch {
            x: rect.x as u32,
            y: rect.y as u32,
            width: rect.width,
            height: rect.height,
            encoding: pb::CellEncoding::Probability as i32,
            values,
            unknown: if any_unknown { unknown } else { Vec::new() },
            occupancy: Vec::new(),
        })
    }
}
