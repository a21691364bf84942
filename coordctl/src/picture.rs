//! The fused map as a picture: occupancy in grey levels, frontier in orange,
//! segments tinted, forbidden regions outlined in red, each robot as a disc
//! with a line to its target (a square).

use anyhow::{Context, ensure};

use client_sim::picture::{PALETTE, Picture, segment_tint};
use exploration::grid::{Cell, GridFrame};
use exploration::math::Point2;
use exploration_proto::v1 as pb;

const UNKNOWN: [u8; 3] = [190, 200, 215];
const FRONTIER: [u8; 3] = [255, 140, 0];
const FORBIDDEN: [u8; 3] = [220, 0, 0];

/// Draws `snapshot` with `regions` outlined and, when given, the segment
/// `labels` (one per cell) tinting the free space.
pub fn render(
    snapshot: &pb::MapSnapshot,
    regions: &[pb::Region],
    labels: Option<&[u32]>,
    target_px: u32,
) -> anyhow::Result<Picture> {
    let frame = snapshot.frame.context("the executive sent a map without its frame")?;
    let origin = frame.origin.unwrap_or_default();
    let grid = GridFrame::new(frame.resolution, Point2::new(origin.x, origin.y), frame.width, frame.height);
    ensure!(
        snapshot.cells.len() == grid.len(),
        "the executive sent {} cells for a {} x {} map",
        snapshot.cells.len(),
        frame.width,
        frame.height
    );
    let label = |index: usize| -> u32 { labels.and_then(|l| l.get(index)).copied().unwrap_or(0) };
    let mut is_frontier = vec![false; grid.len()];
    if snapshot.frontier_mask.len() == grid.len().div_ceil(8) {
        for (index, flag) in is_frontier.iter_mut().enumerate() {
            *flag = snapshot.frontier_mask[index / 8] >> (index % 8) & 1 == 1;
        }
    } else {
        // An executive from before the mask lists every frontier cell.
        for point in &snapshot.frontier {
            if let Some(cell) = grid.cell_from_world(&Point2::new(point.x, point.y)) {
                is_frontier[grid.index(cell)] = true;
            }
        }
    }
    let mut picture = Picture::new(grid, target_px, |cell: Cell| {
        let index = grid.index(cell);
        match snapshot.cells[index] {
            _ if is_frontier[index] => FRONTIER,
            255 => UNKNOWN,
            p if p < 50 && label(index) > 0 => segment_tint(label(index)),
            p => {
                let level = 255 - (u32::from(p.min(100)) * 255 / 100) as u8;
                [level, level, level]
            }
        }
    });
    let cell_of = |p: pb::Point| grid.cell_from_world_unchecked(&Point2::new(p.x, p.y));
    for region in regions {
        let Some(a) = region.area else { continue };
        let corners =
            [(a.min_x, a.min_y), (a.max_x, a.min_y), (a.max_x, a.max_y), (a.min_x, a.max_y), (a.min_x, a.min_y)]
                .map(|(x, y)| cell_of(pb::Point { x, y }));
        picture.path(&corners, FORBIDDEN);
        picture.path(&[corners[0], corners[2]], FORBIDDEN);
        picture.path(&[corners[1], corners[3]], FORBIDDEN);
    }
    for (i, robot) in snapshot.robots.iter().enumerate() {
        let colour = PALETTE[i % PALETTE.len()];
        let pose = robot.pose.unwrap_or_default();
        let at = cell_of(pb::Point { x: pose.x, y: pose.y });
        if let Some(target) = robot.target.filter(|_| robot.task_id != 0) {
            let goal = cell_of(target);
            picture.path(&[at, goal], colour);
            picture.marker(goal, colour, true);
        }
        picture.marker(at, colour, false);
    }
    Ok(picture)
}
