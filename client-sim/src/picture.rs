//! Pictures of runs: the map with each robot's trajectory in its own colour,
//! start and end marked (Burgard et al. 2005, Fig. 3), and, when there is
//! one, the segmentation tinted segment by segment.

use std::path::Path;

use image::{Rgb, RgbImage};

use exploration::grid::{Cell, GridFrame};

/// Distinct colours for trajectories.
pub const PALETTE: [[u8; 3]; 10] = [
    [230, 25, 75],
    [60, 180, 75],
    [0, 130, 200],
    [245, 130, 48],
    [145, 30, 180],
    [70, 240, 240],
    [240, 50, 230],
    [128, 128, 0],
    [0, 128, 128],
    [170, 110, 40],
];

/// Most pixels a picture has (300 MB of RGB): a large mission's map asked
/// for at many pixels per cell would otherwise take tens of gigabytes.
const MOST_PIXELS: u64 = 100_000_000;

/// Pixels per cell for a picture of `width` × `height` cells whose longer
/// side is about `target_px` (see [`Picture::new`]).
fn scale(width: u32, height: u32, target_px: u32) -> u32 {
    let cells = u64::from(width) * u64::from(height);
    let fitting = (1..=16u32).rev().find(|&s| cells * u64::from(s * s) <= MOST_PIXELS).unwrap_or(1);
    (target_px / width.max(height).max(1)).clamp(1, fitting)
}

/// A picture of a grid, one square of `scale` pixels per cell, y up.
#[derive(Debug, Clone)]
pub struct Picture {
    frame: GridFrame,
    scale: u32,
    image: RgbImage,
}

impl Picture {
    /// A picture of `frame` with cells drawn by `colour`, scaled so the
    /// longer side is about `target_px` pixels: from 1 to 16 pixels per
    /// cell, and fewer where the picture would pass [`MOST_PIXELS`].
    pub fn new(frame: GridFrame, target_px: u32, colour: impl Fn(Cell) -> [u8; 3]) -> Self {
        let scale = scale(frame.width, frame.height, target_px);
        let mut image = RgbImage::new(frame.width * scale, frame.height * scale);
        for cell in frame.bounds().cells() {
            let c = colour(cell);
            let (px, py) = (cell.x as u32 * scale, (frame.height - 1 - cell.y as u32) * scale);
            for dy in 0..scale {
                for dx in 0..scale {
                    image.put_pixel(px + dx, py + dy, Rgb(c));
                }
            }
        }
        Self { frame, scale, image }
    }

    fn centre(&self, cell: Cell) -> (i64, i64) {
        let s = i64::from(self.scale);
        (i64::from(cell.x) * s + s / 2, (i64::from(self.frame.height) - 1 - i64::from(cell.y)) * s + s / 2)
    }

    fn dot(&mut self, x: i64, y: i64, colour: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as u32) < self.image.width() && (y as u32) < self.image.height() {
            self.image.put_pixel(x as u32, y as u32, Rgb(colour));
        }
    }

    /// A polyline through the centres of `cells`.
    pub fn path(&mut self, cells: &[Cell], colour: [u8; 3]) {
        let width = (self.scale / 3).max(1) as i64;
        for pair in cells.windows(2) {
            let (a, b) = (self.centre(pair[0]), self.centre(pair[1]));
            let steps = (a.0 - b.0).abs().max((a.1 - b.1).abs()).max(1);
            for k in 0..=steps {
                let x = a.0 + (b.0 - a.0) * k / steps;
                let y = a.1 + (b.1 - a.1) * k / steps;
                for dy in -width / 2..=width / 2 {
                    for dx in -width / 2..=width / 2 {
                        self.dot(x + dx, y + dy, colour);
                    }
                }
            }
        }
    }

    /// A filled disc (`square` false) or square marker at a cell.
    pub fn marker(&mut self, cell: Cell, colour: [u8; 3], square: bool) {
        let (cx, cy) = self.centre(cell);
        let r = i64::from(self.scale.max(2)) * 2;
        for dy in -r..=r {
            for dx in -r..=r {
                let edge = if square { dx.abs().max(dy.abs()) } else { ((dx * dx + dy * dy) as f64).sqrt() as i64 };
                if edge <= r {
                    let rim = edge > r - 2;
                    self.dot(cx + dx, cy + dy, if rim { [0, 0, 0] } else { colour });
                }
            }
        }
    }

    /// Saves as PNG, whatever the file is called (`--png /dev/stdout`).
    pub fn save(&self, path: &Path) -> Result<(), image::ImageError> {
        self.image.save_with_format(path, image::ImageFormat::Png)
    }
}

/// A light tint for segment `label` (0: none).
pub fn segment_tint(label: u32) -> [u8; 3] {
    let [r, g, b] = PALETTE[(label as usize) % PALETTE.len()];
    [(200 + r / 5), (200 + g / 5), (200 + b / 5)]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The longer side comes near the size asked for, within 1 to 16
    /// pixels per cell, and never past the pixel budget: the largest
    /// mission at 20 pixels per cell would be 19 GB of RGB.
    #[test]
    fn pictures_scale_within_the_pixel_budget() {
        assert_eq!(scale(100, 50, 1200), 12);
        assert_eq!(scale(100, 50, 10), 1);
        assert_eq!(scale(100, 50, 100_000), 16);
        assert_eq!(scale(20_000, 1_250, 400_000), 2);
        assert_eq!(scale(20_000, 20_000, u32::MAX), 1, "over the budget at one pixel per cell, still drawn");
    }
}
