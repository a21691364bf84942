//! The policies on offer, their parameters, and validated configurations.

use std::collections::BTreeMap;

use super::{Burgard, BurgardJoint, Colares, Greedy, Hungarian, MinPos, Nearest, Policy, SegmentationPolicy, Simmons};

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

const SWITCH_METRES: ParamSpec = ParamSpec {
    name: "switch_margin",
    description: "hysteresis: a robot leaves its current target only for one cheaper by more than this, metres",
    default: 1.0,
    min: 0.0,
    max: 1_000.0,
};

const SWITCH_UTILITY: ParamSpec = ParamSpec {
    name: "switch_margin",
    description: "hysteresis: a robot leaves its current target only for one better by more than this, in utility",
    default: 0.1,
    min: 0.0,
    max: 1_000.0,
};

const BETA: ParamSpec = ParamSpec {
    name: "beta",
    description: "weight of travel cost against utility (Burgard et al. 2005, Algorithm 1, line 5); the paper uses 1",
    default: 1.0,
    min: 0.0,
    max: 1000.0,
};

const OCC_MAX: ParamSpec = ParamSpec {
    name: "occ_max",
    description: "cells with a higher occupancy probability are not traversable (Burgard et al. 2005, §II-A)",
    default: 0.6,
    min: 0.0,
    max: 1.0,
};

const SMOOTHING: ParamSpec = ParamSpec {
    name: "smoothing_sigma_m",
    description: "standard deviation of the Gaussian the map is smoothed with before costing (§II-A), metres",
    default: 0.1,
    min: 0.0,
    max: 5.0,
};

/// Every policy the executive offers.
pub fn catalogue() -> &'static [PolicyDescriptor] {
    &[
        PolicyDescriptor {
            name: super::nearest::NAME,
            description: "each robot heads for its closest frontier cell, without arbitration (Yamauchi 1998; Bautin et al. 2011, Algorithm 1; the uncoordinated baseline of Burgard et al. 2005)",
            params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
        },
        PolicyDescriptor {
            name: super::greedy::NAME,
            description: "repeatedly the robot-frontier pair of lowest path cost, both removed; when frontiers run out, start again from all of them (Bautin et al. 2011, Algorithm 2)",
            params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
        },
        PolicyDescriptor {
            name: super::burgard::NAME,
            description: "Burgard et al. 2005, Algorithm 1: greedy on utility minus beta times value-iteration cost; utilities of frontier cells visible from chosen targets drop by P(d) = 1 - d/max_range",
            params: &[MIN_FRONTIER_SIZE, SWITCH_UTILITY, BETA, OCC_MAX, SMOOTHING],
        },
        PolicyDescriptor {
            name: super::burgard_joint::NAME,
            description: "Burgard et al. 2005, Algorithm 2: the joint assignment maximizing the sum of U(t_i | others) - beta * V_i^2; exact for small teams, randomized search with hill climbing beyond",
            params: &[
                MIN_FRONTIER_SIZE,
                SWITCH_UTILITY,
                BETA,
                OCC_MAX,
                SMOOTHING,
                ParamSpec {
                    name: "candidates",
                    description: "targets considered per robot in the exact search: its best by U - beta * V^2",
                    default: 6.0,
                    min: 1.0,
                    max: 64.0,
                },
                ParamSpec {
                    name: "exact_limit",
                    description: "largest number of joint assignments searched exhaustively; beyond it, randomized search",
                    default: 50_000.0,
                    min: 1.0,
                    max: 10_000_000.0,
                },
                ParamSpec {
                    name: "restarts",
                    description: "random starting assignments of the randomized search (besides Algorithm 1's)",
                    default: 8.0,
                    min: 0.0,
                    max: 1_000.0,
                },
            ],
        },
        PolicyDescriptor {
            name: super::simmons::NAME,
            description: "Simmons et al. 2000: greedy on bids' net utility (1 - d) * I - c, d the overlap of gain rectangles with those already assigned; minimum gain; hysteresis ratio",
            params: &[
                MIN_FRONTIER_SIZE,
                ParamSpec {
                    name: "hysteresis_ratio",
                    description: "a frontier inside the gain region of the robot's current task has its gain divided by this (§4.2; usually 0.85)",
                    default: 0.85,
                    min: 0.01,
                    max: 1.0,
                },
                ParamSpec {
                    name: "min_gain",
                    description: "a robot whose best discounted gain is below this many cells stays idle (§4.2)",
                    default: 1.0,
                    min: 0.0,
                    max: 1_000_000.0,
                },
                ParamSpec {
                    name: "gain_scale",
                    description: "u = gain_scale * (1 - d) * I - c, both in metres: I, the unknown area in reach, as metres of driving that reveal it (area / sensor width 2r), c the path; 1 counts a metre of revealing driving as a metre of path",
                    default: 1.0,
                    min: 0.0,
                    max: 1_000.0,
                },
                ParamSpec {
                    name: "spacing_m",
                    description: "bid frontier cells are at least this far apart (§4.1: about a robot radius, 30 cm)",
                    default: 0.3,
                    min: 0.0,
                    max: 10.0,
                },
            ],
        },
        PolicyDescriptor {
            name: super::minpos::NAME,
            description: "Bautin et al. 2011, Algorithm 3 (MinPos): each robot takes the frontier for which the fewest robots are strictly closer, ties by path cost",
            params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
        },
        PolicyDescriptor {
            name: super::segmentation::NAME,
            description: "Wurm et al. 2008, Algorithm 1: Voronoi segmentation of the explored map, Hungarian assignment of robots to segments, then to frontiers inside each segment",
            params: &[
                MIN_FRONTIER_SIZE,
                SWITCH_METRES,
                ParamSpec {
                    name: "inside_discount",
                    description: "a segment's cost is multiplied by this for a robot already inside it (Algorithm 1, line 4)",
                    default: 0.5,
                    min: 0.0,
                    max: 1.0,
                },
                ParamSpec {
                    name: "min_drop_m",
                    description: "a critical point's clearance is at least this much below the passage on both its sides, metres",
                    default: 0.2,
                    min: 0.0,
                    max: 10.0,
                },
                ParamSpec {
                    name: "min_segment_m2",
                    description: "smaller segments merge into a neighbour, square metres",
                    default: 1.0,
                    min: 0.0,
                    max: 10_000.0,
                },
            ],
        },
        PolicyDescriptor {
            name: super::hungarian::NAME,
            description: "Ko et al. 2003, as described by Burgard et al. 2005 and Wurm et al. 2008: optimal robot-to-frontier assignment on path costs (the Hungarian method)",
            params: &[MIN_FRONTIER_SIZE, SWITCH_METRES],
        },
        PolicyDescriptor {
            name: super::colares::NAME,
            description: "Colares & Chaimowicz 2016: U(f) = Inf(f) + Dist(f) - Coord(f), information potential, a beta-shaped distance factor and a negative wavefront from the other robots",
            params: &[
                MIN_FRONTIER_SIZE,
                SWITCH_UTILITY,
                ParamSpec {
                    name: "alpha",
                    description: "exponent alpha of the distance factor w^(alpha-1) (1-w)^(beta-1) (Eq. 4); the paper's best: 5 or 8",
                    default: 5.0,
                    min: 1.0,
                    max: 50.0,
                },
                ParamSpec {
                    name: "beta",
                    description: "exponent beta of the distance factor (Eq. 4); the paper's best: 9 or 8",
                    default: 9.0,
                    min: 1.0,
                    max: 50.0,
                },
                ParamSpec {
                    name: "sigma",
                    description: "width of the Gaussian of P(occ) centred on 0.5 that gives a cell's information potential (§3.1)",
                    default: 0.15,
                    min: 0.01,
                    max: 10.0,
                },
                ParamSpec {
                    name: "commit",
                    description: "1, the paper's: a robot keeps the frontier cell it chose while that cell is still frontier; 0: it chooses again at every replanning (not in the paper; can livelock, as Eq. 4 peaks at a distance)",
                    default: 1.0,
                    min: 0.0,
                    max: 1.0,
                },
                ParamSpec {
                    name: "window",
                    description: "side n of the n × n window whose frontier cells make a cell's frontier (§3.1), cells",
                    default: 5.0,
                    min: 1.0,
                    max: 101.0,
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
        let p = |name: &str| self.get(name);
        match self.descriptor.name {
            super::nearest::NAME => Box::new(Nearest { switch_margin: p("switch_margin") }),
            super::greedy::NAME => Box::new(Greedy { switch_margin: p("switch_margin") }),
            super::burgard::NAME => Box::new(Burgard {
                beta: p("beta"),
                occ_max: p("occ_max"),
                smoothing_sigma_m: p("smoothing_sigma_m"),
                switch_margin: p("switch_margin"),
            }),
            super::burgard_joint::NAME => Box::new(BurgardJoint {
                burgard: Burgard {
                    beta: p("beta"),
                    occ_max: p("occ_max"),
                    smoothing_sigma_m: p("smoothing_sigma_m"),
                    switch_margin: p("switch_margin"),
                },
                candidates: p("candidates").round() as usize,
                exact_limit: p("exact_limit").round() as u64,
                restarts: p("restarts").round() as usize,
            }),
            super::simmons::NAME => Box::new(Simmons {
                hysteresis_ratio: p("hysteresis_ratio"),
                min_gain: p("min_gain"),
                gain_scale: p("gain_scale"),
                spacing_m: p("spacing_m"),
            }),
            super::minpos::NAME => Box::new(MinPos { switch_margin: p("switch_margin") }),
            super::segmentation::NAME => Box::new(SegmentationPolicy {
                switch_margin: p("switch_margin"),
                inside_discount: p("inside_discount"),
                min_drop_m: p("min_drop_m"),
                min_segment_m2: p("min_segment_m2"),
            }),
            super::hungarian::NAME => Box::new(Hungarian { switch_margin: p("switch_margin") }),
            super::colares::NAME => Box::new(Colares {
                switch_margin: p("switch_margin"),
                alpha: p("alpha"),
                beta: p("beta"),
                sigma: p("sigma"),
                window: p("window").round() as usize,
                commit: p("commit") >= 0.5,
            }),
            other => unreachable!("catalogued policy {other} has no constructor"),
        }
    }
}
