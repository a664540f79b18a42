"""Contrast of a window of events warped by a rotation (Gallego and Scaramuzza 2017; seed 001).

A camera turning at angular velocity w (rad/s, camera frame) sees a world direction at time t along
the ray exp([w (t - t_ref)]x) r of the one it saw at t_ref. Warping each event's ray r_k to t_ref
this way and voting it bilinearly into an image of warped events (IWE) gives a sharp image when w
is right and a blurred one otherwise; the variance of the IWE (smoothed by a small Gaussian) is the
contrast that is maximised. Its gradient is exact for bilinear voting: with S the IWE smoothed
twice over (a Gaussian of sigma where the variance's is sigma / sqrt(2)), d var / dw = 2 / n_px *
sum_k grad S(x_k') . dx_k'/dw, so one objective and gradient cost two passes over the events and
one blur, whatever the window.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np


@numba.njit(cache=True, nogil=True, fastmath=True)
def _warp(rays, dt, omega, fx, fy, cx, cy, u, v, ju, jv):  # noqa: ANN001, ANN202 - numba kernel
    """Warped pixels (u, v) of unit rays (N x 3) rotated by exp([omega dt_k]x), and their derivatives
    (N x 3) with respect to omega: d(R r)/dw = -dt [R r]x J_l(w dt) (J_l: SO(3)'s left Jacobian)."""
    wx, wy, wz = omega[0], omega[1], omega[2]
    speed = math.sqrt(wx * wx + wy * wy + wz * wz)
    for k in range(rays.shape[0]):
        s = dt[k]
        tx, ty, tz = wx * s, wy * s, wz * s
        phi = speed * abs(s)
        rx, ry, rz = rays[k, 0], rays[k, 1], rays[k, 2]
        # Rodrigues with t = w dt unnormalised: R r = r + b (t x r) + a1 t (t . r) - a1 |t|^2 r, where
        # b = sin(phi) / phi and a1 = (1 - cos(phi)) / phi^2; by their series where phi is small (a window
        # turns less than 0.5 rad: the terms left out are below 1e-8), the libm calls cost more than the rest
        q = phi * phi
        if phi < 0.5:
            b = 1 - q / 6 * (1 - q / 20 * (1 - q / 42))
            a1 = 0.5 * (1 - q / 12 * (1 - q / 30 * (1 - q / 56)))
            a2 = (1 - q / 20 * (1 - q / 42 * (1 - q / 72))) / 6
        else:
            b, a1, a2 = math.sin(phi) / phi, (1 - math.cos(phi)) / q, (phi - math.sin(phi)) / (q * phi)
        dot = tx * rx + ty * ry + tz * rz
        px = rx + b * (ty * rz - tz * ry) + a1 * (tx * dot - q * rx)
        py = ry + b * (tz * rx - tx * rz) + a1 * (ty * dot - q * ry)
        pz = rz + b * (tx * ry - ty * rx) + a1 * (tz * dot - q * rz)
        if pz < 1e-3:
            u[k] = -1e9
            v[k] = -1e9
            continue
        iz = 1.0 / pz
        u[k] = fx * px * iz + cx
        v[k] = fy * py * iz + cy
        # J_l = I + a1 [t]x + a2 [t]x^2, [t]x^2 = t t^T - |t|^2 I
        tt = q
        j00, j11, j22 = 1 + a2 * (tx * tx - tt), 1 + a2 * (ty * ty - tt), 1 + a2 * (tz * tz - tt)
        j01, j10 = -a1 * tz + a2 * tx * ty, a1 * tz + a2 * tx * ty
        j02, j20 = a1 * ty + a2 * tx * tz, -a1 * ty + a2 * tx * tz
        j12, j21 = -a1 * tx + a2 * ty * tz, a1 * tx + a2 * ty * tz
        # du/dp = fx (1/z, 0, -x/z^2), dv/dp = fy (0, 1/z, -y/z^2); dp/dw = s (-[p]x) J_l
        gu0, gu2 = fx * iz, -fx * px * iz * iz
        gv1, gv2 = fy * iz, -fy * py * iz * iz
        # rows of -[p]x: (0, pz, -py), (-pz, 0, px), (py, -px, 0)
        m0 = (s * (pz * j10 - py * j20), s * (pz * j11 - py * j21), s * (pz * j12 - py * j22))
        m1 = (s * (-pz * j00 + px * j20), s * (-pz * j01 + px * j21), s * (-pz * j02 + px * j22))
        m2 = (s * (py * j00 - px * j10), s * (py * j01 - px * j11), s * (py * j02 - px * j12))
        for i in range(3):
            ju[k, i] = gu0 * m0[i] + gu2 * m2[i]
            jv[k, i] = gv1 * m1[i] + gv2 * m2[i]


@numba.njit(cache=True, nogil=True)
def _cell(u, v, w, h):  # noqa: ANN001, ANN202 - numba helper
    """The top-left pixel (row, column) of the 2 x 2 a sub-pixel point (u, v) falls in, and its offsets there;
    row -1 where that block is not wholly inside a w x h image."""
    x0, y0 = math.floor(u), math.floor(v)
    if x0 < 0 or y0 < 0 or x0 >= w - 1 or y0 >= h - 1:
        return -1, 0, 0.0, 0.0
    return int(y0), int(x0), u - x0, v - y0


@numba.njit(cache=True, nogil=True)
def _vote(u, v, image):  # noqa: ANN001, ANN202 - numba kernel
    """Bilinear votes of the warped pixels into `image` (zeroed first)."""
    h, w = image.shape
    image[:] = 0.0
    for k in range(u.shape[0]):
        i, j, fx, fy = _cell(u[k], v[k], w, h)
        if i < 0:
            continue
        image[i, j] += (1 - fx) * (1 - fy)
        image[i, j + 1] += fx * (1 - fy)
        image[i + 1, j] += (1 - fx) * fy
        image[i + 1, j + 1] += fx * fy


@numba.njit(cache=True, nogil=True)
def _gradient(u, v, ju, jv, smooth, out):  # noqa: ANN001, ANN202 - numba kernel
    """sum_k grad(bilinear `smooth`)(u_k, v_k) . d(u_k, v_k)/dw into `out` (3)."""
    h, w = smooth.shape
    g0 = g1 = g2 = 0.0
    for k in range(u.shape[0]):
        i, j, fx, fy = _cell(u[k], v[k], w, h)
        if i < 0:
            continue
        a, b, c, d = smooth[i, j], smooth[i, j + 1], smooth[i + 1, j], smooth[i + 1, j + 1]
        du = (b - a) * (1 - fy) + (d - c) * fy
        dv = (c - a) * (1 - fx) + (d - b) * fx
        g0 += du * ju[k, 0] + dv * jv[k, 0]
        g1 += du * ju[k, 1] + dv * jv[k, 1]
        g2 += du * ju[k, 2] + dv * jv[k, 2]
    out[0], out[1], out[2] = g0, g1, g2


@numba.njit(cache=True, nogil=True)
def _moments(image, smooth):  # noqa: ANN001, ANN202 - numba kernel
    """sum(image * smooth) and sum(image), in one pass on one thread (numpy's dot would call a BLAS that
    may wake threads for it)."""
    inner = total = 0.0
    for i in range(image.shape[0]):
        for j in range(image.shape[1]):
            inner += image[i, j] * smooth[i, j]
            total += image[i, j]
    return inner, total


class RotationContrast:
    """The IWE variance of one window of events (unit rays and times relative to the reference time)
    as a function of the angular velocity, with its gradient; buffers are reused across windows."""

    def __init__(self, K: np.ndarray, width: int, height: int, sigma_px: float = 1.0) -> None:
        K = np.asarray(K, np.float64)
        self.fx, self.fy, self.cx, self.cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        self.sigma = sigma_px
        self.image = np.zeros((height, width), np.float32)
        self._ksize = (2 * math.ceil(2.5 * sigma_px) + 1,) * 2  # the Gaussian cut at 2.5 sigma
        self.rays = np.zeros((0, 3))
        self.dt = np.zeros(0)
        self._u = self._v = np.zeros(0)
        self._ju = self._jv = np.zeros((0, 3))

    def set_events(self, rays: np.ndarray, dt_s: np.ndarray) -> None:
        """The window: unit rays (N x 3) and their times from the reference time (s)."""
        self.rays, self.dt = np.ascontiguousarray(rays, np.float64), np.ascontiguousarray(dt_s, np.float64)
        n = len(self.dt)
        if len(self._u) < n:
            self._u, self._v = np.empty(n), np.empty(n)
            self._ju, self._jv = np.empty((n, 3)), np.empty((n, 3))

    def iwe(self, omega: np.ndarray) -> np.ndarray:
        """The image of warped events at `omega` (not smoothed; a view on a reused buffer)."""
        n = len(self.dt)
        u, v, ju, jv = self._u[:n], self._v[:n], self._ju[:n], self._jv[:n]
        _warp(self.rays, self.dt, np.asarray(omega, np.float64), self.fx, self.fy, self.cx, self.cy, u, v, ju, jv)
        _vote(u, v, self.image)
        return self.image

    def warped(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The pixels (u, v) the last `iwe` or call warped the window's `n` events to."""
        return self._u[:n], self._v[:n]

    def __call__(self, omega: np.ndarray) -> tuple[float, np.ndarray]:
        """Variance of the IWE at `omega` smoothed by a Gaussian of sigma / sqrt(2), and its gradient (3).
        One blur serves both: with S the IWE smoothed by sigma, that variance is <IWE, S> / n_px - mean^2."""
        n = len(self.dt)
        image = self.iwe(omega)
        smooth = cv2.GaussianBlur(image, self._ksize, self.sigma)
        grad = np.empty(3)
        _gradient(self._u[:n], self._v[:n], self._ju[:n], self._jv[:n], smooth, grad)
        inner, total = _moments(image, smooth)
        mean = total / image.size
        return inner / image.size - mean * mean, grad * (2.0 / image.size)
