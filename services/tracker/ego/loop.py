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
from services.tracker.ego import STEREO_WEAK_SHARE
from services.tracker.ego.gyro import Gyro
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
class RefreshParams:
    # a keyframe is asked for once an estimate explains under this share of the best inlier share since the last
    # keyframe (0: never): the map's edges fire only where the camera moves across them, and a map made while it
    # moved one way explains the events of another way poorly (held-out stereo rig 12 was lost so, 2 cm off, as it
    # turned). For stereo, whose depth needs no travel (see `loop_params`); the space sweep's keyframes need a
    # baseline, and asked for early they placed their points poorly (dev seeds 1-6: mean 7.1 % ATE, 10.1 at 0.6)
    weak_share: float = 0.0
    min_gap_us: int = 200_000  # ... no sooner than this after the last keyframe


class MapRefresh:
    """When the tracker needs a new keyframe before the mapper's own rule (travel, time) gives one: its estimates
    explain the events ever less well (`RefreshParams.weak_share`), or it was just lost (what its last good
    poses placed is a map to be found again on). Shared by the offline loop and the live tracker service, which
    asks the mapper for it."""

    def __init__(self, params: RefreshParams | None = None) -> None:
        self.params = params or RefreshParams()
        self._tracking = False
        self.keyframe_at(-(1 << 62))

    def keyframe_at(self, t_us: int) -> None:
        """A keyframe (of the tracker's map) was made at `t_us`: the best share is measured again from here."""
        self._since_us, self._best = t_us, 0.0

    def due(self, est: PoseEstimate) -> bool:
        """Whether to ask for a keyframe after this estimate (never where `weak_share` is 0); asked, not again
        within `min_gap_us` unless a keyframe comes (a mapper that cannot make one yet is not asked at 50 Hz)."""
        was, self._tracking = self._tracking, est.state == TRACKING
        if not self.params.weak_share:
            return False
        if est.state != TRACKING:
            return was
        self._best = max(self._best, est.inliers)
        if est.inliers >= self.params.weak_share * self._best or est.t_us - self._since_us < self.params.min_gap_us:
            return False
        self._since_us = est.t_us
        return True


@dataclass
class LoopParams:
    tracker: SixDofParams = field(default_factory=SixDofParams)
    keyframes: KeyframeParams = field(default_factory=tracking_map)
    refresh: RefreshParams = field(default_factory=RefreshParams)


def loop_params(stereo: bool = False) -> LoopParams:
    """The loop's defaults, mapped by the space sweep or by `stereo`."""
    if not stereo:
        return LoopParams()
    return LoopParams(keyframes=tracking_map(stereo=True), refresh=RefreshParams(weak_share=STEREO_WEAK_SHARE))


class MappedOdometry:
    """Events (undistorted, sorted) in, 6-DoF pose estimates out, with the map built on the way."""

    def __init__(self, K: np.ndarray, width: int, height: int, known: Trajectory,
                 params: LoopParams | None = None, mapper: KeyframeMapper | StereoMapper | None = None,
                 gyro: Gyro | None = None) -> None:
        """`mapper` builds the map: the space sweep of the tracked camera's events (by default), or a stereo
        rig's mapper, then fed both cameras' events (`add`); `gyro`, the tracked camera's, if it has one."""
        self.params = params or LoopParams()
        self.tracker = SixDofTracker(K, width, height, self.params.tracker, gyro=gyro)
        self.mapper = mapper or KeyframeMapper(K, width, height, self.params.keyframes)
        self.known = known
        self.refresh = MapRefresh(self.params.refresh)
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
        estimates = []
        # an update at a time: a keyframe asked for after one is in the map of the next, as live
        step = self.tracker.params.step_us
        ends = np.arange(self.tracker.next_us, int(cameras[0]["t"][-1]) + 1, step)
        cuts = [np.searchsorted(ev["t"], ends, side="left") for ev in cameras]
        for piece in zip(*(np.split(ev, cut) for ev, cut in zip(cameras, cuts, strict=True)), strict=True):
            estimates += self._step(piece)
        return estimates

    def _step(self, cameras: tuple[np.ndarray, ...]) -> list[PoseEstimate]:
        """`add` of events that complete one update at most."""
        estimates = self.tracker.add(cameras[0])
        self._pending.append(cameras)
        for est in estimates:
            lost = est.state != TRACKING
            if not lost:
                self._rows.append(est.tum_row())
            # lost, what the good poses placed makes a keyframe if it can (the sweep's needs travel), a map to be
            # found again on
            if self.refresh.due(est) or lost:
                self._early()
            if lost:
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
            for kf in self.mapper.add(*events, self._trajectory()):
                self._keyframe(kf)

    def _trajectory(self) -> Trajectory:
        """The poses so far: the known start's, then the good estimates'."""
        return Trajectory(np.asarray(self._rows))

    def _early(self) -> None:
        """A keyframe now, of what the mapper holds up to the latest good pose, if it can make one (see
        `MapRefresh`): the tracker's map is failing it."""
        self._map_until(int(self._rows[-1][0] * 1e6))
        if kf := self.mapper.early(self._trajectory()):
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
        self.refresh.keyframe_at(int(self._rows[-1][0] * 1e6) if self._rows else kf.t_us)
        # the mapper's next segment starts after this keyframe's time: the poses before it are not needed again,
        # and the trajectory built for each update stays a segment long, not the whole run's (40 ms a build at 10
        # minutes of poses, against the update's 20)
        first = next((i for i, row in enumerate(self._rows) if row[0] * 1e6 >= kf.t_us), len(self._rows))
        del self._rows[:max(min(first - 1, len(self._rows) - 2), 0)]

