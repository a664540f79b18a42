"""The global map: keyframes' points fused on a voxel grid, with a cap on its size.

Each voxel keeps the mean of the points that fell in it, how many did, and the last keyframe that saw
it; the map keeps each keyframe's time and pose (not its images), what a saved map needs to say.
Points of several keyframes on one surface merge instead of piling up; a map over its cap forgets the
voxels seen longest ago, so memory stays bounded on a long flight.

The map shows only voxels with support: at least `min_neighbours` other voxels in the 3 x 3 x 3 block
around them (EMVS's radius outlier removal, on the grid). Edges are lines and surfaces of voxels; a
lone voxel is most often a wrong peak, a lucky alignment of rays (on the `6dof` dev maps, 80-90 % of the
lone ones are within 5 % of their depth against 93-97 % of the rest). Lone voxels are kept, not shown:
a later keyframe may give them neighbours.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from services.mapper.keyframes import Keyframe


# key offsets of a voxel's 26 neighbours (keys pack 21 bits per axis: x << 42 | y << 21 | z)
_BLOCK = np.array([(dx << 42) + (dy << 21) + dz for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
                   if dx or dy or dz], np.int64)


class VoxelMap:
    def __init__(self, voxel_m: float = 0.03, max_points: int = 1_000_000, min_neighbours: int = 2) -> None:
        self.voxel_m, self.max_points, self.min_neighbours = voxel_m, max_points, min_neighbours
        self.reset()

    def reset(self) -> None:
        """Forgets every point."""
        self._keys = np.zeros(0, np.int64)
        self._sums = np.zeros((0, 3), np.float64)
        self._counts = np.zeros(0, np.int64)
        self._conf = np.zeros(0, np.float32)
        self._keyframe = np.zeros(0, np.int64)
        self.views: list[tuple[int, np.ndarray, np.ndarray]] = []  # per keyframe: t_us, R (camera to world), p

    def __len__(self) -> int:
        return len(self._keys)

    def _key(self, points: np.ndarray) -> np.ndarray:
        """One int64 per voxel: 21 bits per axis (+-1 million voxels from the origin)."""
        cell = np.floor(points / self.voxel_m).astype(np.int64) + (1 << 20)
        cell = np.clip(cell, 0, (1 << 21) - 1)
        return (cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2]

    def add_keyframe(self, kf: Keyframe) -> np.ndarray:
        """Fuses a keyframe's points (see `add`) and keeps its time and pose; the voxels it touched."""
        new = self.add(kf.points, kf.confidence, len(self.views))
        self.views.append((kf.t_us, kf.R, kf.p))
        return new

    def add(self, points: np.ndarray, confidence: np.ndarray, keyframe: int) -> np.ndarray:
        """Fuses points (N x 3, world) seen by `keyframe`; the voxels' new means of those it touched."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if not len(points):
            return np.zeros((0, 3), np.float32)
        added = self._key(points)
        keys = np.concatenate([self._keys, added])
        uniq, inverse = np.unique(keys, return_inverse=True)
        n = len(uniq)
        sums = np.zeros((n, 3))
        np.add.at(sums, inverse, np.vstack([self._sums, points]))
        counts = np.bincount(inverse, weights=np.concatenate([self._counts, np.ones(len(points))]),
                             minlength=n).astype(np.int64)
        conf = np.zeros(n, np.float32)
        np.maximum.at(conf, inverse, np.concatenate([self._conf, np.asarray(confidence, np.float32)]))
        last = np.zeros(n, np.int64)
        np.maximum.at(last, inverse, np.concatenate([self._keyframe, np.full(len(points), keyframe)]))
        self._keys, self._sums, self._counts, self._conf, self._keyframe = uniq, sums, counts, conf, last
        if n > self.max_points:
            self._evict(n - self.max_points)
        touched = np.unique(added)
        at = np.minimum(np.searchsorted(self._keys, touched), len(self._keys) - 1)
        at = at[(self._keys[at] == touched) & self._supported(touched)]  # (a keyframe over the cap lost some)
        return (self._sums[at] / self._counts[at, None]).astype(np.float32)

    def _supported(self, keys: np.ndarray) -> np.ndarray:
        """Which of the map's voxels `keys` have at least `min_neighbours` others in their 3 x 3 x 3 block;
        all where that is 0."""
        if self.min_neighbours <= 0 or not len(keys):
            return np.ones(len(keys), bool)
        found = np.zeros(len(keys), np.int64)
        for off in _BLOCK:  # 26 lookups, each over every key at once
            near = keys + off
            at = np.minimum(np.searchsorted(self._keys, near), len(self._keys) - 1)
            found += self._keys[at] == near
        return found >= self.min_neighbours

    def _evict(self, excess: int) -> None:
        """Forgets the `excess` voxels whose last keyframe is oldest."""
        keep = np.sort(np.argsort(self._keyframe, kind="stable")[excess:])
        self._keys, self._sums, self._counts = self._keys[keep], self._sums[keep], self._counts[keep]
        self._conf, self._keyframe = self._conf[keep], self._keyframe[keep]

    def points(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The map's supported voxels: points (N x 3 float32), their observation counts, best peak heights,
        last keyframes."""
        shown = self._supported(self._keys)
        return ((self._sums[shown] / np.maximum(self._counts[shown], 1)[:, None]).astype(np.float32),
                self._counts[shown], self._conf[shown], self._keyframe[shown])
