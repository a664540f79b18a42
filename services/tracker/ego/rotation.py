"""Camera rotation from events: angular velocity by contrast maximisation, integrated to orientation.

Every `step_us` of sensor time the latest events form a window long enough for the predicted motion
to sweep about `travel_px` pixels across it (a fast turn needs a short window, a slow one a long one:
too little motion leaves the contrast flat in w, too much breaks the constant-velocity model), with
at least `min_events` and at most `max_events` events (more are thinned evenly). The window's angular
velocity maximises the contrast of its warped events (`contrast.py`), warm-started from the last
estimate extrapolated, by L-BFGS on the exact gradient; the orientation integrates the estimates
between the windows' middle times (trapezoid rule), where the poses are reported. A window with
too few events (the camera and the scene still) says the camera is still: w = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from services.geometry import pixel_rays, unit_rays
from services.messages import EVENT_DTYPE
from services.tracker.ego.contrast import RotationContrast
from services.tracker.ego.panorama import PanoramaMap

# the state of an estimate: from a window's contrast; too few events to move; or lost: the best rate found
# leaves the events no sharper than not turning at all (noise, flicker, a scene of independently moving
# things), so it means nothing. A still or lost estimate says w = 0, and the next window starts cold
TRACKING, STILL, LOST = 0, 1, 2
STATES = ("tracking", "still", "lost")  # their names


@dataclass
class RotationParams:
    step_us: int = 10_000  # an estimate this often (100 Hz)
    # the window's length: the predicted motion sweeps about this far across it (on sim:rotation seed 1, 12 px
    # gave 6.6 % of the peak speed rms, 25 px 1.8 %, 50 px 0.8 %)
    travel_px: float = 50.0
    min_window_us: int = 1_000
    max_window_us: int = 50_000
    min_events: int = 2_000  # fewer in the longest window: the camera is still
    max_events: int = 10_000  # more are thinned evenly (20 000: 0.8 % rms of the peak speed, not 1.1 %, at 2x the cost)
    sigma_px: float = 1.0  # the Gaussian the image of warped events is smoothed by (see `RotationContrast`)
    iterations: int = 6  # L-BFGS iterations at most per window (from the warm start: 20 gained nothing)
    # a cold start (the first window, or after a still spell) assumes this speed for its first window's length,
    # and starts from the best of these rates about each axis
    cold_speed_deg_s: float = 1000.0
    cold_starts_deg_s: tuple[float, ...] = (150.0, 400.0, 800.0)
    cold_sigma_px: float = 3.0  # the blur of its first round (star fields at 300-700 deg/s: 1 px stayed at 0, 3 px
    cold_iterations: int = 20  # converged in 10-16 iterations)
    # a window whose best rate's contrast is under this many times that of w = 0 is lost. Uniform noise at
    # 1 Mev/s: 0.73-0.78. Tracking (dev seeds 1 and 2 at 616 and 1000 deg/s peaks): 1 % of windows under 1.3,
    # the least 0.93 and 0.89, nearly still where the motion turns back (at 1.0, four such windows were lost
    # on seed 1 and the cold starts after them erred by up to 88 deg/s)
    min_gain: float = 0.85
    # tracking against the panoramic map of the events (`panorama.py`): every estimate's orientation is
    # aligned to it with this many of its warped events at most, and turned by `map_gain` of the alignment's
    # step (seed 1, 10 s: 1 gave 0.59 deg RMS and jumps that doubled the rate error read from the poses, 1.9 %
    # of the peak; 0.2 gave 0.44 deg and 1.0 %; 0.05 let it drift, 0.76 deg); every `map_every`th window is
    # added to it
    panorama: bool = True
    align_events: int = 2_000
    map_gain: float = 0.2
    map_every: int = 5


@dataclass
class RotationEstimate:
    t_us: int  # the window's middle time, where the pose is
    quat: np.ndarray  # x, y, z, w of R_world_cam (the world frame: the camera's at the start)
    omega: np.ndarray  # rad/s, camera frame
    state: int
    events: int  # in the window (before thinning)
    window_us: int
    contrast_gain: float  # the contrast at the estimate over that at w = 0 (how much the motion explains)

    def tum_row(self) -> list[float]:
        """t tx ty tz qx qy qz qw, at the origin (a rotation has no position)."""
        return [self.t_us / 1e6, 0.0, 0.0, 0.0, *self.quat.tolist()]


class RotationTracker:
    """Turns a stream of (undistorted) events into rotation estimates; `add` returns those completed."""

    def __init__(self, K: np.ndarray, width: int, height: int, params: RotationParams | None = None) -> None:
        self.params = params or RotationParams()
        K = np.asarray(K, np.float64)
        self.K, self.focal = K, float(K[0, 0])
        self._rays = pixel_rays(K, width, height)
        self.width = width
        self.contrast = RotationContrast(K, width, height, self.params.sigma_px)
        self._coarse = RotationContrast(K, width, height, self.params.cold_sigma_px)
        turns = np.radians(self.params.cold_starts_deg_s)[:, None, None] * np.concatenate([np.eye(3), -np.eye(3)])
        self._cold_starts = np.vstack([np.full((1, 3), 1e-3), turns.reshape(-1, 3)])
        self.map = PanoramaMap(K, width, height, sigma_px=self.params.sigma_px) if self.params.panorama else None
        self._t = np.zeros(0, np.int64)  # events kept for the next windows
        self._pix = np.zeros(0, np.int64)
        self._next_us: int | None = None
        self._start_us = 0
        self._windows = 0
        self.orientation = Rotation.identity()
        self._last: RotationEstimate | None = None
        self._before: RotationEstimate | None = None

    def add(self, events: np.ndarray) -> list[RotationEstimate]:
        """Feeds a time-ordered chunk of events (fields t, x, y); the estimates whose windows it completed."""
        if not len(events):
            return []
        p = self.params
        self._t = np.concatenate([self._t, events["t"].astype(np.int64)])
        self._pix = np.concatenate([self._pix, events["y"].astype(np.int64) * self.width + events["x"]])
        if self._next_us is None:
            self._start_us = int(self._t[0])
            self._next_us = self._start_us + p.step_us
        out = []
        newest = int(self._t[-1])
        while self._next_us <= newest:
            out.append(self._estimate(self._next_us))
            self._next_us += p.step_us
        keep = np.searchsorted(self._t, self._next_us - p.max_window_us)
        self._t, self._pix = self._t[keep:], self._pix[keep:]
        return out

    def _predicted(self, t_us: int) -> np.ndarray:
        """The angular velocity the last two estimates extrapolate to `t_us`."""
        if self._last is None:
            return np.zeros(3)
        if self._before is None:
            return self._last.omega
        span = self._last.t_us - self._before.t_us
        slope = (self._last.omega - self._before.omega) / max(span, 1)
        return self._last.omega + slope * min(t_us - self._last.t_us, span)

    def _estimate(self, end_us: int) -> RotationEstimate:
        p = self.params
        # no longer than puts its middle after the last estimate's: the poses' times go forward
        longest = p.max_window_us if self._last is None else min(p.max_window_us, 2 * (end_us - self._last.t_us) - 2)
        if self._last is None or self._last.state != TRACKING:
            # a cold start, maybe on a camera already turning fast: near w = 0 the contrast of sharp events has
            # no slope toward a fast turn's rate (and a kink at 0, where events sit on whole pixels), so the
            # first round blurs them by `cold_sigma_px`, in a window as long as the fastest turn asks for, from
            # the best of a few rates (still, or turning about one axis); the second refines that rate as any
            # warm start is
            coarse = self._solve(end_us, self._window_us(math.radians(p.cold_speed_deg_s)), longest,
                                 self._cold_starts, self._coarse, p.cold_iterations)
            guess = None if coarse is None else coarse[0]
        else:
            guess = self._predicted(end_us)
        solved = None if guess is None else self._solve(end_us, self._window_us(float(np.linalg.norm(guess))),
                                                        longest, guess)
        if solved is None:
            lo, hi = np.searchsorted(self._t, [end_us - longest, end_us], side="right")
            n = int(hi - lo)
            return self._integrate(RotationEstimate(end_us - longest // 2, np.zeros(4), np.zeros(3), STILL, n,
                                                    longest, 1.0))
        omega, gain, n, t = solved
        state = TRACKING if gain >= p.min_gain else LOST
        est = self._integrate(RotationEstimate((int(t[0]) + int(t[-1])) // 2, np.zeros(4),
                                               omega if state == TRACKING else np.zeros(3), state, n,
                                               int(t[-1] - t[0]), gain))
        if self.map is not None and state == TRACKING:
            self._track_map(est)
        return est

    def _window_us(self, speed_rad_s: float) -> int:
        """The window in which a turn at this speed sweeps `travel_px` across the image, within the limits."""
        p = self.params
        speed_px_s = speed_rad_s * self.focal
        return int(np.clip(1e6 * p.travel_px / max(speed_px_s, 1e-9), p.min_window_us, p.max_window_us))

    def _solve(self, end_us: int, window: int, longest: int, guess: np.ndarray,
               contrast: RotationContrast | None = None,
               iterations: int | None = None) -> tuple[np.ndarray, float, int, np.ndarray] | None:
        """The angular velocity that maximises the contrast of the window ending at `end_us` (at most
        `longest`; widened to the latest `min_events` where it holds fewer), from `guess`: with the contrast
        gain, the window's event count and its (thinned) times; None where even the longest holds too few.
        The contrast is `self.contrast`'s unless `contrast` is given (the cold start's blurred one); a guess
        of several rows starts from the one of highest contrast."""
        p = self.params
        contrast = contrast or self.contrast
        lo, hi = np.searchsorted(self._t, [end_us - min(window, longest), end_us], side="right")
        if hi - lo < p.min_events:  # too few in the window the motion asks for: take the latest min_events
            lo = max(hi - p.min_events, int(np.searchsorted(self._t, end_us - longest, side="right")))
        n = int(hi - lo)
        if n < p.min_events:
            return None
        idx = np.arange(lo, hi, max(1, math.ceil(n / p.max_events)))
        t = self._t[idx]
        mid = (int(t[0]) + int(t[-1])) // 2
        contrast.set_events(self._rays[self._pix[idx]], (t - mid) * 1e-6)
        scale = contrast(np.zeros(3))[0] or 1.0
        if guess.ndim == 2:
            guess = guess[int(np.argmax([contrast(g)[0] for g in guess]))]

        def negative(omega: np.ndarray) -> tuple[float, np.ndarray]:
            value, grad = contrast(omega)
            return -value / scale, -grad / scale

        result = minimize(negative, guess, jac=True, method="L-BFGS-B",
                          options={"maxiter": iterations or p.iterations, "maxls": 6})
        return np.asarray(result.x, np.float64), float(-result.fun), n, t

    def _track_map(self, est: RotationEstimate) -> None:
        """The estimate's orientation aligned to the panoramic map by its warped events; every `map_every`th
        window's image of them added to the map."""
        p = self.params
        image = self.contrast.iwe(est.omega)
        n = len(self.contrast.dt)
        u, v = self.contrast.warped(n)
        inside = np.flatnonzero((u >= 0) & (u < image.shape[1] - 1) & (v >= 0) & (v < image.shape[0] - 1))
        pick = inside[::max(1, math.ceil(len(inside) / p.align_events))]
        aligned = self.map.align(unit_rays(self.K, u[pick], v[pick]), self.orientation)
        step = (self.orientation.inv() * aligned).as_rotvec()
        self.orientation = self.orientation * Rotation.from_rotvec(p.map_gain * step)
        est.quat = self.orientation.as_quat()
        if self.map.windows == 0 or self._windows % p.map_every == 0:
            self.map.insert(cv2.GaussianBlur(image, (0, 0), p.sigma_px), self.orientation)
        self._windows += 1

    def _integrate(self, est: RotationEstimate) -> RotationEstimate:
        """The orientation at the estimate's time: the last one turned by the mean of the two angular
        velocities over the time between them (the first estimate starts the world frame)."""
        if self._last is not None:
            dt_s = (est.t_us - self._last.t_us) * 1e-6
            self.orientation = self.orientation * Rotation.from_rotvec(0.5 * (self._last.omega + est.omega) * dt_s)
        else:  # from the first event on
            self.orientation = Rotation.from_rotvec(est.omega * (est.t_us - self._start_us) * 1e-6)
        est.quat = self.orientation.as_quat()
        self._before, self._last = self._last, est
        return est


def warm_up() -> None:
    """Loads the kernels of an update (compiles them, the first time on a machine; see `services.kernels`) on a
    small camera panning over a few bright dots, which it tracks (so the panorama's kernels load too)."""
    width, height, focal = 64, 48, 50.0
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    rng = np.random.default_rng(0)
    dots = rng.uniform([0, 4], [width, height - 4], (24, 2))
    t = np.arange(0, 300_000, 50)  # us: an event per dot every 50 us, as the view pans at 200 px/s
    x = (dots[:, 0][None, :] + 200e-6 * t[:, None]) % width
    events = np.zeros(x.size, EVENT_DTYPE)
    events["t"] = np.repeat(t, len(dots))
    events["x"], events["y"] = x.ravel(), np.tile(dots[:, 1], len(t))
    tracker = RotationTracker(K, width, height)
    for chunk in np.array_split(events, 30):
        tracker.add(chunk)
