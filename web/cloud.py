"""The dashboard's copy of a point cloud stream (PointCloud deltas on one key), kept small for browsers.

New points arrive as chunks; each chunk is sent to the browser once, as its own scene node. When the
chunks grow many, or the points more than the cap, they are merged into one base and decimated to the
cap, so a browser holds a bounded number of nodes and points however long the map grows."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.messages import PointCloud
from web.render import colormap

COLOURINGS = ("depth", "height", "intensity")
MAX_CHUNKS = 16  # chunks kept apart before a merge


@dataclass
class Chunk:
    """Points (world, m), their depth from the camera that saw them (m), their colours when published."""

    points: np.ndarray
    depth: np.ndarray
    colors: np.ndarray | None = None

    @classmethod
    def of(cls, msg: PointCloud) -> Chunk:
        centre = msg.keyframe[:3, 3] if msg.keyframe is not None else np.zeros(3)
        pts = np.asarray(msg.points, np.float32)
        return cls(pts, np.linalg.norm(pts - centre.astype(np.float32), axis=1), msg.colors)

    def __len__(self) -> int:
        return len(self.points)


def merge(chunks: list[Chunk], cap: int, rng: np.random.Generator) -> Chunk:
    """One chunk of all, decimated uniformly at random to at most `cap` points."""
    points = np.concatenate([c.points for c in chunks])
    depth = np.concatenate([c.depth for c in chunks])
    colors = (np.concatenate([c.colors for c in chunks])
              if all(c.colors is not None for c in chunks) else None)
    if len(points) > cap:
        keep = np.sort(rng.choice(len(points), cap, replace=False))
        points, depth = points[keep], depth[keep]
        colors = colors[keep] if colors is not None else None
    return Chunk(points, depth, colors)


@dataclass
class MapLayer:
    """One key's points: a merged `base` and the `chunks` since, with the colour range they share."""

    cap: int = 100_000
    base: Chunk | None = None
    chunks: list[Chunk] = field(default_factory=list)
    depth_range: tuple[float, float] | None = None
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    @property
    def total(self) -> int:
        return (len(self.base) if self.base else 0) + sum(len(c) for c in self.chunks)

    def add(self, msg: PointCloud) -> Chunk | None:
        """Take a delta; the new chunk, or None when it held no points."""
        if not len(msg.points):
            return None
        chunk = Chunk.of(msg)
        self.chunks.append(chunk)
        if self.depth_range is None:
            self.depth_range = _range(chunk.depth)
        return chunk

    def replace(self, msg: PointCloud) -> None:
        """The whole map (a query's answer) instead of what is held."""
        self.clear()
        if len(msg.points):
            self.base = merge([Chunk.of(msg)], self.cap, self.rng)
            self.depth_range = _range(self.base.depth)

    def clear(self) -> None:
        self.base, self.chunks, self.depth_range = None, [], None

    def merge_due(self) -> bool:
        return len(self.chunks) >= MAX_CHUNKS or self.total > self.cap

    def merge(self) -> Chunk:
        """Fold the chunks into the base (decimated to the cap); the colour range is renewed from it."""
        self.base = merge(([self.base] if self.base else []) + self.chunks, self.cap, self.rng)
        self.chunks = []
        self.depth_range = _range(self.base.depth)
        return self.base

    def colours(self, chunk: Chunk, colouring: str) -> np.ndarray:
        """RGB uint8 per point: by depth or height (a colour map), or by the published intensity."""
        if colouring == "intensity":
            if chunk.colors is not None:
                return np.asarray(chunk.colors, np.uint8)
            return np.full((len(chunk), 3), 200, np.uint8)
        if colouring == "height":  # y points down in the world frame: up is -y
            up = -chunk.points[:, 1]
            return colormap(up, *_range(up))
        return colormap(chunk.depth, *(self.depth_range or _range(chunk.depth)))


def _range(values: np.ndarray) -> tuple[float, float]:
    lo, hi = np.percentile(values, (2, 98)) if len(values) else (0.0, 1.0)
    return float(lo), float(max(hi, lo + 1e-3))
