//! Building blocks on the exact inputs of `../shared/bench/peers.py` ("gen v1",
//! seed 42), so that each figure can be set against scipy / scikit-image
//! measured on the same machine in the same sitting. Each benchmark prints
//! the same `check` figures as the peer once, to show both solved the same
//! problem.

use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;

use exploration::assign::linear_sum_assignment;
use exploration::cost::{Corners, TraversalMap, cost_map_with};
use exploration::frontier::{Adjacency, FrontierMap, clusters};
use exploration::grid::{Cell, GridFrame, OccupancyGrid};
use exploration::math::Point2;
use exploration::segment::{distance_transform, padded_skeleton, skeletonize};

mod gen_v1;

const SEED: u64 = 42;

fn unit_frame(n: usize) -> GridFrame {
    GridFrame::new(1.0, Point2::origin(), n as u32, n as u32)
}

fn costmap(c: &mut Criterion) {
    let n = 2000;
    let occupied = gen_v1::obstacles(n, n, SEED);
    let frame = unit_frame(n);
    let costs: Vec<f32> = occupied.iter().map(|&o| if o { f32::INFINITY } else { 1.0 }).collect();
    let traversal = TraversalMap::from_costs(frame, costs);
    let source = Cell::new((n / 2) as i32, (n / 2) as i32);
    let map = cost_map_with(&traversal, &[source], Corners::Cut);
    let (mut reachable, mut sum, mut max) = (0u64, 0f64, 0f64);
    for cell in frame.bounds().cells() {
        if let Some(v) = map.cost(cell) {
            reachable += 1;
            sum += v;
            max = max.max(v);
        }
    }
    eprintln!("check costmap_8connected 2000x2000: reachable {reachable} max {max:.3} sum {sum:.1}");
    c.bench_function("costmap_8connected 2000x2000", |b| {
        b.iter(|| cost_map_with(black_box(&traversal), &[source], Corners::Cut))
    });
}

fn frontier(c: &mut Criterion) {
    let n = 2000;
    let values = gen_v1::occupancy(n, n, SEED);
    let cells: Vec<u8> = values
        .iter()
        .map(|&v| match v {
            gen_v1::FREE => 5,
            gen_v1::OCC => 100,
            _ => exploration::grid::UNKNOWN,
        })
        .collect();
    let grid = OccupancyGrid::from_cells(unit_frame(n), cells);
    let detect = || {
        let frontier = FrontierMap::detect_with(&grid, Adjacency::EdgesAndCorners);
        let clusters = clusters(&frontier, 1);
        (frontier, clusters)
    };
    let (frontier, clusters) = detect();
    eprintln!(
        "check frontier_label_centroids 2000x2000: frontier_cells {} clusters {} largest {}",
        frontier.len(),
        clusters.len(),
        clusters.iter().map(|c| c.len()).max().unwrap_or(0)
    );
    c.bench_function("frontier_mask 2000x2000", |b| {
        b.iter(|| FrontierMap::detect_with(black_box(&grid), Adjacency::EdgesAndCorners))
    });
    c.bench_function("frontier_label_centroids 2000x2000", |b| b.iter(detect));
}

fn distance_and_skeleton(c: &mut Criterion) {
    let n = 2000;
    let free: Vec<bool> = gen_v1::obstacles(n, n, SEED).iter().map(|&o| !o).collect();
    let squared = distance_transform(&free, n, n);
    let sum: f64 = squared.iter().filter(|&&d| d != u32::MAX).map(|&d| f64::from(d).sqrt()).sum();
    let sum_sq: u64 = squared.iter().filter(|&&d| d != u32::MAX).map(|&d| u64::from(d)).sum();
    let skeleton = skeletonize(&free, n, n);
    eprintln!(
        "check edt 2000x2000: sum {sum:.1} sum_sq_int {sum_sq}; skeleton 2000x2000: skeleton_cells {}",
        skeleton.iter().filter(|&&s| s).count()
    );
    c.bench_function("edt 2000x2000", |b| b.iter(|| distance_transform(black_box(&free), n, n)));
    c.bench_function("skeletonize 2000x2000", |b| b.iter(|| skeletonize(black_box(&free), n, n)));
    // What the segmentation runs: one distance transform feeds the thinning.
    c.bench_function("edt+skeleton 2000x2000", |b| b.iter(|| padded_skeleton(black_box(&free), n, n)));
}

fn assignment(c: &mut Criterion) {
    for (rows, cols) in [(200, 2000), (1000, 1000)] {
        let (q, f) = gen_v1::lsap(rows, cols, SEED);
        let solved = linear_sum_assignment(&f, rows, cols).unwrap();
        let total_q: i64 = solved.row_to_col.iter().enumerate().map(|(i, j)| q[i * cols + j.unwrap()]).sum();
        eprintln!("check lsap {rows}x{cols}: total_q {total_q} assigned {}", solved.row_to_col.len());
        c.bench_function(&format!("lsap {rows}x{cols}"), |b| {
            b.iter(|| linear_sum_assignment(black_box(&f), rows, cols).unwrap())
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10).warm_up_time(std::time::Duration::from_secs(1));
    targets = costmap, frontier, distance_and_skeleton, assignment
}
criterion_main!(benches);
