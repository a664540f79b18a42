"""Built-in event simulator, ESIM-like (Rebecq et al. 2018), with ground truth.

A scene renders log intensity at any time; `EventSimulator` keeps a per-pixel reference level and
emits an event each time the log intensity moves one contrast threshold C (with per-pixel mismatch)
away from it, timing each crossing by linear interpolation between two renders. The render rate
adapts so that nothing moves more than about one pixel between renders. A refractory period blinds
a pixel after it fires; background activity and hot pixels add noise. Every parameter is in
`SimParams`; the same seed gives the same events.

`ObjectsScene` is the static-camera scene of several textured rectangles of known metric size and
depth that move, stop and cross, with ground-truth boxes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol

import cv2
import numba
import numpy as np

from services import events
from services.camera.filters import Refractory
from services.messages import EVENT_DTYPE

LOG_EPS = 1e-3  # keeps log intensity finite on black
DURATION_S = 10.0  # `etam sim`'s default length: under `ObjectsScene`'s period, so its targets never come round again


class Scene(Protocol):
    """What the event simulator needs of a scene."""

    width: int
    height: int

    def render(self, t_us: float) -> np.ndarray: ...

    def max_speed_px_s(self, t_us: float) -> float: ...


@dataclass
class SimParams:
    """Event-generation parameters (contrast thresholds in log intensity units), and the IMU's."""

    contrast: float = 0.25
    contrast_sigma: float = 0.03  # per-pixel mismatch of the threshold
    refractory_us: int = 100  # a pixel that fired is blind this long
    noise_rate_hz: float = 0.05  # background activity per pixel
    hot_pixel_fraction: float = 1e-4  # pixels that fire on their own, far more than the rest
    hot_pixel_rate_hz: float = 100.0
    max_step_px: float = 1.0  # adaptive render rate: largest image motion between renders
    min_dt_us: int = 200
    max_dt_us: int = 5000
    # the IMU of the moving-camera scenes (`sim_imu.py`), an MPU-6500 / BMI160 class part
    imu_rate_hz: float = 1000.0
    gyro_noise: float = 0.01  # white noise density, deg/s/sqrt(Hz)
    gyro_bias: float = 0.5  # standard deviation of the constant bias on each axis, deg/s
    accel_noise: float = 0.003  # m/s^2/sqrt(Hz) (300 ug/sqrt(Hz))
    accel_bias: float = 0.05  # m/s^2

    @classmethod
    def parse(cls, items: list[str]) -> SimParams:
        """Parameters from `name=value` items; ValueError naming an unknown name or a bad value."""
        params = cls()
        kinds = {f.name: f.type for f in dataclasses.fields(cls)}
        for item in items:
            name, _, value = item.partition("=")
            if name not in kinds:
                raise ValueError(f"simulator parameter {name!r} is not one of {', '.join(kinds)}")
            try:
                setattr(params, name, (int if kinds[name] in (int, "int") else float)(value))
            except ValueError:
                raise ValueError(f"simulator parameter {name}={value!r}: expected a number") from None
        if params.imu_rate_hz <= 0:
            raise ValueError(f"simulator parameter imu_rate_hz={params.imu_rate_hz:g}: expected a positive rate")
        for name in ("gyro_noise", "gyro_bias", "accel_noise", "accel_bias"):
            if getattr(params, name) < 0:
                raise ValueError(f"simulator parameter {name}={getattr(params, name):g}: expected 0 or more")
        return params


def _texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A smooth random texture in [0.15, 1] with strong edges, like a printed pattern."""
    coarse = rng.random((max(2, h // 6), max(2, w // 6))).astype(np.float32)
    tex = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    tex = (tex - tex.min()) / max(float(np.ptp(tex)), 1e-6)
    return (0.15 + 0.85 * tex).astype(np.float32)


@dataclass
class MovingObject:
    """A textured rectangle moving along waypoints (pixels, at microsecond times), held at the ends."""

    ident: int
    texture: np.ndarray
    size_m: float  # metric width (of the texture's full width in pixels at depth_m), for depth from size
    depth_m: float
    times_us: np.ndarray
    xs: np.ndarray  # top-left x at each waypoint
    ys: np.ndarray

    def position(self, t_us: float) -> tuple[float, float]:
        return float(np.interp(t_us, self.times_us, self.xs)), float(np.interp(t_us, self.times_us, self.ys))

    def speed_px_s(self, t_us: float) -> float:
        i = int(np.clip(np.searchsorted(self.times_us, t_us, side="right") - 1, 0, len(self.times_us) - 2))
        dt_s = (self.times_us[i + 1] - self.times_us[i]) / 1e6
        return float(np.hypot(self.xs[i + 1] - self.xs[i], self.ys[i + 1] - self.ys[i]) / max(dt_s, 1e-9))


class ObjectsScene:
    """Static camera looking at a flat background; textured objects move, stop, cross, leave and return.

    The motion repeats with period `period_s`, so the scene runs forever with known ground truth.
    """

    def __init__(self, width: int = 346, height: int = 260, seed: int = 0, n_objects: int = 3,
                 period_s: float = 12.0) -> None:
        self.width, self.height = width, height
        rng = np.random.default_rng(seed)
        self.focal_px = 0.9 * width  # about 58 deg horizontal field of view
        self.background = (0.45 + 0.1 * _texture(rng, height, width)).astype(np.float32)
        self._log_background = np.log(self.background + LOG_EPS)
        self.period_us = int(period_s * 1e6)
        self.objects = [self._make_object(rng, i) for i in range(n_objects)]

    def _make_object(self, rng: np.random.Generator, ident: int) -> MovingObject:
        size_m = float(rng.uniform(0.3, 0.8))
        depth_m = float(rng.uniform(2.0, 5.0))
        w = int(np.clip(size_m / depth_m * self.focal_px, 16, self.width // 3))
        size_m = w * depth_m / self.focal_px  # exactly the metric width that images to w pixels
        h = int(np.clip(w * rng.uniform(0.6, 1.4), 12, self.height // 2))
        n_way = 7
        xs = rng.uniform(-0.2 * w, self.width - 0.8 * w, n_way)
        ys = rng.uniform(0, self.height - h, n_way)
        xs[0] = xs[-1] = -1.2 * w if ident % 2 == 0 else self.width + 0.2 * w  # enter and leave the view
        segs = rng.uniform(0.5, 1.0, n_way - 1)
        segs[rng.integers(1, n_way - 2)] *= 0.0  # one segment where the object holds still
        times = np.concatenate([[0.0], np.cumsum(segs)])
        times = times / times[-1] * self.period_us
        stop = int(np.flatnonzero(segs == 0)[0])
        xs[stop + 1], ys[stop + 1] = xs[stop], ys[stop]
        times[stop + 1] = times[stop] + 0.08 * self.period_us
        times = np.maximum.accumulate(np.minimum(times, self.period_us))
        times[-1] = self.period_us
        return MovingObject(ident, _texture(rng, h, w), size_m, depth_m, times.astype(np.float64), xs, ys)

    def _phase(self, t_us: float) -> float:
        return float(t_us % self.period_us)

    def max_speed_px_s(self, t_us: float) -> float:
        ph = self._phase(t_us)
        return max((o.speed_px_s(ph) for o in self.objects), default=0.0)

    def render(self, t_us: float) -> np.ndarray:
        """Log intensity of the whole image at `t_us`, float32 HxW.

        Only the objects' patches are composed (sub-pixel placement by a bilinear warp of the patch
        alone) and taken to log; the rest is the cached log of the static background."""
        ph = self._phase(t_us)
        img = self.background.copy()
        patches = []
        for obj in sorted(self.objects, key=lambda o: -o.depth_m):  # far first, near objects occlude
            x, y = obj.position(ph)
            h, w = obj.texture.shape
            ix, iy = int(np.floor(x)), int(np.floor(y))
            x0, y0, x1, y1 = max(ix, 0), max(iy, 0), min(ix + w + 2, self.width), min(iy + h + 2, self.height)
            if x1 <= x0 or y1 <= y0:
                continue
            m = np.float32([[1, 0, x - ix], [0, 1, y - iy]])
            tex = cv2.warpAffine(obj.texture, m, (w + 2, h + 2), flags=cv2.INTER_LINEAR)
            alpha = cv2.warpAffine(np.ones((h, w), np.float32), m, (w + 2, h + 2), flags=cv2.INTER_LINEAR)
            inside = np.s_[y0 - iy:y1 - iy, x0 - ix:x1 - ix]
            region = img[y0:y1, x0:x1]
            region += alpha[inside] * (tex[inside] - region)
            patches.append(np.s_[y0:y1, x0:x1])
        out = self._log_background.copy()
        for patch in patches:
            out[patch] = np.log(img[patch] + LOG_EPS)
        return out

    def boxes(self, t_us: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground truth of the objects in view: ids, boxes (x, y, w, h, clipped to the image), and
        3D rows (x, y, z of the object's centre in the camera frame in m, its width in m).

        In view means at least a quarter of it inside the image on each axis, and no more than three
        quarters of that hidden behind nearer objects: a target no camera can see is not scored."""
        rows = [row for row in self._view(t_us) if row[0]]
        c = (self.width / 2, self.height / 2)
        ids, boxes, solid = [], [], []
        for _, obj, box, (x, y) in rows:
            (h, w), z = obj.texture.shape, obj.depth_m
            ids.append(obj.ident)
            boxes.append(box)
            solid.append(((x + w / 2 - c[0]) * z / self.focal_px, (y + h / 2 - c[1]) * z / self.focal_px, z,
                          obj.size_m))
        order = np.argsort(ids, kind="stable")
        return (np.asarray(ids, np.int32)[order], np.asarray(boxes, np.float32).reshape(-1, 4)[order],
                np.asarray(solid, np.float32).reshape(-1, 4)[order])

    def unscored(self, t_us: float) -> tuple[np.ndarray, np.ndarray]:
        """Ids and clipped boxes of the objects in the image that `boxes` does not score (mostly out
        of view or hidden): a tracker's box on one is neither a hit nor a false positive (MOT's
        "don't care" regions)."""
        rows = sorted((obj.ident, box) for scored, obj, box, _ in self._view(t_us) if not scored)
        return np.asarray([i for i, _ in rows], np.int32), np.asarray([b for _, b in rows], np.float32).reshape(-1, 4)

    def _view(self, t_us: float) -> list[tuple[bool, MovingObject, tuple[float, float, float, float],
                                               tuple[float, float]]]:
        """Every object with any part in the image: whether it is scored, its box clipped to the image,
        and its top-left corner (unclipped)."""
        ph = self._phase(t_us)
        out = []
        nearer: list[tuple[float, float, float, float]] = []
        for obj in sorted(self.objects, key=lambda o: o.depth_m):
            x, y = obj.position(ph)
            h, w = obj.texture.shape
            x0, y0 = max(x, 0.0), max(y, 0.0)
            x1, y1 = min(x + w, self.width), min(y + h, self.height)
            if x1 > x0 and y1 > y0:
                scored = x1 - x0 >= 0.25 * w and y1 - y0 >= 0.25 * h and _hidden_share((x0, y0, x1, y1), nearer) <= 0.75
                out.append((scored, obj, (x0, y0, x1 - x0, y1 - y0), (x, y)))
            nearer.append((x, y, x + w, y + h))
        return out


def _hidden_share(box: tuple[float, float, float, float], nearer: list[tuple[float, float, float, float]]) -> float:
    """Share of a box (x0, y0, x1, y1) covered by the union of the `nearer` boxes, to the pixel."""
    x0, y0 = int(np.floor(box[0])), int(np.floor(box[1]))
    covered = np.zeros((max(int(np.ceil(box[3])) - y0, 1), max(int(np.ceil(box[2])) - x0, 1)), np.bool_)
    for a0, b0, a1, b1 in nearer:
        covered[max(int(round(b0)) - y0, 0):max(int(round(b1)) - y0, 0),
                max(int(round(a0)) - x0, 0):max(int(round(a1)) - x0, 0)] = True
    return float(covered.mean())


@numba.njit(cache=True, nogil=True)
def _crossings(last, cur, ref, c, t0, t1, width):  # noqa: ANN001, ANN202 - numba kernel
    """Events of every pixel whose log intensity crossed reference levels between two renders
    (`last` at t0, `cur` at t1), each timed by linear interpolation; moves `ref` (in place) by
    the levels crossed. A pixel that did not change crossed nothing: after each render every
    pixel is within one threshold of its reference. Ordered by pixel, not yet by time."""
    total = 0
    for i in range(len(cur)):
        if cur[i] != last[i]:
            total += int(abs(cur[i] - ref[i]) / c[i])
    out = np.empty(total, EVENT_DTYPE)
    n = 0
    span = t1 - t0 - 1
    for i in range(len(cur)):
        if cur[i] == last[i]:
            continue
        delta = cur[i] - ref[i]
        count = int(abs(delta) / c[i])
        if count == 0:
            continue
        step = c[i] if delta > 0 else -c[i]
        l0, l1 = np.float64(last[i]), np.float64(cur[i])
        for k in range(1, count + 1):
            frac = (ref[i] + step * k - l0) / (l1 - l0) if l1 != l0 else 1.0
            frac = min(max(frac, 0.0), 1.0)
            e = out[n]
            e.t, e.x, e.y, e.p = t0 + 1 + np.int64(np.round(frac * span)), i % width, i // width, delta > 0
            n += 1
        ref[i] += step * count
    return out


class EventSimulator:
    """Turns a scene's log intensity over time into events (see the module docstring)."""

    def __init__(self, scene: Scene, params: SimParams | None = None, seed: int = 0) -> None:
        self.scene = scene
        self.params = params or SimParams()
        self._rng = np.random.default_rng(seed + 1)
        shape = (scene.height, scene.width)
        c = self.params.contrast + self.params.contrast_sigma * self._rng.standard_normal(shape)
        self._c = np.clip(c, 0.05, None).astype(np.float32)
        self.t_us = 0
        self._last = scene.render(0)
        self._ref = self._last.copy()
        n_hot = int(round(self.params.hot_pixel_fraction * scene.width * scene.height))
        self._hot = self._rng.choice(scene.width * scene.height, n_hot, replace=False)
        self._refractory = Refractory(scene.width, scene.height, self.params.refractory_us)

    def advance(self, until_us: int) -> np.ndarray:
        """All events in (t_us, until_us], sorted by time."""
        chunks = []
        while self.t_us < until_us:
            p = self.params
            speed = self.scene.max_speed_px_s(self.t_us)
            dt = p.max_dt_us if speed <= 0 else int(np.clip(p.max_step_px / speed * 1e6, p.min_dt_us, p.max_dt_us))
            t1 = min(self.t_us + dt, until_us)
            chunks.append(self._step(t1))
        return events.concat(chunks)  # steps are sorted and in order

    def _step(self, t1: int) -> np.ndarray:
        t0 = self.t_us
        cur = self.scene.render(t1)
        ev = _crossings(self._last.ravel(), cur.ravel(), self._ref.ravel(), self._c.ravel(), t0, t1,
                        self.scene.width)
        self._last, self.t_us = cur, t1
        ev = events.sort_by_time(events.concat([ev, self._noise(t0, t1), self._hot_pixels(t0, t1)]))
        return self._refractory(ev) if self.params.refractory_us > 0 else ev

    def _hot_pixels(self, t0: int, t1: int) -> np.ndarray:
        counts = self._rng.poisson(self.params.hot_pixel_rate_hz * (t1 - t0) / 1e6, len(self._hot))
        pixels = np.repeat(self._hot, counts)
        ev = np.empty(len(pixels), EVENT_DTYPE)
        ev["t"] = self._rng.integers(t0 + 1, t1 + 1, len(pixels))
        ev["y"], ev["x"] = np.divmod(pixels, self.scene.width)
        ev["p"] = self._rng.integers(0, 2, len(pixels))
        return ev

    def _noise(self, t0: int, t1: int) -> np.ndarray:
        lam = self.params.noise_rate_hz * self.scene.width * self.scene.height * (t1 - t0) / 1e6
        n = self._rng.poisson(lam)
        ev = np.empty(n, EVENT_DTYPE)
        ev["t"] = self._rng.integers(t0 + 1, t1 + 1, n)
        ev["x"] = self._rng.integers(0, self.scene.width, n)
        ev["y"] = self._rng.integers(0, self.scene.height, n)
        ev["p"] = self._rng.integers(0, 2, n)
        return ev
