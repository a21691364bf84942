//! One replanning per policy, for 10 and 50 robots, on the largest shared map
//! (`stage_hospital`, 1 400 × 534 cells at 0.1 m) half explored, and for 50
//! robots with a tenth of it known (early in a mission); and for 200 robots
//! on a generated office four times its area, half explored.
//!
//! The shared maps are read from `EXPLORATION_SHARED_MAPS` (or
//! `../shared/maps` beside the workspace); without them the bench says so and
//! runs on the largest bundled map instead.
//!
//! The explored state: the free cells nearest to the start by path length,
//! up to half (or a tenth) of the reachable area, are known, with the walls
//! around them; the robots stand on known free cells drawn with a fixed seed.

use std::collections::VecDeque;
use std::path::PathBuf;

use criterion::{Criterion, criterion_group, criterion_main};

/// The allocator the coordinator and fleet-sim run with.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use client_sim::generate::{Generator, generate};
use client_sim::world::{StartChoice, World};
use exploration::cost::CostCache;
use exploration::frontier::{FrontierMap, clusters};
use exploration::grid::{Cell, OccupancyGrid, UNKNOWN};
use exploration::policy::{Capabilities, PlanningInput, PolicyConfig, RobotView, catalogue};
use exploration::rng::SplitMix64;
use exploration::workers::Workers;

fn map() -> PathBuf {
    let shared = std::env::var_os("EXPLORATION_SHARED_MAPS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/maps"));
    let hospital = shared.join("stage_hospital.yaml");
    if hospital.exists() {
        hospital
    } else {
        eprintln!(
            "NOTE: {} not found (set EXPLORATION_SHARED_MAPS); benchmarking the bundled nav2_warehouse instead",
            hospital.display()
        );
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../maps/nav2_warehouse.yaml")
    }
}

/// Known: the reachable free cells closest to the start, `percent` of them,
/// and every wall cell touching them.
fn explored(world: &World, percent: usize) -> OccupancyGrid {
    let frame = world.frame;
    let mut grid = OccupancyGrid::unknown(frame);
    let mut queue = VecDeque::from([world.start]);
    let mut seen = vec![false; frame.len()];
    seen[frame.index(world.start)] = true;
    let mut known = 0;
    while let Some(c) = queue.pop_front() {
        if known * 100 >= world.reachable_cells * percent {
            break;
        }
        grid.set(c, 12);
        known += 1;
        for (dx, dy) in exploration::grid::NEIGHBOURS_8 {
            let n = Cell::new(c.x + dx, c.y + dy);
            if !frame.contains(n) {
                continue;
            }
            let i = frame.index(n);
            if world.blocked[i] {
                grid.set(n, 97);
            } else if !seen[i] && (dx == 0 || dy == 0) {
                seen[i] = true;
                queue.push_back(n);
            }
        }
    }
    grid
}

fn replan(c: &mut Criterion) {
    let path = map();
    let hospital = World::load(&path, Some(0.1), StartChoice::Auto, 0).expect("the map loads");
    plan_every_policy(c, &hospital, 50, &[10, 50]);
    // Early in a mission: a tenth of it known.
    plan_every_policy(c, &hospital, 10, &[50]);
    // Issue 11's second size: 200 robots on a generated office four times
    // the hospital's area (280 × 107 m at 0.1 m), half explored.
    let (w, h) = (hospital.frame.width as f64 * 0.2, hospital.frame.height as f64 * 0.2);
    let office = generate(Generator::Office, w, h, 0.1, 1, StartChoice::Auto).expect("the office generates");
    plan_every_policy(c, &office, 50, &[200]);
}

/// One replanning of every policy, for each team size in `teams`, on
/// `world` with `percent` of its reachable cells known.
fn plan_every_policy(c: &mut Criterion, world: &World, percent: usize, teams: &[usize]) {
    let grid = explored(world, percent);
    let frame = *grid.frame();
    let frontier = FrontierMap::detect(&grid);
    let free: Vec<Cell> = (0..frame.len()).filter(|&i| grid.value_at(i) == 12).map(|i| frame.cell(i)).collect();
    eprintln!(
        "map {}: {}×{} cells, {} known free, {} frontier cells, {} unknown",
        world.name,
        frame.width,
        frame.height,
        free.len(),
        frontier.len(),
        grid.cells().iter().filter(|&&v| v == UNKNOWN).count()
    );
    let mut rng = SplitMix64::new(42);
    let largest = teams.iter().copied().max().unwrap_or(0);
    let all_robots: Vec<RobotView> = (0..largest as u64)
        .map(|i| RobotView {
            id: i,
            cell: free[rng.below(free.len() as u64) as usize],
            capabilities: Capabilities {
                sensor_range_m: 4.0,
                field_of_view_rad: std::f64::consts::TAU,
                speed_mps: 0.5,
                footprint_radius_m: 0.0,
            },
            current: None,
            excluded: Vec::new(),
        })
        .collect();
    let known = if percent == 50 { String::new() } else { format!(" {percent}% known") };
    let mut group = c.benchmark_group(format!("replan {}{known}", world.name));
    group.sample_size(10);
    for descriptor in catalogue() {
        let config = PolicyConfig::default_for(descriptor.name).unwrap();
        let policy = config.build();
        let clusters = clusters(&frontier, config.min_frontier_size());
        for &n in teams {
            let robots = &all_robots[..n];
            let bids = vec![Vec::new(); n];
            let input = PlanningInput {
                grid: &grid,
                clusters: &clusters,
                robots,
                workers: Workers::unpaced(2),
                bids: &bids,
                seed: 1,
                reserved: &[],
                rooms: None,
            };
            group.bench_function(format!("{} {n} robots", descriptor.name), |b| {
                b.iter(|| policy.plan(&input, &mut CostCache::new(&grid)))
            });
        }
    }
    group.finish();
}

criterion_group!(benches, replan);
criterion_main!(benches);
