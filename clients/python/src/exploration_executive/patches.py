"""Occupancy grids (numpy) as the executive's map patches."""

from __future__ import annotations

import numpy as np

from ._proto.exploration.v1 import exploration_pb2 as pb

ENCODINGS = {
    "probability": pb.CELL_ENCODING_PROBABILITY,
    "log_odds": pb.CELL_ENCODING_LOG_ODDS,
    "occupancy_percent": pb.CELL_ENCODING_OCCUPANCY_PERCENT,
}

#: The occupancy byte of an unknown cell (ROS's -1 as an unsigned byte).
UNKNOWN_PERCENT = 255


def patch_from_grid(
    grid: np.ndarray,
    x: int,
    y: int,
    *,
    encoding: str = "probability",
    unknown: np.ndarray | None = None,
) -> pb.MapPatch:
    """A patch whose lower-left cell is (x, y) of the mission grid.

    ``grid[row, column]``, row 0 the bottom row, holds occupancy
    probabilities (0..1) or log-odds, or for ``occupancy_percent`` the
    values of a ROS ``nav_msgs/OccupancyGrid``: 0..100 percent and -1 (or
    255, the same byte unsigned) for unknown, sent as one byte per cell.
    Cells are unknown where ``unknown`` is true, or, without a mask, where
    the grid holds NaN (or -1).
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding {encoding!r}: expected one of {sorted(ENCODINGS)}")
    if encoding == "occupancy_percent":
        grid = np.asarray(grid)
        default_mask = (grid == -1) | (grid == UNKNOWN_PERCENT)
    else:
        grid = np.asarray(grid, dtype=np.float32)
        default_mask = np.isnan(grid)
    if grid.ndim != 2 or grid.size == 0:
        raise ValueError(f"a patch is a non-empty 2-D grid, got shape {grid.shape}")
    # A cell index is 32 bits on the wire (the executive's grids are smaller still).
    if not (0 <= x < 2**32 and 0 <= y < 2**32):
        raise ValueError(f"the patch's lower-left cell ({x}, {y}) lies off the grid")
    mask = default_mask if unknown is None else np.asarray(unknown, dtype=bool)
    if mask.shape != grid.shape:
        raise ValueError(f"the unknown mask has shape {mask.shape}, the grid {grid.shape}")
    height, width = grid.shape
    patch = pb.MapPatch(x=x, y=y, width=width, height=height, encoding=ENCODINGS[encoding])
    if encoding == "occupancy_percent":
        patch.occupancy = _occupancy_bytes(grid, mask)
    else:
        patch.values.extend(np.where(mask, 0.0, grid).astype(np.float32).ravel().tolist())
        patch.unknown = mask.astype(np.uint8).tobytes() if mask.any() else b""
    return patch


def _occupancy_bytes(grid: np.ndarray, mask: np.ndarray) -> bytes:
    """One byte per cell: the percentage, or 255 where unknown."""
    if not np.issubdtype(grid.dtype, np.integer):
        raise ValueError(f"occupancy_percent takes integer percentages (a ROS grid's int8), got {grid.dtype}")
    bad = ~mask & ((grid < 0) | (grid > 100))
    if bad.any():
        row, column = np.argwhere(bad)[0]
        raise ValueError(f"cell ({row}, {column}) holds {grid[row, column]}: expected 0..100 percent, or -1 for unknown")
    return np.where(mask, UNKNOWN_PERCENT, grid).astype(np.uint8).tobytes()
