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
    right and bottom count their missing pixels as empty). Each cell row is counted per pixel
    column in bytes (the compare loop then runs on 32 lanes at a time), then summed per cell:
    cells of 4 (2) px read their bytes as one 32 (16) bit word, which times 0x01010101 (0x0101)
    has the bytes' sum in its top byte (each at most `cell`: no sum carries, in either byte order)."""
    h, w = image.shape
    rows, cols = -(-h // cell), -(-w // cell)
    out = np.zeros((rows, cols), np.int32)
    column = np.zeros(-(-cols * cell // 4) * 4, np.uint8)  # per pixel column, over the rows of one cell row
    words, halves = column.view(np.uint32), column.view(np.uint16)
    for cy in range(rows):
        column[:] = 0
        for y in range(cy * cell, min(cy * cell + cell, h)):
            src = image[y]
            for x in range(w):
                column[x] += src[x] >= active
        dst = out[cy]
        if cell == 4:
            for i in range(cols):
                dst[i] = ((words[i] * np.uint32(0x01010101)) >> np.uint32(24)) & np.uint32(0xFF)
        elif cell == 2:
            for i in range(cols):
                dst[i] = ((halves[i] * np.uint16(0x0101)) >> np.uint16(8)) & np.uint16(0xFF)
        else:
            for i in range(cols):
                total = 0
                for j in range(i * cell, i * cell + cell):
                    total += column[j]
                dst[i] = total
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
def _reflected(n, r):  # noqa: ANN001, ANN202 - numba kernel
    """For each index -r..n+r-1 of an axis padded by `r`, the index it reads (`_reflect`)."""
    out = np.empty(n + 2 * r, np.int64)
    for i in range(n + 2 * r):
        out[i] = _reflect(i - r, n)
    return out


@numba.njit(cache=True, nogil=True)
def box_sums(counts, window):  # noqa: ANN001, ANN201 - numba kernel
    """The counts summed over a `window` x `window` square around each cell (borders reflected):
    along x on each row copied with its reflected borders, then along y over whole rows, each sum
    a loop over contiguous cells that the compiler runs on many at once."""
    rows, cols = counts.shape
    r = window // 2
    at_x, at_y = _reflected(cols, r), _reflected(rows, r)
    across = np.zeros((rows, cols), np.int32)
    padded = np.empty(cols + 2 * r, np.int32)
    for y in range(rows):
        src, dst = counts[y], across[y]
        for i in range(cols + 2 * r):
            padded[i] = src[at_x[i]]
        for d in range(2 * r + 1):
            for x in range(cols):
                dst[x] += padded[x + d]
    out = np.zeros((rows, cols), np.int32)
    for y in range(rows):
        dst = out[y]
        for d in range(2 * r + 1):
            src = across[at_y[y + d]]
            for x in range(cols):
                dst[x] += src[x]
    return out


@numba.njit(cache=True, nogil=True)
def close(mask, kernel):  # noqa: ANN001, ANN201 - numba kernel
    """Morphological closing (dilation, outside empty, then erosion, outside full) of a mask of 0s
    and 1s (the passes OR and AND its values) by a symmetric 0/1 kernel, on a copy padded by the
    kernel's reach, so no step tests a border. Each pass ORs (ANDs) whole rows shifted by one kernel
    offset at a time: loops the compiler runs on many cells at once."""
    rows, cols = mask.shape
    ry, rx = kernel.shape[0] // 2, kernel.shape[1] // 2
    dys, dxs = np.nonzero(kernel)
    grown = np.zeros((rows + 2 * ry, cols + 2 * rx), np.uint8)
    for k in range(len(dys)):
        for y in range(rows):
            dst, src = grown[y + dys[k], dxs[k]:dxs[k] + cols], mask[y]
            for x in range(cols):
                dst[x] |= src[x]
    grown[:ry] = 1  # outside counts as full for the erosion
    grown[rows + ry:] = 1
    grown[:, :rx] = 1
    grown[:, cols + rx:] = 1
    out = np.ones_like(mask)
    for k in range(len(dys)):
        for y in range(rows):
            dst, src = out[y], grown[y + dys[k], dxs[k]:dxs[k] + cols]
            for x in range(cols):
                dst[x] &= src[x]
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
    labels numbered in raster order of their first cell, stats rows x, y, w, h, area.
    Labels runs of set cells, not cells: a run joins the runs of the row above that touch it, so
    a dense mask costs a few unions per row instead of four neighbour lookups per cell."""
    rows, cols = mask.shape
    most = rows * ((cols + 1) // 2)
    start = np.empty(most, np.int32)
    stop = np.empty(most, np.int32)
    row = np.empty(most, np.int32)
    parent = np.empty(most, np.int32)
    n = 0
    above, above_end = 0, 0  # the runs of the previous row
    for y in range(rows):
        first = n
        x = 0
        while x < cols:
            if not mask[y, x]:
                x += 1
                continue
            s = x
            while x < cols and mask[y, x]:
                x += 1
            start[n], stop[n], row[n], parent[n] = s, x, y, n
            while above < above_end and stop[above] < s:  # ends left of this run's diagonal
                above += 1
            k = above
            while k < above_end and start[k] <= x:  # touches this run, diagonals included
                a, b = _root(parent, n), _root(parent, k)
                parent[max(a, b)] = min(a, b)  # the root is the run met first in raster order
                k += 1
            n += 1
        above, above_end = first, n
    final = np.zeros(n, np.int32)
    count = 1
    for i in range(n):
        r = _root(parent, i)
        if r == i:
            final[i] = count
            count += 1
        else:
            final[i] = final[r]
    labels = np.zeros((rows, cols), np.int32)
    stats = np.zeros((count, 5), np.int32)
    x1 = np.zeros(count, np.int32)
    y1 = np.zeros(count, np.int32)
    for lab in range(1, count):  # element by element: whole-column assignments compiled a second of error messages
        stats[lab, X], stats[lab, Y] = cols, rows
    for i in range(n):
        lab = final[i]
        labels[row[i], start[i]:stop[i]] = lab
        stats[lab, X] = min(stats[lab, X], start[i])
        stats[lab, Y] = min(stats[lab, Y], row[i])
        x1[lab] = max(x1[lab], stop[i])
        y1[lab] = max(y1[lab], row[i] + 1)
        stats[lab, AREA] += stop[i] - start[i]
    for lab in range(1, count):
        stats[lab, W], stats[lab, H] = x1[lab] - stats[lab, X], y1[lab] - stats[lab, Y]
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
