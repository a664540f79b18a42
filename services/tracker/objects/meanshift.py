"""Mean-shift of a box on an image: the box moves to the weighted centroid of what it covers."""

from __future__ import annotations

import numpy as np


def mean_shift(image: np.ndarray, box: np.ndarray, iterations: int = 3) -> np.ndarray:
    """`box` (x, y, w, h) moved, keeping its size, to the centroid of `image` under it; unchanged
    where it covers nothing."""
    h_img, w_img = image.shape
    box = np.asarray(box, np.float32).copy()
    for _ in range(iterations):
        x0, y0 = int(max(box[0], 0)), int(max(box[1], 0))
        x1, y1 = int(min(box[0] + box[2], w_img)), int(min(box[1] + box[3], h_img))
        if x1 <= x0 or y1 <= y0:
            break
        patch = image[y0:y1, x0:x1]
        mass = float(patch.sum())
        if mass <= 0:
            break
        cx = float(patch.sum(axis=0) @ np.arange(x0, x1)) / mass + 0.5
        cy = float(patch.sum(axis=1) @ np.arange(y0, y1)) / mass + 0.5
        shift = np.array([cx - box[0] - box[2] / 2, cy - box[1] - box[3] / 2], np.float32)
        box[:2] += shift
        if np.abs(shift).max() < 0.5:
            break
    return box
