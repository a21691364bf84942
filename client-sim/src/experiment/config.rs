//! An experiment as its TOML file describes it (see `experiments/`): worlds,
//! team sizes, policies, communication ranges, seeds, plots and the paper's
//! checks, validated on load.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::fleet::{CommRange, DEFAULT_MODEL, Interference};
use crate::generate::Generator;
use exploration::math::ShortNumber;

/// An experiment, as its TOML file describes it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Experiment {
    /// Short name; the results folder is named after it.
    pub name: String,
    /// The paper and figure it mirrors.
    #[serde(default)]
    pub paper: String,
    /// The paper's claim, in one line.
    #[serde(default)]
    pub claim: String,
    /// Commentary for the report: how our setting differs, why we agree or not.
    #[serde(default)]
    pub notes: String,
    /// Seeds 1 ..= seeds for every cell.
    pub seeds: u64,
    /// A run taking longer is stopped and recorded as timed out.
    #[serde(default = "default_time_limit")]
    pub time_limit_s: f64,
    /// Simulator settings for every run.
    #[serde(default)]
    pub sim: SimSettings,
    /// The worlds.
    pub worlds: Vec<WorldEntry>,
    /// Team sizes.
    pub robots: Vec<usize>,
    /// Policies (with parameters).
    pub policies: Vec<PolicyEntry>,
    /// Communication ranges: "unlimited", metres ("5"), or a share of the
    /// map's diameter ("0.3d"). Default: unlimited only.
    #[serde(default)]
    pub comm_ranges: Vec<String>,
    /// Plots to draw.
    #[serde(default)]
    pub plots: Vec<PlotSpec>,
    /// Claims to test.
    #[serde(default)]
    pub checks: Vec<CheckSpec>,
    /// Draw a picture of seed 1 of every cell.
    #[serde(default)]
    pub pictures: bool,
    /// Figures tabulated per world beside the exploration time, e.g.
    /// `switches_per_100`, `t90`.
    #[serde(default)]
    pub tables: Vec<String>,
}

/// Longest a run may be given: a day.
const MAX_TIME_LIMIT_S: f64 = 86_400.0;

/// Most runs in one experiment: their list is made before the first starts,
/// and `seeds = 100000000000` made one until memory ran out.
const MAX_RUNS: u64 = 1_000_000;

fn default_time_limit() -> f64 {
    600.0
}

/// Simulator settings (the papers' values are the defaults).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimSettings {
    /// Cell size, metres (Burgard et al. 2005: 0.15).
    pub cell_size: f64,
    /// Sensor range, metres.
    pub sensor_range: f64,
    /// Field of view, degrees.
    pub fov: f64,
    /// Speed, m/s (0.5: a cell per step).
    pub speed: f64,
    /// Footprint radius, metres.
    pub footprint: f64,
    /// Heterogeneous teams: robot i takes model i mod len (overrides the above).
    pub models: Vec<ModelEntry>,
    /// Probability a move near another robot happens (0.7); 1: none.
    pub interference: f64,
    /// Interference distance, metres.
    pub interference_radius: f64,
    /// "random" (a seeded random start, as the papers), "auto" (roomiest cell).
    pub start: String,
    /// "together" or "spread".
    pub layout: String,
    /// Step limit per run.
    pub max_steps: u64,
}

impl Default for SimSettings {
    fn default() -> Self {
        Self {
            cell_size: 0.15,
            sensor_range: DEFAULT_MODEL.sensor_range_m,
            fov: 360.0,
            speed: DEFAULT_MODEL.speed_mps,
            footprint: 0.0,
            models: Vec::new(),
            interference: 0.7,
            interference_radius: 1.0,
            start: "random".into(),
            layout: "together".into(),
            max_steps: 30_000,
        }
    }
}

/// One robot model of a heterogeneous team.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelEntry {
    /// Sensor range, metres.
    pub sensor_range: f64,
    /// Field of view, degrees.
    pub fov: f64,
    /// Speed, m/s.
    pub speed: f64,
    /// Footprint radius, metres.
    pub footprint: f64,
}

/// A world of the matrix.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldEntry {
    /// Its name in the results.
    pub name: String,
    /// A map_server YAML, relative to the experiment file, or `$SHARED/…`
    /// for the shared collection (`EXPLORATION_SHARED_MAPS`).
    pub map: Option<String>,
    /// A generator: unstructured[:density], office, corridor, maze[:width], empty.
    pub generator: Option<String>,
    /// Generated width, metres.
    #[serde(default = "default_side")]
    pub width_m: f64,
    /// Generated height, metres.
    #[serde(default = "default_side")]
    pub height_m: f64,
    /// Cell size for this world, overriding the simulator's.
    pub cell_size: Option<f64>,
}

fn default_side() -> f64 {
    20.0
}

/// A policy of the matrix.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PolicyEntry {
    /// The policy.
    pub name: String,
    /// Its label in the results (default: the name).
    #[serde(default)]
    pub label: String,
    /// Parameter overrides.
    #[serde(default)]
    pub params: BTreeMap<String, f64>,
    /// Give the missions the worlds' rooms and corridors (Wurm et al. 2008,
    /// §VI) instead of segmenting online.
    #[serde(default)]
    pub given_segmentation: bool,
}

impl PolicyEntry {
    pub(crate) fn label(&self) -> &str {
        if self.label.is_empty() { &self.name } else { &self.label }
    }
}

/// A plot to draw from the results.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlotSpec {
    /// `time_vs_robots`, `coverage_over_time`, `gain_vs_robots`, `time_vs_comm_range`.
    pub kind: String,
    /// The figure plotted: steps, t50, t90, t95, t100, distance, replans, wall_time_s.
    #[serde(default = "default_metric")]
    pub metric: String,
    /// Only this world (default: one plot per world).
    pub world: Option<String>,
    /// Team size (coverage_over_time).
    pub robots: Option<usize>,
    /// Baseline label (gain_vs_robots).
    pub baseline: Option<String>,
    /// Labels plotted (default: all).
    #[serde(default)]
    pub policies: Vec<String>,
    /// Title (default: from the kind).
    #[serde(default)]
    pub title: String,
}

fn default_metric() -> String {
    "steps".into()
}

/// A claim to test on the results.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckSpec {
    /// What the claim says, in a few words.
    pub claim: String,
    /// `faster`: `better` significantly lower than `worse` (Welch, 95 %);
    /// `similar`: no significant difference; `gain`: mean gain of `better`
    /// over `worse` in percent, against `expected_gain`; `beats_best`: per
    /// team size, over all the worlds together, `better` against whichever
    /// of `against` has the lowest mean there, gaining at least
    /// `expected_gain` percent (0: not significantly worse).
    pub kind: String,
    /// Label expected better.
    pub better: String,
    /// Label compared with (not for `beats_best`).
    #[serde(default)]
    pub worse: String,
    /// For `beats_best`: the labels whose best it must beat (default: every other).
    #[serde(default)]
    pub against: Vec<String>,
    /// The figure compared.
    #[serde(default = "default_metric")]
    pub metric: String,
    /// Team sizes to test (default: all above 1).
    #[serde(default)]
    pub robots: Vec<usize>,
    /// Worlds to test (default: all).
    #[serde(default)]
    pub worlds: Vec<String>,
    /// Communication range to test (default: unlimited).
    pub comm_range: Option<String>,
    /// For `gain`: the paper's figure, percent.
    pub expected_gain: Option<f64>,
}

/// Why an experiment could not run.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    /// Reading or writing a file.
    #[error("{path}: {cause}")]
    Io {
        /// Which file.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// The configuration is not valid.
    #[error("{path}: {message}")]
    Config {
        /// Which file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Drawing a plot.
    #[error("plot {0}")]
    Plot(String),
}

pub(crate) fn io(path: &Path) -> impl Fn(std::io::Error) -> ExperimentError + '_ {
    move |cause| ExperimentError::Io { path: path.to_owned(), cause }
}

impl Experiment {
    /// Reads an experiment file.
    pub fn load(path: &Path) -> Result<Self, ExperimentError> {
        let text = coordinator::files::read_text_at_most(path, 1).map_err(io(path))?;
        let experiment: Self = toml::from_str(&text)
            .map_err(|e| ExperimentError::Config { path: path.to_owned(), message: e.to_string() })?;
        let bad = |message: String| ExperimentError::Config { path: path.to_owned(), message };
        if experiment.seeds == 0
            || experiment.worlds.is_empty()
            || experiment.robots.is_empty()
            || experiment.policies.is_empty()
        {
            return Err(bad("seeds, worlds, robots and policies must not be empty".into()));
        }
        if experiment.robots.contains(&0) {
            return Err(bad("robots: a team has at least one robot".into()));
        }
        let time_limit = experiment.time_limit_s;
        if !(time_limit > 0.0 && time_limit <= MAX_TIME_LIMIT_S) {
            return Err(bad(format!(
                "time_limit_s {}: give seconds above 0, at most {MAX_TIME_LIMIT_S} (a day)",
                ShortNumber(time_limit)
            )));
        }
        let ranges = experiment.comm_ranges.len().max(1) as u128;
        let runs = [experiment.worlds.len(), experiment.robots.len(), experiment.policies.len()]
            .iter()
            .fold(u128::from(experiment.seeds) * ranges, |n, &k| n.saturating_mul(k as u128));
        if runs > MAX_RUNS as u128 {
            return Err(bad(format!(
                "{runs} runs (seeds × worlds × ranges × team sizes × policies); an experiment has at most {MAX_RUNS}"
            )));
        }
        for w in &experiment.worlds {
            match (&w.map, &w.generator) {
                (Some(_), None) => {}
                (None, Some(g)) => {
                    Generator::parse(g).map_err(|e| bad(format!("world {:?}: generator {e}", w.name)))?;
                }
                _ => return Err(bad(format!("world {:?}: give either map or generator", w.name))),
            }
        }
        Interference::with(experiment.sim.interference, experiment.sim.interference_radius).map_err(bad)?;
        if experiment.sim.max_steps == 0 {
            return Err(bad("max_steps must be at least 1".into()));
        }
        for r in &experiment.comm_ranges {
            parse_range(r).map_err(|e| bad(format!("{e}, or unlimited")))?;
        }
        Ok(experiment)
    }
}

/// A communication range: `None` for unlimited.
pub(crate) fn parse_range(s: &str) -> Result<Option<CommRange>, String> {
    match s.trim() {
        "unlimited" => Ok(None),
        range => CommRange::parse(range).map(Some),
    }
}
