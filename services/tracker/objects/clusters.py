"""Moving clusters in a decayed event image (seed 003's contour method): local occupancy threshold,
closing, connected components, and a tight box around each component's recent events.

The threshold is on occupancy (the share of pixels with a recent event), not on counts, so a hot
or flickering pixel weighs no more than one event and sparse, slow objects still form one region.
The region found that way is wider than the object by the smoothing window and trails behind it, so
each box is taken instead from the pixels with an event in about the last `tau`, trimmed of the
outermost `trim` share on each side.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np


@dataclass
class ClusterParams:
    density: float = 0.08  # share of pixels with a recent event, over `window_px` squares
    window_px: int = 9
    close_px: int = 9
    min_area_px: int = 60
    recent: float = 0.35  # decayed weight of a pixel counted in the box (one event ~ 1 tau ago)
    trim: float = 0.01  # share of a cluster's recent pixels left outside its box on each side


def detect_clusters(image: np.ndarray, params: ClusterParams) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (N x 4: x, y, w, h) and masses (decayed event count) of the moving clusters in `image`."""
    density = cv2.blur(np.minimum(image, 1.0), (params.window_px, params.window_px))
    mask = (density > params.density).astype(np.uint8)
    if params.close_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.close_px, params.close_px))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= params.min_area_px) + 1
    if not len(keep):
        return np.zeros((0, 4), np.float32), np.zeros(0, np.float32)
    boxes = _trimmed_boxes(labels, image, n, np.float32(params.recent), params.trim)[keep]
    mass = np.bincount(labels.ravel(), image.ravel(), n)[keep].astype(np.float32)
    ok = (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
    return boxes[ok], mass[ok]


@numba.njit(cache=True, nogil=True)
def _trimmed_boxes(labels, image, n, recent, trim):  # noqa: ANN001, ANN202 - numba kernel
    """Per label, the box holding all but `trim` of its recent pixels on each side (x, y, w, h)."""
    h, w = labels.shape
    col = np.zeros((n, w), np.int32)
    row = np.zeros((n, h), np.int32)
    for y in range(h):
        for x in range(w):
            lab = labels[y, x]
            if lab and image[y, x] >= recent:
                col[lab, x] += 1
                row[lab, y] += 1
    out = np.zeros((n, 4), np.float32)
    for lab in range(1, n):
        total = col[lab].sum()
        if total == 0:
            continue
        cut = trim * total
        lo, hi = _quantiles(col[lab], cut)
        out[lab, 0], out[lab, 2] = lo, hi + 1 - lo
        lo, hi = _quantiles(row[lab], cut)
        out[lab, 1], out[lab, 3] = lo, hi + 1 - lo
    return out


@numba.njit(cache=True, nogil=True)
def _quantiles(hist, cut):  # noqa: ANN001, ANN202 - numba kernel
    """First and last bins of `hist` once `cut` counts are left off each end."""
    acc = 0
    lo = 0
    for i in range(len(hist)):
        acc += hist[i]
        if acc > cut:
            lo = i
            break
    acc = 0
    hi = len(hist) - 1
    for i in range(len(hist) - 1, -1, -1):
        acc += hist[i]
        if acc > cut:
            hi = i
            break
    return lo, hi
