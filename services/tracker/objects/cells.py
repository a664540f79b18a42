"""Binary-image steps of cluster detection on a coarse grid of cells, as numba kernels.

The grid is small (87 x 65 cells at 346 x 260), so OpenCV's per-call overhead and its thread pool
(whose spinning workers take the other core from the rest of an update) cost more than the work
itself; these kernels do the same steps in one thread, in integers, so results are exact:
occupancy counts, box sums with reflected borders, a closing, and 8-connected
components with their boxes and areas (the layout of OpenCV's `connectedComponentsWithStats`).
"""

from __future__ import annotations

import numba
import numpy as np

X, Y, W, H, AREA = range(5)  # columns of the component stats


@numba.njit(cache=True, nogil=True)
def occupancy(image, cell, active):  # noqa: ANN001, ANN201 - numba kernel
    """Per `cell` x `cell` square, how many pixels reach `active` (int32, partial squares at the
    right and bottom count their missing pixels as empty)."""
    h, w = image.shape
    rows, cols = -(-h // cell), -(-w // cell)
    out = np.zeros((rows, cols), np.int32)
    column = np.zeros(cols * cell, np.int32)  # per pixel column, over the rows of one cell row
    for cy in range(rows):
        column[:] = 0
        for y in range(cy * cell, min(cy * cell + cell, h)):
            src = image[y]
            for x in range(w):
                column[x] += src[x] >= active
        for cx in range(cols):
            out[cy, cx] = column[cx * cell:cx * cell + cell].sum()
    return out


@numba.njit(cache=True, nogil=True)
def _reflect(i, n):  # noqa: ANN001, ANN202 - numba kernel
    """Index `i` reflected into 0..n-1 without repeating the edge (OpenCV's BORDER_REFLECT_101)."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * n - 2 - i
    return i


@numba.njit(cache=True, nogil=True)
def box_sums(counts, window):  # noqa: ANN001, ANN201 - numba kernel
    """The counts summed over a `window` x `window` square around each cell (borders reflected);
    running sums, along x and then along y."""
    rows, cols = counts.shape
    r = window // 2
    across = np.zeros((rows, cols), np.int32)
    for y in range(rows):
        src = counts[y]
        total = 0
        for i in range(-r, r):
            total += src[_reflect(i, cols)]
        for x in range(cols):
            total += src[_reflect(x + r, cols)]
            across[y, x] = total
            total -= src[_reflect(x - r, cols)]
    out = np.zeros((rows, cols), np.int32)
    total_row = np.zeros(cols, np.int32)
    for i in range(-r, r):
        total_row += across[_reflect(i, rows)]
    for y in range(rows):
        total_row += across[_reflect(y + r, rows)]
        out[y] = total_row
        total_row -= across[_reflect(y - r, rows)]
    return out


@numba.njit(cache=True, nogil=True)
def close(mask, kernel):  # noqa: ANN001, ANN201 - numba kernel
    """Morphological closing (dilation, outside empty, then erosion, outside full) of a sparse 0/1
    mask by a symmetric 0/1 kernel: both passes only work at the set cells."""
    rows, cols = mask.shape
    dys, dxs = np.nonzero(kernel)
    dys -= kernel.shape[0] // 2
    dxs -= kernel.shape[1] // 2
    grown = np.zeros_like(mask)
    for y in range(rows):
        for x in range(cols):
            if mask[y, x]:
                for k in range(len(dys)):
                    yy, xx = y + dys[k], x + dxs[k]
                    if 0 <= yy < rows and 0 <= xx < cols:
                        grown[yy, xx] = 1
    out = np.zeros_like(mask)
    for y in range(rows):
        for x in range(cols):
            if not grown[y, x]:
                continue
            keep = 1
            for k in range(len(dys)):
                yy, xx = y + dys[k], x + dxs[k]
                if 0 <= yy < rows and 0 <= xx < cols and not grown[yy, xx]:
                    keep = 0
                    break
            out[y, x] = keep
    return out


@numba.njit(cache=True, nogil=True)
def _root(parent, i):  # noqa: ANN001, ANN202 - numba kernel
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@numba.njit(cache=True, nogil=True)
def components(mask):  # noqa: ANN001, ANN201 - numba kernel
    """8-connected components of a 0/1 mask: (n, labels, stats) with label 0 the background,
    labels numbered in raster order of their first cell, stats rows x, y, w, h, area."""
    rows, cols = mask.shape
    labels = np.zeros((rows, cols), np.int32)
    parent = np.zeros(rows * cols + 1, np.int32)
    n = 1
    for y in range(rows):
        for x in range(cols):
            if not mask[y, x]:
                continue
            best = 0
            for dy, dx in ((-1, -1), (-1, 0), (-1, 1), (0, -1)):
                yy, xx = y + dy, x + dx
                if yy < 0 or xx < 0 or xx >= cols or not labels[yy, xx]:
                    continue
                r = _root(parent, labels[yy, xx])
                if best == 0:
                    best = r
                elif r != best:
                    lo, hi = min(r, best), max(r, best)
                    parent[hi] = lo
                    best = lo
            if best == 0:
                parent[n] = n
                best = n
                n += 1
            labels[y, x] = best
    final = np.zeros(n, np.int32)
    count = 1
    for i in range(1, n):  # roots are always the smallest label of their set: raster order of first cell
        r = _root(parent, i)
        if r == i:
            final[i] = count
            count += 1
        else:
            final[i] = final[r]
    stats = np.zeros((count, 5), np.int32)
    stats[:, X] = cols
    stats[:, Y] = rows
    x1 = np.zeros(count, np.int32)
    y1 = np.zeros(count, np.int32)
    for y in range(rows):
        for x in range(cols):
            lab = final[labels[y, x]]
            labels[y, x] = lab
            if lab:
                stats[lab, X] = min(stats[lab, X], x)
                stats[lab, Y] = min(stats[lab, Y], y)
                x1[lab] = max(x1[lab], x + 1)
                y1[lab] = max(y1[lab], y + 1)
                stats[lab, AREA] += 1
    stats[:, W] = x1 - stats[:, X]
    stats[:, H] = y1 - stats[:, Y]
    stats[0] = 0
    return count, labels, stats


@numba.njit(cache=True, nogil=True)
def labels_exceeding(labels, values, least, n):  # noqa: ANN001, ANN201 - numba kernel
    """Per label (0..n-1), whether any of its cells has a value above `least`."""
    out = np.zeros(n, np.bool_)
    rows, cols = labels.shape
    for y in range(rows):
        for x in range(cols):
            if values[y, x] > least:
                out[labels[y, x]] = True
    return out
