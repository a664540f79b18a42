"""Where the targets sharing one blob are: boxes of known sizes placed to explain its recent pixels.

When targets cross or walk side by side, their events form one blob and its box is the union of
theirs. The tracks still know each target's size, so each box is moved (coordinate ascent over
integer shifts near its prediction) to cover as many recent pixels as it can that no other box
already explains, and as little empty image: a pixel gains `1 - density` if it fired recently and
loses `density` if not. Pixels under another box count for nothing, so a target partly hidden
behind a nearer one is placed by the part of it still in view, and one wholly inside another's box
stays at its prediction, held there by a small pull.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np


@dataclass
class LayoutParams:
    recent: float = 0.35  # decayed weight of a pixel that fired recently (as the cluster boxes use)
    density: float = 0.1  # share of recent pixels above which covering a pixel pays
    reach_px: int = 6  # each box moves at most this far from its prediction per round
    pull: float = 0.2  # cost of a box's squared shift from its prediction, per px^2
    rounds: int = 2


def fit_layout(image: np.ndarray, boxes: np.ndarray, params: LayoutParams) -> np.ndarray:
    """The boxes (K x 4: x, y, w, h, sizes kept) moved onto the recent pixels of a decayed image."""
    rows = np.asarray(boxes, np.float32).reshape(-1, 4).tolist()
    h_img, w_img = image.shape
    margin = params.reach_px * params.rounds
    x0 = max(math.floor(min(r[0] for r in rows)) - margin, 0)
    y0 = max(math.floor(min(r[1] for r in rows)) - margin, 0)
    x1 = min(math.ceil(max(r[0] + r[2] for r in rows)) + margin, w_img)
    y1 = min(math.ceil(max(r[1] + r[3] for r in rows)) + margin, h_img)
    if x1 <= x0 or y1 <= y0:
        return np.asarray(rows, np.float32).reshape(-1, 4)
    pred = np.array([(r[0] - x0, r[1] - y0) for r in rows])
    start = [(round(r[0]) - x0, round(r[1]) - y0) for r in rows]
    pos = np.array(start, np.int64)
    size = np.array([(max(round(r[2]), 1), max(round(r[3]), 1)) for r in rows], np.int64)
    _fit(image[y0:y1, x0:x1], np.float32(params.recent), np.float32(params.density), pos, size, pred,
         params.reach_px, params.pull, params.rounds)
    for r, (px, py), was in zip(rows, pos.tolist(), start, strict=True):
        if (px, py) != was:  # boxes left where they were keep their sub-pixel prediction
            r[0], r[1] = px + x0, py + y0
    return np.asarray(rows, np.float32)


@numba.njit(cache=True, nogil=True)
def _fit(region, recent, density, pos, size, pred, reach, pull, rounds):  # noqa: ANN001, ANN202 - numba kernel
    """Coordinate ascent of the box positions `pos` (in place): each box in turn takes the shift
    within `reach` (and the region) that best covers the pixels no other box covers, less `pull`
    times its squared distance from `pred`. One integral image of the gain serves every sum: what
    the others cover is cut out by inclusion-exclusion over their intersections (rectangles), 2^(K-1)
    sums per shift: cheap for the two to four targets one blob holds."""
    h, w = region.shape
    total = np.zeros((h + 1, w + 1), np.float64)
    for y in range(h):
        run = 0.0
        for x in range(w):
            run += (1.0 if region[y, x] >= recent else 0.0) - density
            total[y + 1, x + 1] = total[y, x + 1] + run
    k_n = len(pos)
    others = np.empty(k_n - 1, np.int64)
    for _ in range(rounds):
        for k in range(k_n):
            m = 0
            for j in range(k_n):
                if j != k:
                    others[m] = j
                    m += 1
            best, bx, by = -np.inf, pos[k, 0], pos[k, 1]
            for ya in range(max(pos[k, 1] - reach, 0), min(pos[k, 1] + reach, h - size[k, 1]) + 1):
                for xa in range(max(pos[k, 0] - reach, 0), min(pos[k, 0] + reach, w - size[k, 0]) + 1):
                    score = 0.0
                    for subset in range(1 << m):  # subset 0 is the box itself
                        x0, y0, x1, y1, sign = xa, ya, xa + size[k, 0], ya + size[k, 1], 1.0
                        for t in range(m):
                            if subset >> t & 1:
                                j = others[t]
                                x0, y0 = max(x0, pos[j, 0]), max(y0, pos[j, 1])
                                x1, y1 = min(x1, pos[j, 0] + size[j, 0]), min(y1, pos[j, 1] + size[j, 1])
                                sign = -sign
                        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
                        if x1 > x0 and y1 > y0:
                            score += sign * (total[y1, x1] - total[y0, x1] - total[y1, x0] + total[y0, x0])
                    ex, ey = xa - pred[k, 0], ya - pred[k, 1]
                    score -= pull * (ex * ex + ey * ey)
                    if score > best:
                        best, bx, by = score, xa, ya
            pos[k, 0], pos[k, 1] = bx, by
