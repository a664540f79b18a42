"""Two targets in one blob told apart by its shape: a union of two rectangles leaves two empty corners.

A moving textured target fires over its whole box, so its recent pixels fill a rectangle (and a short
trail). Two targets that came in together, or met and went on side by side at one speed, form one blob
and so one box, which motion cannot cut while they move alike. Offset from each other, though, their
union leaves two opposite corners of that box empty: the top-left and bottom-right ones (or the other
two), each as wide and as tall as the targets are offset. Those corners give both boxes at once, whole,
even where the nearer target hides part of the farther. One target leaves no such corners: its trail
rounds its own by a few pixels, under `min_share` of its sides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from services.tracker.objects import cells


@dataclass
class ShapeParams:
    min_share: float = 0.1  # each empty corner spans at least this share of the box's width and of its height
    min_px: int = 8  # ... and this many pixels on each side (0: the split is off)
    min_fill: float = 0.3  # each of the two boxes has at least this share of its 2 x 2 px blocks firing
    min_area_px: int = 600  # smaller boxes are not split


def two_rectangles(image: np.ndarray, box: np.ndarray | tuple, recent: float, params: ShapeParams) -> np.ndarray | None:
    """The two boxes (2 x 4: x, y, w, h) whose union the recent pixels (decayed weight `recent` or more, as the
    detections' boxes count them) of `box` in a decayed `image` fill, if they leave two opposite corners of it empty;
    None if they fill it as one target does (or it is too small to tell)."""
    x, y, w, h = (float(v) for v in box)
    if params.min_px <= 0 or w * h < params.min_area_px:
        return None
    found = _two_rectangles(image, x, y, w, h, np.float32(recent), params.min_share, params.min_px,
                            params.min_fill)
    return found if len(found) else None


@numba.njit(cache=True, nogil=True)
def _two_rectangles(image, x, y, w, h, recent, min_share, min_px, min_fill):  # noqa: ANN001, ANN202 - numba kernel
    """`two_rectangles` on blocks of 2 x 2 px, a block firing where two of its pixels do (a lone noise event
    does not fill a corner). Most boxes hold one target and some of its pixels fire in the smallest corner that
    could count on each diagonal: those are told from those corners alone, not the whole box."""
    h_img, w_img = image.shape
    x0, y0 = max(int(x), 0), max(int(y), 0)
    x1, y1 = min(int(np.ceil(x + w)), w_img), min(int(np.ceil(y + h)), h_img)
    none = np.zeros((0, 4), np.float32)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return none
    rows, cols = (y1 - y0) // 2, (x1 - x0) // 2
    least_c = max(min_share * cols, min_px / 2)
    least_r = max(min_share * rows, min_px / 2)
    # the smallest corner that counts, in px
    cw, ch = 2 * int(np.ceil(least_c)), 2 * int(np.ceil(least_r))
    if cw > 2 * cols or ch > 2 * rows:
        return none
    xe, ye = x0 + 2 * cols, y0 + 2 * rows  # the blocks' end (a last odd row or column is left out)
    if not (_clear(image, x0, y0, cw, ch, recent) and _clear(image, xe - cw, ye - ch, cw, ch, recent)) and not (
            _clear(image, xe - cw, y0, cw, ch, recent) and _clear(image, x0, ye - ch, cw, ch, recent)):
        return none
    filled = cells.occupancy(image[y0:ye, x0:xe], 2, recent) >= 2
    out, corners = none, 0
    for flip in range(2):  # 0: top-left and bottom-right corners empty; 1: top-right and bottom-left
        a1, b1 = _empty_corner(filled, flip == 1, False, least_c, least_r)
        a2, b2 = _empty_corner(filled, flip == 0, True, least_c, least_r)
        if a1 * b1 == 0 or a2 * b2 == 0:
            continue
        corners += 1
        if corners == 2:  # all four corners empty: a cross of two targets, or a ring, which two corners cannot cut
            return none
        # the upper box spans the columns its corner leaves down to the lower corner; the lower one the rest
        if flip == 0:  # upper box on the right, lower on the left
            up = (a1, 0, cols, rows - b2)
            low = (0, b1, cols - a2, rows)
        else:
            up = (0, 0, cols - a1, rows - b2)
            low = (a2, b1, cols, rows)
        if _fill(filled, up) < min_fill or _fill(filled, low) < min_fill:
            continue
        out = np.empty((2, 4), np.float32)
        for k, (c0, r0, c1, r1) in enumerate((up, low)):
            px0, py0 = x0 + 2 * c0, y0 + 2 * r0
            out[k, 0], out[k, 1] = px0, py0
            out[k, 2], out[k, 3] = 2 * (c1 - c0), 2 * (r1 - r0)
    return out


@numba.njit(cache=True, nogil=True)
def _clear(image, x0, y0, w, h, recent):  # noqa: ANN001, ANN202 - numba kernel
    """Whether no 2 x 2 px block of the `w` x `h` px at (x0, y0) has two pixels firing."""
    return cells.occupancy(image[y0:y0 + h, x0:x0 + w], 2, recent).max() < 2


@numba.njit(cache=True, nogil=True)
def _empty_corner(filled, right, bottom, least_c, least_r):  # noqa: ANN001, ANN202 - numba kernel
    """Width and height (in blocks) of the biggest empty rectangle in one corner of `filled` at least `least_c`
    wide and `least_r` tall, or (0, 0): from the staircase of its rows' first filled block, walked from that corner."""
    rows, cols = filled.shape
    reach = cols  # empty blocks from the corner's side, on every row walked so far
    best_a = best_b = 0
    for i in range(rows):
        r = rows - 1 - i if bottom else i
        run = 0
        while run < reach and not filled[r, cols - 1 - run if right else run]:
            run += 1
        reach = run
        if reach < least_c:
            break
        if i + 1 >= least_r and reach * (i + 1) > best_a * best_b:
            best_a, best_b = reach, i + 1
    return best_a, best_b


@numba.njit(cache=True, nogil=True)
def _fill(filled, rect):  # noqa: ANN001, ANN202 - numba kernel
    """The share of firing blocks in `rect` (c0, r0, c1, r1) of `filled`."""
    c0, r0, c1, r1 = rect
    if c1 <= c0 or r1 <= r0:
        return 0.0
    return filled[r0:r1, c0:c1].sum() / ((c1 - c0) * (r1 - r0))


def warm_up() -> None:
    """Loads the kernels (see `tracker.warm_up`): its warm-up scene has no blob big enough to test."""
    image = np.zeros((48, 64), np.float32)
    image[4:24, 20:60] = 1.0
    image[14:44, 4:40] = 1.0
    two_rectangles(image, (4, 4, 56, 40), 0.5, ShapeParams())
