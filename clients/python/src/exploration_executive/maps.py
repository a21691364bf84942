"""ROS map_server maps (YAML + PGM) as numpy grids in the executive's frame."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from ._proto.exploration.v1 import exploration_pb2 as pb

#: Cell values of a :class:`MapServerMap`, as the executive stores them
#: (occupancy in percent) with 255 for unknown.
FREE, OCCUPIED, UNKNOWN = 0, 100, 255


@dataclass(frozen=True)
class MapServerMap:
    """An occupancy map in the mission convention: ``cells[y, x]`` with row 0
    the bottom row, values :data:`FREE`, :data:`OCCUPIED` or :data:`UNKNOWN`."""

    cells: np.ndarray
    resolution: float
    origin: tuple[float, float]

    @classmethod
    def load(cls, yaml_path: str | Path) -> "MapServerMap":
        """Reads a map_server YAML and its PGM image (trinary interpretation)."""
        yaml_path = Path(yaml_path)
        spec = yaml.safe_load(yaml_path.read_text())
        pixels = read_pgm(yaml_path.parent / spec["image"])
        darkness = pixels.astype(np.float64) / 255.0
        p_occupied = darkness if spec.get("negate", 0) else 1.0 - darkness
        cells = np.full(pixels.shape, UNKNOWN, dtype=np.uint8)
        cells[p_occupied > float(spec["occupied_thresh"])] = OCCUPIED
        cells[p_occupied < float(spec["free_thresh"])] = FREE
        origin = spec["origin"]
        # Image row 0 is the top of the map; the mission's row 0 is its bottom.
        return cls(np.flipud(cells).copy(), float(spec["resolution"]), (float(origin[0]), float(origin[1])))

    @property
    def width(self) -> int:
        return int(self.cells.shape[1])

    @property
    def height(self) -> int:
        return int(self.cells.shape[0])

    def coarsened(self, resolution: float) -> "MapServerMap":
        """The map at a coarser ``resolution``, conservatively: a cell is
        occupied if any finer cell in it is, free only if all of them are."""
        factor = max(1, round(resolution / self.resolution))
        if factor == 1:
            return self
        h, w = -(-self.height // factor) * factor, -(-self.width // factor) * factor
        padded = np.full((h, w), UNKNOWN, dtype=np.uint8)
        padded[: self.height, : self.width] = self.cells
        blocks = padded.reshape(h // factor, factor, w // factor, factor).swapaxes(1, 2)
        coarse = np.full(blocks.shape[:2], UNKNOWN, dtype=np.uint8)
        coarse[(blocks == FREE).all(axis=(2, 3))] = FREE
        coarse[(blocks == OCCUPIED).any(axis=(2, 3))] = OCCUPIED
        return MapServerMap(coarse, self.resolution * factor, self.origin)

    def frame(self) -> pb.MapFrame:
        """The mission frame covering this map."""
        return pb.MapFrame(
            resolution=self.resolution,
            origin=pb.Point(x=self.origin[0], y=self.origin[1]),
            width=self.width,
            height=self.height,
        )

    def world(self, x: int, y: int) -> tuple[float, float]:
        """The centre of cell (x, y), metres."""
        return (self.origin[0] + (x + 0.5) * self.resolution, self.origin[1] + (y + 0.5) * self.resolution)

    def cell(self, x: float, y: float) -> tuple[int, int]:
        """The cell holding the world point (x, y)."""
        return (int((x - self.origin[0]) // self.resolution), int((y - self.origin[1]) // self.resolution))


def read_pgm(path: str | Path) -> np.ndarray:
    """An 8-bit binary PGM (P5) image as a (height, width) array."""
    data = Path(path).read_bytes()
    fields: list[bytes] = []
    i = 0
    # Every scan stops at the end of the data: a truncated header (b"P5")
    # must be an error, not a loop that never ends.
    while len(fields) < 4:
        while i < len(data) and data[i : i + 1].isspace():
            i += 1
        if i >= len(data):
            raise ValueError(f"{path}: the PGM header ends after {len(fields)} of its 4 fields")
        if data[i : i + 1] == b"#":
            i = data.find(b"\n", i)
            i = len(data) if i < 0 else i + 1
            continue
        start = i
        while i < len(data) and not data[i : i + 1].isspace():
            i += 1
        fields.append(data[start:i])
    magic = fields[0]
    if magic != b"P5" or not all(f.isdigit() for f in fields[1:]):
        raise ValueError(f"{path}: only 8-bit binary PGM (P5) is read, found the header {b' '.join(fields)!r}")
    width, height, maxval = (int(f) for f in fields[1:])
    if maxval > 255 or width == 0 or height == 0:
        raise ValueError(f"{path}: only 8-bit binary PGM (P5) is read, found {width} × {height} with maxval {maxval}")
    if len(data) - (i + 1) < width * height:
        raise ValueError(f"{path}: {width} × {height} pixels announced, {max(0, len(data) - i - 1)} bytes follow")
    pixels = np.frombuffer(data, dtype=np.uint8, count=width * height, offset=i + 1)
    return pixels.reshape(height, width)
