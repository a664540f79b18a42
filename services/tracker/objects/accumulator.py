"""Exponentially decayed event-count image (a leaky integrator per pixel), as in seeds 002 and 003.

Events only append on `accept`; the image is formed once per `generate`: the old image is decayed
by one multiply and each new event adds ``w * exp(-(t_now - t_event) / tau)``.
Weights that decay below `FLOOR` are set to zero: left alone they become subnormal floats, on which
every multiply is some twenty times slower (the decay then cost more than all the rest of an update).
"""

from __future__ import annotations

import math

import numba
import numpy as np

FLOOR = 1e-3  # far below any weight a detector looks at (an event some 7 tau ago)


class DecayedAccumulator:
    """Accepts event arrays (with optional weights) and generates the decayed count image at a time (us)."""

    def __init__(self, width: int, height: int, tau_us: float = 30_000.0) -> None:
        self.width, self.height = width, height
        self.tau_us = float(tau_us)
        self.image = np.zeros((height, width), np.float32)
        self.t_us: int | None = None
        self._pending: list[tuple[np.ndarray, np.ndarray | None]] = []

    def accept(self, events: np.ndarray, weights: np.ndarray | None = None) -> None:
        if len(events):
            self._pending.append((events, weights))

    def generate(self, t_us: int) -> np.ndarray:
        """The decayed image at `t_us` (later than every accepted event); the same array each call."""
        if self.t_us is not None:
            _decay(self.image.reshape(-1), np.float32(math.exp(-max(t_us - self.t_us, 0) / self.tau_us)),
                   np.float32(FLOOR))
        for ev, weights in self._pending:
            # float32 exp over the whole array is SIMD; per event in the scatter loop it costs twice as much
            value = np.exp(np.minimum(ev["t"] - t_us, 0).astype(np.float32) * np.float32(1.0 / self.tau_us))
            if weights is not None:
                value *= weights
            _scatter_add(self.image, ev["x"], ev["y"], value)
        self._pending = []
        self.t_us = t_us
        return self.image

    def reset(self) -> None:
        self.image[:] = 0
        self._pending = []
        self.t_us = None


def to_uint8(image: np.ndarray) -> np.ndarray:
    """A decayed image as 8 bits for OpenCV's detectors: three recent events saturate a pixel."""
    return np.clip(image * 85.0, 0, 255).astype(np.uint8)


@numba.njit(cache=True, nogil=True)
def _scatter_add(image, xs, ys, values):  # noqa: ANN001, ANN202 - numba kernel
    h, w = image.shape
    for i in range(len(xs)):
        x, y = xs[i], ys[i]
        if x < w and y < h:
            image[y, x] += values[i]


@numba.njit(cache=True, nogil=True)
def _decay(flat, factor, floor):  # noqa: ANN001, ANN202 - numba kernel
    for i in range(flat.size):
        v = flat[i] * factor
        flat[i] = v if v >= floor else 0.0
