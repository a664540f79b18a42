"""New events per box since the last update: whether a detected target still moves.

A target that stops leaves its decayed image to fade over a few tau, and the boxes detected in the
fading image shrink towards the pixels that fired most: a track corrected by them slides off its
still target. The count of new events in a detection tells a fading one from a moving one. Counts
are kept on a grid of small cells, so counting costs one pass over the events and a box's count is
four reads of an integral image.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np


class FreshCounts:
    """Counts the events accepted since the last `take`, per `cell_px` square."""

    def __init__(self, width: int, height: int, cell_px: int = 4) -> None:
        self.cell = cell_px
        self.counts = np.zeros((-(-height // cell_px), -(-width // cell_px)), np.float64)

    def accept(self, events: np.ndarray) -> None:
        if len(events):
            _count(self.counts, events["x"], events["y"], self.cell)

    def take(self, boxes: np.ndarray) -> np.ndarray:
        """New events in each box (N x 4: x, y, w, h; cells it touches), then the counts restart."""
        integral = cv2.integral(self.counts)
        rows, cols = self.counts.shape
        b = np.asarray(boxes, np.float64).reshape(-1, 4)
        x0 = np.clip(np.floor(b[:, 0] / self.cell), 0, cols).astype(np.int64)
        y0 = np.clip(np.floor(b[:, 1] / self.cell), 0, rows).astype(np.int64)
        x1 = np.clip(np.ceil((b[:, 0] + b[:, 2]) / self.cell), 0, cols).astype(np.int64)
        y1 = np.clip(np.ceil((b[:, 1] + b[:, 3]) / self.cell), 0, rows).astype(np.int64)
        self.counts[:] = 0
        return integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]

    def reset(self) -> None:
        self.counts[:] = 0


@numba.njit(cache=True, nogil=True)
def _count(counts, xs, ys, cell):  # noqa: ANN001, ANN202 - numba kernel
    rows, cols = counts.shape
    for i in range(len(xs)):
        cx, cy = xs[i] // cell, ys[i] // cell
        if cx < cols and cy < rows:
            counts[cy, cx] += 1.0
