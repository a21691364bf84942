//! Ground-truth worlds: ROS map_server maps, coarsened to the simulation's
//! cells, with the start cell and the free space reachable from it.
//!
//! Pixel rule (map_server, `negate: 0`): p = (255 − v) / 255; occupied if
//! p > occupied_thresh, free if p < free_thresh, unknown otherwise. Unknown
//! pixels (hollow wall cores, the outside of a drawing) are walls of the
//! ground truth, and so is everything beyond the image border. A coarse cell
//! is free only if every pixel it touches is free: averaging would open holes
//! in the one-pixel walls many of these maps have.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use exploration::grid::{Cell, GridFrame, NEIGHBOURS_8, OccupancyGrid};
use exploration::math::Point2;
use exploration::rng::SplitMix64;
use exploration::segment::{DEFAULT_MIN_DROP_M, DEFAULT_MIN_SEGMENT_M2, segment_complete};

/// Why a map could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum WorldError {
    /// A file could not be read.
    #[error("cannot read {path}: {cause}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: std::io::Error,
    },
    /// The YAML is not a map_server description.
    #[error("{path}: {message}")]
    Yaml {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The image does not decode.
    #[error("cannot decode image {path}: {cause}")]
    Image {
        /// The file.
        path: PathBuf,
        /// Why.
        cause: image::ImageError,
    },
    /// Nothing to explore.
    #[error("{0}")]
    Empty(String),
    /// A size or cell size no executive would take.
    #[error("{0}")]
    Size(String),
}

/// Refuses a world of `width_m` × `height_m` at `cell` metres that is not a
/// grid an executive takes, by the executive's own check of a mission's
/// grid (`coordinator::validate::frame`), before its cells are allocated: a
/// mistyped `--cell-size 0` or `--size 1e9x1e9` would otherwise ask for more
/// memory than there is.
pub fn check_grid(name: &str, width_m: f64, height_m: f64, cell: f64) -> Result<(), WorldError> {
    let refuse = |why: String| Err(WorldError::Size(format!("{name}: {why}")));
    if !(width_m.is_finite() && width_m > 0.0 && height_m.is_finite() && height_m > 0.0) {
        return refuse(format!("the size must be positive metres, not {width_m} × {height_m}"));
    }
    // `as` saturates what no i64 holds; the check then refuses it.
    let cells = |metres: f64| (metres / cell).ceil() as i64;
    match coordinator::validate::frame(cell, Point2::origin(), cells(width_m), cells(height_m), "") {
        Ok(_) => Ok(()),
        Err(e) => refuse(format!("{e} (a world of {} × {} m in cells of {cell} m)", short(width_m), short(height_m))),
    }
}

/// A length for a message: centimetres, or an exponent where the figure
/// would run to hundreds of digits (a resolution of 1e300 in a YAML).
fn short(metres: f64) -> String {
    if metres.abs() < 1e7 { format!("{metres:.2}") } else { format!("{metres:.3e}") }
}

/// What a map_server YAML says.
#[derive(Debug, Clone, PartialEq)]
pub struct MapDescription {
    /// The image file, resolved against the YAML's folder.
    pub image: PathBuf,
    /// Metres per pixel.
    pub resolution: f64,
    /// World position of the lower-left pixel's corner.
    pub origin: Point2,
    /// Whether black means free.
    pub negate: bool,
    /// Above this, a pixel is occupied.
    pub occupied_thresh: f64,
    /// Below this, a pixel is free.
    pub free_thresh: f64,
}

impl MapDescription {
    /// Reads a map_server YAML file.
    pub fn load(path: &Path) -> Result<Self, WorldError> {
        let text = coordinator::files::read_text_at_most(path, 1)
            .map_err(|cause| WorldError::Io { path: path.to_owned(), cause })?;
        let yaml_error = |message: String| WorldError::Yaml { path: path.to_owned(), message };
        let docs = yaml_rust2::YamlLoader::load_from_str(&text).map_err(|e| yaml_error(e.to_string()))?;
        let doc = docs.first().ok_or_else(|| yaml_error("empty document".into()))?;
        let number = |key: &str| -> Result<f64, WorldError> {
            let v = &doc[key];
            v.as_f64()
                .or_else(|| v.as_i64().map(|i| i as f64))
                .ok_or_else(|| yaml_error(format!("`{key}` is missing or not a number")))
        };
        let image = doc["image"].as_str().ok_or_else(|| yaml_error("`image` is missing".into()))?;
        let origin = doc["origin"]
            .as_vec()
            .filter(|v| v.len() >= 2)
            .ok_or_else(|| yaml_error("`origin` must be [x, y, yaw]".into()))?;
        let coordinate = |i: usize| {
            origin[i]
                .as_f64()
                .or_else(|| origin[i].as_i64().map(|v| v as f64))
                .ok_or_else(|| yaml_error("`origin` holds a non-number".into()))
        };
        let negate = match &doc["negate"] {
            yaml_rust2::Yaml::Integer(i) => *i != 0,
            yaml_rust2::Yaml::Boolean(b) => *b,
            yaml_rust2::Yaml::BadValue => false,
            other => return Err(yaml_error(format!("`negate` is {other:?}"))),
        };
        let folder = path.parent().unwrap_or(Path::new("."));
        let description = Self {
            image: folder.join(image),
            resolution: number("resolution")?,
            origin: Point2::new(coordinate(0)?, coordinate(1)?),
            negate,
            occupied_thresh: number("occupied_thresh")?,
            free_thresh: number("free_thresh")?,
        };
        if description.resolution.is_nan() || description.resolution <= 0.0 {
            return Err(yaml_error("`resolution` must be positive".into()));
        }
        Ok(description)
    }
}

/// The true world the simulated robots move in.
#[derive(Debug, Clone)]
pub struct World {
    /// Its grid in the mission's world frame.
    pub frame: GridFrame,
    /// Per cell: a wall (or anything a robot cannot stand in).
    pub blocked: Vec<bool>,
    /// Where the team starts.
    pub start: Cell,
    /// Per cell: free and connected to the start (8-connected, no corner cutting).
    pub reachable: Vec<bool>,
    /// How many cells are reachable.
    pub reachable_cells: usize,
    /// Where the world came from.
    pub name: String,
    /// Its rooms and corridors, where whoever made it knows them (the
    /// office generator): a label per cell from 1, 0 on walls.
    pub rooms: Option<Vec<u32>>,
}

/// Where the robots start.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StartChoice {
    /// The cell of the main free area furthest from any wall.
    Auto,
    /// A random cell of the main free area, drawn with the run's seed.
    Random,
    /// The cell holding this world point.
    At(Point2),
}

impl World {
    /// Loads a map_server map and coarsens it to `cell_size` metres.
    pub fn load(yaml: &Path, cell_size: Option<f64>, start: StartChoice, seed: u64) -> Result<Self, WorldError> {
        let description = MapDescription::load(yaml)?;
        let image = image::open(&description.image)
            .map_err(|cause| WorldError::Image { path: description.image.clone(), cause })?;
        let luma = image.to_luma8();
        let (w, h) = luma.dimensions();
        let free_pixels: Vec<bool> = luma
            .pixels()
            .map(|p| {
                let v = f64::from(p.0[0]);
                let occupancy = if description.negate { v / 255.0 } else { (255.0 - v) / 255.0 };
                occupancy < description.free_thresh
            })
            .collect();
        let name = yaml.file_stem().map_or_else(|| yaml.display().to_string(), |s| s.to_string_lossy().into_owned());
        Self::from_pixels(
            &name,
            w as usize,
            h as usize,
            &free_pixels,
            description.resolution,
            description.origin,
            cell_size.unwrap_or(description.resolution),
            start,
            seed,
        )
    }

    /// Builds a world from free pixels (row 0 at the top, as images are).
    #[allow(clippy::too_many_arguments)]
    pub fn from_pixels(
        name: &str,
        width: usize,
        height: usize,
        free_pixels: &[bool],
        resolution: f64,
        origin: Point2,
        cell_size: f64,
        start: StartChoice,
        seed: u64,
    ) -> Result<Self, WorldError> {
        check_grid(name, width as f64 * resolution, height as f64 * resolution, cell_size)?;
        let scale = cell_size / resolution;
        let cols = ((width as f64) / scale).ceil().max(1.0) as u32;
        let rows = ((height as f64) / scale).ceil().max(1.0) as u32;
        let frame = GridFrame::new(cell_size, origin, cols, rows);
        let mut blocked = vec![true; frame.len()];
        // Pixel spans touched by each coarse column and row (y up in cells, down in pixels).
        let span = |index: u32, limit: usize| {
            let lo = (f64::from(index) * scale + 1e-9).floor() as usize;
            let hi = ((f64::from(index + 1) * scale - 1e-9).ceil() as usize).min(limit);
            (lo, hi)
        };
        for cy in 0..rows {
            let (py0, py1) = span(cy, height);
            for cx in 0..cols {
                let (px0, px1) = span(cx, width);
                let complete = px1 > px0 && py1 > py0 && px1 <= width && py1 <= height;
                let all_free = complete
                    && (py0..py1).all(|py| {
                        let image_row = height - 1 - py;
                        (px0..px1).all(|px| free_pixels[image_row * width + px])
                    });
                // Cells reaching past the image are walls: the border is a wall.
                let past_edge =
                    f64::from(cx + 1) * scale > width as f64 + 1e-9 || f64::from(cy + 1) * scale > height as f64 + 1e-9;
                blocked[frame.index(Cell::new(cx as i32, cy as i32))] = !all_free || past_edge;
            }
        }
        if blocked.iter().all(|&b| b) && free_pixels.iter().any(|&f| f) {
            // The image has free space, the coarse grid none: say why.
            return Err(WorldError::Empty(format!(
                "{name}: no cell of {cell_size} m is free: a cell is free only if all its pixels are free \
                 and it lies wholly inside the {} × {} m image; try smaller cells",
                short(width as f64 * resolution),
                short(height as f64 * resolution)
            )));
        }
        Self::from_blocked(name, frame, blocked, start, seed)
    }

    /// Builds a world from a grid of walls.
    pub fn from_blocked(
        name: &str,
        frame: GridFrame,
        blocked: Vec<bool>,
        start: StartChoice,
        seed: u64,
    ) -> Result<Self, WorldError> {
        let components = Components::label(&frame, &blocked);
        let main = components.main().ok_or_else(|| WorldError::Empty(format!("{name}: no free cell")))?;
        let start = match start {
            StartChoice::At(point) => {
                let cell = frame
                    .cell_from_world(&point)
                    .ok_or_else(|| WorldError::Empty(format!("{name}: start {point:?} is off the map")))?;
                if blocked[frame.index(cell)] {
                    return Err(WorldError::Empty(format!("{name}: start {point:?} is inside a wall")));
                }
                cell
            }
            StartChoice::Auto => components.roomiest_cell(&frame, &blocked, main),
            StartChoice::Random => {
                let cells: Vec<usize> = (0..frame.len()).filter(|&i| components.label[i] == main).collect();
                let mut rng = SplitMix64::new(seed);
                frame.cell(cells[rng.below(cells.len() as u64) as usize])
            }
        };
        let reachable = reachable_from(&frame, &blocked, start);
        let reachable_cells = reachable.iter().filter(|&&r| r).count();
        Ok(Self { frame, blocked, start, reachable, reachable_cells, name: name.to_owned(), rooms: None })
    }

    /// Its rooms and corridors as a mission that plans on a given
    /// segmentation gets them (Wurm et al. 2008, §VI: "we assumed a given
    /// segmentation of the environment into rooms and corridors"): the
    /// generator's own where it made rooms, otherwise the segmentation of
    /// the complete map with the `segmentation` policy's defaults. A label
    /// per cell from 1, 0 where no robot can be.
    pub fn given_rooms(&self) -> Vec<u32> {
        if let Some(rooms) = &self.rooms {
            return rooms.clone();
        }
        let cells = self.reachable.iter().map(|&free| if free { 0 } else { 100 }).collect();
        let grid = OccupancyGrid::from_cells(self.frame, cells);
        let r = self.frame.resolution;
        let min_cells = (DEFAULT_MIN_SEGMENT_M2 / (r * r)).ceil() as usize;
        segment_complete(&grid, DEFAULT_MIN_DROP_M / r, min_cells).labels
    }

    /// Whether a cell is a wall; cells off the grid are.
    pub fn is_blocked(&self, cell: Cell) -> bool {
        !self.frame.contains(cell) || self.blocked[self.frame.index(cell)]
    }

    /// The longest straight-line distance across the grid, metres.
    pub fn diameter_m(&self) -> f64 {
        f64::from(self.frame.width).hypot(f64::from(self.frame.height)) * self.frame.resolution
    }
}

/// Cells free and connected to `start` by moves that do not cut corners
/// (the same components as 4-connectivity).
pub fn reachable_from(frame: &GridFrame, blocked: &[bool], start: Cell) -> Vec<bool> {
    let mut reachable = vec![false; frame.len()];
    let mut queue = VecDeque::from([start]);
    reachable[frame.index(start)] = true;
    while let Some(c) = queue.pop_front() {
        for (dx, dy) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
            let n = Cell::new(c.x + dx, c.y + dy);
            if frame.contains(n) {
                let i = frame.index(n);
                if !blocked[i] && !reachable[i] {
                    reachable[i] = true;
                    queue.push_back(n);
                }
            }
        }
    }
    reachable
}

/// 4-connected components of free cells.
/// The rooms of a world whose doors are known: the free cells split with
/// the doors closed, then each door cell joined to a room beside it. A label
/// per cell from 1, 0 on walls.
pub(crate) fn rooms_behind_doors(frame: &GridFrame, blocked: &[bool], is_door: impl Fn(Cell) -> bool) -> Vec<u32> {
    let closed: Vec<bool> = (0..frame.len()).map(|i| blocked[i] || is_door(frame.cell(i))).collect();
    let components = Components::label(frame, &closed);
    let mut rooms: Vec<u32> = components.label.iter().map(|&l| if l == u32::MAX { 0 } else { l + 1 }).collect();
    let mut queue: VecDeque<usize> = (0..frame.len()).filter(|&i| rooms[i] != 0).collect();
    while let Some(i) = queue.pop_front() {
        let c = frame.cell(i);
        for (dx, dy) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
            let n = Cell::new(c.x + dx, c.y + dy);
            if frame.contains(n) {
                let j = frame.index(n);
                if !blocked[j] && rooms[j] == 0 {
                    rooms[j] = rooms[i];
                    queue.push_back(j);
                }
            }
        }
    }
    rooms
}

struct Components {
    label: Vec<u32>,
    sizes: Vec<usize>,
    touches_border: Vec<bool>,
}

impl Components {
    fn label(frame: &GridFrame, blocked: &[bool]) -> Self {
        let mut label = vec![u32::MAX; frame.len()];
        let mut sizes = Vec::new();
        let mut touches_border = Vec::new();
        for start in 0..frame.len() {
            if blocked[start] || label[start] != u32::MAX {
                continue;
            }
            let id = sizes.len() as u32;
            let mut size = 0;
            let mut border = false;
            let mut stack = vec![start];
            label[start] = id;
            while let Some(i) = stack.pop() {
                size += 1;
                let c = frame.cell(i);
                border |= c.x == 0 || c.y == 0 || c.x + 1 == frame.width as i32 || c.y + 1 == frame.height as i32;
                for (dx, dy) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
                    let n = Cell::new(c.x + dx, c.y + dy);
                    if frame.contains(n) {
                        let j = frame.index(n);
                        if !blocked[j] && label[j] == u32::MAX {
                            label[j] = id;
                            stack.push(j);
                        }
                    }
                }
            }
            sizes.push(size);
            touches_border.push(border);
        }
        Self { label, sizes, touches_border }
    }

    /// The component a team should start in: the largest one, unless the
    /// largest inner one (not touching the border) is at least a quarter of
    /// its size, as when the white outside of a drawing is the largest free
    /// area (`stage_hospital`, `stage_autolab`).
    fn main(&self) -> Option<u32> {
        let largest = (0..self.sizes.len()).max_by_key(|&i| (self.sizes[i], std::cmp::Reverse(i)))?;
        let inner = (0..self.sizes.len())
            .filter(|&i| !self.touches_border[i])
            .max_by_key(|&i| (self.sizes[i], std::cmp::Reverse(i)));
        Some(match inner {
            Some(i) if self.touches_border[largest] && self.sizes[i] * 4 >= self.sizes[largest] => i as u32,
            _ => largest as u32,
        })
    }

    /// The cell of `component` furthest from any wall; when the component
    /// reaches the border (an open outside), only the central 60 % of the
    /// walls' bounding box is searched, so the team starts inside the building.
    fn roomiest_cell(&self, frame: &GridFrame, blocked: &[bool], component: u32) -> Cell {
        let clearance = chessboard_clearance(frame, blocked);
        let (mut x0, mut y0, mut x1, mut y1) = (0, 0, frame.width as i32 - 1, frame.height as i32 - 1);
        if self.touches_border[component as usize] {
            let walls: Vec<Cell> = (0..frame.len()).filter(|&i| blocked[i]).map(|i| frame.cell(i)).collect();
            if let (Some(minx), Some(maxx), Some(miny), Some(maxy)) = (
                walls.iter().map(|c| c.x).min(),
                walls.iter().map(|c| c.x).max(),
                walls.iter().map(|c| c.y).min(),
                walls.iter().map(|c| c.y).max(),
            ) {
                let (w, h) = (f64::from(maxx - minx), f64::from(maxy - miny));
                x0 = minx + (0.2 * w) as i32;
                x1 = maxx - (0.2 * w) as i32;
                y0 = miny + (0.2 * h) as i32;
                y1 = maxy - (0.2 * h) as i32;
            }
        }
        let mut best: Option<(u32, usize)> = None;
        for (i, (&label, &clear)) in self.label.iter().zip(&clearance).enumerate() {
            if label != component {
                continue;
            }
            let c = frame.cell(i);
            if c.x < x0 || c.x > x1 || c.y < y0 || c.y > y1 {
                continue;
            }
            if best.is_none_or(|(b, _)| clear > b) {
                best = Some((clear, i));
            }
        }
        match best {
            Some((_, i)) => frame.cell(i),
            // The central box missed the component: take its roomiest cell anywhere.
            None => {
                let i = (0..frame.len())
                    .filter(|&i| self.label[i] == component)
                    .max_by_key(|&i| (clearance[i], std::cmp::Reverse(i)))
                    .unwrap_or(0);
                frame.cell(i)
            }
        }
    }
}

/// Chessboard distance from every cell to the nearest wall (off-grid counts).
fn chessboard_clearance(frame: &GridFrame, blocked: &[bool]) -> Vec<u32> {
    let mut distance = vec![u32::MAX; frame.len()];
    let mut queue = VecDeque::new();
    for i in 0..frame.len() {
        let c = frame.cell(i);
        let at_edge = c.x == 0 || c.y == 0 || c.x + 1 == frame.width as i32 || c.y + 1 == frame.height as i32;
        if blocked[i] {
            distance[i] = 0;
            queue.push_back(i);
        } else if at_edge {
            distance[i] = 1;
            queue.push_back(i);
        }
    }
    while let Some(i) = queue.pop_front() {
        let c = frame.cell(i);
        for (dx, dy) in NEIGHBOURS_8 {
            let n = Cell::new(c.x + dx, c.y + dy);
            if frame.contains(n) {
                let j = frame.index(n);
                if distance[j] == u32::MAX {
                    distance[j] = distance[i] + 1;
                    queue.push_back(j);
                }
            }
        }
    }
    distance
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cell size or a size that would not fit an executive is refused
    /// before the grid is allocated (these asked for terabytes, or for a
    /// capacity that overflows), and the largest grid it takes is built.
    #[test]
    fn worlds_no_executive_takes_are_refused_before_allocating() {
        let free = vec![true; 4];
        for cell in [0.0, -0.1, 1e-9, f64::NAN, f64::INFINITY] {
            let refused = World::from_pixels("tiny", 2, 2, &free, 0.05, Point2::origin(), cell, StartChoice::Auto, 1);
            assert!(matches!(refused, Err(WorldError::Size(_))), "cell {cell}: {refused:?}");
        }
        use crate::generate::{Generator, generate};
        for (w, h) in [(1e9, 10.0), (0.0, 10.0), (f64::NAN, 10.0), (3001.0, 3001.0)] {
            let refused = generate(Generator::Empty, w, h, 0.15, 1, StartChoice::Auto);
            assert!(matches!(refused, Err(WorldError::Size(_))), "{w} × {h}: {refused:?}");
        }
        assert!(check_grid("edge", 2500.0, 156.25, 0.125).is_ok(), "20 000 × 1 250 cells, the limits");
        assert!(check_grid("edge", 2500.0, 156.375, 0.125).is_err(), "one row more");
        assert!(check_grid("edge", 2500.125, 1.0, 0.125).is_err(), "one column more");
        // A YAML's resolution of 1e300 is named in a line, not 300 digits.
        let message = check_grid("vast", 4e300, 4e300, 0.15).unwrap_err().to_string();
        assert!(message.contains("4.000e300 × 4.000e300 m") && message.len() < 200, "{message}");
    }

    #[test]
    fn coarsening_keeps_one_pixel_walls_closed() {
        // 6×4 pixels, a one-pixel vertical wall in column 3 (image rows top first).
        let picture = ["...#..", "...#..", "...#..", "...#.."];
        let free: Vec<bool> = picture.iter().flat_map(|r| r.chars().map(|c| c == '.')).collect();
        let world = World::from_pixels("wall", 6, 4, &free, 0.05, Point2::origin(), 0.1, StartChoice::Auto, 0).unwrap();
        assert_eq!((world.frame.width, world.frame.height), (3, 2));
        // Coarse column 1 holds pixel columns 2 and 3: the wall survives.
        for y in 0..2 {
            assert!(world.is_blocked(Cell::new(1, y)));
            assert!(!world.is_blocked(Cell::new(0, y)));
            assert!(!world.is_blocked(Cell::new(2, y)));
        }
        // The two sides are not connected.
        assert_eq!(world.reachable_cells, 2);
    }

    /// Cells larger than the image, or than any free patch of it, leave
    /// no free cell; the refusal says that the cells are too large.
    #[test]
    fn cells_too_large_for_the_image_are_named() {
        let free = vec![true; 16];
        for cell in [0.45, 0.5, 10.0] {
            let refused = World::from_pixels("small", 4, 4, &free, 0.1, Point2::origin(), cell, StartChoice::Auto, 1);
            let Err(WorldError::Empty(message)) = refused else { panic!("cell {cell}: {refused:?}") };
            assert!(message.contains("no cell of") && message.contains("0.40 × 0.40 m"), "{message}");
        }
        let walls = vec![false; 16];
        let refused = World::from_pixels("walls", 4, 4, &walls, 0.1, Point2::origin(), 0.1, StartChoice::Auto, 1);
        let Err(WorldError::Empty(message)) = refused else { panic!("{refused:?}") };
        assert!(message.ends_with("no free cell"), "an image without free pixels: {message}");
    }

    #[test]
    fn image_rows_run_top_down_and_the_start_is_roomy() {
        let mut picture = vec!["##########".to_string(); 1];
        for _ in 0..6 {
            picture.push("#........#".to_string());
        }
        picture.push("##########".to_string());
        picture[1] = "#.#......#".to_string(); // a wall pixel near the top-left
        let free: Vec<bool> = picture.iter().flat_map(|r| r.chars().map(|c| c == '.')).collect();
        let world = World::from_pixels("room", 10, 8, &free, 1.0, Point2::origin(), 1.0, StartChoice::Auto, 0).unwrap();
        // Image row 1 is grid row 6: the wall pixel is cell (2, 6).
        assert!(world.is_blocked(Cell::new(2, 6)));
        assert!(!world.is_blocked(Cell::new(2, 1)));
        assert_eq!(world.reachable_cells, 8 * 6 - 1);
        let s = world.start;
        assert!(!world.is_blocked(s));
        assert!((3..=6).contains(&s.x) && (2..=5).contains(&s.y), "start {s:?} is not central");
    }

    #[test]
    fn an_enclosed_building_beats_the_larger_outside() {
        // A 20×12 image: a closed building (walls on x 2..=17, y 2..=9) in a
        // larger free outside that touches the border.
        let (w, h) = (20usize, 12usize);
        let free: Vec<bool> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let on_wall =
                    ((x == 2 || x == 17) && (2..=9).contains(&y)) || ((y == 2 || y == 9) && (2..=17).contains(&x));
                !on_wall
            })
            .collect();
        let world = World::from_pixels("house", w, h, &free, 1.0, Point2::origin(), 1.0, StartChoice::Auto, 0).unwrap();
        assert_eq!(world.reachable_cells, 14 * 6, "the team starts inside the house");
    }

    #[test]
    fn the_shared_maps_yaml_parses() {
        let dir = tempfile::tempdir().unwrap();
        let yaml = dir.path().join("m.yaml");
        std::fs::write(
            &yaml,
            "# comment\nimage: m.pgm\nmode: trinary\nresolution: 0.050000\norigin: [-15.0, -15, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
        )
        .unwrap();
        let d = MapDescription::load(&yaml).unwrap();
        assert_eq!(d.image, dir.path().join("m.pgm"));
        assert_eq!(d.origin, Point2::new(-15.0, -15.0));
        assert_eq!(d.resolution, 0.05);
        assert!(!d.negate);
        std::fs::write(&yaml, "image: m.pgm\nresolution: 0.05\n").unwrap();
        let err = MapDescription::load(&yaml).unwrap_err();
        assert!(err.to_string().contains("origin"), "{err}");
    }
}
