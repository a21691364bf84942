//! The policies on offer, their parameters, and validated configurations.

use std::collections::BTreeMap;

use super::Policy;

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
#[derive(Debug, Clone, Copy)]
pub struct PolicyDescriptor {
    /// The name it is selected by.
    pub name: &'static str,
    /// One line on what it does and where it comes from.
    pub description: &'static str,
    /// Its parameters.
    pub params: &'static [ParamSpec],
    /// Builds it from a configuration validated against `params`.
    pub build: fn(&PolicyConfig) -> Box<dyn Policy>,
}

/// Parameter shared by all frontier-based policies.
pub(super) const MIN_FRONTIER_SIZE: ParamSpec = ParamSpec {
    name: "min_frontier_size",
    description: "frontier clusters with fewer cells are ignored",
    default: 1.0,
    min: 1.0,
    max: 10_000.0,
};

pub(super) const SWITCH_METRES: ParamSpec = ParamSpec {
    name: "switch_margin",
    description: "hysteresis: a robot leaves its current target only for one cheaper by more than this, metres",
    default: 1.0,
    min: 0.0,
    max: 1_000.0,
};

pub(super) const SWITCH_UTILITY: ParamSpec = ParamSpec {
    name: "switch_margin",
    description: "hysteresis: a robot leaves its current target only for one better by more than this, in utility",
    default: 0.1,
    min: 0.0,
    max: 1_000.0,
};

pub(super) const BETA: ParamSpec = ParamSpec {
    name: "beta",
    description: "weight of travel cost against utility (Burgard et al. 2005, Algorithm 1, line 5); the paper uses 1",
    default: 1.0,
    min: 0.0,
    max: 1000.0,
};

pub(super) const OCC_MAX: ParamSpec = ParamSpec {
    name: "occ_max",
    description: "cells with a higher occupancy probability are not traversable (Burgard et al. 2005, §II-A)",
    default: 0.6,
    min: 0.0,
    max: 1.0,
};

pub(super) const SMOOTHING: ParamSpec = ParamSpec {
    name: "smoothing_sigma_m",
    description: "standard deviation of the Gaussian the map is smoothed with before costing (§II-A), metres",
    default: 0.1,
    min: 0.0,
    max: 5.0,
};

/// Every policy the executive offers, in the order they are listed.
pub fn catalogue() -> &'static [PolicyDescriptor] {
    &[
        super::nearest::DESCRIPTOR,
        super::greedy::DESCRIPTOR,
        super::burgard::DESCRIPTOR,
        super::burgard_joint::DESCRIPTOR,
        super::simmons::DESCRIPTOR,
        super::minpos::DESCRIPTOR,
        super::segmentation::DESCRIPTOR,
        super::hungarian::DESCRIPTOR,
        super::colares::DESCRIPTOR,
        super::unassigned::DESCRIPTOR,
        super::tours::DESCRIPTOR,
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
    #[error("parameter {name:?} of policy {policy:?} is {}; it must lie in [{min}, {max}]", crate::math::ShortNumber(*value))]
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
#[derive(Debug, Clone)]
pub struct PolicyConfig {
    descriptor: &'static PolicyDescriptor,
    params: BTreeMap<&'static str, f64>,
}

/// Two configurations are equal when they name the same policy with the same values.
impl PartialEq for PolicyConfig {
    fn eq(&self, other: &Self) -> bool {
        self.descriptor.name == other.descriptor.name && self.params == other.params
    }
}

impl PolicyConfig {
    /// Validates `name` and `overrides` against the catalogue; parameters not
    /// overridden take their defaults.
    pub fn new(name: &str, overrides: &BTreeMap<String, f64>) -> Result<Self, PolicyError> {
        let descriptor = catalogue().iter().find(|d| d.name == name).ok_or_else(|| PolicyError::UnknownPolicy {
            name: name.to_owned(),
            valid: catalogue().iter().map(|d| d.name).collect(),
        })?;
        let mut params: BTreeMap<&'static str, f64> = descriptor.params.iter().map(|p| (p.name, p.default)).collect();
        for (key, &value) in overrides {
            let spec =
                descriptor.params.iter().find(|p| p.name == key).ok_or_else(|| PolicyError::UnknownParameter {
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
        self.params.get(MIN_FRONTIER_SIZE.name).map_or(1, |v| v.round() as usize)
    }

    /// Builds the policy.
    pub fn build(&self) -> Box<dyn Policy> {
        (self.descriptor.build)(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Cell;
    use crate::grid::testing::grid_from_picture;
    use crate::policy::testing::{plan_targets, robot};

    /// Every parameter of every policy: the worst values a request can carry
    /// are refused, naming the parameter; the ends of its range are taken,
    /// and the policy built from them plans without panicking.
    #[test]
    fn every_parameter_refuses_what_lies_outside_its_range_and_plans_at_its_ends() {
        let grid = grid_from_picture(&[
            "#########?#####", //
            "?.............?", //
            "#.....#.......#", //
            "#.....#.......?", //
            "####?##########", //
        ]);
        let robots = [robot(0, Cell::new(2, 2), 3.0), robot(1, Cell::new(9, 3), 3.0), robot(2, Cell::new(12, 1), 3.0)];
        for descriptor in catalogue() {
            for spec in descriptor.params {
                let with =
                    |value: f64| PolicyConfig::new(descriptor.name, &BTreeMap::from([(spec.name.to_owned(), value)]));
                for worst in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, spec.min - 1.0, spec.max + 1.0, -1e300] {
                    let refused = with(worst).expect_err(&format!("{} {} = {worst}", descriptor.name, spec.name));
                    assert!(
                        matches!(refused, PolicyError::OutOfRange { name, .. } if name == spec.name),
                        "{refused:?}"
                    );
                }
                for end in [spec.min, spec.max] {
                    let config = with(end).unwrap_or_else(|e| panic!("{} {} = {end}: {e}", descriptor.name, spec.name));
                    let targets = plan_targets(config.build().as_ref(), &grid, &robots);
                    assert_eq!(targets.len(), robots.len(), "{} {} = {end}", descriptor.name, spec.name);
                }
            }
        }
    }
}
