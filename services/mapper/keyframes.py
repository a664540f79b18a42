"""Keyframes of a semi-dense map: events cut into segments by the camera's travel, each swept into a
depth map at the pose of its middle (the reference view) and lifted into world points.

A segment ends when the camera has travelled `baseline_share` of the scene's depth since it began:
parallax, not time, is what lets rays meet at the right depth (the depth error of a peak one pixel off
is about depth / parallax in pixels). The scene's depth is the median of the last keyframe's, or a
guess between the planes' limits before the first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from services.mapper import sweep
from services.mapper.trajectory import Trajectory

POSE_EVERY = 1024  # events that share one pose while voting (about a millisecond at 1 Mev/s)


@dataclass
class KeyframeParams:
    sweep: sweep.SweepParams = field(default_factory=sweep.SweepParams)
    baseline_share: float = 0.25  # a segment ends once the camera travelled this share of the scene's depth
    max_events: int = 4_000_000  # ... or held this many events (bounds memory when the camera barely moves)
    # ... or spans this long (0: no limit); for depth that needs no travel (stereo), a map that keeps up with the
    # camera where it turns more than it moves
    max_span_us: int = 0


@dataclass
class Keyframe:
    t_us: int  # the reference view's time
    R: np.ndarray  # its orientation (3 x 3, camera to world) and position (3, m)
    p: np.ndarray
    depth: np.ndarray  # H x W, m, NaN where no edge was found
    points: np.ndarray  # N x 3 world points (float32) of the depth map's finite pixels
    confidence: np.ndarray  # N peak heights (votes)
    events: int


Build = Callable[[np.ndarray, Trajectory], Keyframe]  # a segment's items and the trajectory to its keyframe


class KeyframeMapper:
    """Feeds events (with a trajectory covering their times) and returns each keyframe as it completes.

    A segment's events are swept (`sweep_keyframe`) unless `build` makes keyframes of other items with a
    time field `t` (a stereo rig's depth estimates)."""

    def __init__(self, K: np.ndarray, width: int, height: int, params: KeyframeParams | None = None,
                 build: Build | None = None) -> None:
        self.K, self.width, self.height = np.asarray(K, np.float64), width, height
        self.params = params or KeyframeParams()
        self.depths = sweep.plane_depths(self.params.sweep)
        self.scene_depth = float(np.sqrt(self.depths[0] * self.depths[-1]))
        self.build = build or (lambda events, trajectory: sweep_keyframe(
            events, trajectory, self.K, width, height, self.depths, self.params.sweep))
        self.drop()

    def drop(self) -> None:
        """A new segment: the events held are dropped unswept, the travel counted from nothing."""
        self._chunks: list[np.ndarray] = []
        self._n = 0
        self._t0: int | None = None  # the segment's first time
        self._last: np.ndarray | None = None  # where the camera was last seen, and how far it went in the segment
        self._travel = 0.0

    @property
    def held(self) -> int:
        """How many items the current segment holds."""
        return self._n

    def add(self, events: np.ndarray, trajectory: Trajectory) -> list[Keyframe]:
        """Events sorted by time; the keyframes their segments completed."""
        out: list[Keyframe] = []
        while len(events):
            cut = self._segment_end(events, trajectory)
            self._chunks.append(events[:cut])
            self._n += cut
            events = events[cut:]
            if cut == 0 or len(events) or self._n >= self.params.max_events:
                if self._n:
                    out.append(self.finish(trajectory))
        return out

    def _segment_end(self, events: np.ndarray, trajectory: Trajectory) -> int:
        """How many of `events` belong to the current segment (all, unless the travel limit falls in them)."""
        p = self.params
        stamps = events["t"][::POSE_EVERY]
        _, pos = trajectory.at(stamps)
        if self._last is None:
            self._last = pos[0]
        steps = np.linalg.norm(np.diff(np.vstack([self._last, pos]), axis=0), axis=1)
        travel = self._travel + np.cumsum(steps)
        limit = p.baseline_share * self.scene_depth
        over = np.flatnonzero(travel >= limit)
        room = p.max_events - self._n
        if self._t0 is None:
            self._t0 = int(events["t"][0])
        if p.max_span_us:
            late = np.flatnonzero(stamps - self._t0 >= p.max_span_us)
            over = np.union1d(over, late[:1])
        if len(over):
            cut = int(over[0]) * POSE_EVERY
        else:
            cut = len(events)
            self._travel, self._last = float(travel[-1]), pos[-1]
        # a segment takes at least one pose's worth of events, so that it ends
        return max(min(cut, room, len(events)), 0 if self._n else min(POSE_EVERY, len(events)))

    def flush(self, trajectory: Trajectory, min_share: float = 0.5) -> Keyframe | None:
        """At the end of the events: the last segment's keyframe if the camera travelled at least `min_share`
        of a segment's baseline in it (a shorter one would place its points poorly), else None."""
        if (keyframe := self.early(trajectory, min_share)) is None:
            self.drop()
        return keyframe

    def early(self, trajectory: Trajectory, min_share: float = 0.5) -> Keyframe | None:
        """A keyframe asked for before the segment's end (the tracker needs a fresh map): of the events held, if
        the camera travelled at least `min_share` of a segment's baseline (else None, and the segment goes on)."""
        if self._n and self._travel >= min_share * self.params.baseline_share * self.scene_depth:
            return self.finish(trajectory)
        return None

    def finish(self, trajectory: Trajectory) -> Keyframe:
        """The keyframe of the events held so far (the segment ends here)."""
        events = np.concatenate(self._chunks)
        self.drop()
        keyframe = self.build(events, trajectory)
        if len(keyframe.points):
            local = keyframe.depth[np.isfinite(keyframe.depth)]
            self.scene_depth = float(np.median(local))
        return keyframe


def sweep_keyframe(events: np.ndarray, trajectory: Trajectory, K: np.ndarray, width: int, height: int,
                   depths: np.ndarray, params: sweep.SweepParams) -> Keyframe:
    """One segment's events swept at the pose of their middle time into a keyframe."""
    t_ref = int((int(events["t"][0]) + int(events["t"][-1])) // 2)
    R_ref, p_ref = (a[0] for a in trajectory.at(t_ref))
    which = np.arange(len(events)) // POSE_EVERY
    stamps = np.add.reduceat(events["t"].astype(np.float64), np.arange(0, len(events), POSE_EVERY))
    stamps /= np.diff(np.append(np.arange(0, len(events), POSE_EVERY), len(events)))
    R, p = trajectory.at(stamps)
    R_ref_cam = np.einsum("ji,njk->nik", R_ref, R)
    t_ref_cam = (p - p_ref) @ R_ref
    xy = np.stack([events["x"], events["y"]], axis=1).astype(np.float64)
    dsi = np.zeros((len(depths), height, width), np.float32)
    sweep.vote(dsi, sweep.ray_coefficients(xy, K, R_ref_cam, t_ref_cam, which), depths)
    depth, conf = sweep.semi_dense_depth(dsi, depths, params, K, t_ref_cam[::max(len(t_ref_cam) // 32, 1)])
    return lift(t_ref, R_ref, p_ref, depth, conf, K, len(events))


def lift(t_us: int, R: np.ndarray, p: np.ndarray, depth: np.ndarray, confidence: np.ndarray, K: np.ndarray,
         n: int) -> Keyframe:
    """The keyframe of a reference view's depth map (H x W, NaN where none) and per-pixel confidence: its
    finite pixels lifted into world points; `n` items made it."""
    ys, xs = np.nonzero(np.isfinite(depth))
    z = depth[ys, xs].astype(np.float64)
    cam = np.stack([(xs - K[0, 2]) / K[0, 0] * z, (ys - K[1, 2]) / K[1, 1] * z, z], axis=1)
    points = (cam @ R.T + p).astype(np.float32)
    return Keyframe(t_us, R, p, depth, points, confidence[ys, xs].astype(np.float32), n)
