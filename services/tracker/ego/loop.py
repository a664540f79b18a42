"""Tracking and mapping in one loop (seed 001's EVO / ESVO): the 6-DoF tracker follows the keyframe
map, and the keyframe mapper builds the map from the tracker's poses.

Bootstrapping: a first map from a short known motion. The events of the `known` trajectory's span are
swept into a first keyframe at those poses; from the span's end the tracker starts at the known pose
(with the one `step_us` before it for its first velocity), and no known pose is used after. Each good
estimate extends the trajectory the mapper sweeps with; the mapper is fed only the events that good
estimates cover, and a lost update drops the events before it, so no keyframe is built across a spell
without poses. Each new keyframe's points join the tracker's map.

A stereo rig's loop (ESVO's) maps by stereo (`StereoMapper`) from both cameras' events and tracks the
first camera: its depth needs no travel of the camera, only the rig's baseline, so its keyframes may come
more often, and its map does not grow out of the tracker's own drift as the space sweep's does.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from services import events as ev_ops
from services.mapper.keyframes import Keyframe, KeyframeMapper, KeyframeParams
from services.mapper.stereo import StereoMapper
from services.mapper.trajectory import Trajectory
from services.tracker.ego.sixdof import TRACKING, PoseEstimate, SixDofParams, SixDofTracker


def tracking_map(params: KeyframeParams | None = None, stereo: bool = False) -> KeyframeParams:
    """Keyframe settings (from `params`, or the defaults) for a map the 6-DoF tracker follows, here or in the
    mapper service (`--tracking-map`), by the space sweep or by `stereo`."""
    # a keyframe's points are what the tracker aligns to, and a sparse map let it drift: the loop keeps peaks
    # half as high over their neighbourhood and seen with 10 px of parallax, not 20 (dev seeds 1-3, 1.5 s known:
    # 2.9, 0.9 and 5.9 % ATE, against 12.6, 2.4 and 2.7 % with the mapper's defaults)
    base = params or KeyframeParams()
    base = replace(base, sweep=replace(base.sweep, threshold=0.05, min_parallax_px=10.0))
    # stereo depth needs no travel: a keyframe every 10 % of the scene's depth, or every second, keeps the map in
    # view (dev seeds 1-3: no update lost and 1.5, 0.9, 0.9 % ATE, against 0-7 lost and 1.4, 1.1, 0.9 % at the
    # sweep's 25 %)
    return replace(base, baseline_share=0.1, max_span_us=1_000_000) if stereo else base


@dataclass
class LoopParams:
    tracker: SixDofParams = field(default_factory=SixDofParams)
    keyframes: KeyframeParams = field(default_factory=tracking_map)


class MappedOdometry:
    """Events (undistorted, sorted) in, 6-DoF pose estimates out, with the map built on the way."""

    def __init__(self, K: np.ndarray, width: int, height: int, known: Trajectory,
                 params: LoopParams | None = None, mapper: KeyframeMapper | StereoMapper | None = None) -> None:
        """`mapper` builds the map: the space sweep of the tracked camera's events (by default), or a stereo
        rig's mapper, then fed both cameras' events (`add`)."""
        self.params = params or LoopParams()
        self.tracker = SixDofTracker(K, width, height, self.params.tracker)
        self.mapper = mapper or KeyframeMapper(K, width, height, self.params.keyframes)
        self.known = known
        self.keyframes: list[Keyframe] = []
        self._rows: list[list[float]] = []  # TUM rows of the trajectory the mapper sweeps with
        self._boot: list[tuple[np.ndarray, ...]] = []
        self._pending: list[tuple[np.ndarray, ...]] = []  # events waiting for a good estimate after them
        self.started = False

    def add(self, *cameras: np.ndarray) -> list[PoseEstimate]:
        """Events sorted by time, of the tracked camera and of the mapper's others (a stereo rig's right one, up
        to the same time); the estimates of the updates they completed. Events before the known start are passed
        over (no pose places them)."""
        if not self.started:
            cuts = [np.searchsorted(ev["t"], [self.known.start_us, self.known.end_us], side="left") for ev in cameras]
            self._boot.append(tuple(ev[lo:cut] for ev, (lo, cut) in zip(cameras, cuts, strict=True)))
            cameras = tuple(ev[cut:] for ev, (_, cut) in zip(cameras, cuts, strict=True))
            if not len(cameras[0]):
                return []
            self._start()
        elif not len(cameras[0]):
            return []
        estimates = self.tracker.add(cameras[0])
        self._pending.append(cameras)
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
        parts, self._boot = [ev_ops.concat(cam) for cam in zip(*self._boot, strict=True)], []
        if not len(parts[0]):
            raise ValueError("no events during the known start: nothing to build a first map from")
        for kf in self.mapper.add(*parts, self.known):
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
        if len(events[0]) and len(self._rows) >= 2:
            for kf in self.mapper.add(*events, Trajectory(np.asarray(self._rows))):
                self._keyframe(kf)

    def _drop_until(self, t_us: int) -> None:
        """A lost update: the events before it have no pose, and the segment the mapper held ends unswept."""
        self._take_pending(t_us)
        self.mapper.drop()

    def _take_pending(self, t_us: int) -> tuple[np.ndarray, ...]:
        """Each camera's pending events up to `t_us`, no longer pending."""
        cameras = [ev_ops.concat(cam) if len(cam) > 1 else cam[0] for cam in zip(*self._pending, strict=True)]
        cuts = [int(np.searchsorted(ev["t"], t_us, side="right")) for ev in cameras]
        self._pending = [tuple(ev[cut:] for ev, cut in zip(cameras, cuts, strict=True))]
        return tuple(ev[:cut] for ev, cut in zip(cameras, cuts, strict=True))

    def _keyframe(self, kf: Keyframe) -> None:
        self.keyframes.append(kf)
        self.tracker.add_points(kf.points)

