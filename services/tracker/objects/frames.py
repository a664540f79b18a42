"""Adaptive event-frame formation (seed 002): the window moves between time-based and count-based.

Each update forms candidate frames, the events of the last `dt_us` and the last `n` events (plus a
time window 0.7x and 1.4x as long, so the window can move even when the event rate is steady),
scores them, keeps the best, and carries its extent over to both rules: `n` becomes the events it
held and `dt_us` the time it spanned. A slow target thus gets a longer window and a fast one a
shorter one, without a hand-set constant.

Seed 002 scores frames with a small learned network; here the score is hand-made and cheap:
*structure* (the share of event pixels with enough active neighbours, low for a too-short, noisy
window) times *sharpness* (edge strength per event, low for a too-long, smeared one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from services.tracker.objects.activity import count_into


@dataclass
class AdaptiveParams:
    dt_us: int = 30_000  # the starting time window
    min_dt_us: int = 5_000
    max_dt_us: int = 200_000
    min_events: int = 200


def frame_quality(image: np.ndarray) -> float:
    """Structure x sharpness of an image of event counts (whole numbers; see the module's note); 0 for an
    empty one."""
    total = float(cv2.sumElems(image)[0])
    if total <= 0:
        return 0.0
    active = image > 0
    neighbours = cv2.boxFilter(active.view(np.uint8), cv2.CV_16U, (5, 5), normalize=False)
    structure = np.count_nonzero(active & (neighbours >= 6)) / max(np.count_nonzero(active), 1)
    clipped = np.minimum(image, 3).astype(np.uint8)  # whole counts, so 8 bits and exact integer gradients
    sharpness = (cv2.norm(cv2.Sobel(clipped, cv2.CV_16S, 1, 0, ksize=3), cv2.NORM_L1)
                 + cv2.norm(cv2.Sobel(clipped, cv2.CV_16S, 0, 1, ksize=3), cv2.NORM_L1)) / total
    return float(structure * sharpness)


class AdaptiveWindow:
    """Keeps the recent events; `generate(t)` returns the best of the candidate frames."""

    def __init__(self, width: int, height: int, params: AdaptiveParams | None = None) -> None:
        self.width, self.height = width, height
        self.params = params or AdaptiveParams()
        self.dt_us = self.params.dt_us
        self.n: int | None = None
        self.image = np.zeros((height, width), np.float32)
        self._recent = RecentEvents()
        self.chosen = ""  # "time" or "count", for inspection

    def accept(self, events: np.ndarray) -> None:
        if len(events):
            self._recent.append(events)

    def generate(self, t_us: int) -> np.ndarray:
        p = self.params
        recent = self._recent
        recent.drop_before(t_us - p.max_dt_us)
        t, x, y = recent.columns()
        n = max(self.n if self.n is not None else 0, p.min_events)
        # seed 002's two candidates, plus a shorter and a longer time window so the window can move
        # when the event rate does not; each the events from a start index on
        starts = [max(len(t) - n, 0)]
        for dt in (self.dt_us, self.dt_us * 0.7, self.dt_us * 1.4):
            dt = float(np.clip(dt, p.min_dt_us, p.max_dt_us))
            starts.append(int(np.searchsorted(t, math.ceil(t_us - dt), side="left")))  # ints: no cast of t
        # the candidates are suffixes of one another: their images are built in one pass, shortest first
        images: list[np.ndarray] = [self.image] * len(starts)
        counts, end = np.zeros((self.height, self.width), np.int32), len(t)
        for k in sorted(range(len(starts)), key=lambda k: -starts[k]):
            count_into(counts, x[starts[k]:end], y[starts[k]:end], 0)
            end = starts[k]
            images[k] = counts.copy()
        best = int(np.argmax([frame_quality(img) for img in images]))  # of equal ones, the first
        self.chosen, self.image = ("count" if best == 0 else "time"), images[best].astype(np.float32)
        first = starts[best]
        self.n = max(len(t) - first, p.min_events)
        span = t_us - int(t[first]) if first < len(t) else self.dt_us
        self.dt_us = int(np.clip(span, p.min_dt_us, p.max_dt_us))
        return self.image

    def reset(self) -> None:
        self._recent = RecentEvents()
        self.dt_us, self.n = self.params.dt_us, None


class RecentEvents:
    """Events as contiguous columns (t, x, y) that grow at the end and are dropped from the front,
    in place: copying a window's worth of events every update cost more than scoring its frames."""

    def __init__(self, capacity: int = 4096) -> None:
        self._t = np.zeros(capacity, np.int64)
        self._x = np.zeros(capacity, np.uint16)
        self._y = np.zeros(capacity, np.uint16)
        self._lo = self._hi = 0

    def append(self, events: np.ndarray) -> None:
        n, live = len(events), self._hi - self._lo
        if self._hi + n > len(self._t):  # full: move the live part to the front, in bigger arrays if need be
            size = max(len(self._t), 2 * (live + n))
            for name in ("_t", "_x", "_y"):
                old = getattr(self, name)
                new = old if size == len(old) else np.zeros(size, old.dtype)
                new[:live] = old[self._lo:self._hi]
                setattr(self, name, new)
            self._lo, self._hi = 0, live
        end = self._hi + n
        self._t[self._hi:end], self._x[self._hi:end], self._y[self._hi:end] = events["t"], events["x"], events["y"]
        self._hi = end

    def drop_before(self, t_us: int) -> None:
        self._lo += int(np.searchsorted(self._t[self._lo:self._hi], t_us, side="left"))

    def columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Views of the live events' times, columns and rows."""
        live = slice(self._lo, self._hi)
        return self._t[live], self._x[live], self._y[live]
