"""Exponentially decayed event-count image (a leaky integrator per pixel), as in seeds 002 and 003.

Events only append on `accept`; the image is formed once per `generate`: the old image is decayed
by one multiply and each new event adds ``w * exp(-(t_now - t_event) / tau)`` in one compiled pass.
"""

from __future__ import annotations

import math

import numba
import numpy as np


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
            self.image *= np.float32(math.exp(-max(t_us - self.t_us, 0) / self.tau_us))
        for ev, weights in self._pending:
            w = np.zeros(0, np.float32) if weights is None else weights.astype(np.float32, copy=False)
            _add_decayed(self.image, ev["x"], ev["y"], ev["t"], w, t_us, 1.0 / self.tau_us)
        self._pending = []
        self.t_us = t_us
        return self.image

    def reset(self) -> None:
        self.image[:] = 0
        self._pending = []
        self.t_us = None


@numba.njit(cache=True, nogil=True)
def _add_decayed(image, xs, ys, ts, weights, t_now, inv_tau):  # noqa: ANN001, ANN202 - numba kernel
    h, w = image.shape
    weighted = len(weights) > 0
    for i in range(len(xs)):
        x, y = xs[i], ys[i]
        if x < w and y < h:
            age = t_now - ts[i]
            decay = math.exp(-age * inv_tau) if age > 0 else 1.0
            image[y, x] += (weights[i] if weighted else 1.0) * decay
