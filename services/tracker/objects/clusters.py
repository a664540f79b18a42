"""Moving clusters in a decayed event image (seed 003's contour method): local occupancy threshold,
closing, connected components, and a tight box around each component's recent events.

Thresholding, closing and labelling run on a grid of small cells rather than on every pixel: the
same regions at a sixteenth of the work, which keeps an update well under a millisecond.

The threshold is on occupancy (the share of pixels with a recent event), not on counts, so a hot
or flickering pixel weighs no more than one event and sparse, slow objects still form one region.
It has two levels (hysteresis, as Canny's edges): a region must reach `density` somewhere and then
extends over the cells around down to `grow`, so a target with little texture is found whole, not
in pieces, while sensor noise, which never reaches `density`, forms none.
The region found that way is wider than the object by the smoothing window and trails behind it, so
each box is taken instead from the pixels with an event in about the last `tau`, trimmed of the
outermost `trim` share on each side. The same smoothing joins two targets that pass close by into
one region; where its recent pixels fall in parts about `part_gap_px` apart, each part gets its own box.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from services.tracker.objects import cells


@dataclass
class ClusterParams:
    density: float = 0.08  # share of pixels with a recent event, over `window_cells` squares of cells
    grow: float = 0.05  # a region reaching `density` somewhere extends over its cells above this share
    cell_px: int = 4  # occupancy is thresholded, closed and labelled on a grid of cells this size
    window_cells: int = 3
    close_cells: int = 3
    min_area_px: int = 60
    active: float = 0.05  # decayed weight of a pixel counted as occupied (an event ~ 3 tau ago)
    recent: float = 0.35  # decayed weight of a pixel counted in the box (one event ~ 1 tau ago)
    trim: float = 0.01  # share of a cluster's recent pixels left outside its box on each side
    part_gap_px: int = 6  # a cluster whose recent pixels fall in parts about this far apart is split (0: never)
    part_share: float = 0.1  # a part holds at least this share of its cluster's recent pixels


def detect_clusters(image: np.ndarray, params: ClusterParams) -> np.ndarray:
    """Boxes (N x 4: x, y, w, h) of the moving clusters in a decayed event image."""
    c, k = params.cell_px, params.window_cells
    window_px = k * k * c * c
    disc = _disc(max(params.close_cells, 1))  # 1 x 1: no closing
    part_window = params.part_gap_px // 2  # in blocks of 2 x 2 px
    return _detect(image, c, np.float32(params.active), k, params.density * window_px,
                   min(params.grow, params.density) * window_px, disc,
                   -(-params.min_area_px // (c * c)), np.float32(params.recent), params.trim,
                   part_window, params.part_share, params.min_area_px)


@numba.njit(cache=True, nogil=True)
def _detect(image, cell, active, window, least, least_grow, disc, min_cells, recent, trim,  # noqa: ANN001, ANN202 - numba kernel
            part_window, part_share, part_px):
    """All of `detect_clusters` in one call: an update's Python overhead was as long as its kernels."""
    sums = cells.box_sums(cells.occupancy(image, cell, active), window)
    mask = (sums > least_grow).astype(np.uint8)
    if disc.size > 1:
        mask = cells.close(mask, disc)
    n, labels, stats = cells.components(mask)
    big = (stats[:, cells.AREA] >= min_cells) & cells.labels_exceeding(labels, sums, least, n)
    big[0] = False
    boxes = _trimmed_boxes(labels, big, cell, image, recent, trim)[big]
    boxes = boxes[(boxes[:, 2] > 0) & (boxes[:, 3] > 0)]
    if part_window < 1:
        return boxes
    out = np.empty((0, 4), np.float32)
    for i in range(len(boxes)):
        out = np.concatenate((out, _parts(image, boxes[i], recent, part_window, part_share, part_px)))
    return out


@numba.njit(cache=True, nogil=True)
def _parts(image, box, recent, window, least_share, least_px):  # noqa: ANN001, ANN202 - numba kernel
    """The parts of one box whose recent pixels lie apart by about `window` blocks of 2 x 2 px or more,
    each boxed, if two or more hold `least_share` of its recent pixels and `least_px` pixels; else the
    box itself. Parts are found on the blocks (a quarter of the work), boxed on the pixels."""
    x0, y0, cols, rows = int(box[0]), int(box[1]), int(box[2]), int(box[3])
    region = image[y0:y0 + rows, x0:x0 + cols]
    blocks = cells.occupancy(region, 2, recent)
    n, labels, _ = cells.components((cells.box_sums(blocks, window) > 0).astype(np.uint8))
    count = np.zeros(n, np.int64)
    for by in range(labels.shape[0]):
        for bx in range(labels.shape[1]):
            count[labels[by, bx]] += blocks[by, bx]
    keep = (count >= least_share * count.sum()) & (count >= least_px)
    keep[0] = False
    kept = np.flatnonzero(keep)
    if len(kept) < 2:  # most boxes: decided on the blocks, no pass over the pixels
        return box.reshape(1, 4)
    lo = np.full((n, 2), 1 << 30, np.int64)
    hi = np.full((n, 2), -1, np.int64)
    for y in range(rows):
        for x in range(cols):
            if region[y, x] >= recent:
                lab = labels[y // 2, x // 2]
                lo[lab, 0], lo[lab, 1] = min(lo[lab, 0], x), min(lo[lab, 1], y)
                hi[lab, 0], hi[lab, 1] = max(hi[lab, 0], x), max(hi[lab, 1], y)
    out = np.empty((len(kept), 4), np.float32)
    for i, lab in enumerate(kept):
        out[i, 0], out[i, 1] = x0 + lo[lab, 0], y0 + lo[lab, 1]
        out[i, 2], out[i, 3] = hi[lab, 0] - lo[lab, 0] + 1, hi[lab, 1] - lo[lab, 1] + 1
    return out


@functools.cache
def _disc(size: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


@numba.njit(cache=True, nogil=True)
def _trimmed_boxes(labels, keep, cell, image, recent, trim):  # noqa: ANN001, ANN202 - numba kernel
    """Per kept cell label, the box holding all but `trim` of its recent pixels on each side (x, y, w, h).
    One pass reads only the pixels under labelled cells, into per-label column and row counts."""
    h, w = image.shape
    n = len(keep)
    col = np.zeros((n, w), np.int32)
    row = np.zeros((n, h), np.int32)
    rows, cols = labels.shape
    for cy in range(rows):
        cell_row = labels[cy]
        cx = 0
        while cx < cols:  # runs of cells of one kept label, each read in tight loops along its rows
            lab = cell_row[cx]
            end = cx + 1
            while end < cols and cell_row[end] == lab:
                end += 1
            if lab and keep[lab]:
                x0, x1 = cx * cell, min(end * cell, w)
                counts = col[lab]
                for y in range(cy * cell, min(cy * cell + cell, h)):
                    src = image[y]
                    found = 0
                    for x in range(x0, x1):
                        hit = src[x] >= recent
                        counts[x] += hit
                        found += hit
                    row[lab, y] += found
            cx = end
    out = np.zeros((n, 4), np.float32)
    for lab in range(1, n):
        total = col[lab].sum()
        if not keep[lab] or total == 0:
            continue
        trimmed_box(col[lab], row[lab], trim * total, out[lab])
    return out


@numba.njit(cache=True, nogil=True)
def trimmed_box(col, row, cut, out):  # noqa: ANN001, ANN201 - numba kernel
    """Into `out` (x, y, w, h): the box of pixels counted per column and row, once `cut` of them are
    left off each side (from column and row 0)."""
    lo, hi = _trimmed_ends(col, cut)
    out[0], out[2] = lo, hi + 1 - lo
    lo, hi = _trimmed_ends(row, cut)
    out[1], out[3] = lo, hi + 1 - lo


@numba.njit(cache=True, nogil=True)
def _trimmed_ends(hist, cut):  # noqa: ANN001, ANN202 - numba kernel
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
