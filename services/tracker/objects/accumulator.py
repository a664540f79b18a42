"""Exponentially decayed event-count image (a leaky integrator per pixel), as in seeds 002 and 003.

Events only append on `accept`; the image is formed once per `generate`, with each event weighted
by ``exp(-(t_now - t_event) / tau)`` through one `np.bincount`, so per-event work stays vectorised.
"""

from __future__ import annotations

import numpy as np

from services import events


class DecayedAccumulator:
    """Accepts event arrays and generates the decayed count image at a given time (us)."""

    def __init__(self, width: int, height: int, tau_us: float = 30_000.0) -> None:
        self.width, self.height = width, height
        self.tau_us = float(tau_us)
        self.image = np.zeros((height, width), np.float32)
        self.t_us: int | None = None
        self._pending: list[np.ndarray] = []

    def accept(self, events: np.ndarray) -> None:
        if len(events):
            self._pending.append(events)

    def generate(self, t_us: int) -> np.ndarray:
        """The decayed image at `t_us` (later than every accepted event); the same array each call."""
        if self.t_us is not None:
            self.image *= np.float32(np.exp(-max(t_us - self.t_us, 0) / self.tau_us))
        if self._pending:
            ev = events.concat(self._pending) if len(self._pending) > 1 else self._pending[0]
            self._pending = []
            inside = (ev["x"] < self.width) & (ev["y"] < self.height)
            ev = events.take(ev, inside)
            weights = np.exp(-np.maximum(t_us - ev["t"], 0) / self.tau_us)
            idx = ev["y"].astype(np.int64) * self.width + ev["x"]
            counts = np.bincount(idx, weights, self.width * self.height)
            self.image += counts.reshape(self.image.shape).astype(np.float32)
        self.t_us = t_us
        return self.image

    def reset(self) -> None:
        self.image[:] = 0
        self._pending = []
        self.t_us = None
