-- How map_patches.cells is encoded: 0 = little-endian f32 log-odds per cell
-- (NaN unknown), as before; 1 = the same bytes as one LZ4 block. A sensor's
-- patch is mostly runs of a few values, and the patch log is most of the
-- database: a fleet of a thousand robots wrote 12 MB/s of it uncompressed.
ALTER TABLE map_patches ADD COLUMN cells_format INTEGER NOT NULL DEFAULT 0;
