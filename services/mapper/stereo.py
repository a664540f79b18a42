"""Stereo depth from two event cameras (ESVO, Zhou et al. 2021; seed 001): time surfaces, matching along
epipolar lines, inverse-depth fusion.

A time surface maps each pixel to exp(-(t - t_last) / tau), t_last the time of its latest event: an edge
that just swept by is bright, with a trail that fades behind it. Two cameras that see the same edge at
the same time see the same trail, so at each stereo frame (every `every_ms`) each left pixel that fired
lately is matched along its epipolar line (a row, once the pair is rectified) by the sum of squared
differences of time-surface patches, ESVO's cost; the best disparity, refined between pixels by a
parabola, gives the depth. Estimates that are not clearly better than another disparity along the
line (a repeated texture) are dropped.

One estimate is noisy (a pixel of disparity at 4 m and 10 cm of baseline is 13 % of depth). Each is
kept as a world point with its inverse depth's standard deviation; a keyframe projects the estimates
of its segment into its reference view and fuses those at each pixel: the ones within a gate of their
median, by inverse-variance weights (Gaussian fusion of inverse depth, with outliers rejected).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from services.mapper import sweep
from services.mapper.keyframes import Keyframe, KeyframeMapper, KeyframeParams, lift
from services.mapper.trajectory import Trajectory

# world point, its distance from the camera that saw it (m), the sigma of its inverse depth there
ESTIMATE_DTYPE = np.dtype([("t", "<i8"), ("xyz", "<f4", 3), ("range", "<f4"), ("sigma", "<f4")])


@dataclass
class StereoParams:
    tau_ms: float = 20.0  # the time surfaces' decay
    every_ms: float = 40.0  # a stereo frame this often
    recent_ms: float = 10.0  # left pixels with an event this recent at a frame are matched
    patch_px: int = 11  # the SSD patch (odd)
    uniqueness: float = 0.85  # the best cost must be below this share of the best one over a pixel away
    min_contrast: float = 0.05  # ... and the left patch's time surface must vary by at least this (RMS)
    sigma_px: float = 0.5  # one match's disparity error (its standard deviation)
    gate_sigma: float = 2.0  # fusion keeps the estimates this many of their sigmas from the pixel's median
    min_fused: int = 3  # ... and a pixel needs at least this many of them


class TimeSurface:
    """The latest event time of every pixel of one camera."""

    def __init__(self, width: int, height: int) -> None:
        self.last = np.full((height, width), -(1 << 62), np.int64)

    def add(self, events: np.ndarray) -> None:
        _latest(self.last, events["x"], events["y"], events["t"])

    def image(self, t_us: int, tau_ms: float) -> np.ndarray:
        """exp(-(t - t_last) / tau), 0 for pixels that never fired (float32)."""
        age = np.maximum(t_us - self.last, 0).astype(np.float32)
        return np.exp(age * np.float32(-1e-3 / tau_ms))


@numba.njit(cache=True, nogil=True)
def _latest(last, x, y, t):  # noqa: ANN001, ANN202 - numba kernel
    for i in range(len(t)):
        if t[i] > last[y[i], x[i]]:
            last[y[i], x[i]] = t[i]


def relative_pose(T_body_left: np.ndarray | None, T_body_right: np.ndarray | None) -> np.ndarray:
    """The right camera's pose in the left camera's frame (4x4), from their poses in the rig (T_body_cam;
    None for the left one: it is the body)."""
    if T_body_right is None:
        raise ValueError("the second camera has no pose in the rig (T_body_cam)")
    left = np.eye(4) if T_body_left is None else np.asarray(T_body_left, np.float64)
    return np.linalg.inv(left) @ np.asarray(T_body_right, np.float64)


class Rectifier:
    """Maps two cameras' images onto a common image plane where epipolar lines are rows, and back.

    `T_left_right` is the right camera's pose in the left camera's frame (4x4). A rig whose cameras
    already share intrinsics and orientation, with the right one along the left one's x axis (the
    simulator's), is used as it is."""

    def __init__(self, K_left: np.ndarray, K_right: np.ndarray, T_left_right: np.ndarray, width: int,
                 height: int) -> None:
        R, t = np.asarray(T_left_right, np.float64)[:3, :3], np.asarray(T_left_right, np.float64)[:3, 3]
        self.baseline_m = float(np.linalg.norm(t))
        if self.baseline_m <= 0:
            raise ValueError("the two cameras are at the same place: no stereo baseline")
        aligned = np.allclose(R, np.eye(3), atol=1e-6) and abs(t[1]) + abs(t[2]) < 1e-6 * self.baseline_m
        if aligned and t[0] > 0 and np.allclose(K_left, K_right):
            self.K, self.R_left, self.maps = np.asarray(K_left, np.float64), np.eye(3), None
            return
        zero = np.zeros(5)
        # OpenCV wants the map from left to right camera coordinates: X_right = R^T (X_left - t)
        R1, R2, P1, P2, *_ = cv2.stereoRectify(K_left, zero, K_right, zero, (width, height), np.ascontiguousarray(R.T),
                                              (-R.T @ t).reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        if abs(P2[0, 3]) < abs(P2[1, 3]) or P2[0, 3] > 0:
            raise ValueError("the second camera is not to the right of the first: give the rig's left camera first")
        self.K, self.R_left = P1[:3, :3].copy(), R1.T  # R_left: rectified to left camera frame
        self.maps = [cv2.initUndistortRectifyMap(K, zero, Rr, P[:3, :3], (width, height), cv2.CV_32FC1)
                     for K, Rr, P in ((K_left, R1, P1), (K_right, R2, P2))]

    def apply(self, image: np.ndarray, camera: int, nearest: bool = False) -> np.ndarray:
        """Camera `camera`'s (0 left, 1 right) image on the rectified plane (0 outside the view)."""
        if self.maps is None:
            return image
        mx, my = self.maps[camera]
        return cv2.remap(image, mx, my, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR, borderValue=0)


def match(left: np.ndarray, right: np.ndarray, mask: np.ndarray, d_min: float, d_max: float,
          params: StereoParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and disparities (right x = left x - d) of the `mask`ed left pixels that match
    (rectified time surfaces, SSD of patches), searched over [d_min, d_max]."""
    h, w = left.shape
    r = params.patch_px // 2
    lo, hi = max(int(np.floor(d_min)), 1), min(int(np.ceil(d_max)), w - 2 * r - 1)
    ys, xs = np.nonzero(mask)
    inside = (ys >= r) & (ys < h - r) & (xs >= r + lo) & (xs < w - r)
    ys, xs = ys[inside], xs[inside]
    if hi - lo < 2 or not len(ys):
        return ys, xs, np.zeros(0)
    cost, contrast = _ssd(left, right, ys.astype(np.int64), xs.astype(np.int64), lo, hi, r)
    best = np.argmin(cost, axis=1)
    rows = np.arange(len(ys))
    c0 = cost[rows, best]
    near = np.abs(np.arange(cost.shape[1])[None] - best[:, None]) <= 1
    other = np.where(near, np.inf, cost).min(axis=1)
    inner = (best > 0) & (best < cost.shape[1] - 1)
    cm, cp = cost[rows, np.maximum(best - 1, 0)], cost[rows, np.minimum(best + 1, cost.shape[1] - 1)]
    with np.errstate(invalid="ignore"):
        curve = cm - 2 * c0 + cp
        ok = inner & np.isfinite(curve) & (curve > 0) & (c0 < params.uniqueness * other) \
            & (contrast >= params.min_contrast ** 2)
    shift = 0.5 * (cm[ok] - cp[ok]) / curve[ok]
    return ys[ok], xs[ok], lo + best[ok] + shift


@numba.njit(cache=True, nogil=True, parallel=True)
def _ssd(left, right, ys, xs, lo, hi, r):  # noqa: ANN001, ANN202 - numba kernel
    """Per left pixel: the mean squared difference of its (2r+1)^2 patch and the right one's at each
    disparity lo..hi (inf where that leaves the image), and its patch's variance. Per disparity (in
    parallel), an integral image of the squared differences gives every pixel's patch sum in four reads."""
    h, w = left.shape
    n, n_d, size = len(ys), hi - lo + 1, (2 * r + 1) ** 2
    cost = np.full((n, n_d), np.inf, np.float32)
    for j in numba.prange(n_d):
        d = lo + j
        acc = np.empty((h + 1, w + 1))
        acc[0, :] = 0.0
        acc[:, :d + 1] = 0.0
        for y in range(h):
            row = 0.0
            for x in range(d, w):
                e = left[y, x] - right[y, x - d]
                row += e * e
                acc[y + 1, x + 1] = acc[y, x + 1] + row
        for i in range(n):
            y, x = ys[i], xs[i]
            if x - d - r < 0:
                continue
            y0, y1, x0, x1 = y - r, y + r + 1, x - r, x + r + 1
            cost[i, j] = (acc[y1, x1] - acc[y0, x1] - acc[y1, x0] + acc[y0, x0]) / size
    contrast = np.zeros(n, np.float32)
    for i in range(n):
        s, s2 = 0.0, 0.0
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                a = left[ys[i] + dy, xs[i] + dx]
                s += a
                s2 += a * a
        contrast[i] = s2 / size - (s / size) ** 2
    return cost, contrast


class StereoMatcher:
    """Two cameras' events in, depth estimates (ESTIMATE_DTYPE: world points) out, a stereo frame every
    `every_ms`, searching depths in `depth_range` (m). Both cameras' events must be given up to the same
    time."""

    def __init__(self, K_left: np.ndarray, K_right: np.ndarray, T_left_right: np.ndarray, width: int, height: int,
                 params: StereoParams | None = None, depth_range: tuple[float, float] = (0.5, 8.0)) -> None:
        self.params = params or StereoParams()
        self.depth_range = depth_range
        self.rectifier = Rectifier(K_left, K_right, T_left_right, width, height)
        self.surfaces = (TimeSurface(width, height), TimeSurface(width, height))
        self.fb = float(self.rectifier.K[0, 0] * self.rectifier.baseline_m)  # disparity (px) times depth (m)
        self._next_us: int | None = None
        self.skipped = 0  # frames not matched (see `add`)

    def add(self, left: np.ndarray, right: np.ndarray, trajectory: Trajectory,
            max_frames: int | None = None) -> np.ndarray:
        """Events of both cameras (sorted by time) up to the same time; the estimates of the frames they
        complete, in world coordinates by the left camera's `trajectory`. With `max_frames`, only the
        latest that many of those frames are matched (a live mapper that fell behind catches up; the
        time surfaces still take every event); the others are counted in `skipped`."""
        if not len(left):
            self.surfaces[1].add(right)
            return np.zeros(0, ESTIMATE_DTYPE)
        step = int(self.params.every_ms * 1000)
        if self._next_us is None:
            self._next_us = int(left["t"][0]) + step
        end = max(int(left["t"][-1]), int(right["t"][-1]) if len(right) else 0)
        due = range(self._next_us, end + 1, step)
        skip = max(len(due) - max_frames, 0) if max_frames is not None else 0
        self.skipped += skip
        out, done = [], [0, 0]
        for t in due[skip:]:
            for k, (surface, events) in enumerate(zip(self.surfaces, (left, right), strict=True)):
                upto = int(np.searchsorted(events["t"], t, side="right"))
                surface.add(events[done[k]:upto])
                done[k] = upto
            out.append(self.frame(t, trajectory))
        self._next_us += len(due) * step
        for surface, events, k in zip(self.surfaces, (left, right), done, strict=True):
            surface.add(events[k:])
        return np.concatenate(out) if out else np.zeros(0, ESTIMATE_DTYPE)

    def restart(self) -> None:
        """The next frame comes `every_ms` after the next events given (the time surfaces keep what they hold)."""
        self._next_us = None

    def frame(self, t_us: int, trajectory: Trajectory) -> np.ndarray:
        """The estimates of the stereo frame at `t_us` (the surfaces hold every event up to it)."""
        p = self.params
        left, right = (s.image(t_us, p.tau_ms) for s in self.surfaces)
        recent = (t_us - self.surfaces[0].last <= p.recent_ms * 1000).astype(np.uint8)
        left, right = self.rectifier.apply(left, 0), self.rectifier.apply(right, 1)
        recent = self.rectifier.apply(recent, 0, nearest=True)
        ys, xs, d = match(left, right, recent > 0, self.fb / self.depth_range[1], self.fb / self.depth_range[0], p)
        if not len(d):
            return np.zeros(0, ESTIMATE_DTYPE)
        K, z = self.rectifier.K, self.fb / d
        cam = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], axis=1)
        R, pos = (a[0] for a in trajectory.at(t_us))
        out = np.empty(len(d), ESTIMATE_DTYPE)
        out["t"], out["xyz"] = t_us, cam @ (R @ self.rectifier.R_left).T + pos
        out["range"] = np.linalg.norm(cam, axis=1)
        out["sigma"] = p.sigma_px / self.fb  # of the inverse depth: rho = d / fb
        return out


EARLY_ESTIMATES = 5_000  # a keyframe asked for early holds this many estimates at least (a second holds 40-70 000)


class StereoMapper:
    """A stereo rig's events in (both cameras' up to the same time), keyframes out: the matcher's estimates
    cut into segments by the camera's travel, as the space sweep's events are (`KeyframeMapper`), and
    each segment fused at its middle."""

    def __init__(self, K_left: np.ndarray, K_right: np.ndarray, T_left_right: np.ndarray, width: int, height: int,
                 params: KeyframeParams | None = None, stereo: StereoParams | None = None) -> None:
        params, stereo = params or KeyframeParams(), stereo or StereoParams()
        self.matcher = StereoMatcher(K_left, K_right, T_left_right, width, height, stereo,
                                     (params.sweep.z_min_m, params.sweep.z_max_m))
        K = np.asarray(K_left, np.float64)
        self.keyframes = KeyframeMapper(K, width, height, params, build=lambda estimates, trajectory: fuse_keyframe(
            estimates, trajectory, K, width, height, stereo, params.sweep))

    def add(self, left: np.ndarray, right: np.ndarray, trajectory: Trajectory,
            max_frames: int | None = None) -> list[Keyframe]:
        return self.keyframes.add(self.matcher.add(left, right, trajectory, max_frames), trajectory)

    def flush(self, trajectory: Trajectory) -> Keyframe | None:
        return self.keyframes.flush(trajectory)

    def finish(self, trajectory: Trajectory) -> Keyframe:
        """The keyframe of the estimates held so far (the segment ends here)."""
        return self.keyframes.finish(trajectory)

    def early(self, trajectory: Trajectory) -> Keyframe | None:
        """A keyframe asked for before the segment's end: of the estimates held, if `EARLY_ESTIMATES` (stereo
        depth needs no travel, but a keyframe of a few frames has few points)."""
        return self.keyframes.finish(trajectory) if self.held >= EARLY_ESTIMATES else None

    @property
    def held(self) -> int:
        return self.keyframes.held

    def drop(self) -> None:
        """A spell without poses: the segment held ends unfused, and stereo frames start again with the next
        events (a frame in the spell would be placed by a pose nobody knows)."""
        self.keyframes.drop()
        self.matcher.restart()


def fuse_keyframe(estimates: np.ndarray, trajectory: Trajectory, K: np.ndarray, width: int, height: int,
                  params: StereoParams, filters: sweep.SweepParams) -> Keyframe:
    """A segment's estimates fused into the depth map of the left camera at the segment's middle time,
    then median filtered as the sweep's are (`filters`)."""
    t_ref = int((int(estimates["t"][0]) + int(estimates["t"][-1])) // 2)
    R_ref, p_ref = (a[0] for a in trajectory.at(t_ref))
    cam = (estimates["xyz"].astype(np.float64) - p_ref) @ R_ref
    z = cam[:, 2]
    front = z > 1e-6
    u = np.round(K[0, 0] * cam[:, 0] / np.where(front, z, 1) + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * cam[:, 1] / np.where(front, z, 1) + K[1, 2]).astype(np.int64)
    ok = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    # inverse depth seen from the reference: rho_ref = 1 / z; its sigma scales by (rho_ref / rho)^2 ~ (d / z)^2
    rho = 1.0 / z[ok]
    sigma = estimates["sigma"][ok] * (estimates["range"][ok] * rho) ** 2
    inv, count = fuse(v[ok] * width + u[ok], rho, sigma, params.gate_sigma, width * height)
    keep = (count >= params.min_fused) & (inv > 0)
    depth = np.where(keep, 1.0 / np.where(keep, inv, 1), np.nan).reshape(height, width).astype(np.float32)
    depth = sweep.masked_median(depth, filters.median_px // 2, filters.min_neighbours, filters.median_gap)
    return lift(t_ref, R_ref, p_ref, depth, count.reshape(height, width).astype(np.float32), K, len(estimates))


def fuse(pixel: np.ndarray, rho: np.ndarray, sigma: np.ndarray, gate: float,
         n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (of `n_pixels`): the inverse-variance weighted mean of the inverse depths within `gate`
    sigmas of their median (0 where none), and how many those were."""
    order = np.lexsort((rho, pixel))
    pixel, rho, sigma = pixel[order], rho[order], sigma[order]
    starts = np.flatnonzero(np.r_[True, pixel[1:] != pixel[:-1]]) if len(pixel) else np.zeros(0, np.int64)
    sizes = np.diff(np.r_[starts, len(pixel)])
    median = np.repeat(0.5 * (rho[starts + (sizes - 1) // 2] + rho[starts + sizes // 2]), sizes)
    w = np.where(np.abs(rho - median) <= gate * sigma, 1.0 / sigma.astype(np.float64) ** 2, 0.0)
    weight = np.zeros(n_pixels)
    total = np.zeros(n_pixels)
    count = np.zeros(n_pixels, np.int64)
    np.add.at(weight, pixel, w)
    np.add.at(total, pixel, w * rho)
    np.add.at(count, pixel, w > 0)
    return np.where(weight > 0, total / np.where(weight > 0, weight, 1), 0.0), count
