"""Where the targets sharing one blob are: boxes of known sizes placed to explain its recent pixels.

When targets cross or walk side by side, their events form one blob and its box is the union of
theirs. The tracks still know each target's size, so each box is moved (coordinate ascent over
integer shifts near its prediction) to cover as many recent pixels as it can that no other box
already explains, and as little empty image: a pixel gains `1 - density` if it fired recently and
loses `density` if not. Pixels under another box count for nothing, so a target partly hidden
behind a nearer one is placed by the part of it still in view, and one wholly inside another's box
stays at its prediction, held there by a small pull. Beyond the image nothing fires, so a box
whose target is leaving goes on out with it, instead of being held inside on the other's events.

A slow or faint target fires few of its pixels, maybe fewer than `density`: then its own pixels
would cost more than they pay, and its box would rather slide under a busier neighbour's, where
pixels count for nothing (traced on a slowly moving target that a faster one passed in front of).
So each box pays from its own target's expected share of recent pixels, if that is the lower.

Pixels under the boxes of the tracks outside the blob (`fixed`) count for nothing either: they are
those targets' own. Without that, a box at the edge of its blob slid onto a neighbouring blob's
pixels, nearer its prediction than its own target's (traced on two targets moving together below
a third: the upper one's box left its blob for the third's trail). On three sets of 60 seeds id
switches per object-minute went 1.89 -> 1.86, 2.46 -> 2.31, 2.46 -> 2.29, precision@20 up 0.001-0.002.

A size known from before the merge can be wrong (two targets that came in together, a box that
held a trail), and a blob may last seconds; so each edge may also move a pixel a round, against a
pull towards the size the track last measured on its own, which keeps right sizes from drifting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from services.tracker.objects.clusters import trimmed_box

# beyond this many boxes reaching into where a box may go, its gains are summed on a mask of what they cover: the
# exact sums over their intersections (`_cover`) cost 2^m each (a method that made 40 tracks stalled on one update)
EXACT_OTHERS = 4


@dataclass
class LayoutParams:
    recent: float = 0.35  # decayed weight of a pixel that fired recently (as the cluster boxes use)
    density: float = 0.1  # share of recent pixels above which covering a pixel pays
    reach_px: int = 6  # each box moves at most this far from its prediction per round
    # cost of a box's squared shift from its prediction, per px^2. With the other tracks' pixels left to them
    # (`fixed`), 0.4 against 0.2 took id switches per object-minute 1.86 -> 1.84, 2.31 -> 2.19, 2.29 -> 2.12 and
    # 1.67 -> 1.52 on four sets of 60 seeds (200-259, 500-679), precision@20 +0.000-0.002 (0.3: 1.57 and 0.55:
    # 1.56 on the last set; 0.8: 2.22 on the second)
    pull: float = 0.4
    rounds: int = 2
    resize_px: int = 1  # each edge moves at most this far per round (0: sizes kept)
    size_pull: float = 0.2  # cost of a relative size change from the track's own, per px^2 of box
    sparse_share: float = 0.5  # a box pays from this share of its target's expected fill where below `density`


def fit_layout(image: np.ndarray, boxes: np.ndarray, params: LayoutParams,
               sizes: np.ndarray | None = None, fills: np.ndarray | None = None,
               fixed: np.ndarray | None = None) -> np.ndarray:
    """The boxes (K x 4: x, y, w, h) moved onto the recent pixels of a decayed image, their sizes
    pulled towards `sizes` (K x 2: w, h; the boxes' own if not given), each paying for empty pixels
    by `density` or by its share of `fills` (K: the share of their pixels the targets usually fire), the lower;
    the pixels of `fixed` boxes (F x 4: other tracks', which stay where they are) count for nothing."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    own = boxes[:, 2:] if sizes is None else np.asarray(sizes, np.float64).reshape(-1, 2)
    density = np.full(len(boxes), params.density, np.float32)
    if fills is not None:
        density = np.minimum(density, params.sparse_share * np.asarray(fills, np.float32))
    fixed = np.zeros((0, 4)) if fixed is None else np.asarray(fixed, np.float64).reshape(-1, 4)
    return _placed(image, boxes, own, np.float32(params.recent), density, params.reach_px,
                   params.pull, params.rounds, params.resize_px, params.size_pull, fixed)


@numba.njit(cache=True, nogil=True)
def _placed(image, boxes, own, recent, density, reach, pull, rounds, resize, size_pull, fixed):  # noqa: ANN001, ANN202 - numba kernel
    """`fit_layout` on the region the boxes can reach: boxes start at their rounded corners and
    sizes; one left where it started keeps its sub-pixel prediction. Only the fixed boxes that reach
    into the region are kept (each doubles the cost of a cover)."""
    h_img, w_img = image.shape
    margin = reach * rounds
    x0 = int(np.floor(boxes[:, 0].min())) - margin
    y0 = int(np.floor(boxes[:, 1].min())) - margin
    x1 = int(np.ceil((boxes[:, 0] + boxes[:, 2]).max())) + margin
    y1 = int(np.ceil((boxes[:, 1] + boxes[:, 3]).max())) + margin
    out = boxes.astype(np.float32)
    ix0, iy0, ix1, iy1 = max(x0, 0), max(y0, 0), min(x1, w_img), min(y1, h_img)
    if ix1 <= ix0 or iy1 <= iy0:
        return out
    if ix0 == x0 and iy0 == y0 and ix1 == x1 and iy1 == y1:
        region = image[y0:y1, x0:x1]
    else:  # beyond the image nothing fires: a box may go on out of it, as its target does
        region = np.zeros((y1 - y0, x1 - x0), image.dtype)
        for y in range(iy0, iy1):  # by element: a block assignment compiled a second of error messages
            for x in range(ix0, ix1):
                region[y - y0, x - x0] = image[y, x]
    k_n = len(boxes)
    near = ((fixed[:, 0] < x1) & (fixed[:, 0] + fixed[:, 2] > x0) & (fixed[:, 1] < y1)
            & (fixed[:, 1] + fixed[:, 3] > y0))
    all_boxes = np.concatenate((boxes, fixed[near]))
    n_all = len(all_boxes)
    pred = np.empty((n_all, 2))
    pos = np.empty((n_all, 2), np.int64)
    size = np.empty((n_all, 2), np.int64)
    for k in range(n_all):
        pred[k, 0], pred[k, 1] = all_boxes[k, 0] - x0, all_boxes[k, 1] - y0
        pos[k, 0], pos[k, 1] = round(all_boxes[k, 0]) - x0, round(all_boxes[k, 1]) - y0
        size[k, 0], size[k, 1] = max(round(all_boxes[k, 2]), 1), max(round(all_boxes[k, 3]), 1)
    start, was_size = pos.copy(), size.copy()
    _fit(region, recent, density, pos, size, pred, reach, pull, rounds, np.maximum(own, 1.0),
         resize, size_pull, k_n)
    for k in range(k_n):
        resized = size[k, 0] != was_size[k, 0] or size[k, 1] != was_size[k, 1]
        if resized or pos[k, 0] != start[k, 0] or pos[k, 1] != start[k, 1]:
            out[k, 0], out[k, 1] = pos[k, 0] + x0, pos[k, 1] + y0
        if resized:
            out[k, 2], out[k, 3] = size[k, 0], size[k, 1]
    return out


@numba.njit(cache=True, nogil=True)
def _fit(region, recent, density, pos, size, pred, reach, pull, rounds, own, resize, size_pull, k_move):  # noqa: ANN001, ANN202 - numba kernel
    """Coordinate ascent of the first `k_move` boxes `pos` and `size` (in place; the rest stay): each in turn takes
    the shift within `reach` (and the region) that best covers the pixels no other box covers (at its `density`), less
    `pull` times its squared distance from `pred`; then each of its edges the move within `resize` that does, less
    `size_pull` times its squared relative size change from `own`, per px^2 of box.
    One integral image of recent pixels (int32: exact, and lighter than the gains' floats) serves every
    sum (see `_cover`), unless more than `EXACT_OTHERS` boxes reach into where a box may go (see `_uncovered`)."""
    h, w = region.shape
    total = np.zeros((h + 1, w + 1), np.int32)
    for y in range(h):
        run = 0
        src, above, row = region[y], total[y], total[y + 1]
        for x in range(w):
            run += src[x] >= recent
            row[x + 1] = above[x + 1] + run
    k_n = len(pos)
    others = np.empty(k_n - 1, np.int64)
    rect = np.empty(4, np.int64)
    window = np.empty(4, np.int64)
    exact = np.zeros((0, 0), np.int32)  # no mask: `_gain` sums exactly
    for _ in range(rounds):
        for k in range(k_move):
            # where this box may go in this round: the others beyond it do not change its gains
            window[0], window[1] = max(pos[k, 0] - reach - resize, 0), max(pos[k, 1] - reach - resize, 0)
            window[2] = min(pos[k, 0] + size[k, 0] + reach + resize, w)
            window[3] = min(pos[k, 1] + size[k, 1] + reach + resize, h)
            m = 0
            for j in range(k_n):
                if (j != k and pos[j, 0] < window[2] and pos[j, 0] + size[j, 0] > window[0]
                        and pos[j, 1] < window[3] and pos[j, 1] + size[j, 1] > window[1]):
                    others[m] = j
                    m += 1
            free, area = (_uncovered(region, recent, pos, size, others, m, window) if m > EXACT_OTHERS
                          else (exact, exact))
            best, bx, by = -np.inf, pos[k, 0], pos[k, 1]
            for ya in range(max(pos[k, 1] - reach, 0), min(pos[k, 1] + reach, h - size[k, 1]) + 1):
                for xa in range(max(pos[k, 0] - reach, 0), min(pos[k, 0] + reach, w - size[k, 0]) + 1):
                    ex, ey = xa - pred[k, 0], ya - pred[k, 1]
                    score = (_gain(total, free, area, window, density[k], pos, size, others, m,
                                   xa, ya, xa + size[k, 0], ya + size[k, 1]) - pull * (ex * ex + ey * ey))
                    if score > best:
                        best, bx, by = score, xa, ya
            pos[k, 0], pos[k, 1] = bx, by
            rect[0], rect[1], rect[2], rect[3] = bx, by, bx + size[k, 0], by + size[k, 1]
            for edge in range(4 if resize > 0 else 0):  # x0, y0, x1, y1
                at, best, best_at = rect[edge], -np.inf, rect[edge]
                for v in range(at - resize, at + resize + 1):
                    rect[edge] = v
                    bw, bh = rect[2] - rect[0], rect[3] - rect[1]
                    if bw < 1 or bh < 1 or rect[0] < 0 or rect[1] < 0 or rect[2] > w or rect[3] > h:
                        continue
                    dw, dh = bw / own[k, 0] - 1.0, bh / own[k, 1] - 1.0
                    score = (_gain(total, free, area, window, density[k], pos, size, others, m,
                                   rect[0], rect[1], rect[2], rect[3])
                             - size_pull * own[k, 0] * own[k, 1] * (dw * dw + dh * dh))
                    if score > best:
                        best, best_at = score, v
                rect[edge] = best_at
            pos[k, 0], pos[k, 1], size[k, 0], size[k, 1] = rect[0], rect[1], rect[2] - rect[0], rect[3] - rect[1]


@numba.njit(cache=True, nogil=True)
def _uncovered(region, recent, pos, size, others, m, window):  # noqa: ANN001, ANN202 - numba kernel
    """Integral images over `window` (x0, y0, x1, y1 of the region) of the recent pixels and of all pixels that none
    of the first `m` boxes of `others` covers: made where those are more than `EXACT_OTHERS` (for a few, `_cover`
    sums them exactly from the region's one integral image, cheaper)."""
    x0, y0, x1, y1 = window[0], window[1], window[2], window[3]
    covered = np.zeros((y1 - y0, x1 - x0), np.bool_)
    for t in range(m):
        j = others[t]
        covered[max(pos[j, 1] - y0, 0):max(pos[j, 1] + size[j, 1] - y0, 0),
                max(pos[j, 0] - x0, 0):max(pos[j, 0] + size[j, 0] - x0, 0)] = True
    free = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.int32)
    area = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.int32)
    for y in range(y1 - y0):
        run_free = run_area = 0
        for x in range(x1 - x0):
            if not covered[y, x]:
                run_area += 1
                run_free += region[y0 + y, x0 + x] >= recent
            free[y + 1, x + 1] = free[y, x + 1] + run_free
            area[y + 1, x + 1] = area[y, x + 1] + run_area
    return free, area


@numba.njit(cache=True, nogil=True, inline="always")
def _gain(total, free, area, window, density, pos, size, others, m, x0, y0, x1, y1):  # noqa: ANN001, ANN202 - numba kernel
    """What covering box (x0, y0)-(x1, y1) gains: from the window's integral images of uncovered pixels where
    `_uncovered` made them, else by `_cover`."""
    if m <= EXACT_OTHERS:
        return _cover(total, density, pos, size, others, m, x0, y0, x1, y1)
    wx0, wy0 = window[0], window[1]
    hw, ww = free.shape[0] - 1, free.shape[1] - 1
    sx0, sy0 = min(max(x0 - wx0, 0), ww), min(max(y0 - wy0, 0), hw)
    sx1, sy1 = min(max(x1 - wx0, 0), ww), min(max(y1 - wy0, 0), hw)
    recent = free[sy1, sx1] - free[sy0, sx1] - free[sy1, sx0] + free[sy0, sx0]
    pixels = area[sy1, sx1] - area[sy0, sx1] - area[sy1, sx0] + area[sy0, sx0]
    return recent - density * pixels


@numba.njit(cache=True, nogil=True, inline="always")
def _cover(total, density, pos, size, others, m, x0, y0, x1, y1):  # noqa: ANN001, ANN202 - numba kernel
    """The gain of the pixels of box (x0, y0)-(x1, y1) that none of the first `m` boxes of `others`
    covers (their recent pixels less `density` times their area), from the integral image `total`: what
    they cover is cut out by inclusion-exclusion over their intersections (rectangles), 2^m sums: cheap
    for the two to four targets a blob holds."""
    h, w = total.shape[0] - 1, total.shape[1] - 1
    score = 0.0
    for subset in range(1 << m):  # subset 0 is the box itself
        sx0, sy0, sx1, sy1, sign = x0, y0, x1, y1, 1.0
        for t in range(m):
            if subset >> t & 1:
                j = others[t]
                sx0, sy0 = max(sx0, pos[j, 0]), max(sy0, pos[j, 1])
                sx1, sy1 = min(sx1, pos[j, 0] + size[j, 0]), min(sy1, pos[j, 1] + size[j, 1])
                sign = -sign
        sx0, sy0, sx1, sy1 = max(sx0, 0), max(sy0, 0), min(sx1, w), min(sy1, h)
        if sx1 > sx0 and sy1 > sy0:
            recent = total[sy1, sx1] - total[sy0, sx1] - total[sy1, sx0] + total[sy0, sx0]
            score += sign * (recent - density * ((sx1 - sx0) * (sy1 - sy0)))
    return score


def leftover(image: np.ndarray, region: np.ndarray, boxes: np.ndarray, recent: float,
             trim: float = 0.01) -> tuple[np.ndarray, int, int]:
    """The box (x, y, w, h) of the recent pixels of `region` that none of `boxes` (K x 4) holds, trimmed
    of the outermost `trim` share on each side; how many there are; how many recent pixels the region has."""
    return _leftover(image, np.asarray(region, np.float64), np.asarray(boxes, np.float64).reshape(-1, 4),
                     np.float32(recent), trim)


@numba.njit(cache=True, nogil=True)
def _leftover(image, region, boxes, recent, trim):  # noqa: ANN001, ANN202 - numba kernel
    """`leftover` in one pass over the region's pixels, into column and row counts of those left."""
    h_img, w_img = image.shape
    x0, y0 = max(int(np.floor(region[0])), 0), max(int(np.floor(region[1])), 0)
    x1 = min(int(np.ceil(region[0] + region[2])), w_img)
    y1 = min(int(np.ceil(region[1] + region[3])), h_img)
    out = np.zeros(4, np.float32)
    if x1 <= x0 or y1 <= y0:
        return out, 0, 0
    col = np.zeros(x1 - x0, np.int64)
    row = np.zeros(y1 - y0, np.int64)
    total = 0
    for y in range(y0, y1):
        for x in range(x0, x1):
            if image[y, x] < recent:
                continue
            total += 1
            held = False
            for k in range(len(boxes)):
                if boxes[k, 0] <= x < boxes[k, 0] + boxes[k, 2] and boxes[k, 1] <= y < boxes[k, 1] + boxes[k, 3]:
                    held = True
                    break
            if not held:
                col[x - x0] += 1
                row[y - y0] += 1
    n = col.sum()
    if n == 0:
        return out, n, total
    trimmed_box(col, row, trim * n, out)
    out[0] += x0
    out[1] += y0
    return out, n, total
