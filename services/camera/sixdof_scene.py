"""`6dof`: a hand-held-like camera moving in front of textured 3D structure (seed 001's setting).

A room of planes printed with flat-toned patterns (back wall at 5 m, floor, side walls) with printed boxes
at 0.8-3 m. Each pixel's ray is intersected with every surface (vectorised over pixels), the nearest hit gives the
intensity (from a texture in metric surface coordinates) and the depth. The camera's position and
orientation are smooth periodic functions of time, so poses and depth maps are exact ground truth.
The world frame is the (left) camera's frame at t = 0 (x right, y down, z forward). A stereo rig is two
scenes with the same seed, the second with `baseline_m`: it sits that far along the first camera's x axis.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np
from scipy.spatial.transform import Rotation

from services.camera.simulator import _texture

TEXTURE_PX_PER_M = 200.0


@numba.njit(cache=True, nogil=True, parallel=True)
def _ray_cast(o, R, rays, planes, box_lo, box_hi, px_per_m, tex_size):  # noqa: ANN001, ANN202 - numba kernel
    """Nearest hit of each ray (camera frame, rotated by R, from o) on axis-aligned planes
    (axis, coordinate) and boxes (lo, hi corners): distance along the ray, and the texture pixel
    (wrapped) of the point's coordinates along the surface; boxes' faces get shifted patches."""
    n = len(rays)
    best = np.full(n, np.inf, np.float32)
    u = np.zeros(n, np.float32)
    v = np.zeros(n, np.float32)
    for i in numba.prange(n):  # pixels are independent: one per thread in turn
        r0, r1, r2 = rays[i, 0], rays[i, 1], rays[i, 2]
        d = (R[0, 0] * r0 + R[0, 1] * r1 + R[0, 2] * r2, R[1, 0] * r0 + R[1, 1] * r1 + R[1, 2] * r2,
             R[2, 0] * r0 + R[2, 1] * r1 + R[2, 2] * r2)
        inv = (1.0 / d[0] if d[0] != 0 else 1e9, 1.0 / d[1] if d[1] != 0 else 1e9, 1.0 / d[2] if d[2] != 0 else 1e9)
        hit, hu, hv = np.inf, 0.0, 0.0
        for j in range(len(planes)):
            axis = int(planes[j, 0])
            if d[axis] == 0:
                continue
            dist = (planes[j, 1] - o[axis]) * inv[axis]
            if 0 < dist < hit:
                a, b = (1, 2) if axis == 0 else ((0, 2) if axis == 1 else (0, 1))
                hit, hu, hv = dist, o[a] + dist * d[a], o[b] + dist * d[b]
        for j in range(len(box_lo)):
            near, far, face = -np.inf, np.inf, 0
            for k in range(3):
                t0, t1 = (box_lo[j, k] - o[k]) * inv[k], (box_hi[j, k] - o[k]) * inv[k]
                lo, hi = min(t0, t1), max(t0, t1)
                if lo > near:
                    near, face = lo, k
                far = min(far, hi)
            if near <= far and 0 < near < hit:
                a = 1 if face == 0 else 0
                b = 1 if face == 2 else 2
                hit, hu, hv = near, o[a] + near * d[a] + 7.0 * face, o[b] + near * d[b]
        best[i], u[i], v[i] = hit, hu * px_per_m % tex_size, hv * px_per_m % tex_size
    return best, u, v


def _printed(smooth: np.ndarray, levels: int = 4) -> np.ndarray:
    """A smooth texture cut into `levels` flat tones with sharp (1 px soft) edges between them, as posters,
    furniture and printed patterns show a real camera. A smooth field's events come from wherever the
    motion crosses its gradients, which moves with the motion's direction: it has no fixed edges to map
    or to track a pose against."""
    flat = 0.2 + 0.8 * np.floor(np.clip(smooth, 0.0, 0.999) * levels) / levels
    return cv2.GaussianBlur(flat.astype(np.float32), (0, 0), 1.0)


class SixDofScene:
    """Renders log intensity and depth for the camera pose at any time; see the module docstring."""

    def __init__(self, width: int = 346, height: int = 260, seed: int = 0, period_s: float = 10.0,
                 baseline_m: float = 0.0) -> None:
        self.width, self.height = width, height
        self.T_body_cam = np.eye(4)
        self.T_body_cam[0, 3] = baseline_m  # body = the left camera
        rng = np.random.default_rng(seed)
        self.focal_px = 0.9 * width
        self.period_us = int(period_s * 1e6)
        self._w = 2 * np.pi / period_s
        tex = _printed(cv2.resize(_texture(rng, 128, 128), (512, 512), interpolation=cv2.INTER_CUBIC))
        self._log_tex = np.log(np.clip(tex, 0.05, None) + 1e-3).astype(np.float32)
        # planes: (axis, coordinate); boxes: (lo xyz, hi xyz)
        self.planes = [(2, 5.0), (1, 1.2), (0, -2.5), (0, 2.5)]
        self.boxes = []
        for _ in range(3):
            size = rng.uniform(0.3, 0.6, 3)
            centre = np.array([rng.uniform(-1.0, 1.0), rng.uniform(0.3, 1.2) - size[1] / 2, rng.uniform(1.2, 3.0)])
            self.boxes.append((centre - size / 2, centre + size / 2))
        self._planes = np.array(self.planes, np.float64)
        self._box_lo = np.array([lo for lo, _ in self.boxes], np.float64).reshape(-1, 3)
        self._box_hi = np.array([hi for _, hi in self.boxes], np.float64).reshape(-1, 3)
        ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
        rays = np.stack([(xs - width / 2) / self.focal_px, (ys - height / 2) / self.focal_px, np.ones_like(xs)], -1)
        self._rays = (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).reshape(-1, 3)
        self._reach_px = self.focal_px + np.hypot(width, height) / 2

    def _motion(self, t_us: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and yaw, pitch, roll (rad): sums of slow sines, all zero at t = 0 (3, or N x 3 for N
        times)."""
        t = (np.asarray(t_us, np.float64) % self.period_us) / 1e6
        w = self._w
        p = np.stack([0.4 * np.sin(w * t), 0.15 * np.sin(2 * w * t), 0.5 * (1 - np.cos(w * t))], axis=-1)
        a = np.stack([0.25 * np.sin(w * t), 0.1 * np.sin(3 * w * t), 0.08 * np.sin(2 * w * t)], axis=-1)
        return p, a

    def rotation(self, t_us: float | np.ndarray) -> Rotation:
        return Rotation.from_euler("YXZ", self._motion(t_us)[1])

    def position(self, t_us: float | np.ndarray) -> np.ndarray:
        """This camera's centre in the world (m): the body's plus its rotated offset (3, or N x 3)."""
        return self._motion(t_us)[0] + self.rotation(t_us).apply(self.T_body_cam[:3, 3])

    def pose(self, t_us: float) -> tuple[np.ndarray, np.ndarray]:
        """Position (m) and quaternion x y z w of T_world_cam."""
        return self.position(t_us), self.rotation(t_us).as_quat()

    def omega(self, t_us: float | np.ndarray) -> np.ndarray:
        """The body rate (rad/s, in the camera's frame; 3, or N x 3)."""
        h = 50.0
        return (self.rotation(t_us - h).inv() * self.rotation(t_us + h)).as_rotvec() / (2 * h * 1e-6)

    def max_speed_px_s(self, t_us: float) -> float:
        h = 500.0
        v = np.linalg.norm(self.position(t_us + h) - self.position(t_us - h)) / (2 * h * 1e-6)
        return float(np.linalg.norm(self.omega(t_us)) * self._reach_px + v / 0.5 * self.focal_px)

    def _hits(self, t_us: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per pixel: ray length to the nearest surface, and the texture pixel seen there (x, y)."""
        return _ray_cast(self.position(t_us), self.rotation(t_us).as_matrix(), self._rays, self._planes,
                         self._box_lo, self._box_hi, TEXTURE_PX_PER_M, float(self._log_tex.shape[0]))

    def render(self, t_us: float) -> np.ndarray:
        _, u, v = self._hits(t_us)
        map_x, map_y = u.reshape(self.height, self.width), v.reshape(self.height, self.width)
        return cv2.remap(self._log_tex, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def depth(self, t_us: float) -> np.ndarray:
        """Metric depth (z in the camera frame) of every pixel, float32, NaN where nothing is hit."""
        s, _, _ = self._hits(t_us)
        z = s * self._rays[:, 2]
        return np.where(np.isfinite(z), z, np.nan).astype(np.float32).reshape(self.height, self.width)
