"""`rotation`: a camera spinning in place (up to ~1000 deg/s) inside a textured panorama (seed 000).

The world is an equirectangular panorama at infinity; the camera's orientation follows smooth
periodic yaw, pitch and roll, so ground truth (T_world_cam, angular velocity) is exact at any time.
The world frame is the camera's frame at t = 0 (x right, y down, z forward).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from services.camera.simulator import LOG_EPS, _texture


class RotationScene:
    """Renders log intensity for the camera orientation at any time; see the module docstring."""

    def __init__(self, width: int = 346, height: int = 260, seed: int = 0, max_omega_deg_s: float = 800.0,
                 period_s: float = 8.0, panorama_size: tuple[int, int] = (2048, 1024),
                 peak_deg_s: float | None = None) -> None:
        """Each angular rate is bounded by `max_omega_deg_s` (the sequence then peaks at 616 deg/s), or,
        with `peak_deg_s`, the whole motion is scaled so that the speed peaks at that."""
        self.width, self.height = width, height
        rng = np.random.default_rng(seed)
        self.focal_px = 0.9 * width
        pw, ph = panorama_size
        coarse = _texture(rng, ph // 4, pw // 4)  # blobs of ~25 px: a scene, not pixel noise
        pano = cv2.resize(coarse, (pw, ph), interpolation=cv2.INTER_CUBIC)
        for _ in range(60):  # sharp-edged patches: strong gradients for tracking and mosaicing
            x, y = rng.integers(0, pw - 80), rng.integers(ph // 4, 3 * ph // 4 - 60)
            pano[y:y + rng.integers(15, 60), x:x + rng.integers(15, 80)] = rng.uniform(0.1, 1.0)
        self.panorama = pano.astype(np.float32)
        self._log_pano = np.log(self.panorama + LOG_EPS)
        self.period_us = int(period_s * 1e6)
        w = 2 * np.pi / period_s
        peak = np.deg2rad(max_omega_deg_s)
        # amplitude x frequency bounds each angular rate; phases 0 start every rate at zero
        self._terms = [(0.7 * peak / w, w, 0.0), (0.3 * peak / (3 * w), 3 * w, 0.0)], \
                      [(0.12 * peak / (2 * w), 2 * w, 0.0)], [(0.08 * peak / (5 * w), 5 * w, 0.0)]
        if peak_deg_s is not None:
            for _ in range(4):  # the speed is nearly linear in the amplitudes: a few rescalings converge
                gain = np.deg2rad(peak_deg_s) / self.peak_speed()
                self._terms = tuple([(a * gain, w, ph) for a, w, ph in terms] for terms in self._terms)
        ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
        rays = np.stack([(xs - width / 2) / self.focal_px, (ys - height / 2) / self.focal_px, np.ones_like(xs)], -1)
        self._rays = (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).reshape(-1, 3)
        self._reach_px = self.focal_px + np.hypot(width, height) / 2

    def _angles(self, t_us: float | np.ndarray) -> np.ndarray:
        """Yaw, pitch, roll (3, or N x 3 for N times): each a sum of a (1 - cos(w t + ph)) terms, so the
        camera starts slowly."""
        t = (np.asarray(t_us, np.float64) % self.period_us) / 1e6
        return np.stack([sum(a * (np.cos(ph) - np.cos(w * t + ph)) for a, w, ph in terms) for terms in self._terms],
                        axis=-1)

    def peak_speed(self, samples: int = 8000) -> float:
        """The highest angular speed (rad/s) over a period."""
        t, h = np.linspace(0, self.period_us, samples, endpoint=False), 50.0
        before, after = (Rotation.from_euler("YXZ", self._angles(t + d)) for d in (-h, h))
        return float(np.linalg.norm((before.inv() * after).as_rotvec(), axis=1).max() / (2 * h * 1e-6))

    def rotation(self, t_us: float) -> Rotation:
        """R_world_cam: yaw about y (down), then pitch about x, then roll about z."""
        yaw, pitch, roll = self._angles(t_us)
        return Rotation.from_euler("YXZ", [yaw, pitch, roll])

    def omega(self, t_us: float) -> np.ndarray:
        """Angular velocity in the camera frame (rad/s), by a 0.1 ms central difference."""
        h = 50.0
        return (self.rotation(t_us - h).inv() * self.rotation(t_us + h)).as_rotvec() / (2 * h * 1e-6)

    def pose(self, t_us: float) -> tuple[np.ndarray, np.ndarray]:
        """Position (always 0) and quaternion x y z w of T_world_cam."""
        return np.zeros(3), self.rotation(t_us).as_quat()

    def max_speed_px_s(self, t_us: float) -> float:
        return float(np.linalg.norm(self.omega(t_us)) * self._reach_px)

    def render(self, t_us: float) -> np.ndarray:
        d = self._rays @ self.rotation(t_us).as_matrix().T  # world directions of every pixel
        lon = np.arctan2(d[:, 0], d[:, 2])
        lat = np.arcsin(np.clip(-d[:, 1], -1, 1))
        ph, pw = self.panorama.shape
        map_x = ((lon + np.pi) / (2 * np.pi) * pw).astype(np.float32).reshape(self.height, self.width)
        map_y = ((np.pi / 2 - lat) / np.pi * ph).astype(np.float32).reshape(self.height, self.width)
        return cv2.remap(self._log_pano, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
