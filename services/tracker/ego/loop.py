"""Tracking and mapping in one loop (seed 001's EVO / ESVO): the 6-DoF tracker follows the keyframe
map, and the keyframe mapper builds the map from the tracker's poses.

Bootstrapping: a first map from a short known motion. The events of the `known` trajectory's span are
swept into a first keyframe at those poses; from the span's end the tracker starts at the known pose
(with the one `step_us` before it for its first velocity), and no known pose is used after. Each good
estimate extends the trajectory the mapper sweeps with; the mapper is fed only the events that good
estimates cover, and a lost update drops the events before it, so no keyframe is built across a spell
without poses. Each new keyframe's points join the tracker's map.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from services import events as ev_ops
from services.mapper.keyframes import Keyframe, KeyframeMapper, KeyframeParams
from services.mapper.trajectory import Trajectory
from services.tracker.ego.sixdof import TRACKING, PoseEstimate, SixDofParams, SixDofTracker


def tracking_map(params: KeyframeParams | None = None) -> KeyframeParams:
    """Keyframe settings (from `params`, or the defaults) for a map the 6-DoF tracker follows, here or in the
    mapper service (`--tracking-map`)."""
    # a keyframe's points are what the tracker aligns to, and a sparse map let it drift: the loop keeps peaks
    # half as high over their neighbourhood and seen with 10 px of parallax, not 20 (dev seeds 1-3, 1.5 s known:
    # 2.9, 0.9 and 5.9 % ATE, against 12.6, 2.4 and 2.7 % with the mapper's defaults)
    base = params or KeyframeParams()
    return replace(base, sweep=replace(base.sweep, threshold=0.05, min_parallax_px=10.0))


@dataclass
class LoopParams:
    tracker: SixDofParams = field(default_factory=SixDofParams)
    keyframes: KeyframeParams = field(default_factory=tracking_map)


class MappedOdometry:
    """Events (undistorted, sorted) in, 6-DoF pose estimates out, with the map built on the way."""

    def __init__(self, K: np.ndarray, width: int, height: int, known: Trajectory,
                 params: LoopParams | None = None) -> None:
        self.params = params or LoopParams()
        self.tracker = SixDofTracker(K, width, height, self.params.tracker)
        self.mapper = KeyframeMapper(K, width, height, self.params.keyframes)
        self.known = known
        self.keyframes: list[Keyframe] = []
        self._rows: list[list[float]] = []  # TUM rows of the trajectory the mapper sweeps with
        self._boot: list[np.ndarray] = []
        self._pending: list[np.ndarray] = []  # events waiting for a good estimate after them
        self.started = False

    def add(self, events: np.ndarray) -> list[PoseEstimate]:
        """Events sorted by time; the estimates of the updates they completed. Events before the known start
        are passed over (no pose places them)."""
        if not self.started:
            lo, cut = np.searchsorted(events["t"], [self.known.start_us, self.known.end_us], side="left")
            self._boot.append(events[lo:cut])
            events = events[cut:]
            if not len(events):
                return []
            self._start()
        elif not len(events):
            return []
        estimates = self.tracker.add(events)
        self._pending.append(events)
        for est in estimates:
            if est.state == TRACKING:
                self._rows.append(est.tum_row())
            else:
                self._drop_until(est.t_us)
        if estimates:
            self._map_until(int(self._rows[-1][0] * 1e6))
        return estimates

    def _start(self) -> None:
        """The first keyframe from the known motion's events, and the tracker at its last pose."""
        self.started = True
        parts, self._boot = [b for b in self._boot if len(b)], []
        if not parts:
            raise ValueError("no events during the known start: nothing to build a first map from")
        for kf in self.mapper.add(ev_ops.concat(parts), self.known):
            self._keyframe(kf)
        # the rest of the known motion makes a keyframe if long enough to place its points, or the only one
        last = self.mapper.flush(self.known) if self.keyframes else self.mapper.finish(self.known)
        if last is not None:
            self._keyframe(last)
        end = self.known.end_us
        self.tracker.start_on(self.known, end)
        times = np.unique(np.append(self.known.t_us[self.known.t_us <= end], end))
        R, p = self.known.at(times)
        quats = Rotation.from_matrix(R).as_quat()
        self._rows = [[t / 1e6, *pi, *qi] for t, pi, qi in zip(times, p, quats, strict=True)]

    def _map_until(self, t_us: int) -> None:
        """The pending events up to `t_us` to the mapper, with the trajectory so far."""
        events = self._take_pending(t_us)
        if len(events) and len(self._rows) >= 2:
            for kf in self.mapper.add(events, Trajectory(np.asarray(self._rows))):
                self._keyframe(kf)

    def _drop_until(self, t_us: int) -> None:
        """A lost update: the events before it have no pose, and the segment the mapper held ends unswept."""
        self._take_pending(t_us)
        self.mapper.drop()

    def _take_pending(self, t_us: int) -> np.ndarray:
        """The pending events up to `t_us`, no longer pending."""
        events = ev_ops.concat(self._pending) if len(self._pending) > 1 else self._pending[0]
        cut = int(np.searchsorted(events["t"], t_us, side="right"))
        self._pending = [events[cut:]]
        return events[:cut]

    def _keyframe(self, kf: Keyframe) -> None:
        self.keyframes.append(kf)
        self.tracker.add_points(kf.points)

