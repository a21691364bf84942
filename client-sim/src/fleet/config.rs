//! What one run is: the world, the team, the policy and the papers'
//! simulator models, each a setting with the paper's value as its default.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use exploration::math::ShortNumber;

use crate::generate::{Generator, generate};
use crate::robot::RobotModel;
use crate::world::{StartChoice, World, WorldError};

/// Which world to explore.
#[derive(Debug, Clone, PartialEq)]
pub enum WorldSpec {
    /// A ROS map_server map (YAML).
    Map(PathBuf),
    /// A generated world of the given size, metres.
    Generated {
        /// What kind.
        generator: Generator,
        /// Width, metres.
        width_m: f64,
        /// Height, metres.
        height_m: f64,
    },
}

impl WorldSpec {
    /// Builds the world for a run.
    pub fn build(&self, cell_size: Option<f64>, start: StartChoice, seed: u64) -> Result<World, WorldError> {
        match self {
            Self::Map(path) => World::load(path, cell_size, start, seed),
            Self::Generated { generator, width_m, height_m } => {
                generate(*generator, *width_m, *height_m, cell_size.unwrap_or(0.15), seed, start)
            }
        }
    }
}

/// Robots close to each other slow each other down (Burgard et al. 2005,
/// §IV-C: "whenever robots are close to each other, the system performs the
/// planned movement with a probability of 0.7").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Interference {
    /// Closer than this (metres), robots interfere.
    pub radius_m: f64,
    /// Probability that a planned move happens when they do.
    pub success: f64,
}

impl Interference {
    /// Interference where a move near another robot (closer than
    /// `radius_m`) happens with probability `success`; none when `success`
    /// is 1. NaN or values outside their ranges are refused, not clamped.
    pub fn with(success: f64, radius_m: f64) -> Result<Option<Self>, String> {
        if !(0.0..=1.0).contains(&success) {
            return Err(format!("interference {}: a move's probability must lie in [0, 1]", ShortNumber(success)));
        }
        if !(radius_m.is_finite() && radius_m >= 0.0) {
            return Err(format!(
                "interference radius {}: give a finite distance of 0 metres or more",
                ShortNumber(radius_m)
            ));
        }
        Ok((success < 1.0).then_some(Self { radius_m, success }))
    }
}

/// How far robots can communicate (Burgard et al. 2005, §II-D).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommRange {
    /// In metres.
    Metres(f64),
    /// As a share of the map's diameter (Fig. 12's axis).
    OfDiameter(f64),
}

impl CommRange {
    /// Metres (`5`, `5m`) or a share of the map's diameter (`0.3d`); a range
    /// must be a positive number.
    pub fn parse(text: &str) -> Result<Self, String> {
        let text = text.trim();
        let (range, number) = match text.strip_suffix('d') {
            Some(share) => (Self::OfDiameter as fn(f64) -> Self, share),
            None => (Self::Metres as fn(f64) -> Self, text.strip_suffix('m').unwrap_or(text)),
        };
        match number.trim().parse::<f64>() {
            Ok(value) if value.is_finite() && value > 0.0 => Ok(range(value)),
            _ => Err(format!(
                "communication range {text:?}: give a positive number of metres (5) or a share of the map's diameter (0.3d)"
            )),
        }
    }

    /// The range in metres on `world`.
    pub fn metres(&self, world: &World) -> f64 {
        match self {
            Self::Metres(m) => *m,
            Self::OfDiameter(f) => f * world.diameter_m(),
        }
    }
}

/// A failure injected into one robot of the team.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fault {
    /// The robot, by index (robot-0 is 0).
    pub robot: usize,
    /// What goes wrong.
    pub kind: FaultKind,
}

/// What goes wrong with a robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FaultKind {
    /// From this step on it is silent and still: the executive's lease runs out.
    Dies(u64),
    /// From this step on it cannot move but reports: the executive sees it stall.
    Freezes(u64),
    /// It reports targets inside this world rectangle (min, max corners) unreachable.
    CannotReach(exploration::math::Point2, exploration::math::Point2),
}

/// Where the team starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Layout {
    /// Packed around the start cell, one robot per cell (the papers' teams
    /// start close to each other).
    #[default]
    Together,
    /// Each robot at its own random cell of the main free area.
    Spread,
}

/// Everything a run is made of.
#[derive(Debug, Clone)]
pub struct RunConfig {
    /// The world.
    pub world: WorldSpec,
    /// Team size.
    pub robots: usize,
    /// Coordination policy.
    pub policy: String,
    /// Policy parameter overrides.
    pub params: BTreeMap<String, f64>,
    /// Seed of every random choice.
    pub seed: u64,
    /// An executive to use; `None` starts one on loopback.
    pub server: Option<String>,
    /// Operator token of the executive: the one `server` requires, or the
    /// one the embedded executive is started with (a random one if `None`).
    pub token: Option<String>,
    /// TLS settings for `server` (an `https://` URL).
    pub tls: Option<exploration_proto::client::ClientTls>,
    /// Database of the embedded executive; `None` uses a temporary file.
    pub db: Option<PathBuf>,
    /// Simulation cell size, metres; `None` keeps a map's own.
    pub cell_size: Option<f64>,
    /// The robots' models, robot i taking model i mod len (heterogeneous teams).
    pub models: Vec<RobotModel>,
    /// Where the team starts.
    pub start: StartChoice,
    /// Together or spread.
    pub layout: Layout,
    /// Interference between close robots; `None` for none.
    pub interference: Option<Interference>,
    /// Limited communication; `None` for unlimited.
    pub comm_range: Option<CommRange>,
    /// Give up after this many steps.
    pub max_steps: u64,
    /// Give up after this many steps in which no robot has a task, or 10×
    /// this many in which the team learns nothing new.
    pub stall_steps: u64,
    /// How long a robot keeps retrying an unreachable executive.
    pub retry_budget: Duration,
    /// Robots of a bidding policy (`simmons`) bid every this many steps.
    pub bid_every: u64,
    /// Print progress to stderr.
    pub progress: bool,
    /// Failures to inject.
    pub faults: Vec<Fault>,
    /// The mission's lease, seconds; `None` keeps the executive's default.
    pub lease_s: Option<f64>,
    /// The mission's stall timeout, seconds; `None` keeps the executive's default.
    pub stall_s: Option<f64>,
    /// Wall-clock time per step, to watch or steer a run as it happens;
    /// `None` runs as fast as the executive answers.
    pub pace: Option<Duration>,
    /// After exploration, keep stepping while the executive sends the robots
    /// home, until every live robot is there (or `max_steps` more steps).
    pub return_home: bool,
    /// Give the mission the world's rooms and corridors (Wurm et al. 2008,
    /// §VI; see [`World::given_rooms`]) instead of letting it segment the
    /// explored map online.
    pub given_segmentation: bool,
    /// Serve the embedded executive's live web view at this address (port 0:
    /// any free port); its URL and a read-only token are printed.
    pub view: Option<SocketAddr>,
    /// After the run, keep the embedded executive (and its view) serving
    /// until Ctrl-C, for a person still looking.
    pub linger: bool,
}

/// The robot of the papers' simulations: 360° sensor of 4 m, point-sized, 0.5 m/s.
pub const DEFAULT_MODEL: RobotModel = RobotModel {
    sensor_range_m: 4.0,
    field_of_view_rad: std::f64::consts::TAU,
    speed_mps: 0.5,
    footprint_radius_m: 0.0,
};

impl RunConfig {
    /// A run of `robots` robots with `policy` on the map at `map`, with the defaults.
    pub fn new(map: impl Into<PathBuf>, robots: usize, policy: &str) -> Self {
        Self::on(WorldSpec::Map(map.into()), robots, policy)
    }

    /// A run of `robots` robots with `policy` in `world`, with the defaults.
    pub fn on(world: WorldSpec, robots: usize, policy: &str) -> Self {
        Self {
            world,
            robots,
            policy: policy.to_owned(),
            params: BTreeMap::new(),
            seed: 1,
            server: None,
            token: None,
            tls: None,
            db: None,
            cell_size: Some(0.15),
            models: vec![DEFAULT_MODEL],
            start: StartChoice::Auto,
            layout: Layout::Together,
            interference: Some(Interference { radius_m: 1.0, success: 0.7 }),
            comm_range: None,
            max_steps: 50_000,
            view: None,
            linger: false,
            stall_steps: 200,
            retry_budget: Duration::from_secs(120),
            bid_every: 5,
            progress: false,
            faults: Vec::new(),
            lease_s: None,
            stall_s: None,
            pace: None,
            return_home: false,
            given_segmentation: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn communication_ranges_read_in_metres_or_of_the_diameter() {
        let world = generate(Generator::Empty, 30.0, 40.0, 0.5, 1, StartChoice::Auto).unwrap();
        assert_eq!(CommRange::Metres(7.0).metres(&world), 7.0);
        assert!((CommRange::OfDiameter(0.3).metres(&world) - 15.0).abs() < 1e-9);
        assert_eq!(Interference::with(0.7, 1.0), Ok(Some(Interference { radius_m: 1.0, success: 0.7 })));
        assert_eq!(Interference::with(1.0, 1.0), Ok(None), "1: no interference");
        for (success, radius) in [(f64::NAN, 1.0), (1.5, 1.0), (-0.1, 1.0), (0.7, f64::NAN), (0.7, -1.0)] {
            assert!(Interference::with(success, radius).is_err(), "{success} {radius}");
        }
        assert_eq!(CommRange::parse(" 5m "), Ok(CommRange::Metres(5.0)));
        assert_eq!(CommRange::parse("0.3d"), Ok(CommRange::OfDiameter(0.3)));
        for bad in ["NaN", "-2", "0", "infd", "five", ""] {
            assert!(CommRange::parse(bad).is_err(), "{bad:?}");
        }
    }
}
