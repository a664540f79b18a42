"""Space sweep (EMVS, Rebecq et al. 2018; seed 001): semi-dense depth of a reference view from events.

Each event, with the camera pose of its time, is a viewing ray. Rays are cast through a disparity
space image (DSI): a stack of planes parallel to the reference view, uniform in inverse depth, where
each ray adds a bilinear vote at the pixel where it crosses each plane. Where an edge of the scene
is, rays from many viewpoints meet: the DSI peaks along the pixel's column of planes at its depth.
The depth map keeps the peak (refined between planes by a parabola) of the pixels whose peak stands
out from their neighbourhood (an adaptive threshold on the peak's height), then median filtered.

A ray crossing the plane at inverse depth s lands, in the reference image, at u = A + B s (and
v likewise): A and B are computed once per event, so a vote costs a multiply-add and four adds.
Note: EMVS is covered by a patent (WO/2018/037079); check its terms before commercial use.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np


@dataclass
class SweepParams:
    planes: int = 100
    z_min_m: float = 0.5  # nearest and farthest depths the planes span, uniform in inverse depth
    z_max_m: float = 8.0
    threshold: float = 0.1  # a peak stands out by this share of the highest peak above its neighbourhood's
    threshold_sigma_px: float = 2.0  # the neighbourhood: a Gaussian of this width
    min_votes: float = 3.0  # ... and has at least this many votes
    # a pixel whose point the segment's cameras saw from viewpoints fewer than this many pixels apart (its parallax
    # at the found depth) is dropped: a peak one pixel off is 1 / parallax of its depth off
    min_parallax_px: float = 20.0
    median_px: int = 5  # the depth map's median filter (over kept pixels only), odd
    # a kept pixel with fewer kept neighbours than this in that window is an outlier (EMVS's radius filter, done
    # on the image grid where a keyframe's points lie)
    min_neighbours: int = 3
    # ... or whose own depth is further than this share from its neighbourhood's median (a pixel between two
    # surfaces, or a lone wrong peak); 0: off
    median_gap: float = 0.05


def plane_depths(params: SweepParams) -> np.ndarray:
    """Depths (m) of the DSI's planes, nearest first, uniform in inverse depth."""
    return 1.0 / np.linspace(1.0 / params.z_min_m, 1.0 / params.z_max_m, params.planes)


def ray_coefficients(xy: np.ndarray, K: np.ndarray, R_ref_cam: np.ndarray, t_ref_cam: np.ndarray,
                     which: np.ndarray) -> np.ndarray:
    """Per event (N x 2 undistorted pixels; `which` pose of R_ref_cam (M x 3 x 3) and t_ref_cam (M x 3,
    the event camera's centre in the reference frame) each was seen from): (A_u, B_u, A_v, B_v, t_z), its ray
    landing at u = A_u + B_u s, v = A_v + B_v s on the plane of inverse depth s (valid where 1 / s > t_z);
    rows of rays that point away from the reference view are NaN."""
    return _coefficients(np.ascontiguousarray(xy, np.float64), np.asarray(K, np.float64),
                         np.ascontiguousarray(R_ref_cam, np.float64), np.ascontiguousarray(t_ref_cam, np.float64),
                         np.asarray(which, np.int64))


@numba.njit(cache=True, nogil=True)
def _coefficients(xy, K, R, t, which):  # noqa: ANN001, ANN202 - numba kernel
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    out = np.empty((len(xy), 5))
    for i in range(len(xy)):
        j = which[i]
        f0, f1 = (xy[i, 0] - cx) / fx, (xy[i, 1] - cy) / fy
        a0 = R[j, 0, 0] * f0 + R[j, 0, 1] * f1 + R[j, 0, 2]
        a1 = R[j, 1, 0] * f0 + R[j, 1, 1] * f1 + R[j, 1, 2]
        a2 = R[j, 2, 0] * f0 + R[j, 2, 1] * f1 + R[j, 2, 2]
        if a2 <= 1e-6:
            out[i, :] = np.nan
            continue
        rx, ry, tz = a0 / a2, a1 / a2, t[j, 2]
        out[i, 0], out[i, 1] = fx * rx + cx, fx * (t[j, 0] - tz * rx)
        out[i, 2], out[i, 3] = fy * ry + cy, fy * (t[j, 1] - tz * ry)
        out[i, 4] = tz
    return out


def vote(dsi: np.ndarray, coef: np.ndarray, depths: np.ndarray) -> None:
    """Adds every event's bilinear votes (rows of `ray_coefficients`) to the DSI (planes x H x W, float32,
    in place). The events are first put in the order of the row they land on at the middle plane, as
    float32: each plane's votes then sweep down its rows instead of jumping over the whole plane, and
    half as many bytes are read per plane (30 % faster than time order in float64)."""
    if len(coef):
        _vote(dsi, _by_row(coef, 1.0 / float(depths[len(depths) // 2]), dsi.shape[1]), depths)


@numba.njit(cache=True, nogil=True)
def _by_row(coef, s, h):  # noqa: ANN001, ANN202 - numba kernel
    """The rows of `coef` as float32, stably ordered by the image row their ray lands on at inverse depth
    s (a counting sort; rows off the image and NaN rows keep their place at either end)."""
    n = len(coef)
    key = np.empty(n, np.int64)
    start = np.zeros(h + 1, np.int64)
    for i in range(n):
        v = coef[i, 2] + coef[i, 3] * s
        key[i] = min(max(int(v), 0), h - 1) if v == v else h - 1
        start[key[i] + 1] += 1
    for b in range(h):
        start[b + 1] += start[b]
    out = np.empty((n, coef.shape[1]), np.float32)
    for i in range(n):
        j = start[key[i]]
        start[key[i]] += 1
        out[j] = coef[i]
    return out


@numba.njit(cache=True, nogil=True, parallel=True, fastmath={"contract", "arcp", "nsz", "reassoc"})  # NaN-safe
def _vote(dsi, coef, depths):  # noqa: ANN001, ANN202 - numba kernel; planes in parallel: no two threads write one cell
    n_planes, h, w = dsi.shape
    for k in numba.prange(n_planes):
        z = np.float32(depths[k])
        s = np.float32(1.0 / depths[k])
        plane = dsi[k]
        for i in range(len(coef)):
            if not z > coef[i, 4]:  # behind the event's camera (or a NaN row)
                continue
            u, v = coef[i, 0] + coef[i, 1] * s, coef[i, 2] + coef[i, 3] * s
            if not (u >= 0 and u < w - 1 and v >= 0 and v < h - 1):
                continue
            x0, y0 = int(u), int(v)
            du, dv = u - x0, v - y0
            plane[y0, x0] += (1 - du) * (1 - dv)
            plane[y0, x0 + 1] += du * (1 - dv)
            plane[y0 + 1, x0] += (1 - du) * dv
            plane[y0 + 1, x0 + 1] += du * dv


def semi_dense_depth(dsi: np.ndarray, depths: np.ndarray, params: SweepParams, K: np.ndarray | None = None,
                     centres: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The reference view's depth map (m, NaN where not kept) and the peak heights (votes), from a DSI; with
    intrinsics `K` and the segment's camera centres in the reference frame (M x 3), only where the parallax
    is enough (`min_parallax_px`)."""
    peak = dsi.argmax(axis=0)
    conf = np.take_along_axis(dsi, peak[None], axis=0)[0]
    # a parabola through the peak and its two neighbours places it between planes (inverse depth is
    # linear in the plane index)
    inner = np.clip(peak, 1, len(depths) - 2)
    lo, mid, hi = (np.take_along_axis(dsi, (inner + d)[None], axis=0)[0] for d in (-1, 0, 1))
    curve = lo - 2 * mid + hi
    shift = np.where(curve < 0, 0.5 * (lo - hi) / np.where(curve < 0, curve, -1), 0.0)
    index = np.where(peak == inner, peak + np.clip(shift, -0.5, 0.5), peak)
    inv = np.interp(index, np.arange(len(depths)), 1.0 / depths)
    local = cv2.GaussianBlur(conf, (0, 0), params.threshold_sigma_px)
    keep = (conf > local + params.threshold * conf.max()) & (conf >= params.min_votes)
    if params.min_parallax_px > 0 and K is not None and centres is not None and len(centres):
        keep &= parallax_px(K, centres, dsi.shape[1:]) * inv >= params.min_parallax_px
    depth = np.where(keep, 1.0 / inv, np.nan).astype(np.float32)
    return masked_median(depth, params.median_px // 2, params.min_neighbours, params.median_gap), conf


def parallax_px(K: np.ndarray, centres: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Per pixel of the reference view: the widest baseline (m) across its ray among the camera centres,
    times the focal length; divided by a depth, the parallax (px) a point there shows."""
    h, w = shape
    ys, xs = np.mgrid[0:h, 0:w]
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones((h, w))], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    c = centres - centres.mean(axis=0)
    widest = np.zeros((h, w))
    for i in range(len(c)):  # few centres (subsampled by the caller), every pixel at once
        along = rays @ c[i]
        widest = np.maximum(widest, np.linalg.norm(c[i] - along[..., None] * rays, axis=-1))
    return 2.0 * K[0, 0] * widest


@numba.njit(cache=True, nogil=True)
def masked_median(depth: np.ndarray, r: int, min_neighbours: int, gap: float) -> np.ndarray:  # pragma: no cover
    """Each finite pixel replaced by the median of the finite pixels in its (2r+1)^2 neighbourhood, or NaN
    where fewer than `min_neighbours` others are finite there or (`gap` > 0) its depth is more than `gap`
    times the median away from it."""
    h, w = depth.shape
    out = np.full_like(depth, np.nan)
    buf = np.empty((2 * r + 1) ** 2, depth.dtype)
    for y in range(h):
        for x in range(w):
            if not np.isfinite(depth[y, x]):
                continue
            n = 0
            for yy in range(max(y - r, 0), min(y + r + 1, h)):
                for xx in range(max(x - r, 0), min(x + r + 1, w)):
                    d = depth[yy, xx]
                    if np.isfinite(d):
                        buf[n] = d
                        n += 1
            if n > min_neighbours:
                m = np.median(buf[:n])
                if gap <= 0 or abs(depth[y, x] - m) <= gap * m:
                    out[y, x] = m
    return out
