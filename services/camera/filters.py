"""Event filters, composable in a chain (tonic's transforms in shape, dv-processing's verbs in use).

Each filter is a small object called on a packet of events (EVENT_DTYPE, sorted by time) that
returns the events it keeps; state (last times per pixel, learnt hot pixels) carries over from
packet to packet, so a live stream and a file are filtered alike. Per-event loops are numba kernels.
A chain is written on the command line as `name[:args]` items, e.g.
`ba:2000 refractory:500 roi:0,0,320,200 polarity:on hotpixels undistort`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numba
import numpy as np

from services import events as ev_ops
from services.messages import EVENT_DTYPE

if TYPE_CHECKING:
    from services.camera.formats import Recording


@numba.njit(cache=True, nogil=True)
def _ba_kernel(events, support, out, window_us, width, height, base_us):  # noqa: ANN001, ANN202
    """Keep an event when a neighbour (8-connected, not itself) fired within `window_us` before it.

    Each event stamps its time (int32, relative to `base_us`: half the memory traffic of int64) on
    its 8 neighbours in `support`, which is padded by one pixel all round so that nothing needs a
    bounds check; an event is then kept by one read of its own pixel there. Kept events are copied
    to the front of `out`; their count is returned."""
    n = 0
    for i in range(len(events)):
        e = events[i]
        x, y = np.int64(e.x), np.int64(e.y)
        if x >= width or y >= height:
            continue
        t = np.int32(e.t - base_us)
        if np.int64(t) - support[y + 1, x + 1] <= window_us:
            out[n] = e
            n += 1
        for dy in range(3):
            for dx in range(3):
                if dy != 1 or dx != 1:
                    support[y + dy, x + dx] = t
    return n


@numba.njit(cache=True, nogil=True)
def _refractory_kernel(events, last, out, period_us, width, height):  # noqa: ANN001, ANN202
    """Drop an event when its own pixel fired less than `period_us` before; copy the kept ones to
    the front of `out` and return their count."""
    n = 0
    for i in range(len(events)):
        e = events[i]
        if e.x >= width or e.y >= height:
            continue
        if e.t - last[e.y, e.x] >= period_us:
            last[e.y, e.x] = e.t
            out[n] = e
            n += 1
    return n


def _inside(events: np.ndarray, width: int, height: int) -> np.ndarray:
    return events[(events["x"] < width) & (events["y"] < height)]


class BackgroundActivity:
    """Background-activity filter: noise events are isolated in space and time, signal is not."""

    REBASE_US = 1 << 30  # int32 times relative to a base that moves on every ~18 minutes

    def __init__(self, width: int, height: int, window_us: int = 2000) -> None:
        self.width, self.height, self.window_us = width, height, int(window_us)
        self._never = np.iinfo(np.int32).min // 2
        self._support = np.full((height + 2, width + 2), self._never, np.int32)
        self._base: int | None = None

    def __call__(self, events: np.ndarray) -> np.ndarray:
        if not len(events):
            return events
        last = int(events["t"][-1])
        if self._base is None:
            self._base = int(events["t"][0])
        elif last - self._base > self.REBASE_US:  # keep relative times inside int32
            shift = last - self._base - (self.REBASE_US >> 1)
            self._support = np.maximum(self._support.astype(np.int64) - shift, self._never).astype(np.int32)
            self._base += shift
        out = np.empty(len(events), EVENT_DTYPE)
        n = _ba_kernel(events, self._support, out, self.window_us, self.width, self.height, self._base)
        return out[:n]


class Refractory:
    """At most one event per pixel per `period_us`."""

    def __init__(self, width: int, height: int, period_us: int = 500) -> None:
        self.width, self.height, self.period_us = width, height, int(period_us)
        self._last = np.full((height, width), np.iinfo(np.int64).min // 2, np.int64)

    def __call__(self, events: np.ndarray) -> np.ndarray:
        out = np.empty(len(events), EVENT_DTYPE)
        return out[:_refractory_kernel(events, self._last, out, self.period_us, self.width, self.height)]


class Mask:
    """Keep events where `mask` is true: a region of interest, or an image that blacks out pixels
    (blinking LEDs, the drone's own propellers)."""

    def __init__(self, mask: np.ndarray) -> None:
        self.mask = np.asarray(mask, bool)

    @classmethod
    def roi(cls, width: int, height: int, x: int, y: int, w: int, h: int) -> Mask:
        mask = np.zeros((height, width), bool)
        mask[y:y + h, x:x + w] = True
        return cls(mask)

    @classmethod
    def from_image(cls, path: str | Path, width: int, height: int) -> Mask:
        img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"mask image {path} cannot be read")
        if img.shape != (height, width):
            raise ValueError(f"mask image {path} is {img.shape[1]}x{img.shape[0]}, the sensor {width}x{height}")
        return cls(img > 127)

    def __call__(self, events: np.ndarray) -> np.ndarray:
        events = _inside(events, self.mask.shape[1], self.mask.shape[0])
        return events[self.mask[events["y"], events["x"]]]


class Polarity:
    """Keep one polarity (1 = ON, 0 = OFF)."""

    def __init__(self, keep: int) -> None:
        self.keep = int(keep)

    def __call__(self, events: np.ndarray) -> np.ndarray:
        return events[events["p"] == self.keep]


class HotPixels:
    """Learns, over the first `learn_us` of the stream, the pixels that fire far more than the rest
    (more than `factor` times the 99.9th percentile of pixel counts), then drops their events."""

    def __init__(self, width: int, height: int, learn_us: int = 1_000_000, factor: float = 5.0) -> None:
        self.width, self.height, self.learn_us, self.factor = width, height, learn_us, factor
        self._counts = np.zeros(width * height, np.int64)
        self._start: int | None = None
        self.hot: np.ndarray | None = None  # learnt mask of hot pixels

    def __call__(self, events: np.ndarray) -> np.ndarray:
        events = _inside(events, self.width, self.height)
        if not len(events):
            return events
        idx = events["y"].astype(np.int64) * self.width + events["x"]
        if self.hot is None:
            self._start = int(events["t"][0]) if self._start is None else self._start
            self._counts += np.bincount(idx, minlength=self.width * self.height)
            if int(events["t"][-1]) - self._start >= self.learn_us:
                active = self._counts[self._counts > 0]
                limit = self.factor * max(np.percentile(active, 99.9), 1.0) if len(active) else np.inf
                self.hot = self._counts > limit
            return events
        return events[~self.hot[idx]]


class Undistort:
    """Moves each event to its undistorted pixel (a lookup table made once from the calibration);
    events that land outside the image are dropped."""

    def __init__(self, width: int, height: int, K: np.ndarray, dist_model: str, dist: np.ndarray) -> None:
        self.width, self.height = width, height
        ys, xs = np.mgrid[0:height, 0:width]
        pts = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64).reshape(-1, 1, 2)
        if dist_model == "equidistant":
            und = cv2.fisheye.undistortPoints(pts, K, np.asarray(dist[:4], np.float64), P=K)
        else:
            und = cv2.undistortPoints(pts, K, np.asarray(dist, np.float64), P=K)
        und = np.rint(und.reshape(-1, 2)).astype(np.int64)
        self._ok = (und[:, 0] >= 0) & (und[:, 0] < width) & (und[:, 1] >= 0) & (und[:, 1] < height)
        self._x, self._y = und[:, 0].astype(np.uint16), und[:, 1].astype(np.uint16)

    @classmethod
    def of(cls, rec: Recording) -> Undistort | None:
        """The undistortion of a recording's calibration; None where it has no distortion to undo."""
        cal = rec.calibration
        return None if cal is None else cls.needed(rec.width, rec.height, rec.K_or_default(), cal.dist_model,
                                                    cal.dist)

    @classmethod
    def needed(cls, width: int, height: int, K: np.ndarray, dist_model: str,
               dist: np.ndarray | None) -> Undistort | None:
        """The undistortion of a camera's calibration (a file's, a CameraInfo's); None where there is none to undo."""
        if dist_model == "none" or dist is None or not np.any(dist):
            return None
        return cls(width, height, K, dist_model, dist)

    def __call__(self, events: np.ndarray) -> np.ndarray:
        events = _inside(events, self.width, self.height)
        idx = events["y"].astype(np.int64) * self.width + events["x"]
        keep = self._ok[idx]
        out = ev_ops.take(events, keep)  # a copy: the input may be a read-only view on a message
        out["x"], out["y"] = self._x[idx[keep]], self._y[idx[keep]]
        return out


class FilterChain:
    """Filters applied in order."""

    def __init__(self, filters: Sequence) -> None:
        self.filters = list(filters)

    def __call__(self, events: np.ndarray) -> np.ndarray:
        for f in self.filters:
            if not len(events):
                break
            events = f(events)
        return events


def parse_chain(specs: Sequence[str], width: int, height: int, K: np.ndarray | None = None,
                dist_model: str = "none", dist: np.ndarray | None = None) -> FilterChain:
    """A chain from command-line items `name[:args]`; ValueError naming the item at fault."""
    filters = []
    for spec in specs:
        name, _, arg = spec.partition(":")
        try:
            if name == "ba":
                filters.append(BackgroundActivity(width, height, int(arg or 2000)))
            elif name == "refractory":
                filters.append(Refractory(width, height, int(arg or 500)))
            elif name == "roi":
                x, y, w, h = (int(v) for v in arg.split(","))
                filters.append(Mask.roi(width, height, x, y, w, h))
            elif name == "mask":
                filters.append(Mask.from_image(arg, width, height))
            elif name == "polarity":
                filters.append(Polarity({"on": 1, "off": 0}[arg]))
            elif name == "hotpixels":
                filters.append(HotPixels(width, height, int(arg or 1_000_000)))
            elif name == "undistort":
                if K is None or dist is None or dist_model == "none":
                    raise ValueError("the source has no distortion calibration")
                filters.append(Undistort(width, height, K, dist_model, dist))
            else:
                raise ValueError("unknown filter (ba, refractory, roi, mask, polarity, hotpixels, undistort)")
        except (ValueError, KeyError) as exc:
            raise ValueError(f"filter {spec!r}: {exc}") from None
    return FilterChain(filters)
