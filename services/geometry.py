"""Pinhole geometry shared by the services' algorithms."""

from __future__ import annotations

import numpy as np


def unit_rays(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Unit viewing rays (N x 3, camera frame) of pixels (u, v), any shape flattened, through intrinsics K."""
    K = np.asarray(K, np.float64)
    u, v = np.asarray(u, np.float64).ravel(), np.asarray(v, np.float64).ravel()
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], 1)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def pixel_rays(K: np.ndarray, width: int, height: int, step: int = 1) -> np.ndarray:
    """`unit_rays` of every `step`th pixel's centre of a width x height sensor, row by row."""
    ys, xs = np.mgrid[0:height // step, 0:width // step].astype(np.float64) * step + (step - 1) / 2
    return unit_rays(K, xs, ys)
