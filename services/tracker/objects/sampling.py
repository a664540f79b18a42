"""Density-insensitive key-event sampling (seed 004).

A regular grid is laid over the sensor; each cell keeps the one event nearest its centre. Dense
regions (a fast, textured target) are thinned the most and sparse ones (a slow target) the least,
so subsampled events still cover every part of the scene, unlike random sampling, which keeps
dense regions dense and erases sparse ones.
"""

from __future__ import annotations

import numba
import numpy as np


def key_events(events: np.ndarray, width: int, height: int, cell_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ascending, so time order is kept) of the key events of `events`, one per occupied
    `cell_px` square, and how many events each one stands for."""
    if not len(events):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return _nearest_per_cell(events["x"], events["y"], width, height, int(cell_px))


@numba.njit(cache=True, nogil=True)
def _nearest_per_cell(xs, ys, width, height, cell):  # noqa: ANN001, ANN202 - numba kernel
    cols = (width + cell - 1) // cell
    rows = (height + cell - 1) // cell
    best = np.full(cols * rows, -1, np.int64)
    best_d = np.full(cols * rows, np.inf)
    count = np.zeros(cols * rows, np.int64)
    half = (cell - 1) / 2.0
    for i in range(len(xs)):
        x, y = xs[i], ys[i]
        if x >= width or y >= height:
            continue
        cx, cy = x // cell, y // cell
        c = cy * cols + cx
        count[c] += 1
        dx = x - (cx * cell + half)
        dy = y - (cy * cell + half)
        d = dx * dx + dy * dy
        if d < best_d[c]:
            best_d[c] = d
            best[c] = i
    keep = best >= 0
    idx = best[keep]
    weight = count[keep]
    order = np.argsort(idx)
    return idx[order], weight[order]
