"""New events per box since the last update: whether a detected target still moves.

A target that stops leaves its decayed image to fade over a few tau, and the boxes detected in the
fading image shrink towards the pixels that fired most: a track corrected by them slides off its
still target. The count of new events in a detection tells a fading one from a moving one. Counts
are kept on a grid of small cells, so counting costs one pass over the events and a box's count a
sum over its few cells.
"""

from __future__ import annotations

import numba
import numpy as np


class FreshCounts:
    """Counts the events accepted since the last `reset`, per `2**cell_shift` px square."""

    def __init__(self, width: int, height: int, cell_shift: int = 2) -> None:
        self.shift = cell_shift  # cells of 2**shift pixels
        cell = 1 << cell_shift
        self.counts = np.zeros((-(-height // cell), -(-width // cell)), np.int32)

    def accept(self, events: np.ndarray) -> None:
        if len(events):
            count_into(self.counts, events["x"], events["y"], self.shift)

    def count(self, boxes: np.ndarray) -> np.ndarray:
        """New events in each box (N x 4: x, y, w, h; the cells it touches)."""
        return _count_in(self.counts, np.asarray(boxes, np.float32).reshape(-1, 4), self.shift)

    def reset(self) -> None:
        """Counting starts again (after each update)."""
        self.counts[:] = 0


@numba.njit(cache=True, nogil=True)
def count_into(counts, xs, ys, shift):  # noqa: ANN001, ANN201 - numba kernel
    """Adds each event to its cell of `2**shift` px in `counts` (rows x cols); events beyond it are left out."""
    rows, cols = counts.shape
    for i in range(len(xs)):
        cx, cy = np.int32(xs[i]) >> shift, np.int32(ys[i]) >> shift
        if cx < cols and cy < rows:
            counts[cy, cx] += 1


@numba.njit(cache=True, nogil=True)
def _count_in(counts, boxes, shift):  # noqa: ANN001, ANN202 - numba kernel
    rows, cols = counts.shape
    cell = 1 << shift
    out = np.zeros(len(boxes), np.float64)
    for k in range(len(boxes)):
        x0, y0 = max(int(np.floor(boxes[k, 0] / cell)), 0), max(int(np.floor(boxes[k, 1] / cell)), 0)
        x1 = min(int(np.ceil((boxes[k, 0] + boxes[k, 2]) / cell)), cols)
        y1 = min(int(np.ceil((boxes[k, 1] + boxes[k, 3]) / cell)), rows)
        for cy in range(y0, y1):
            for cx in range(x0, x1):
                out[k] += counts[cy, cx]
    return out
