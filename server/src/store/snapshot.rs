//! The fused map as stored bytes: what a compacted patch log keeps in place
//! of the patches it folded (see [`super::compact`]). Shared by every
//! backend, so that a map snapshot means the same bytes in each.
//!
//! Layout, little-endian, then compressed as one LZ4 block: a format
//! number, the grid's width and height, one f32 log-odds sum per cell, the
//! number of layers, and per layer its robot, its number of tiles and per
//! tile x, y, width, height and its log-odds (NaN where the robot knows
//! nothing).

use exploration::fusion::{FusionParts, LayerParts, MapFusion, Patch};
use exploration::grid::{CellRect, GridFrame};

/// The layout above.
const FORMAT: u32 = 1;

/// A fusion as stored bytes, with the size they decompress to.
pub fn encode(fusion: &MapFusion) -> (Vec<u8>, u64) {
    let parts = fusion.parts();
    let frame = fusion.frame();
    let mut raw = Vec::with_capacity(16 + parts.sum.len() * 4);
    for word in [FORMAT, frame.width, frame.height] {
        raw.extend_from_slice(&word.to_le_bytes());
    }
    raw.extend(parts.sum.iter().flat_map(|v| v.to_le_bytes()));
    raw.extend_from_slice(&(parts.layers.len() as u32).to_le_bytes());
    for layer in &parts.layers {
        raw.extend_from_slice(&layer.id.to_le_bytes());
        raw.extend_from_slice(&(layer.tiles.len() as u32).to_le_bytes());
        for tile in &layer.tiles {
            let rect = tile.rect();
            for word in [rect.x as u32, rect.y as u32, rect.width, rect.height] {
                raw.extend_from_slice(&word.to_le_bytes());
            }
            raw.extend(tile.log_odds().iter().flat_map(|v| v.to_le_bytes()));
        }
    }
    (lz4_flex::block::compress(&raw), raw.len() as u64)
}

/// The fusion stored as `bytes` (which decompress to `raw_bytes`) for a
/// mission on `frame` with `robots` robots; every field checked, so that a
/// damaged snapshot is an error, never a panic or a wrong map.
pub fn decode(bytes: &[u8], raw_bytes: u64, frame: &GridFrame, robots: usize) -> Result<MapFusion, String> {
    // One sum per cell, and per robot at most every cell again with a tile
    // header per cell: no valid snapshot is larger.
    let cells = frame.len() as u64;
    let limit = (robots as u64 + 1).saturating_mul(cells.saturating_mul(20).saturating_add(64));
    if raw_bytes > limit {
        return Err(format!("claims {raw_bytes} bytes, more than a map of {cells} cells and {robots} robots holds"));
    }
    let mut raw = vec![0; usize::try_from(raw_bytes).map_err(|_| format!("{raw_bytes} bytes do not fit in memory"))?];
    let written = lz4_flex::block::decompress_into(bytes, &mut raw).map_err(|e| e.to_string())?;
    if written != raw.len() {
        return Err(format!("decompresses to {written} bytes, not the {raw_bytes} recorded"));
    }
    let mut at = Reader { raw: &raw, offset: 0 };
    let format = at.u32()?;
    if format != FORMAT {
        return Err(format!("format {format} is not {FORMAT}"));
    }
    let (width, height) = (at.u32()?, at.u32()?);
    if (width, height) != (frame.width, frame.height) {
        return Err(format!("is of a {width}×{height} grid, the mission's is {}×{}", frame.width, frame.height));
    }
    let sum = at.f32s(frame.len())?;
    let layer_count = at.u32()? as usize;
    if layer_count > robots {
        return Err(format!("has {layer_count} layers for {robots} robots"));
    }
    let mut layers = Vec::with_capacity(layer_count);
    for _ in 0..layer_count {
        let id = at.u64()?;
        let tile_count = at.u32()? as usize;
        let mut tiles = Vec::with_capacity(tile_count.min(frame.len()));
        for _ in 0..tile_count {
            let (x, y, w, h) = (at.u32()?, at.u32()?, at.u32()?, at.u32()?);
            let (x, y) = (i32::try_from(x).map_err(|e| e.to_string())?, i32::try_from(y).map_err(|e| e.to_string())?);
            let rect = CellRect::new(x, y, w, h);
            if !frame.contains_rect(&rect) {
                return Err(format!("layer {id}: the tile {rect:?} leaves the grid"));
            }
            let values = at.f32s(rect.area() as usize)?;
            tiles.push(Patch::from_stored(rect, values).map_err(|e| format!("layer {id}: {e}"))?);
        }
        layers.push(LayerParts { id, tiles });
    }
    if at.offset != raw.len() {
        return Err(format!("has {} bytes after its last layer", raw.len() - at.offset));
    }
    MapFusion::from_parts(*frame, FusionParts { sum, layers }).map_err(|e| e.to_string())
}

/// Reads the layout's fields in order, refusing to read past the end.
struct Reader<'a> {
    raw: &'a [u8],
    offset: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        let end = self.offset.checked_add(n).filter(|&end| end <= self.raw.len());
        let end = end.ok_or_else(|| format!("ends at byte {} in the middle of a field", self.raw.len()))?;
        let bytes = &self.raw[self.offset..end];
        self.offset = end;
        Ok(bytes)
    }

    fn u32(&mut self) -> Result<u32, String> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from(self.u32()?) | (u64::from(self.u32()?) << 32))
    }

    fn f32s(&mut self, n: usize) -> Result<Vec<f32>, String> {
        let bytes = self.take(n.checked_mul(4).ok_or("a field larger than memory")?)?;
        Ok(bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exploration::math::Point2;

    fn fusion() -> MapFusion {
        let frame = GridFrame::new(0.1, Point2::origin(), 90, 50);
        let mut fusion = MapFusion::new(frame);
        for (robot, x, p) in [(3, 10, 0.9_f32), (5, 40, 0.2), (3, 30, 0.6)] {
            let rect = CellRect::new(x, 5, 40, 40);
            let values = vec![p; rect.area() as usize];
            let unknown: Vec<bool> = (0..rect.area()).map(|k| k % 7 == 0).collect();
            fusion.apply(robot, &Patch::from_probabilities(rect, &values, &unknown).unwrap()).unwrap();
        }
        fusion
    }

    #[test]
    fn a_stored_fusion_comes_back_the_same() {
        let original = fusion();
        let (bytes, raw) = encode(&original);
        let back = decode(&bytes, raw, original.frame(), 2).unwrap();
        assert_eq!(back.grid().cells(), original.grid().cells());
        let bits = |f: &MapFusion| f.parts().sum.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&back), bits(&original));
        assert_eq!(back.layer_count(), 2);
    }

    #[test]
    fn damaged_snapshots_are_errors() {
        let original = fusion();
        let frame = *original.frame();
        let (bytes, raw) = encode(&original);
        assert!(decode(&bytes, raw, &frame, 1).unwrap_err().contains("2 layers for 1 robots"));
        assert!(decode(&bytes, u64::MAX, &frame, 2).unwrap_err().contains("claims"));
        assert!(decode(&bytes, raw - 1, &frame, 2).is_err());
        assert!(decode(&bytes[..bytes.len() / 2], raw, &frame, 2).is_err());
        let other = GridFrame::new(0.1, Point2::origin(), 91, 50);
        assert!(decode(&bytes, raw, &other, 2).unwrap_err().contains("90×50"));
        // A byte flipped in the sums: refused or, if still a valid number
        // on a known cell, decoded; never a panic.
        for k in 0..bytes.len() {
            let mut flipped = bytes.clone();
            flipped[k] ^= 0x5a;
            let _ = decode(&flipped, raw, &frame, 2);
        }
    }
}
