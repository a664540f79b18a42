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

from dataclasses import dataclass

import cv2
import numpy as np

from services import events as ev_ops


@dataclass
class AdaptiveParams:
    dt_us: int = 30_000  # the starting time window
    min_dt_us: int = 5_000
    max_dt_us: int = 200_000
    min_events: int = 200


def frame_quality(image: np.ndarray) -> float:
    """Structure x sharpness of an event-count image (see the module's note); 0 for an empty one."""
    total = float(image.sum())
    if total <= 0:
        return 0.0
    active = (image > 0).astype(np.float32)
    neighbours = cv2.boxFilter(active, -1, (5, 5), normalize=False)
    structure = float((active * (neighbours >= 6)).sum() / max(active.sum(), 1.0))
    clipped = np.minimum(image, 3.0)
    gx = cv2.Sobel(clipped, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(clipped, cv2.CV_32F, 0, 1, ksize=3)
    sharpness = float(np.abs(gx).sum() + np.abs(gy).sum()) / total
    return structure * sharpness


class AdaptiveWindow:
    """Keeps the recent events; `generate(t)` returns the better of the two candidate frames."""

    def __init__(self, width: int, height: int, params: AdaptiveParams | None = None) -> None:
        self.width, self.height = width, height
        self.params = params or AdaptiveParams()
        self.dt_us = self.params.dt_us
        self.n: int | None = None
        self.image = np.zeros((height, width), np.float32)
        self._buffer = np.zeros(0, ev_ops.EVENT_DTYPE)
        self._pending: list[np.ndarray] = []
        self.chosen = ""  # "time" or "count", for inspection

    def accept(self, events: np.ndarray) -> None:
        if len(events):
            self._pending.append(events)

    def generate(self, t_us: int) -> np.ndarray:
        p = self.params
        if self._pending:
            self._buffer = ev_ops.concat([self._buffer, *self._pending])
            self._pending = []
        first = int(np.searchsorted(self._buffer["t"], t_us - p.max_dt_us, side="left"))
        if first:
            self._buffer = self._buffer[first:]
        buf = self._buffer
        n = max(self.n if self.n is not None else 0, p.min_events)
        # seed 002's two candidates, plus a shorter and a longer time window so the window can move
        # when the event rate does not
        candidates = [buf[max(len(buf) - n, 0):]]
        for dt in (self.dt_us, self.dt_us * 0.7, self.dt_us * 1.4):
            dt = float(np.clip(dt, p.min_dt_us, p.max_dt_us))
            candidates.append(buf[int(np.searchsorted(buf["t"], t_us - dt, side="left")):])
        images = [self._image(c) for c in candidates]
        best = int(np.argmax([frame_quality(img) for img in images]))
        chosen = candidates[best]
        self.chosen, self.image = ("count" if best == 0 else "time"), images[best]
        self.n = max(len(chosen), p.min_events)
        span = t_us - int(chosen["t"][0]) if len(chosen) else self.dt_us
        self.dt_us = int(np.clip(span, p.min_dt_us, p.max_dt_us))
        return self.image

    def _image(self, events: np.ndarray) -> np.ndarray:
        inside = (events["x"] < self.width) & (events["y"] < self.height)
        idx = events["y"][inside].astype(np.int64) * self.width + events["x"][inside]
        return np.bincount(idx, minlength=self.width * self.height).reshape(self.height, self.width).astype(np.float32)

    def reset(self) -> None:
        self._buffer = np.zeros(0, ev_ops.EVENT_DTYPE)
        self._pending = []
        self.dt_us, self.n = self.params.dt_us, None
