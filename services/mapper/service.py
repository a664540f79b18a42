"""The mapper service: a semi-dense map (or, for a rotating camera, a panoramic mosaic) from one
camera's events and a pose stream, live.

It follows the camera's events (fifo, drop-oldest) and poses (the tracker's ego pose, or the
simulator's truth with `--poses truth`), holds events until poses cover their time, and feeds them
to the same keyframe sweep as `etam map`, in a worker thread so that receiving never waits on a
sweep. Each keyframe's fused points are published on ``mapper/map/points``, and its semi-dense depth
map (m, NaN where none; the tracker's `xyz` reads it) on ``mapper/map/depth``; ``mapper/map/all``
answers with the whole map; commands `reset` and `save` (`path`: a PLY file) act on it. The map
is a capped voxel grid, and pending events and poses are bounded too, so memory stays bounded.

With `--build mosaic` the same events and poses feed the mosaic's gradient filter instead (`etam
mosaic`'s), and its Poisson reconstruction is published at most twice a second on
``mapper/map/mosaic`` (a 16-bit PNG Image, 0 where never observed); `save` then writes that PNG.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from pathlib import Path

import numpy as np

from services import keys
from services.messages import (
    EVENT_DTYPE, Command, EventPacket, Message, PointCloud, Pose, Reply, image_from_array,
)
from services.mapper.cloud import VoxelMap
from services.mapper.keyframes import Keyframe, KeyframeMapper, KeyframeParams
from services.mapper.mosaic import Mosaic, MosaicParams
from services.mapper.offline import write_mosaic
from services.mapper.ply import write_map
from services.mapper.trajectory import Trajectory
from services.runtime import Service, ServiceOptions

log = logging.getLogger(__name__)

POSES_KEPT = 3_000  # the latest poses held (a minute at 50 Hz, many segments): older events are dropped
WORK_PERIOD_S = 0.05  # new events and poses are taken in batches at most this often
PENDING_EVENTS = 2_000_000  # events held while they wait for poses (32 MB); the oldest go beyond
MOSAIC_PERIOD_S = 0.5  # the mosaic is rebuilt (a Poisson solve, ~0.2 s at 2048 x 1024) and published this often
MODES = ("depth", "mosaic")


class MapperService(Service):
    kind = "mapper"

    def __init__(self, options: ServiceOptions, params: KeyframeParams | None = None, cam: str = "cam0",
                 poses: str = "ego", mode: str = "depth", mosaic_params: MosaicParams | None = None) -> None:
        super().__init__(options)
        if mode not in MODES:
            raise ValueError(f"mapper mode {mode!r} is not one of {', '.join(MODES)}")
        self.map_params, self.mosaic_params = params or KeyframeParams(), mosaic_params or MosaicParams()
        self.cam, self.poses, self.mode = cam, poses, mode
        self.mosaic: Mosaic | None = None
        self._mosaic_published = 0.0
        self.K: dict[str, np.ndarray] = {}
        self.cloud = VoxelMap()
        self.mapper: KeyframeMapper | None = None
        self._rows: collections.deque[np.ndarray] = collections.deque(maxlen=POSES_KEPT)
        self._pending: collections.deque[np.ndarray] = collections.deque()
        self._n_pending = 0
        self._size: tuple[int, int] | None = None
        self._wake = asyncio.Event()
        self.status = {"mode": mode, "poses": poses, "camera": cam, "keyframes": 0, "map_points": 0,
                       "dropped_events": 0}

    def pose_key(self) -> str:
        if self.poses == "truth":
            return keys.key(self.rig, "camera", self.cam, "truth/pose")
        return keys.key(self.rig, "tracker", "ego", "pose")

    async def main(self) -> None:
        self.serve("all", self._whole_map)
        await asyncio.gather(self._events(), self._follow_poses(), self._work(),
                             self.follow_intrinsics(self.cam, self.K, lambda: self.cam not in self.K))

    async def _events(self) -> None:
        async for _, msg in self.subscribe(keys.events(self.rig, self.cam), EventPacket, policy="fifo", maxsize=4096):
            assert isinstance(msg, EventPacket)
            if self.paused or not len(msg.events):
                continue
            self._size = (msg.width, msg.height)
            self._pending.append(msg.events)
            self._n_pending += len(msg.events)
            while self._n_pending > PENDING_EVENTS:  # no poses for a long while: the oldest go, counted
                old = self._pending.popleft()
                self._n_pending -= len(old)
                if not self.status["dropped_events"]:
                    log.warning("no poses on %s cover the events: dropping the oldest", self.pose_key())
                self.status["dropped_events"] += len(old)
            self._wake.set()

    async def _follow_poses(self) -> None:
        async for _, msg in self.subscribe(self.pose_key(), Pose, policy="fifo", maxsize=1024):
            assert isinstance(msg, Pose)
            if self._rows and msg.t <= self._rows[-1][0] * 1e6:
                if msg.t < self._rows[-1][0] * 1e6 - 1e6:  # time went back: the source restarted
                    log.info("poses went back in time: starting a new map")
                    self._clear()
                else:
                    continue
            self._rows.append(np.array([msg.t / 1e6, *msg.p, *msg.q]))
            self._wake.set()

    async def _work(self) -> None:
        """Sweeps the events that poses cover, in a worker thread, and publishes each keyframe's points."""
        out, depth_out, mosaic_out = self.publisher("points"), self.publisher("depth"), self.publisher("mosaic")
        while True:
            await self._wake.wait()
            await asyncio.sleep(WORK_PERIOD_S)  # a batch, not one pass (and one trajectory) per packet
            self._wake.clear()
            K = self.K.get(self.cam)
            if K is None or self._size is None or len(self._rows) < 2:
                continue
            until_us = int(round(self._rows[-1][0] * 1e6))
            ready = self._take_until(until_us)
            if not len(ready):
                continue
            trajectory = Trajectory(np.array(self._rows))
            ready = ready[ready["t"] >= trajectory.start_us]
            if self.mode == "mosaic":
                await self._fold_mosaic(ready, trajectory, K, mosaic_out)
                continue
            if self.mapper is None:
                self.mapper = KeyframeMapper(K, *self._size, self.map_params)
            for kf in await asyncio.to_thread(self.mapper.add, ready, trajectory):
                new = self.cloud.add_keyframe(kf)
                out.publish(PointCloud(t=kf.t_us, stamp=kf.t_us, points=new, keyframe=_matrix(kf)))
                depth_out.publish(image_from_array(kf.t_us, kf.depth, "rawf32"))  # the tracker's xyz reads it
                log.info("keyframe %d at %.3f s: %d points, map %d", len(self.cloud.views), kf.t_us / 1e6,
                         len(kf.points), len(self.cloud))
                self.status.update(keyframes=len(self.cloud.views), map_points=len(self.cloud))

    async def _fold_mosaic(self, ready: np.ndarray, trajectory: Trajectory, K: np.ndarray, out) -> None:  # noqa: ANN001
        """Folds events into the mosaic (in a worker thread) and publishes it when it is due."""
        if self.mosaic is None:
            self.mosaic = Mosaic(K, *self._size, self.mosaic_params)
        mosaic = self.mosaic
        await asyncio.to_thread(mosaic.add, ready, trajectory)
        if time.monotonic() - self._mosaic_published < MOSAIC_PERIOD_S or not len(ready):
            return
        self._mosaic_published = time.monotonic()
        image = await asyncio.to_thread(mosaic.image)
        t_us = int(ready["t"][-1])
        out.publish(image_from_array(t_us, image, "png"))
        self.status.update(mosaic_events=mosaic.events, mosaic_observed=round(float((image > 0).mean()), 4))

    def _take_until(self, until_us: int) -> np.ndarray:
        """The pending events up to `until_us` (later ones stay pending), in time order."""
        taken = []
        while self._pending and self._pending[0]["t"][-1] <= until_us:
            taken.append(self._pending.popleft())
        if self._pending and self._pending[0]["t"][0] <= until_us:
            head = self._pending[0]
            cut = int(np.searchsorted(head["t"], until_us, side="right"))
            taken.append(head[:cut])
            self._pending[0] = head[cut:]
        n = sum(len(t) for t in taken)
        self._n_pending -= n
        return np.concatenate(taken) if taken else np.zeros(0, EVENT_DTYPE)

    def _whole_map(self, _: Message | None) -> Message:
        points, _, conf, _ = self.cloud.points()
        t = self.cloud.views[-1][0] if self.cloud.views else 0
        return PointCloud(t=t, stamp=t, points=points, confidence=conf)

    def _clear(self) -> None:
        self.cloud.reset()
        self.mapper = None
        self.mosaic = None
        self._rows.clear()
        self._pending.clear()
        self._n_pending = 0

    def on_command(self, cmd: Command) -> Reply | None:
        if cmd.op == "reset":
            self._clear()
            return Reply(ok=True)
        if cmd.op == "save":
            path = (cmd.args or {}).get("path")
            if not isinstance(path, str) or not path:
                return Reply(ok=False, error="save: give args {'path': 'FILE.ply'}")
            try:
                if self.mode == "mosaic":
                    return self._save_mosaic(path)
                n = write_map(Path(path), self.cloud, f"etam mapper {self.rig}/{self.name}")
            except OSError as exc:
                return Reply(ok=False, error=f"save: {path}: {exc.strerror or exc}")
            return Reply(ok=True, result={"path": path, "points": n})
        return None

    def _save_mosaic(self, path: str) -> Reply:
        """The mosaic as `etam mosaic` writes it (so `etam eval mosaic` reads it)."""
        if self.mosaic is None:
            return Reply(ok=False, error="save: no mosaic yet (no events with poses so far)")
        return Reply(ok=True, result={"path": path, "observed": write_mosaic(Path(path), self.mosaic)})


def _matrix(kf: Keyframe) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = kf.R, kf.p
    return T
