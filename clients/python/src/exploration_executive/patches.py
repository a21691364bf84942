"""Occupancy grids (numpy) as the executive's map patches."""

from __future__ import annotations

import numpy as np

from ._proto.exploration.v1 import exploration_pb2 as pb

ENCODINGS = {"probability": pb.CELL_ENCODING_PROBABILITY, "log_odds": pb.CELL_ENCODING_LOG_ODDS}


def patch_from_grid(
    grid: np.ndarray,
    x: int,
    y: int,
    *,
    encoding: str = "probability",
    unknown: np.ndarray | None = None,
) -> pb.MapPatch:
    """A patch whose lower-left cell is (x, y) of the mission grid.

    ``grid[row, column]`` holds occupancy probabilities (0..1) or log-odds,
    row 0 the bottom row. Cells are unknown where ``unknown`` is true, or,
    without a mask, where the grid holds NaN.
    """
    grid = np.asarray(grid, dtype=np.float32)
    if grid.ndim != 2 or grid.size == 0:
        raise ValueError(f"a patch is a non-empty 2-D grid, got shape {grid.shape}")
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding {encoding!r}: expected one of {sorted(ENCODINGS)}")
    if x < 0 or y < 0:
        raise ValueError(f"the patch's lower-left cell ({x}, {y}) lies off the grid")
    mask = np.isnan(grid) if unknown is None else np.asarray(unknown, dtype=bool)
    if mask.shape != grid.shape:
        raise ValueError(f"the unknown mask has shape {mask.shape}, the grid {grid.shape}")
    values = np.where(mask, 0.0, grid).astype(np.float32)
    height, width = grid.shape
    return pb.MapPatch(
        x=x,
        y=y,
        width=width,
        height=height,
        encoding=ENCODINGS[encoding],
        values=values.ravel().tolist(),
        unknown=mask.astype(np.uint8).tobytes() if mask.any() else b"",
    )
