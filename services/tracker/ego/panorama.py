"""A panoramic map of where a rotating camera's events fire, to track its orientation against (seed 000).

Integrating angular velocity drifts: every window's small error stays in the orientation. Kim et al.
(2014) track against a mosaic instead; here the mosaic is the one the events draw themselves, the
sharp image of each window's warped events (its edges, at the window's middle time) averaged into an
equirectangular panorama of the world frame (longitude atan2(x, z) over the width, latitude asin(-y)
over the height, as the mapper's mosaic). A new window's warped events are then turned by the small
rotation that lands them on the map's edges best: maximising the map's (smoothed) value summed over
the events' landing points, by L-BFGS on its exact gradient. Where the camera comes back to a part of
the world it mapped before, that pulls the orientation back to where it was then: the drift is bounded
by the map's, not summed over the whole run.
"""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from services.geometry import pixel_rays


@numba.njit(cache=True, nogil=True, fastmath=True)
def _landing(d, width, height):  # noqa: ANN001, ANN202 - numba helper
    """Panorama pixel (u, v) of a unit world direction, and du/dd, dv/dd."""
    lon = math.atan2(d[0], d[2])
    lat = math.asin(min(max(-d[1], -1.0), 1.0))
    u = (lon + math.pi) / (2 * math.pi) * width
    v = (math.pi / 2 - lat) / math.pi * height
    rho = max(d[0] * d[0] + d[2] * d[2], 1e-12)
    ku = width / (2 * math.pi) / rho
    kv = height / math.pi / math.sqrt(rho)  # dlat/d(-y) = 1 / sqrt(1 - y^2), and 1 - y^2 = x^2 + z^2
    return u, v, (ku * d[2], 0.0, -ku * d[0]), (0.0, kv, 0.0)


@numba.njit(cache=True, nogil=True, fastmath=True)
def _turned_cell(R, ray, d, width, height):  # noqa: ANN001, ANN202 - numba helper
    """Where a camera ray turned by R into the world (written into `d`) lands on the panorama: the rows and
    columns of its 2 x 2 block (the longitude wraps), its offsets there, and du/dd, dv/dd; row -1 off the
    poles' edge rows."""
    for i in range(3):
        d[i] = R[i, 0] * ray[0] + R[i, 1] * ray[1] + R[i, 2] * ray[2]
    u, v, du, dv = _landing(d, width, height)
    x0, y0 = math.floor(u), math.floor(v)
    if y0 < 0 or y0 >= height - 1:
        return -1, 0, 0, 0.0, 0.0, du, dv
    j0 = int(x0) % width
    return int(y0), j0, (j0 + 1) % width, u - x0, v - y0, du, dv


@numba.njit(cache=True, nogil=True, fastmath=True)
def _score(rays, R, image, grad):  # noqa: ANN001, ANN202 - numba kernel
    """Sum of the map's bilinear value where rays (N x 3, camera frame) land turned by R, and its gradient
    (into `grad`) for R exp([delta]x) at delta = 0: dd/ddelta = -R [r]x."""
    h, w = image.shape
    total = 0.0
    g0 = g1 = g2 = 0.0
    d = np.empty(3)
    for k in range(rays.shape[0]):
        rx, ry, rz = rays[k, 0], rays[k, 1], rays[k, 2]
        i0, j0, j1, fx, fy, du, dv = _turned_cell(R, rays[k], d, w, h)
        if i0 < 0:
            continue
        a, b, c, e = image[i0, j0], image[i0, j1], image[i0 + 1, j0], image[i0 + 1, j1]
        total += (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + e * fx) * fy
        gu = (b - a) * (1 - fy) + (e - c) * fy
        gv = (c - a) * (1 - fx) + (e - b) * fx
        # dS/dd = gu du + gv dv; dd/ddelta = -R [r]x, so dS/ddelta = -(R^T dS/dd) x... as a row: (R^T s) . (-[r]x)
        sx = gu * du[0] + gv * dv[0]
        sy = gu * du[1] + gv * dv[1]
        sz = gu * du[2] + gv * dv[2]
        qx = R[0, 0] * sx + R[1, 0] * sy + R[2, 0] * sz
        qy = R[0, 1] * sx + R[1, 1] * sy + R[2, 1] * sz
        qz = R[0, 2] * sx + R[1, 2] * sy + R[2, 2] * sz
        # q^T (-[r]x) = (r x q)^T... component-wise: (-(q_y r_z - q_z r_y), ...) = r x q
        g0 += ry * qz - rz * qy
        g1 += rz * qx - rx * qz
        g2 += rx * qy - ry * qx
    grad[0], grad[1], grad[2] = g0, g1, g2
    return total


@numba.njit(cache=True, nogil=True)
def _splat(rays, values, R, total, weight):  # noqa: ANN001, ANN202 - numba kernel
    """Adds each ray's value (turned by R into the world) bilinearly into `total`, and its weight into
    `weight`."""
    h, w = total.shape
    d = np.empty(3)
    for k in range(rays.shape[0]):
        i0, j0, j1, fx, fy, _, _ = _turned_cell(R, rays[k], d, w, h)
        if i0 < 0:
            continue
        for i, j, wt in ((i0, j0, (1 - fx) * (1 - fy)), (i0, j1, fx * (1 - fy)), (i0 + 1, j0, (1 - fx) * fy),
                         (i0 + 1, j1, fx * fy)):
            total[i, j] += wt * values[k]
            weight[i, j] += wt


class PanoramaMap:
    """The averaged edge images of a rotating camera, in the world frame; `align` refines an orientation."""

    def __init__(self, K: np.ndarray, width: int, height: int, size: tuple[int, int] = (1024, 512),
                 sigma_px: float = 1.0, max_step_deg: float = 2.0) -> None:
        K = np.asarray(K, np.float64)
        # windows are added at half the sensor's resolution: its pixels are then about the map's (0.35 deg at the
        # default size for a 58 deg field of view), and splatting them costs a quarter
        self._half = (width // 2, height // 2)
        self._pixel_rays = pixel_rays(K, width, height, step=2)
        self._total = np.zeros(size[::-1], np.float32)
        self._weight = np.zeros(size[::-1], np.float32)
        self.image = np.zeros(size[::-1], np.float32)  # the smoothed average the windows are aligned to
        self.sigma = sigma_px
        self.max_step = math.radians(max_step_deg)
        self.windows = 0

    def insert(self, edges: np.ndarray, orientation: Rotation) -> None:
        """Averages a window's image of warped events (H x W, at its middle time) into the map, seen with
        `orientation` (R_world_cam); scaled by its mean, so a busy window weighs as a quiet one."""
        mean = float(edges.mean())
        if mean <= 0:
            return
        half = cv2.resize(edges, self._half, interpolation=cv2.INTER_AREA)
        _splat(self._pixel_rays, (half / mean).ravel(), orientation.as_matrix(), self._total, self._weight)
        self.windows += 1
        size = (0, 0)
        total = cv2.GaussianBlur(self._total, size, self.sigma)
        weight = cv2.GaussianBlur(self._weight, size, self.sigma)
        self.image = np.where(weight > 0.5, total / np.maximum(weight, 1e-9), 0.0)

    def align(self, rays: np.ndarray, orientation: Rotation) -> Rotation:
        """`orientation` turned by the small rotation (at most `max_step_deg`) that lands the rays (a window's
        warped events, camera frame) on the map's edges best; as it was where the map has none yet."""
        if not self.windows or not len(rays):
            return orientation
        R0 = orientation.as_matrix()
        n = float(len(rays))
        grad = np.empty(3)

        def negative(delta: np.ndarray) -> tuple[float, np.ndarray]:
            R = R0 @ Rotation.from_rotvec(delta).as_matrix()
            value = _score(rays, R, self.image, grad)
            return -value / n, -grad / n

        if negative(np.zeros(3))[0] == 0.0:  # nothing mapped where it looks
            return orientation
        result = minimize(negative, np.zeros(3), jac=True, method="L-BFGS-B", options={"maxiter": 5, "maxls": 5})
        delta = np.asarray(result.x)
        if not np.all(np.isfinite(delta)) or np.linalg.norm(delta) > self.max_step:
            return orientation
        return orientation * Rotation.from_rotvec(delta)
