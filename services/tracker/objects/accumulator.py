"""Exponentially decayed event-count image (a leaky integrator per pixel), as in seeds 002 and 003.

Events only append on `accept`; the image is formed once per `generate`: the old image is decayed
by one multiply and each new event adds ``w * exp(-(t_now - t_event) / tau)``.
Weights that decay below `FLOOR` are set to zero: left alone they become subnormal floats, on which
every multiply is some twenty times slower (the decay then cost more than all the rest of an update).
An event's weight is read from a table of ``exp(-k / tau)`` for every whole microsecond ``k`` up to
where it falls below `FLOOR` (older events add nothing), so adding events is one pass with no exp.
"""

from __future__ import annotations

import math

import numba
import numpy as np

FLOOR = 1e-3  # far below any weight a detector looks at (an event some 7 tau ago)
_UNWEIGHTED = np.ones(1, np.float32)  # `_add`'s weights where every event weighs 1


class DecayedAccumulator:
    """Accepts event arrays (with optional weights) and generates the decayed count image at a time (us)."""

    def __init__(self, width: int, height: int, tau_us: float = 30_000.0) -> None:
        self.width, self.height = width, height
        self.tau_us = float(tau_us)
        self.image = np.zeros((height, width), np.float32)
        self.t_us: int | None = None
        self._pending: list[tuple[np.ndarray, np.ndarray | None]] = []
        age_us = np.arange(math.ceil(self.tau_us * -math.log(FLOOR)), dtype=np.float32)
        self._weight_by_age = np.exp(age_us * np.float32(-1.0 / self.tau_us))

    def accept(self, events: np.ndarray, weights: np.ndarray | None = None) -> None:
        if len(events):
            self._pending.append((events, weights))

    def generate(self, t_us: int) -> np.ndarray:
        """The decayed image at `t_us` (later than every accepted event); the same array each call."""
        if self.t_us is not None:
            _decay(self.image.reshape(-1), np.float32(math.exp(-max(t_us - self.t_us, 0) / self.tau_us)),
                   np.float32(FLOOR))
        for ev, weights in self._pending:
            _add(self.image, ev["x"], ev["y"], ev["t"], t_us, self._weight_by_age,
                 _UNWEIGHTED if weights is None else weights)
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
def _add(image, xs, ys, ts, t_now, weight_by_age, weights):  # noqa: ANN001, ANN202 - numba kernel
    """Each event adds its weight at its age (us) to its pixel, times its own weight when `weights`
    holds one per event (a single entry: all weigh 1)."""
    h, w = image.shape
    n_ages = len(weight_by_age)
    each = len(weights) == len(xs)
    for i in range(len(xs)):
        x, y = xs[i], ys[i]
        age = max(t_now - ts[i], 0)
        if x < w and y < h and age < n_ages:
            image[y, x] += weight_by_age[age] * weights[i] if each else weight_by_age[age]


@numba.njit(cache=True, nogil=True)
def _decay(flat, factor, floor):  # noqa: ANN001, ANN202 - numba kernel
    for i in range(flat.size):
        v = flat[i] * factor
        flat[i] = v if v >= floor else 0.0
