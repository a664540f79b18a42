"""A simulated IMU on the moving camera of the `6dof` and `stereo` scenes, as the DAVIS346's and the
DVXplorer's built-in ones: gyro and accelerometer samples in the camera's frame at a fixed rate.

The rates are the scene's exact motion (its body rate, `omega`, and the specific force from the second
difference of its position, less gravity), plus each sensor's white
noise and a constant bias drawn per seed: a MEMS gyro that was not calibrated at rest is off by some
tenths of a degree per second, which over seconds is degrees of orientation, so whoever uses it must
estimate that bias. Gravity points along the world's +y (down: the world is the first camera's frame
at t = 0, x right, y down, z forward).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy.spatial.transform import Rotation

from services.camera.simulator import SimParams

GRAVITY_M_S2 = 9.81
STEP_US = 1_000  # the second difference's half step


class MovingCamera(Protocol):
    def rotation(self, t_us: np.ndarray) -> Rotation: ...  # camera to world, one per time

    def omega(self, t_us: np.ndarray) -> np.ndarray: ...  # body rate (rad/s, camera frame), N x 3

    def position(self, t_us: np.ndarray) -> np.ndarray: ...  # camera centre in the world (m), N x 3


class SimulatedImu:
    """Samples (t_us, gyro rad/s N x 3, accel m/s^2 N x 3) of a camera moving as `camera` says, at the sample
    times in a span; the same seed gives the same biases and noise for the same spans asked in order."""

    def __init__(self, camera: MovingCamera, params: SimParams | None = None, seed: int = 0) -> None:
        """`params`: the rate and noise (`imu_rate_hz`, `gyro_noise`, `gyro_bias`, `accel_noise`, `accel_bias`)."""
        self.camera, self.noise = camera, params or SimParams()
        self._rng = np.random.default_rng([seed, 0x1A0])
        self.gyro_bias = np.radians(self.noise.gyro_bias) * self._rng.standard_normal(3)
        self.accel_bias = self.noise.accel_bias * self._rng.standard_normal(3)
        self.period_us = 1e6 / self.noise.imu_rate_hz

    def samples(self, since_us: int, until_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The samples with times in (since_us, until_us]."""
        first = np.floor(since_us / self.period_us) + 1
        t = np.round(np.arange(first, np.floor(until_us / self.period_us) + 1) * self.period_us).astype(np.int64)
        gyro, accel = self.exact(t)
        n = self.noise
        root_rate = np.sqrt(n.imu_rate_hz)
        gyro += self.gyro_bias + np.radians(n.gyro_noise) * root_rate * self._rng.standard_normal(gyro.shape)
        accel += self.accel_bias + n.accel_noise * root_rate * self._rng.standard_normal(accel.shape)
        return t, gyro, accel

    def exact(self, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The noiseless body rate (rad/s) and specific force (m/s^2) in the camera's frame at times `t_us`."""
        t = np.asarray(t_us, np.float64)
        h = STEP_US
        gyro = self.camera.omega(t)
        p = [self.camera.position(t + d) for d in (-h, 0, h)]
        accel_world = (p[2] - 2 * p[1] + p[0]) / (h * 1e-6) ** 2
        gravity = np.array([0.0, GRAVITY_M_S2, 0.0])
        return gyro.reshape(-1, 3), self.camera.rotation(t).inv().apply(accel_world - gravity).reshape(-1, 3)
