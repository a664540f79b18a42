"""Targets that share one blob told apart by how they move: sparse optical flow in the decayed image.

Two targets that come in together, or one that passes in front of another, form one connected blob,
and no threshold on the image alone can cut it where they meet. Their events move differently,
though: the decayed image of a textured target translates with it, so Lucas-Kanade flow on a grid
of points inside a blob, between the image of this update and one some 60 ms older, gives each
point its target's velocity (to some 10 px/s at 40 ms on the simulator's textured targets; the error
is in pixels, so a longer lag gives finer velocities and tells more pairs of targets apart).
Where the velocities fall in two groups well apart, the blob holds two targets, and each group's
points give one of them a box. Where tracks share a blob, each one's own part of it (outside the others'
boxes) is followed by the translation that carries the earlier image onto this one there
(`part_velocity`): a target that turns or starts while it shares a blob is followed on its new velocity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from services.tracker.objects.accumulator import to_uint8


@dataclass
class MotionParams:
    lag_us: int = 60_000  # flow between an update's image and the latest one at least this much older (0: off)
    # a past image is kept this often, not at every update: the copy was 5 % of an update's time, and the flow
    # (over 60-80 ms, not 60-70) split as well (three sets of 60 dev seeds: precision@20 0.943 both ways)
    keep_us: int = 20_000
    # flow at points this far apart, where the image has recent events; at 6 px, with every confirmed track's blob
    # tested (see `AssociationParams.motion_retest_us`), the tracker fell from 28 to 26 Mev/s on the speed bench
    grid_px: int = 8
    least_weight: float = 0.25  # a point is sampled where the blurred decayed image is at least this
    blur_px: float = 1.5  # the images are smoothed first: events are sparse, the flow wants gradients
    window_px: int = 11
    min_points: int = 10  # per group
    min_share: float = 0.15  # of the blob's points, per group
    # the two groups' median velocities differ by this much at least, and by `separation` times their spread (40 split
    # fewer of the simulator's pairs and made more id switches; 10 changed nothing there: the spread decides)
    min_gap_px_s: float = 20.0
    separation: float = 3.0  # ... and by this many times their spread (pooled median distance to the median)
    min_area_px: int = 600  # smaller blobs are not split


def split_by_motion(earlier: np.ndarray, image: np.ndarray, box: np.ndarray | tuple, dt_s: float,
                    params: MotionParams) -> np.ndarray | None:
    """The two boxes (2 x 4) of the targets moving apart in a blob's `box`, from the decayed image
    `dt_s` earlier; None when its points move as one (or the blob is too small to tell)."""
    box = np.asarray(box, np.float32)
    if box[2] * box[3] < params.min_area_px:
        return None
    pts, vel = point_flow(earlier, image, box, dt_s, params)
    parts = two_motions(pts, vel, params)
    if parts is None:
        return None
    lo = np.maximum(parts[:, :2], box[:2])
    hi = np.minimum(parts[:, :2] + parts[:, 2:], box[:2] + box[2:])
    return np.concatenate([lo, hi - lo], axis=1)


def point_flow(earlier: np.ndarray, image: np.ndarray, box: np.ndarray, dt_s: float,
               params: MotionParams) -> tuple[np.ndarray, np.ndarray]:
    """Points (N x 2, x y) on a grid inside `box` where the decayed `image` has recent events, and their
    velocities (N x 2, px/s) from the image `dt_s` earlier; points the flow lost are left out."""
    none = np.zeros((0, 2), np.float32)
    h, w = image.shape
    m = params.window_px + 2
    x0, y0 = max(int(box[0]) - m, 0), max(int(box[1]) - m, 0)
    x1, y1 = min(int(np.ceil(box[0] + box[2])) + m, w), min(int(np.ceil(box[1] + box[3])) + m, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return none, none
    a = cv2.GaussianBlur(image[y0:y1, x0:x1], (0, 0), params.blur_px)
    b = cv2.GaussianBlur(earlier[y0:y1, x0:x1], (0, 0), params.blur_px)
    g = params.grid_px
    ys, xs = np.mgrid[int(box[1]) - y0 + g // 2:int(box[1] + box[3]) - y0:g,
                      int(box[0]) - x0 + g // 2:int(box[0] + box[2]) - x0:g]
    xs, ys = xs.ravel(), ys.ravel()
    keep = (xs >= 0) & (xs < x1 - x0) & (ys >= 0) & (ys < y1 - y0)
    xs, ys = xs[keep], ys[keep]
    keep = a[ys, xs] >= params.least_weight
    pts = np.stack([xs[keep], ys[keep]], axis=1).astype(np.float32)
    if len(pts) < 2 * params.min_points:  # too few to make two groups of
        return none, none
    win = (params.window_px, params.window_px)
    back, status, _ = cv2.calcOpticalFlowPyrLK(to_uint8(a), to_uint8(b), pts.reshape(-1, 1, 2), None,
                                               winSize=win, maxLevel=2)
    ok = status.ravel() == 1
    vel = (pts - back.reshape(-1, 2)) / dt_s
    return pts[ok] + np.float32([x0, y0]), vel[ok].astype(np.float32)


def two_motions(pts: np.ndarray, vel: np.ndarray, params: MotionParams) -> np.ndarray | None:
    """Two boxes (2 x 4) around the points of each group if their velocities fall in two groups well
    apart, else None."""
    if len(vel) < 2 * params.min_points:
        return None
    label = _two_groups(vel.astype(np.float64), float(max(params.min_points, params.min_share * len(vel))),
                        float(params.min_gap_px_s), float(params.separation))
    if label[0] < 0:
        return None
    half = params.grid_px / 2
    boxes = []
    for k in (0, 1):
        p = pts[label == k]
        lo, hi = np.percentile(p, 2, axis=0) - half, np.percentile(p, 98, axis=0) + half
        boxes.append([lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1]])
    return np.asarray(boxes, np.float32)


@numba.njit(cache=True, nogil=True)
def _two_groups(vel, least, min_gap, separation):  # noqa: ANN001, ANN202 - numba kernel
    """2-means of velocities (N x 2) with medians for centres, started from the tenth of them at
    each end of their main axis: a label (0 or 1) per point, or all -1 if the groups are not both
    of `least` points and apart by `min_gap` and by `separation` times their pooled spread."""
    n = len(vel)
    label = np.full(n, -1, np.int64)
    mx, my = _median(vel[:, 0]), _median(vel[:, 1])
    cx, cy = vel[:, 0] - mx, vel[:, 1] - my
    sxx, syy, sxy = (cx * cx).sum(), (cy * cy).sum(), (cx * cy).sum()
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # the main axis of the 2 x 2 scatter
    along = cx * np.cos(angle) + cy * np.sin(angle)
    lo, hi = _percentile(along, 10.0), _percentile(along, 90.0)
    centres = np.zeros((2, 2))
    for k, pick in enumerate((along <= lo, along >= hi)):
        centres[k, 0], centres[k, 1] = vel[pick, 0].mean(), vel[pick, 1].mean()
    own = label.copy()
    for _ in range(8):
        for i in range(n):
            d0 = (vel[i, 0] - centres[0, 0]) ** 2 + (vel[i, 1] - centres[0, 1]) ** 2
            d1 = (vel[i, 0] - centres[1, 0]) ** 2 + (vel[i, 1] - centres[1, 1]) ** 2
            own[i] = 0 if d0 <= d1 else 1
        n1 = own.sum()
        if n1 < least or n - n1 < least:
            return label
        for k in range(2):
            members = vel[own == k]
            centres[k, 0], centres[k, 1] = _median(members[:, 0]), _median(members[:, 1])
    spread = 0.0
    for k in range(2):
        members = vel[own == k]
        d = np.sqrt((members[:, 0] - centres[k, 0]) ** 2 + (members[:, 1] - centres[k, 1]) ** 2)
        spread += _median(d) ** 2
    gap = np.sqrt((centres[0, 0] - centres[1, 0]) ** 2 + (centres[0, 1] - centres[1, 1]) ** 2)
    if gap < min_gap or gap < separation * np.sqrt(spread):
        return label
    return own


@numba.njit(cache=True, nogil=True)
def _median(values):  # noqa: ANN001, ANN202 - numba kernel
    """`np.median` of a non-empty array, to the bit: numba's own (and its `np.percentile`) took 5 of the tracker's
    35 s of compiling on a fresh install. Not `_percentile(values, 50)`: halving each middle value before adding them
    loses the last bit of subnormal values (5e-324 twice gave 0), as NumPy's sum-then-halve does not."""
    s = np.sort(values)
    half = len(s) >> 1
    return (s[half - 1] + s[half]) / 2 if len(s) % 2 == 0 else s[half]


@numba.njit(cache=True, nogil=True)
def _percentile(values, q):  # noqa: ANN001, ANN202 - numba kernel
    """`np.percentile(values, q)` of a non-empty array for 0 < q < 100, to the bit (linear between ranks)."""
    s = np.sort(values)
    if len(s) == 1:
        return s[0]
    rank = 1 + (len(s) - 1) * (q / 100.0)
    f = math.floor(rank)
    m = rank - f
    k = int(f - 1)
    return s[k] * (1 - m) + s[k + 1] * m


@dataclass
class ShiftParams:
    """How a track's own part of a shared blob is followed from image to image (`part_velocity`)."""
    # the translation is fitted on images shrunk by 2 and 4: coarse to fine, it reaches 4 px at the coarse scale
    # (16 px, some 250 px/s over 60 ms, off the guess) and half-scale pixels are fine enough (0.05 px: 2 px/s)
    levels: int = 2
    iterations: int = 8
    margin_px: int = 16  # the crop reaches this far past the box (and the guess's move) for the earlier image
    min_pixels: int = 40  # the part's pixels at half size; fewer: no measure
    # ... nor where the part is under this share of the box: a sliver beside the others' boxes holds their targets'
    # edges as much as its own (on four sets of 60 dev seeds id switches per object-minute 1.95 -> 1.80,
    # precision@20 0.948 -> 0.950 against no share asked; 0.3 and 0.7 between; three fresh sets: precision@20
    # +0.001 on each, switches 2.29 -> 2.29, 2.63 -> 2.58, 2.61 -> 2.53)
    min_share: float = 0.5
    # the earlier image, moved by the fit, leaves at most this share of the part's energy unexplained; more, and
    # the part did not translate (a target coming out from behind, or starting to move from a stop)
    max_residual: float = 0.5


def part_velocity(earlier: np.ndarray, image: np.ndarray, box: tuple | np.ndarray, others: list,
                  guess_px_s: tuple[float, float], dt_s: float, params: ShiftParams) -> tuple[float, float] | None:
    """The velocity (px/s) of what the decayed `image` shows in `box` outside the `others` boxes, from the image
    `dt_s` earlier: the translation that best carries that one onto this one there (Lucas-Kanade on the whole part,
    coarse to fine from `guess_px_s`). None where the part is too small (or too small a share of the box) or too
    plain to tell, or did not move as one. Where targets share a blob, the layout places each where its
    prediction says, and corrects little: a target that turned or started there was followed on its old
    velocity, and swapped ids when they parted."""
    h, w = image.shape
    gx, gy = guess_px_s[0] * dt_s, guess_px_s[1] * dt_s
    m = params.margin_px + int(max(abs(gx), abs(gy)))
    scale = 1 << params.levels
    x0, y0 = max(int(box[0]) - m, 0), max(int(box[1]) - m, 0)
    x1, y1 = min(int(np.ceil(box[0] + box[2])) + m, w), min(int(np.ceil(box[1] + box[3])) + m, h)
    x1, y1 = x1 - (x1 - x0) % scale, y1 - (y1 - y0) % scale  # whole pixels at every level
    if x1 - x0 < 4 * scale or y1 - y0 < 4 * scale:
        return None
    rects = np.asarray([box, *others], np.float64).reshape(-1, 4) - np.float64([x0, y0, 0, 0])
    a, b, own = _halves(image, earlier, x0, y0, x1, y1, np.round(rects / 2).astype(np.int64))
    least = max(params.min_pixels, params.min_share * box[2] * box[3] / 4)  # pixels at half size
    dx, dy, ok = _translation(a, b, own, gx / 2, gy / 2, params.levels - 1, params.iterations, least,
                              params.max_residual)
    return (2 * dx / dt_s, 2 * dy / dt_s) if ok else None


@numba.njit(cache=True, nogil=True)
def _halves(image, earlier, x0, y0, x1, y1, rects):  # noqa: ANN001, ANN202 - numba kernel
    """The crop [y0:y1, x0:x1] of both images at half size (2 x 2 means of pixels clipped at 3 events, then
    smoothed by a 3 x 3 binomial: events are sparse, the fit wants gradients) and the mask (1 or 0) of the first
    of `rects` (x y w h at half size, in the crop) outside the others."""
    h, w = (y1 - y0) // 2, (x1 - x0) // 2
    out = np.empty((2, h, w), np.float32)
    across = np.empty((h, w), np.float32)
    for n, im in enumerate((image, earlier)):
        half = out[n]
        for y in range(h):  # `_shrink` fused with the clip: on a clipped copy it took 1.6 times as long
            top, bottom = im[y0 + 2 * y, x0:x1], im[y0 + 2 * y + 1, x0:x1]
            for x in range(w):
                half[y, x] = 0.25 * (min(top[2 * x], 3.0) + min(top[2 * x + 1], 3.0) + min(bottom[2 * x], 3.0)
                                     + min(bottom[2 * x + 1], 3.0))
        for y in range(h):
            across[y, 0], across[y, w - 1] = half[y, 0], half[y, w - 1]
            for x in range(1, w - 1):
                across[y, x] = 0.25 * (half[y, x - 1] + half[y, x + 1]) + 0.5 * half[y, x]
        for x in range(w):  # by element: a row assignment compiled seconds of error messages on a fresh install
            half[0, x], half[h - 1, x] = across[0, x], across[h - 1, x]
        for y in range(1, h - 1):
            for x in range(w):
                half[y, x] = 0.25 * (across[y - 1, x] + across[y + 1, x]) + 0.5 * across[y, x]
    own = np.zeros((h, w), np.float32)
    for k in range(len(rects)):
        rx0, ry0 = max(rects[k, 0], 0), max(rects[k, 1], 0)
        rx1, ry1 = min(max(rects[k, 0] + rects[k, 2], 0), w), min(max(rects[k, 1] + rects[k, 3], 0), h)
        own[ry0:ry1, rx0:rx1] = 1.0 if k == 0 else 0.0
    return out[0], out[1], own


@numba.njit(cache=True, nogil=True)
def _shrink(im):  # noqa: ANN001, ANN202 - numba kernel
    """The image at half size, by 2 x 2 means (its size even)."""
    h, w = im.shape[0] // 2, im.shape[1] // 2
    out = np.empty((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            out[y, x] = 0.25 * (im[2 * y, 2 * x] + im[2 * y, 2 * x + 1]
                                + im[2 * y + 1, 2 * x] + im[2 * y + 1, 2 * x + 1])
    return out


@numba.njit(cache=True, nogil=True)
def _translation(a, b, own, dx, dy, coarser, iterations, min_pixels, max_residual):  # noqa: ANN001, ANN202
    """The shift (dx, dy) with b(x - d) ~ a(x) over the pixels where `own` is at least 0.5, by inverse
    compositional Lucas-Kanade (a's gradients), from the given shift, first on `coarser` halvings of the
    images; and whether it holds: `min_pixels` own pixels, and under `max_residual` of a's energy left."""
    pyramid = [(a, b, own)]
    for _ in range(coarser):
        a, b, own = _shrink(a), _shrink(b), _shrink(own)
        pyramid.append((a, b, own))
    dx, dy = dx / (1 << coarser), dy / (1 << coarser)
    ok = False
    for level in range(coarser, -1, -1):
        a, b, own = pyramid[level]
        h, w = a.shape
        hxx = hxy = hyy = 0.0
        n = 0
        for y in range(1, h - 1):
            for x in range(1, w - 1):
                if own[y, x] >= 0.5:
                    ix, iy = 0.5 * (a[y, x + 1] - a[y, x - 1]), 0.5 * (a[y + 1, x] - a[y - 1, x])
                    hxx += ix * ix
                    hxy += ix * iy
                    hyy += iy * iy
                    n += 1
        det = hxx * hyy - hxy * hxy
        if n < 4 or det <= 1e-12 * (hxx + hyy + 1e-12) ** 2:
            return dx, dy, False
        energy = residual = 0.0
        for _ in range(iterations):
            gx = gy = residual = energy = 0.0
            for y in range(1, h - 1):
                for x in range(1, w - 1):
                    if own[y, x] < 0.5:
                        continue
                    sx, sy = x - dx, y - dy
                    if sx < 0 or sy < 0 or sx >= w - 1 or sy >= h - 1:
                        continue
                    i, j = int(sx), int(sy)
                    fx, fy = sx - i, sy - j
                    bv = ((1 - fx) * (1 - fy) * b[j, i] + fx * (1 - fy) * b[j, i + 1]
                          + (1 - fx) * fy * b[j + 1, i] + fx * fy * b[j + 1, i + 1])
                    e = bv - a[y, x]
                    gx += 0.5 * (a[y, x + 1] - a[y, x - 1]) * e
                    gy += 0.5 * (a[y + 1, x] - a[y - 1, x]) * e
                    residual += e * e
                    energy += a[y, x] * a[y, x]
            step_x, step_y = (hyy * gx - hxy * gy) / det, (hxx * gy - hxy * gx) / det
            dx, dy = dx + step_x, dy + step_y
            if step_x * step_x + step_y * step_y < 2.5e-3:
                break
        ok = n >= min_pixels and energy > 0 and residual <= max_residual * energy
        if level > 0:
            dx, dy = 2 * dx, 2 * dy
    return dx, dy, ok


def warm_up() -> None:
    """Loads the kernels (see `tracker.warm_up`): a blob big enough to test, or shared by two confirmed tracks, is
    rare in its warm-up scene."""
    _two_groups(np.zeros((2, 2)), 1.0, 1.0, 1.0)
    image = np.zeros((32, 32), np.float32)
    part_velocity(image, image, (8, 8, 16, 16), [(16, 8, 16, 16)], (0.0, 0.0), 0.06, ShiftParams())
