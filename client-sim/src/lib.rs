//! A simulated robot fleet that explores real building maps against the
//! exploration executive over gRPC, both to reproduce the papers' results
//! and as a load test.
//!
//! - [`world`]: ground-truth worlds from ROS map_server maps.
//! - [`robot`]: one simulated robot: sensor, motion, its own gRPC client.
//! - [`fleet`]: runs a mission with N robots and measures it.

pub mod fleet;
pub mod robot;
pub mod world;

pub use fleet::{RunConfig, RunReport, SimError, run};
