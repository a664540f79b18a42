"""Panoramic mosaic of a rotating camera's scene from its events (Kim et al. 2014; seed 000).

Every event says that the log intensity at its pixel moved by one contrast step C since the pixel's
last event. With the camera's rotation known, the pixel's viewing ray slid over the panorama by
d = v * tau (v: its velocity on the panorama, tau: the time since that event), so the panorama's
log-intensity gradient g at the ray's landing point obeys g . d = +-C (the sign is the polarity).
Each panorama pixel keeps g and its 2x2 covariance and folds in these scalar measurements with an
extended Kalman filter (one update per event, in numba). The log intensity is then the image whose
gradients best fit g in least squares: the Poisson equation, solved exactly by transforms (FFT across
the longitude, which wraps; cosine transform down the latitude, zero flux at the poles).

The panorama is equirectangular, as the simulator's truth: longitude atan2(x, z) over the width,
latitude asin(-y) over the height, of the ray in the world frame (the camera's frame at the start).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial.transform import Rotation

from services.geometry import pixel_rays
from services.mapper import mosaic_fit
from services.mapper.poisson import poisson
from services.mapper.trajectory import Trajectory

POSE_STEP_US = 250  # the trajectory is sampled this often; rotations between samples are interpolated


@dataclass
class MosaicParams:
    width: int = 2048  # equirectangular panorama, pixels (the simulator's truth size)
    height: int = 1024
    contrast: float = 0.25  # C: the log-intensity step of one event (scales the mosaic only)
    noise: float = 0.25  # measurement noise of g . d, in log intensity (threshold mismatch, noise events)
    prior_sigma: float = 0.2  # gradient prior (log intensity per panorama pixel), before any event
    max_travel_px: float = 30.0  # a pixel whose ray slid further since its last event tells little: skipped
    gate: float = 9.0  # innovations beyond this many variances are outliers (noise events): skipped
    min_updates: int = 3  # a panorama pixel is observed once this many events updated it
    # the fit to the events' own steps (mosaic_fit): pairs of one pixel's consecutive events kept (a
    # uniform sample over time: when full, every other one goes; 17 bytes each), the farthest apart the
    # pair's two rays may land, the weight of the gradient map beside them, and the solver's iterations
    # (0: the gradient map's Poisson reconstruction alone)
    max_pairs: int = 2_000_000
    max_pair_px: float = 60.0
    prior_weight: float = 1.0
    fit_iterations: int = 20


class Mosaic:
    """Gradient map of a panorama, fed with events and a trajectory covering their times."""

    def __init__(self, K: np.ndarray, width: int, height: int, params: MosaicParams | None = None) -> None:
        self.params = params or MosaicParams()
        self.sensor = (width, height)
        K = np.asarray(K, np.float64)
        self._rays = pixel_rays(K, width, height)
        self.reset()

    def reset(self) -> None:
        p = self.params
        self.gradient = np.zeros((p.height, p.width, 2), np.float32)
        self.covariance = np.zeros((p.height, p.width, 3), np.float32)  # Pxx, Pxy, Pyy
        self.covariance[..., 0] = self.covariance[..., 2] = p.prior_sigma ** 2
        self.updates = np.zeros((p.height, p.width), np.int32)
        self._last_us = np.full(self.sensor[0] * self.sensor[1], -1, np.int64)
        self._last_uv = np.full((self.sensor[0] * self.sensor[1], 2), np.nan, np.float32)  # where each last pointed
        self._pairs = np.empty((max(p.max_pairs, 2), 4), np.float32)
        self._polarity = np.empty(len(self._pairs), np.int8)
        self._sampling = np.array([0, 1, 0], np.int64)  # pairs held, keep every this many, eligible seen
        self.events = 0

    def add(self, events: np.ndarray, trajectory: Trajectory) -> int:
        """Folds in events (sorted by time; those outside the trajectory's span are skipped); returns how
        many updated the map."""
        t = events["t"]
        events = events[(t >= trajectory.start_us) & (t <= trajectory.end_us)]
        if not len(events):
            return 0
        t = events["t"]
        sample_t = np.arange(int(t[0]), int(t[-1]) + POSE_STEP_US + 1, POSE_STEP_US, dtype=np.int64)
        R, _ = trajectory.at(sample_t)
        quat, omega = _samples(R, sample_t)
        p = self.params
        used = _update(events["x"].astype(np.int64), events["y"].astype(np.int64), t.astype(np.int64),
                       events["p"].astype(np.int64), self._rays, self.sensor[0], sample_t, quat, omega,
                       self._last_us, self.gradient, self.covariance, self.updates, p.contrast, p.noise ** 2,
                       p.max_travel_px, p.gate, self._last_uv, self._pairs, self._polarity, self._sampling,
                       p.max_pair_px)
        self.events += used
        return used

    def observed(self) -> np.ndarray:
        """Panorama pixels the events have measured (H x W bool)."""
        return self.updates >= self.params.min_updates

    @property
    def pairs(self) -> int:
        """How many event pairs the fit holds."""
        return int(self._sampling[0])

    def log_intensity(self, fit: bool = True) -> np.ndarray:
        """The log intensity (up to an offset), H x W float32: the Poisson reconstruction of the gradient
        map, then (`fit` and `fit_iterations` > 0) fitted to the held event pairs (`mosaic_fit`)."""
        initial = poisson(self.gradient[..., 0], self.gradient[..., 1])
        if not fit or self.params.fit_iterations <= 0 or not self.pairs:
            return initial
        return self.fitted(initial, self.params.fit_iterations)

    def fitted(self, initial: np.ndarray, iterations: int, pair_stride: int = 1) -> np.ndarray:
        """The log intensity fitted to every `pair_stride`-th held pair in `iterations` from `initial` (a
        live view goes on from its last one, a few iterations at a time)."""
        p, n = self.params, self.pairs
        return mosaic_fit.fit(self._pairs[:n:pair_stride], self._polarity[:n:pair_stride] * p.contrast,
                              self.gradient[..., 0], self.gradient[..., 1], self.observed(), initial,
                              p.prior_weight, iterations)

    def image(self) -> np.ndarray:
        """The fitted mosaic as `to_png16` grey levels (what `etam mosaic` and the live service's save write)."""
        return to_png16(self.log_intensity(), self.observed())


def to_png16(log_intensity: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """The mosaic as 16-bit grey levels, linear in log intensity over the observed pixels' range; 0 marks
    pixels never observed (so a plain image viewer shows it, and `from_png16` reads it back)."""
    out = np.zeros(log_intensity.shape, np.uint16)
    if observed.any():
        seen = log_intensity[observed]
        lo, span = float(seen.min()), max(float(np.ptp(seen)), 1e-9)
        out[observed] = np.round(1 + (seen - lo) / span * 65534).astype(np.uint16)
    return out


def from_png16(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Log intensity (up to offset and scale) and the observed mask of a `to_png16` image."""
    if image.ndim != 2 or image.dtype != np.uint16:
        raise ValueError(f"a mosaic is a 16-bit grey image (etam mosaic writes one), got {image.dtype} "
                         f"with shape {image.shape}")
    return image.astype(np.float32), image > 0


def _samples(R: np.ndarray, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quaternions (w, x, y, z; signs kept continuous for interpolation) of rotations N x 3 x 3, and the
    world-frame angular velocity (rad/s) between consecutive samples (N - 1 x 3)."""
    rot = Rotation.from_matrix(R)
    q = rot.as_quat()[:, [3, 0, 1, 2]]
    flip = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
    q[1:] *= flip[:, None]
    step = (rot[1:] * rot[:-1].inv()).as_rotvec()  # R_{i+1} R_i^T, in the world frame
    return q, step / (np.diff(t_us)[:, None] * 1e-6)


@numba.njit(cache=True, nogil=True, inline="always")
def _rotate(qw, qx, qy, qz, rx, ry, rz):  # q r q*: r + 2 qw (q x r) + 2 q x (q x r)
    cx, cy, cz = qy * rz - qz * ry, qz * rx - qx * rz, qx * ry - qy * rx
    return (rx + 2 * (qw * cx + qy * cz - qz * cy), ry + 2 * (qw * cy + qz * cx - qx * cz),
            rz + 2 * (qw * cz + qx * cy - qy * cx))


@numba.njit(cache=True, nogil=True, inline="always")
def _pano(dx, dy, dz, kx, ky):  # a world direction's equirectangular pixel
    return (np.arctan2(dx, dz) + np.pi) * kx, (np.pi / 2 + np.arcsin(min(1.0, max(-1.0, dy)))) * ky


@numba.njit(cache=True, nogil=True, inline="always")
def _fold(g, P, iv, iu, hu, hv, z, noise_var, gate):
    """One scalar EKF update of pixel (iv, iu) with measurement z = g . (hu, hv); False if gated out."""
    pxx, pxy, pyy = P[iv, iu, 0], P[iv, iu, 1], P[iv, iu, 2]
    phu, phv = pxx * hu + pxy * hv, pxy * hu + pyy * hv
    s = hu * phu + hv * phv + noise_var
    innovation = z - (g[iv, iu, 0] * hu + g[iv, iu, 1] * hv)
    if innovation * innovation > gate * s:
        return False
    g[iv, iu, 0] += phu / s * innovation
    g[iv, iu, 1] += phv / s * innovation
    P[iv, iu, 0] = pxx - phu * phu / s
    P[iv, iu, 1] = pxy - phu * phv / s
    P[iv, iu, 2] = pyy - phv * phv / s
    return True


@numba.njit(cache=True, nogil=True)
def _update(x, y, t, p, rays, sensor_w, sample_t, quat, omega, last_us, g, P, n, contrast, noise_var,
            max_travel, gate, last_uv, pairs, polarity, sampling, max_pair):
    ph, pw = n.shape
    kx, ky = pw / (2 * np.pi), ph / np.pi
    j = 0
    used = 0
    for e in range(len(t)):
        te = t[e]
        while j + 2 < len(sample_t) and sample_t[j + 1] <= te:
            j += 1
        pix = y[e] * sensor_w + x[e]
        prev = last_us[pix]
        last_us[pix] = te
        a = (te - sample_t[j]) / (sample_t[j + 1] - sample_t[j])
        qw = (1 - a) * quat[j, 0] + a * quat[j + 1, 0]
        qx = (1 - a) * quat[j, 1] + a * quat[j + 1, 1]
        qy = (1 - a) * quat[j, 2] + a * quat[j + 1, 2]
        qz = (1 - a) * quat[j, 3] + a * quat[j + 1, 3]
        norm = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        dx, dy, dz = _rotate(qw, qx, qy, qz, rays[pix, 0], rays[pix, 1], rays[pix, 2])
        horiz = dx * dx + dz * dz
        if horiz < 1e-6:  # at a pole the longitude is undefined
            last_uv[pix, 0] = np.nan
            continue
        u0, v0 = _pano(dx, dy, dz, kx, ky)
        _keep_pair(last_uv, pix, u0, v0, p[e], pw, max_pair, pairs, polarity, sampling)
        if prev < 0:
            continue
        wx, wy, wz = omega[j, 0], omega[j, 1], omega[j, 2]
        vx, vy, vz = wy * dz - wz * dy, wz * dx - wx * dz, wx * dy - wy * dx  # d' = w x d
        tau = (te - prev) * 1e-6
        hu = (dz * vx - dx * vz) / horiz * kx * tau  # the ray's slide on the panorama since the last event
        hv = vy / np.sqrt(horiz) * ky * tau
        if hu * hu + hv * hv > max_travel * max_travel:
            continue
        # the step of C happened along the slide: it is the gradient at the slide's middle
        u, v = u0 - 0.5 * hu, v0 - 0.5 * hv
        iu = int(np.floor(u + 0.5)) % pw
        iv = min(max(int(np.floor(v + 0.5)), 0), ph - 1)
        if not _fold(g, P, iv, iu, hu, hv, contrast if p[e] else -contrast, noise_var, gate):
            continue
        n[iv, iu] += 1
        used += 1
    return used


@numba.njit(cache=True, nogil=True, inline="always")
def _keep_pair(last_uv, pix, u, v, on, pw, max_pair, pairs, polarity, sampling):
    """Samples the pair (where pixel `pix` pointed at its last event, (u, v) now) for the fit, then makes
    (u, v) its last; `sampling` (held, keep every, eligible seen) halves the pairs and the rate when full."""
    ua, va = last_uv[pix, 0], last_uv[pix, 1]
    last_uv[pix, 0], last_uv[pix, 1] = u, v
    if not ua == ua:  # NaN: the pixel's first event, or it last pointed at a pole
        return
    du = u - ua
    if du > pw / 2:  # the shorter way round
        du -= pw
    elif du < -pw / 2:
        du += pw
    if du * du + (v - va) * (v - va) > max_pair * max_pair:
        return
    sampling[2] += 1
    if sampling[2] % sampling[1]:
        return
    k = sampling[0]
    if k == len(pairs):  # full: every other pair goes, and from now on every other one is kept
        for i in range(k // 2):
            pairs[i] = pairs[2 * i + 1]
            polarity[i] = polarity[2 * i + 1]
        k = sampling[0] = k // 2
        sampling[1] *= 2
    pairs[k, 0], pairs[k, 1], pairs[k, 2], pairs[k, 3] = ua, va, ua + du, v
    polarity[k] = 1 if on else -1
    sampling[0] += 1
