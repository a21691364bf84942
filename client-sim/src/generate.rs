//! Generated worlds, deterministic from a seed, for the environments the
//! papers describe but did not publish: unstructured (random obstacles at a
//! given density; Simmons et al. 2000's 15 %), office (rooms off a corridor;
//! Burgard et al. 2005 Fig. 8b, Simmons et al.'s environment A), corridor
//! (a network of corridors; Burgard et al. Fig. 8c) and maze (Bautin et al.
//! 2011, Fig. 7). Every world is closed by an outer wall.

use exploration::grid::{Cell, GridFrame};
use exploration::math::Point2;
use exploration::rng::SplitMix64;

use crate::world::{StartChoice, World, WorldError, check_grid};

/// What to generate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Generator {
    /// Axis-aligned rectangular obstacles until `density` of the area is covered.
    Unstructured {
        /// Share of the area covered by obstacles (0..1).
        density: f64,
    },
    /// One corridor along the long side with rooms off both sides, a door each.
    Office,
    /// A grid of corridors between solid blocks.
    Corridor,
    /// A perfect maze (one path between any two places) of corridors.
    Maze {
        /// Corridor width, metres.
        corridor_m: f64,
    },
    /// No obstacle but the outer wall.
    Empty,
}

impl Generator {
    /// Parses `unstructured`, `unstructured:0.15`, `office`, `corridor`, `maze`, `maze:1.2`, `empty`;
    /// the error says what was expected.
    pub fn parse(s: &str) -> Result<Self, String> {
        let (kind, arg) = s.split_once(':').map_or((s, None), |(k, a)| (k, Some(a)));
        // The number after the colon, within `range` (which the generator needs).
        let number = |default: f64, what: &str, range: std::ops::RangeInclusive<f64>| {
            let value = arg.map_or(Ok(default), |a| a.trim().parse::<f64>().map_err(|e| format!("{s:?}: {e}")))?;
            if range.contains(&value) {
                Ok(value)
            } else {
                Err(format!("{s:?}: the {what} must lie in [{}, {}]", range.start(), range.end()))
            }
        };
        Ok(match kind.trim() {
            "unstructured" => Self::Unstructured { density: number(0.15, "share of the area covered", 0.0..=0.9)? },
            "office" => Self::Office,
            "corridor" => Self::Corridor,
            "maze" => Self::Maze { corridor_m: number(1.2, "corridor width in metres", 0.15..=100.0)? },
            "empty" => Self::Empty,
            _ => return Err(format!("{s:?}: expected unstructured, office, corridor, maze or empty")),
        })
    }

    /// The name used in reports.
    pub fn name(&self) -> String {
        match self {
            Self::Unstructured { density } => format!("unstructured-{:.0}%", density * 100.0),
            Self::Office => "office".into(),
            Self::Corridor => "corridor".into(),
            Self::Maze { .. } => "maze".into(),
            Self::Empty => "empty".into(),
        }
    }
}

struct Canvas {
    frame: GridFrame,
    blocked: Vec<bool>,
}

impl Canvas {
    fn new(width_m: f64, height_m: f64, cell: f64) -> Self {
        let frame =
            GridFrame::new(cell, Point2::origin(), (width_m / cell).round() as u32, (height_m / cell).round() as u32);
        let mut canvas = Self { frame, blocked: vec![false; frame.len()] };
        let (w, h) = (frame.width as i32, frame.height as i32);
        canvas.fill(0, 0, w, 1, true);
        canvas.fill(0, h - 1, w, 1, true);
        canvas.fill(0, 0, 1, h, true);
        canvas.fill(w - 1, 0, 1, h, true);
        canvas
    }

    fn cells(&self, metres: f64) -> i32 {
        (metres / self.frame.resolution).round().max(1.0) as i32
    }

    /// Sets the rectangle x..x+w, y..y+h (clipped).
    fn fill(&mut self, x: i32, y: i32, w: i32, h: i32, value: bool) {
        for yy in y.max(0)..(y + h).min(self.frame.height as i32) {
            for xx in x.max(0)..(x + w).min(self.frame.width as i32) {
                let i = self.frame.index(Cell::new(xx, yy));
                self.blocked[i] = value;
            }
        }
    }
}

/// Generates a world of `width_m` × `height_m` at `cell` metres.
pub fn generate(
    generator: Generator,
    width_m: f64,
    height_m: f64,
    cell: f64,
    seed: u64,
    start: StartChoice,
) -> Result<World, WorldError> {
    check_grid(&generator.name(), width_m, height_m, cell)?;
    let mut canvas = Canvas::new(width_m, height_m, cell);
    let mut rng = SplitMix64::new(seed ^ 0x6765_6E65_7261_7465);
    let (w, h) = (canvas.frame.width as i32, canvas.frame.height as i32);
    // Where the generator knows doors: which cells they may be in (the office's corridor walls).
    let mut door_band = None;
    match generator {
        Generator::Empty => {}
        Generator::Unstructured { density } => {
            let target = (density.clamp(0.0, 0.9) * f64::from((w - 2) * (h - 2))) as usize;
            let (small, large) = (canvas.cells(0.3), canvas.cells(1.5));
            let mut covered = 0;
            let mut attempts = 0;
            while covered < target && attempts < 100_000 {
                attempts += 1;
                let ow = small + rng.below((large - small + 1) as u64) as i32;
                let oh = small + rng.below((large - small + 1) as u64) as i32;
                let x = 1 + rng.below((w - 1 - ow).max(1) as u64) as i32;
                let y = 1 + rng.below((h - 1 - oh).max(1) as u64) as i32;
                for yy in y..(y + oh).min(h - 1) {
                    for xx in x..(x + ow).min(w - 1) {
                        let i = canvas.frame.index(Cell::new(xx, yy));
                        if !canvas.blocked[i] {
                            canvas.blocked[i] = true;
                            covered += 1;
                        }
                    }
                }
            }
        }
        Generator::Office => {
            // A corridor along the middle of the long side, rooms off both sides:
            // the rooms are what the corridor walls (with their doors) enclose.
            let wall = canvas.cells(0.15);
            let corridor = canvas.cells(2.0);
            let door = canvas.cells(0.9);
            let horizontal = w >= h;
            let (long, short) = if horizontal { (w, h) } else { (h, w) };
            let c0 = short / 2 - corridor / 2;
            let c1 = c0 + corridor;
            let room = canvas.cells(4.0 + rng.next_f64() * 1.0);
            let mut set = |a: i32, b: i32, la: i32, lb: i32, v: bool| {
                if horizontal { canvas.fill(a, b, la, lb, v) } else { canvas.fill(b, a, lb, la, v) }
            };
            // Corridor walls.
            set(0, c0 - wall, long, wall, true);
            set(0, c1, long, wall, true);
            // Room partitions and doors, on both sides.
            let mut x = 0;
            while x < long {
                let width = room + rng.below((room / 3).max(1) as u64) as i32;
                let next = (x + width).min(long);
                if next < long - room / 2 {
                    set(next, 0, wall, c0, true);
                    set(next, c1, wall, short - c1, true);
                }
                // A door into each room (skip rooms too narrow for one).
                if next - x > door + 2 * wall {
                    let d = x + wall + rng.below((next - x - door - 2 * wall).max(1) as u64) as i32;
                    set(d, c0 - wall, door, wall, false);
                    let d = x + wall + rng.below((next - x - door - 2 * wall).max(1) as u64) as i32;
                    set(d, c1, door, wall, false);
                }
                x = next;
            }
            let in_corridor_wall = move |cell: Cell| {
                let across = if horizontal { cell.y } else { cell.x };
                (c0 - wall..c0).contains(&across) || (c1..c1 + wall).contains(&across)
            };
            door_band = Some(in_corridor_wall);
        }
        Generator::Corridor => {
            // Solid blocks between a grid of corridors.
            let corridor = canvas.cells(1.5);
            let block = canvas.cells(4.0);
            let mut y = corridor + 1;
            while y + block < h - corridor {
                let mut x = corridor + 1;
                while x + block < w - corridor {
                    let bw = block + rng.below((block / 2).max(1) as u64) as i32;
                    let bh = block + rng.below((block / 2).max(1) as u64) as i32;
                    canvas.fill(x, y, bw.min(w - 1 - corridor - x), bh.min(h - 1 - corridor - y), true);
                    x += bw + corridor;
                }
                y += block + block / 4 + corridor;
            }
        }
        Generator::Maze { corridor_m } => {
            // Randomized depth-first search over a lattice of corridor cells.
            let wall = canvas.cells(0.15);
            let pitch = canvas.cells(corridor_m) + wall;
            let (cols, rows) = (((w - wall) / pitch).max(1), ((h - wall) / pitch).max(1));
            canvas.fill(0, 0, w, h, true);
            let open = |canvas: &mut Canvas, cx: i32, cy: i32| {
                canvas.fill(wall + cx * pitch, wall + cy * pitch, pitch - wall, pitch - wall, false);
            };
            let mut visited = vec![false; (cols * rows) as usize];
            let mut stack = vec![(0i32, 0i32)];
            visited[0] = true;
            open(&mut canvas, 0, 0);
            while let Some(&(cx, cy)) = stack.last() {
                let mut options: Vec<(i32, i32)> = [(1, 0), (-1, 0), (0, 1), (0, -1)]
                    .into_iter()
                    .map(|(dx, dy)| (cx + dx, cy + dy))
                    .filter(|&(nx, ny)| {
                        nx >= 0 && ny >= 0 && nx < cols && ny < rows && !visited[(ny * cols + nx) as usize]
                    })
                    .collect();
                if options.is_empty() {
                    stack.pop();
                    continue;
                }
                let (nx, ny) = options.swap_remove(rng.below(options.len() as u64) as usize);
                visited[(ny * cols + nx) as usize] = true;
                open(&mut canvas, nx, ny);
                // Knock out the wall between the two lattice cells.
                let (x0, y0) = (wall + cx.min(nx) * pitch, wall + cy.min(ny) * pitch);
                if nx != cx {
                    canvas.fill(x0 + pitch - wall, y0, wall, pitch - wall, false);
                } else {
                    canvas.fill(x0, y0 + pitch - wall, pitch - wall, wall, false);
                }
                stack.push((nx, ny));
            }
        }
    }
    let name = generator.name();
    let rooms = door_band.map(|is_door| crate::world::rooms_behind_doors(&canvas.frame, &canvas.blocked, is_door));
    let mut world = World::from_blocked(&name, canvas.frame, canvas.blocked, start, seed)?;
    world.rooms = rooms;
    Ok(world)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generators_are_deterministic_closed_and_connected_enough() {
        for generator in ["unstructured", "office", "corridor", "maze", "empty"] {
            let g = Generator::parse(generator).unwrap();
            let a = generate(g, 20.0, 15.0, 0.15, 7, StartChoice::Random).unwrap();
            let b = generate(g, 20.0, 15.0, 0.15, 7, StartChoice::Random).unwrap();
            assert_eq!(a.blocked, b.blocked, "{generator}");
            assert_eq!(a.start, b.start, "{generator}");
            let c = generate(g, 20.0, 15.0, 0.15, 8, StartChoice::Random).unwrap();
            if generator != "empty" {
                assert_ne!(a.blocked, c.blocked, "{generator}: another seed, another world");
            }
            // Closed: the border is wall.
            let f = a.frame;
            assert!((0..f.width as i32).all(|x| a.is_blocked(Cell::new(x, 0))));
            // Most free space is one connected area.
            let free = a.blocked.iter().filter(|b| !**b).count();
            assert!(a.reachable_cells * 10 >= free * 6, "{generator}: {} of {free}", a.reachable_cells);
        }
        let u = generate(Generator::Unstructured { density: 0.15 }, 20.0, 20.0, 0.15, 1, StartChoice::Auto).unwrap();
        let inner = ((u.frame.width - 2) * (u.frame.height - 2)) as f64;
        let walls =
            u.blocked.iter().filter(|b| **b).count() as f64 - 2.0 * f64::from(u.frame.width + u.frame.height) + 4.0;
        assert!((walls / inner - 0.15).abs() < 0.02, "density {}", walls / inner);
        assert!(Generator::parse("lava").is_err());
        // Numbers the generators cannot honour are refused, not clamped or wrapped.
        for bad in ["unstructured:2", "unstructured:-1", "unstructured:NaN", "maze:0", "maze:1e30", "maze:x"] {
            assert!(Generator::parse(bad).is_err(), "{bad}");
        }
        assert_eq!(Generator::parse("maze:0.8"), Ok(Generator::Maze { corridor_m: 0.8 }));
    }

    /// The office's rooms are the generator's own: the corridor, and one
    /// room per door-bounded space off it; every free cell is in one.
    #[test]
    fn an_office_knows_its_rooms() {
        let office = generate(Generator::Office, 25.0, 20.0, 0.15, 3, StartChoice::Auto).unwrap();
        let rooms = office.given_rooms();
        assert_eq!(rooms.len(), office.frame.len());
        for (i, &blocked) in office.blocked.iter().enumerate() {
            assert_eq!(rooms[i] == 0, blocked, "cell {:?}", office.frame.cell(i));
        }
        let mut labels: Vec<u32> = rooms.iter().copied().filter(|&l| l != 0).collect();
        labels.sort_unstable();
        labels.dedup();
        // 25 m of 4–6.7 m rooms on each side: 8 to 14 rooms, and the corridor.
        assert!((9..=15).contains(&labels.len()), "{} rooms", labels.len());
        // The corridor (along the middle of the long side) is one room from end to end.
        let y = office.frame.height as i32 / 2;
        let corridor = rooms[office.frame.index(Cell::new(1, y))];
        let along: Vec<u32> =
            (1..office.frame.width as i32 - 1).map(|x| rooms[office.frame.index(Cell::new(x, y))]).collect();
        assert!(along.iter().all(|&l| l == corridor), "{along:?}");
        // Worlds without known rooms get the segmentation of the complete map.
        let maze = generate(Generator::Maze { corridor_m: 1.2 }, 10.0, 10.0, 0.15, 3, StartChoice::Auto).unwrap();
        assert!(maze.rooms.is_none());
        assert!(maze.given_rooms().iter().any(|&l| l != 0));
    }
}
