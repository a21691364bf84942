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
//! - [`segment`]: distance transform, skeleton, critical points and
//!   segments of the explored map.
//! - [`assign`]: optimal assignment (the Hungarian problem) by shortest
//!   augmenting paths.
//! - [`policy`]: the coordination policies of the literature behind one interface.
//! - [`completion`]: whether any robot can still explore the remaining frontier, and why not.
//! - [`rng`]: the seeded SplitMix64 generator every random choice uses.
//! - [`workers`]: the threads a replanning may use, and the hook that paces them.
//!
//! The papers behind the policies are in the repository's `docs/papers.md`.

pub mod assign;
pub mod completion;
pub mod cost;
pub mod frontier;
pub mod fusion;
pub mod grid;
pub mod math;
pub mod policy;
pub mod rng;
pub mod segment;
pub mod visibility;
pub mod workers;

#[cfg(test)]
pub(crate) mod testing {
    //! Test support shared by the modules.

    /// Property-test settings with a fixed seed, so that every run checks the
    /// same cases, and no regression files written into the source tree.
    pub fn seeded_proptest(cases: u32) -> proptest::test_runner::Config {
        proptest::test_runner::Config {
            cases,
            rng_seed: proptest::test_runner::RngSeed::Fixed(0x5EED),
            failure_persistence: None,
            ..proptest::test_runner::Config::default()
        }
    }
}
