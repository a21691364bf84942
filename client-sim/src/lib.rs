//! A simulated robot fleet that explores real building maps against the
//! exploration executive over gRPC, both to reproduce the papers' results
//! and as a load test.
//!
//! - [`world`]: ground-truth worlds from ROS map_server maps.
//! - [`generate`]: generated worlds (unstructured, office, corridor, maze).
//! - [`robot`]: one simulated robot: sensor, motion, its own gRPC client.
//! - [`fleet`]: runs a mission with N robots and measures it.
//! - [`experiment`]: matrices of runs, in parallel, resumable.
//! - [`runs`]: their results, `runs.csv` and `summary.csv`.
//! - [`bound`]: how few steps any policy could take in a run.
//! - [`plots`], [`picture`], [`stats`], [`report`]: what the experiments show.
//! - [`console`]: the tools' lines on standard output and error, which may be closed early.

pub mod bound;
pub mod console;
pub mod experiment;
pub mod fleet;
pub mod generate;
pub mod load;
pub mod picture;
pub mod plots;
pub mod report;
pub mod robot;
pub mod runs;
pub mod stats;
pub mod world;

pub use fleet::{RunConfig, RunReport, SimError, run};
