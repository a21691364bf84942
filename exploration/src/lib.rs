//! Pure algorithms for coordinated multi-robot exploration.
//!
//! No I/O, no async, no protocol types: plain data in, plain data out, so the
//! executive (`server/`) and the simulated fleet (`client-sim/`) share one
//! implementation of every piece.
//!
//! - [`grid`]: the grid frame (cell ↔ world), occupancy grids, cell classes.
//! - [`fusion`]: fuses robots' map patches into one grid without counting a
//!   robot's observation twice.
//! - [`frontier`]: frontier cells and their clusters.
//! - [`cost`]: traversal costs, cost maps (wavefront, Dijkstra, Burgard's
//!   value iteration), obstacle inflation, smoothing, paths, a per-replanning cache.
//! - [`visibility`]: ray casting and the range-sensor model shared with the simulator.
//! - [`policy`]: the coordination policies of the literature behind one interface.
//! - [`rng`]: the seeded SplitMix64 generator every random choice uses.
//!
//! The papers behind the policies are in the repository's `docs/papers.md`.

pub mod cost;
pub mod frontier;
pub mod fusion;
pub mod grid;
pub mod math;
pub mod policy;
pub mod rng;
pub mod visibility;
