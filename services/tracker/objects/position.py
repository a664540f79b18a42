"""3D position of tracked boxes in the camera frame (x right, y down, z forward; m).

From a known object size (seed 003): a target `size_m` wide that spans `w` pixels lies at
Z = fx * size_m / w; its centre pixel back-projected through K at that depth gives x and y.
From a depth image (the mapper's, or a simulator's truth) the depth is instead the median of the
valid depths inside the box.
"""

from __future__ import annotations

import numpy as np


def xyz_from_size(boxes: np.ndarray, size_m: np.ndarray, K: np.ndarray) -> np.ndarray:
    """N x 3 positions of boxes (x, y, w, h) of targets `size_m` wide (N); NaN where unknown."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(boxes[:, 2] > 0, K[0, 0] * np.asarray(size_m, np.float64) / boxes[:, 2], np.nan)
    return _back_project(boxes, z, K)


def xyz_from_depth(boxes: np.ndarray, depth: np.ndarray, K: np.ndarray, min_valid: int = 5) -> np.ndarray:
    """N x 3 positions from the median valid depth (> 0, finite) inside each box; NaN where too few."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    h, w = depth.shape
    z = np.full(len(boxes), np.nan)
    for i, (x, y, bw, bh) in enumerate(boxes):
        x0, y0 = int(np.clip(x, 0, w)), int(np.clip(y, 0, h))
        x1, y1 = int(np.clip(np.ceil(x + bw), 0, w)), int(np.clip(np.ceil(y + bh), 0, h))
        patch = depth[y0:y1, x0:x1]
        valid = patch[np.isfinite(patch) & (patch > 0)]
        if len(valid) >= min_valid:
            z[i] = float(np.median(valid))
    return _back_project(boxes, z, K)


def _back_project(boxes: np.ndarray, z: np.ndarray, K: np.ndarray) -> np.ndarray:
    u = boxes[:, 0] + boxes[:, 2] / 2
    v = boxes[:, 1] + boxes[:, 3] / 2
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    return np.column_stack([x, y, z]).astype(np.float32)


def sizes_for(ids: np.ndarray, default_m: float | None, per_id: dict[int, float]) -> np.ndarray:
    """The metric width of each track id: its own if configured, else the default (NaN if none)."""
    fallback = np.nan if default_m is None else float(default_m)
    return np.array([per_id.get(int(i), fallback) for i in ids], np.float64)
