"""The tracking half of the live tracking-mapping loop: the 6-DoF tracker follows a map that another
process (the mapper service) builds from this tracker's poses.

Bootstrapping is a first map from a short known motion, as `etam odom --mode 6dof` does, split over
the two processes: until the map's first part (a keyframe's points) comes, the known poses (the
simulator's truth) are what the loop runs on (the tracker service passes them on, and the mapper sweeps
its first keyframe with them, asked for after `BOOTSTRAP_US` of known motion), and the events are held.
Then the tracker starts at the last known pose (with the one `step_us` before it for its first velocity),
the held events before it filling its window, and gives its estimates from there on; no known pose is
used after. Started at the keyframe's time instead, where its map fits the events best, it caught up
through the held events unseen, and drifted there: the more, the longer the mapper's sweep took (on a
loaded 2-core VM the stereo rig's first own poses were 11-51 cm off; from the last known pose, 0.5-15 cm).
Each later part of the map joins the tracker's map. The camera's gyro samples, where it sends any, predict
the rotation (`gyro.py`).
"""

from __future__ import annotations

import collections
import threading

import numpy as np

from services import events as ev_ops
from services.mapper.trajectory import Trajectory
from services.tracker.ego.gyro import Gyro
from services.tracker.ego.sixdof import PoseEstimate, SixDofParams, SixDofTracker

BOOTSTRAP_US = 1_500_000  # known motion after which the first keyframe is asked for (`etam odom --bootstrap`'s)
KNOWN_KEPT = 1_000  # known poses kept before the start (20 s of them at 50 Hz)
# events held before the start: the latest this long (the tracker's window before the last known pose, and more
# where the known poses run behind the events)
HELD_US = 4_000_000


class MapFollower:
    """Known poses and map parts in, events (undistorted, sorted) in; 6-DoF estimates out once started.
    `known` and `add_map` may be called while `add` runs in another thread."""

    def __init__(self, K: np.ndarray, width: int, height: int, params: SixDofParams | None = None) -> None:
        self.gyro = Gyro()  # the camera's samples, where it sends any
        self.tracker = SixDofTracker(K, width, height, params, gyro=self.gyro)
        self._known: collections.deque[list[float]] = collections.deque(maxlen=KNOWN_KEPT)  # TUM rows
        self._lock = threading.Lock()  # the known poses, and whether it started
        self._started = False
        self._held: collections.deque[np.ndarray] = collections.deque()
        self._known_until_us = -1  # estimates are given from after the last known pose on
        self.map_parts = 0  # how many parts of the map (keyframes) came so far

    @property
    def started(self) -> bool:
        return self._started

    @property
    def wants_map(self) -> bool:
        """Whether the known motion is long enough for a first keyframe that has not come yet: the mapper is
        asked to end its segment there (as `etam odom` does after `--bootstrap` s), not a baseline later."""
        with self._lock:
            span = (self._known[-1][0] - self._known[0][0]) * 1e6 if self._known else 0.0
        return not self.map_parts and span >= BOOTSTRAP_US

    def known(self, t_us: int, q: np.ndarray, p: np.ndarray) -> bool:
        """A known pose (T_world_cam, quaternion x y z w): whether the loop runs on it (before the start)."""
        with self._lock:
            if self._started or (self._known and t_us <= self._known[-1][0] * 1e6):
                return False
            self._known.append([t_us / 1e6, *np.asarray(p, float), *np.asarray(q, float)])
            return True

    def add_imu(self, t_us: np.ndarray, gyro: np.ndarray) -> None:
        """Gyro samples (rad/s, N x 3, in the camera's frame) of the camera followed; until they cover an update
        (or where they stop), its rotation is predicted from the poses alone."""
        self.gyro.add(t_us, gyro)

    def add_map(self, points: np.ndarray) -> None:
        """World points (N x 3) of one more part of the map (a keyframe's)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if len(points):
            self.tracker.add_points(points)
            self.map_parts += 1

    def add(self, events: np.ndarray) -> list[PoseEstimate]:
        """Events sorted by time; the estimates of the updates they completed (none before the start)."""
        if self._started:
            return self._after_known(self.tracker.add(events))
        if len(events):
            self._held.append(events)
            while int(events["t"][-1]) - int(self._held[0]["t"][-1]) > HELD_US:
                self._held.popleft()
        if not self.map_parts or len(self._known) < 2 or not self._held:
            return []
        return self._start()

    def _start(self) -> list[PoseEstimate]:
        with self._lock:
            known = Trajectory(np.asarray(self._known))
            self._started = True
        held = ev_ops.concat(list(self._held))
        self._held.clear()
        step = self.tracker.params.step_us
        t_us = max(known.end_us, known.start_us + step)
        t_us -= t_us % step  # on the update grid of `etam odom`
        self.tracker.start_on(known, t_us)
        self._known_until_us = known.end_us
        return self._after_known(self.tracker.add(held))

    def _after_known(self, estimates: list[PoseEstimate]) -> list[PoseEstimate]:
        """Those after the last known pose (the held events may end before it: the known poses run ahead)."""
        return [est for est in estimates if est.t_us > self._known_until_us]
