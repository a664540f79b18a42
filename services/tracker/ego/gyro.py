"""The camera's turn between two times from its IMU's gyro, with the gyro's bias learnt from the vision.

Aligning a map to the events leaves one motion poorly told: a small sideways move and a small turn about
the axis across it shift the image alike, more so where the scene is far and flat. Left to the events
and a constant-velocity prediction, the pose can run away along it (seen on the `6dof` scenes at a steady
inlier share). A gyro tells the turn alone, to a fraction of a degree over a second: the 6-DoF tracker
predicts its rotation from it and holds the rotation close to that prediction, leaving the events to
tell the translation.

A MEMS gyro's bias (tenths of a degree per second, unless calibrated at rest) would turn that into a
slow drift of orientation; each good estimate's turn since the one before, against the gyro's over the
same span, corrects the bias estimate a little (`bias_gain`: a time constant of about a second at 50
updates a second, long enough to average out the per-update error of the vision).
"""

from __future__ import annotations

import threading

import cv2
import numpy as np


class Gyro:
    """Gyro samples in (from any thread), the rotation between two times out (`turn`), the bias learnt
    from the turns the vision measured (`learn`); samples no span will start in again are let go (`forget_before`)."""

    def __init__(self, bias_gain: float = 0.02, max_gap_us: int = 20_000) -> None:
        """`max_gap_us`: the most the samples may end before a span's end (live, they may lag the events a
        little), or miss within it, for `turn` to tell it."""
        self.bias = np.zeros(3)
        self.bias_gain, self.max_gap_us = bias_gain, max_gap_us
        self._t = np.zeros(0, np.int64)
        self._w = np.zeros((0, 3))
        self._lock = threading.Lock()

    def add(self, t_us: np.ndarray, gyro: np.ndarray) -> None:
        """Samples (t_us, rad/s N x 3 in the camera's frame), in any order; times at or before the latest added
        before are left out."""
        order = np.argsort(np.asarray(t_us, np.int64).ravel(), kind="stable")
        t_us = np.asarray(t_us, np.int64).ravel()[order]
        gyro = np.asarray(gyro, np.float64).reshape(-1, 3)[order]
        with self._lock:
            newer = t_us > (self._t[-1] if len(self._t) else np.iinfo(np.int64).min)
            self._t, self._w = np.concatenate([self._t, t_us[newer]]), np.concatenate([self._w, gyro[newer]])

    def forget_before(self, t_us: int) -> None:
        """Lets go of the samples no span from `t_us` on needs (all before it but the latest)."""
        with self._lock:
            first = max(int(np.searchsorted(self._t, t_us, side="right")) - 1, 0)
            self._t, self._w = self._t[first:], self._w[first:]

    def turn(self, t0_us: int, t1_us: int) -> np.ndarray | None:
        """R_c0_c1: the camera's rotation at `t1_us` in its frame at `t0_us` (R_world_cam(t1) = R_world_cam(t0)
        @ it), less the bias; None where the samples do not cover the span. Each sample's rate holds from its
        time to the next's (the last one's to `t1_us`); the turns are summed as rotation vectors, which over
        the span of an update (20 ms) differs from their product by far less than the gyro's noise."""
        with self._lock:
            t, w = self._t, self._w
        if t1_us <= t0_us or not len(t) or t[0] > t0_us or t[-1] < t1_us - self.max_gap_us:
            return None
        lo = max(int(np.searchsorted(t, t0_us, side="right")) - 1, 0)
        hi = int(np.searchsorted(t, t1_us, side="left"))
        edges = np.clip(np.append(t[lo:hi], t1_us), t0_us, t1_us)
        dt = np.diff(edges).astype(np.float64) / 1e6
        if len(dt) and dt.max() > self.max_gap_us / 1e6:
            return None
        rotvec = ((w[lo:hi] - self.bias) * dt[:, None]).sum(axis=0)
        return cv2.Rodrigues(rotvec.reshape(3, 1))[0]

    def learn(self, t0_us: int, t1_us: int, seen: np.ndarray) -> None:
        """The vision's rotation R_c0_c1 over a span: the bias moves towards what makes the gyro's agree."""
        gyro = self.turn(t0_us, t1_us)
        if gyro is None:
            return
        off = cv2.Rodrigues(gyro.T @ seen)[0].ravel() / ((t1_us - t0_us) / 1e6)  # what the gyro missed, rad/s
        self.bias = self.bias - self.bias_gain * off
