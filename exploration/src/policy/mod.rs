//! Coordination policies: who goes where next.
//!
//! A policy looks at the fused grid, its frontier clusters and the robots,
//! and returns at most one target per robot. Every policy implements
//! [`Policy`]; [`PolicyConfig`] validates a policy name and parameters
//! against the [`catalogue`] and builds it. Each policy lives in its own file
//! and cites the paper, algorithm and equations it implements.

use std::collections::BTreeMap;

use crate::cost::CostCache;
use crate::frontier::FrontierCluster;
use crate::grid::{Cell, CellRect, OccupancyGrid};

mod burgard;
mod nearest;

pub use burgard::Burgard;
pub use nearest::Nearest;

/// A robot's identity, as the executive numbers them.
pub type RobotId = u64;

/// What a robot can do (Simmons et al. 2000 let bids reflect "their own
/// capabilities (sensor range, travel costs, etc.)"; Wurm et al. 2008, Eq. 4,
/// give infinite cost where a robot cannot pass).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capabilities {
    /// Maximum sensor range, metres (Burgard et al. 2005's max_range of Eq. 2).
    pub sensor_range_m: f64,
    /// Sensor field of view, radians.
    pub field_of_view_rad: f64,
    /// Nominal speed, metres per second.
    pub speed_mps: f64,
    /// Radius of the circular footprint, metres.
    pub footprint_radius_m: f64,
}

/// The task a robot is working on when the policy runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurrentTask {
    /// Its target cell.
    pub target: Cell,
    /// The information-gain region of that target, if known (Simmons et al. 2000, §4.2).
    pub gain_region: Option<CellRect>,
}

/// A robot as the policies see it.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotView {
    /// Its identity.
    pub id: RobotId,
    /// The cell it stands on.
    pub cell: Cell,
    /// Its capabilities.
    pub capabilities: Capabilities,
    /// What it is doing, if anything.
    pub current: Option<CurrentTask>,
}

/// Everything a policy may look at for one replanning.
#[derive(Debug, Clone, Copy)]
pub struct PlanningInput<'a> {
    /// The fused grid.
    pub grid: &'a OccupancyGrid,
    /// Frontier clusters of at least the policy's minimum size.
    pub clusters: &'a [FrontierCluster],
    /// The robots to assign, in a fixed order.
    pub robots: &'a [RobotView],
    /// Threads the policy may use for cost maps.
    pub threads: usize,
}

impl PlanningInput<'_> {
    /// Every frontier cell of every cluster, in cluster order.
    pub fn frontier_cells(&self) -> Vec<Cell> {
        self.clusters
            .iter()
            .flat_map(|c| c.cells.iter().copied())
            .collect()
    }
}

/// Each robot's cost map over its own traversal kind, computed once per
/// replanning (cached) and in parallel on `input.threads` threads.
pub fn robot_cost_maps(
    input: &PlanningInput<'_>,
    costs: &mut CostCache<'_>,
    kinds: &[crate::cost::TraversalKind],
) -> Vec<std::sync::Arc<crate::cost::CostMap>> {
    let mut by_kind: BTreeMap<crate::cost::TraversalKind, Vec<Cell>> = BTreeMap::new();
    for (robot, kind) in input.robots.iter().zip(kinds) {
        by_kind.entry(*kind).or_default().push(robot.cell);
    }
    for (kind, sources) in &by_kind {
        costs.cost_maps(*kind, sources, input.threads);
    }
    input
        .robots
        .iter()
        .zip(kinds)
        .map(|(robot, kind)| costs.cost_map(*kind, robot.cell))
        .collect()
}

/// A target chosen for one robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    /// The cell to go to.
    pub cell: Cell,
    /// The policy's figure of merit for this choice (policy-specific units).
    pub utility: f64,
    /// The path cost the policy computed from the robot to the target.
    pub path_cost: f64,
    /// The information-gain region the target is expected to reveal, if the policy estimates one.
    pub gain_region: Option<CellRect>,
}

/// The outcome of one replanning: a target or nothing for every robot, in
/// the order of [`PlanningInput::robots`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Plan {
    /// One entry per robot.
    pub targets: Vec<Option<Target>>,
}

/// A coordination policy.
pub trait Policy: Send + Sync + std::fmt::Debug {
    /// The name it is selected by.
    fn name(&self) -> &'static str;

    /// Chooses targets for all robots.
    fn plan(&self, input: &PlanningInput<'_>, costs: &mut CostCache<'_>) -> Plan;
}

/// One tunable parameter of a policy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamSpec {
    /// Its name.
    pub name: &'static str,
    /// What it does.
    pub description: &'static str,
    /// Its value when not given.
    pub default: f64,
    /// Smallest allowed value.
    pub min: f64,
    /// Largest allowed value.
    pub max: f64,
}

/// A policy on offer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolicyDescriptor {
    /// The name it is selected by.
    pub name: &'static str,
    /// One line on what it does and where it comes from.
    pub description: &'static str,
    /// Its parameters.
    pub params: &'static [ParamSpec],
}

/// Parameter shared by all frontier-based policies.
const MIN_FRONTIER_SIZE: ParamSpec = ParamSpec {
    name: "min_frontier_size",
    description: "frontier clusters with fewer cells are ignored",
    default: 1.0,
    min: 1.0,
    max: 10_000.0,
};

/// Every policy the executive offers.
pub fn catalogue() -> &'static [PolicyDescriptor] {
    &[
        PolicyDescriptor {
            name: nearest::NAME,
            description: "each robot heads for its closest frontier cell, without arbitration (Yamauchi 1998; the uncoordinated baseline of Burgard et al. 2005)",
            params: &[MIN_FRONTIER_SIZE],
        },
        PolicyDescriptor {
            name: burgard::NAME,
            description: "Burgard et al. 2005, Algorithm 1: greedy on utility minus beta times value-iteration cost; utilities of frontier cells visible from chosen targets drop by P(d) = 1 - d/max_range",
            params: &[
                MIN_FRONTIER_SIZE,
                ParamSpec {
                    name: "beta",
                    description: "weight of travel cost against utility (Algorithm 1, line 5); the paper uses 1",
                    default: 1.0,
                    min: 0.0,
                    max: 1000.0,
                },
                ParamSpec {
                    name: "occ_max",
                    description: "cells with a higher occupancy probability are not traversable (§II-A)",
                    default: 0.6,
                    min: 0.0,
                    max: 1.0,
                },
                ParamSpec {
                    name: "smoothing_sigma_m",
                    description: "standard deviation of the Gaussian the map is smoothed with before costing (§II-A), metres",
                    default: 0.1,
                    min: 0.0,
                    max: 5.0,
                },
            ],
        },
    ]
}

/// Why a policy configuration was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PolicyError {
    /// No policy of that name.
    #[error("unknown policy {name:?}; valid policies: {}", valid.join(", "))]
    UnknownPolicy {
        /// The name given.
        name: String,
        /// The names on offer.
        valid: Vec<&'static str>,
    },
    /// The policy has no parameter of that name.
    #[error("policy {policy:?} has no parameter {name:?}; its parameters: {}", valid.join(", "))]
    UnknownParameter {
        /// The policy.
        policy: &'static str,
        /// The name given.
        name: String,
        /// Its parameters.
        valid: Vec<&'static str>,
    },
    /// A value outside the parameter's range.
    #[error("parameter {name:?} of policy {policy:?} is {value}; it must lie in [{min}, {max}]")]
    OutOfRange {
        /// The policy.
        policy: &'static str,
        /// The parameter.
        name: &'static str,
        /// The value given.
        value: f64,
        /// Lower bound.
        min: f64,
        /// Upper bound.
        max: f64,
    },
}

/// A validated policy choice with every parameter filled in.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyConfig {
    descriptor: &'static PolicyDescriptor,
    params: BTreeMap<&'static str, f64>,
}

impl PolicyConfig {
    /// Validates `name` and `overrides` against the catalogue; parameters not
    /// overridden take their defaults.
    pub fn new(name: &str, overrides: &BTreeMap<String, f64>) -> Result<Self, PolicyError> {
        let descriptor = catalogue().iter().find(|d| d.name == name).ok_or_else(|| {
            PolicyError::UnknownPolicy {
                name: name.to_owned(),
                valid: catalogue().iter().map(|d| d.name).collect(),
            }
        })?;
        let mut params: BTreeMap<&'static str, f64> = descriptor
            .params
            .iter()
            .map(|p| (p.name, p.default))
            .collect();
        for (key, &value) in overrides {
            let spec = descriptor
                .params
                .iter()
                .find(|p| p.name == key)
                .ok_or_else(|| PolicyError::UnknownParameter {
                    policy: descriptor.name,
                    name: key.clone(),
                    valid: descriptor.params.iter().map(|p| p.name).collect(),
                })?;
            // NaN fails this check too.
            if !(value >= spec.min && value <= spec.max) {
                return Err(PolicyError::OutOfRange {
                    policy: descriptor.name,
                    name: spec.name,
                    value,
                    min: spec.min,
                    max: spec.max,
                });
            }
            params.insert(spec.name, value);
        }
        Ok(Self { descriptor, params })
    }

    /// The default configuration of a policy.
    pub fn default_for(name: &str) -> Result<Self, PolicyError> {
        Self::new(name, &BTreeMap::new())
    }

    /// The policy's name.
    pub fn name(&self) -> &'static str {
        self.descriptor.name
    }

    /// Every parameter with its value.
    pub fn params(&self) -> &BTreeMap<&'static str, f64> {
        &self.params
    }

    /// A parameter's value.
    ///
    /// # Panics
    /// If the policy has no such parameter (a programming error).
    pub fn get(&self, name: &str) -> f64 {
        match self.params.get(name) {
            Some(v) => *v,
            None => panic!("policy {} has no parameter {name}", self.name()),
        }
    }

    /// The minimum frontier cluster size the policy considers.
    pub fn min_frontier_size(&self) -> usize {
        self.params
            .get(MIN_FRONTIER_SIZE.name)
            .map_or(1, |v| v.round() as usize)
    }

    /// Builds the policy.
    pub fn build(&self) -> Box<dyn Policy> {
        match self.descriptor.name {
            nearest::NAME => Box::new(Nearest),
            burgard::NAME => Box::new(Burgard {
                beta: self.get("beta"),
                occ_max: self.get("occ_max"),
                smoothing_sigma_m: self.get("smoothing_sigma_m"),
            }),
            other => unreachable!("catalogued policy {other} has no constructor"),
        }
    }
}

#[cfg(test)]
pub(crate) mod testing {
    //! Fixtures shared by the policies' tests.
    use super::*;
    use crate::frontier::{FrontierMap, clusters};

    pub fn robot(id: RobotId, cell: Cell, sensor_range_m: f64) -> RobotView {
        RobotView {
            id,
            cell,
            capabilities: Capabilities {
                sensor_range_m,
                field_of_view_rad: std::f64::consts::TAU,
                speed_mps: 1.0,
                footprint_radius_m: 0.0,
            },
            current: None,
        }
    }

    /// Runs a policy on a grid and returns each robot's target cell.
    pub fn plan_targets(
        policy: &dyn Policy,
        grid: &OccupancyGrid,
        robots: &[RobotView],
    ) -> Vec<Option<Cell>> {
        let frontier = FrontierMap::detect(grid);
        let clusters = clusters(&frontier, 1);
        let input = PlanningInput {
            grid,
            clusters: &clusters,
            robots,
            threads: 1,
        };
        let mut cache = CostCache::new(grid);
        let plan = policy.plan(&input, &mut cache);
        assert_eq!(plan.targets.len(), robots.len());
        plan.targets.iter().map(|t| t.map(|t| t.cell)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configs_validate_names_and_ranges() {
        let err = PolicyConfig::default_for("teleport").unwrap_err();
        assert!(err.to_string().contains("nearest"), "{err}");
        assert!(err.to_string().contains("burgard"), "{err}");

        let mut overrides = BTreeMap::new();
        overrides.insert("beta".to_owned(), 2.5);
        let config = PolicyConfig::new("burgard", &overrides).unwrap();
        assert_eq!(config.get("beta"), 2.5);
        assert_eq!(config.get("occ_max"), 0.6);

        overrides.insert("beta".to_owned(), -1.0);
        let err = PolicyConfig::new("burgard", &overrides).unwrap_err();
        assert!(
            matches!(err, PolicyError::OutOfRange { name: "beta", .. }),
            "{err}"
        );
        overrides.insert("beta".to_owned(), f64::NAN);
        assert!(PolicyConfig::new("burgard", &overrides).is_err());

        let mut unknown = BTreeMap::new();
        unknown.insert("gamma".to_owned(), 1.0);
        let err = PolicyConfig::new("burgard", &unknown).unwrap_err();
        assert!(err.to_string().contains("beta"), "{err}");
    }

    #[test]
    fn every_catalogued_policy_builds_under_its_name() {
        for d in catalogue() {
            let config = PolicyConfig::default_for(d.name).unwrap();
            assert_eq!(config.build().name(), d.name);
            for p in d.params {
                assert!(
                    p.min <= p.default && p.default <= p.max,
                    "{}.{}",
                    d.name,
                    p.name
                );
            }
        }
    }
}
