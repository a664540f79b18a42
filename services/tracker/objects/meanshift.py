"""Mean-shift of a box on an image: the box moves to the weighted centroid of what it covers."""

from __future__ import annotations

import numba
import numpy as np


def mean_shift(image: np.ndarray, box: np.ndarray, iterations: int = 3) -> np.ndarray:
    """`box` (x, y, w, h) moved, keeping its size, to the centroid of `image` under it; unchanged
    where it covers nothing."""
    return _mean_shift(image, np.asarray(box, np.float32).copy(), iterations)


@numba.njit(cache=True, nogil=True)
def _mean_shift(image, box, iterations):  # noqa: ANN001, ANN202 - numba kernel
    h_img, w_img = image.shape
    for _ in range(iterations):
        x0, y0 = int(max(box[0], 0.0)), int(max(box[1], 0.0))
        x1, y1 = int(min(box[0] + box[2], w_img)), int(min(box[1] + box[3], h_img))
        mass = sx = sy = 0.0
        for y in range(y0, y1):
            for x in range(x0, x1):
                v = image[y, x]
                mass += v
                sx += v * x
                sy += v * y
        if mass <= 0:
            break
        dx = sx / mass + 0.5 - box[0] - box[2] / 2
        dy = sy / mass + 0.5 - box[1] - box[3] / 2
        box[0] += dx
        box[1] += dy
        if abs(dx) < 0.5 and abs(dy) < 0.5:
            break
    return box
