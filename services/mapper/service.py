"""The mapper service: a semi-dense map (or, for a rotating camera, a panoramic mosaic) from one
camera's events and a pose stream, live.

It follows the camera's events (fifo, drop-oldest) and poses (the tracker's ego pose, or the
simulator's truth with `--poses truth`), holds events until poses cover their time, and feeds them
to the same keyframe sweep as `etam map`, in a worker thread so that receiving never waits on a
sweep. Each keyframe's fused points are published on ``mapper/map/points``, its own points (the
6-DoF tracker follows them) on ``mapper/map/keyframe``, and its semi-dense depth map (m, NaN where none;
the tracker's `xyz` reads it) on ``mapper/map/depth``; ``mapper/map/all``
answers with the whole map; commands `reset` and `save` (`path`: a PLY file) act on it. The map
is a capped voxel grid, and pending events and poses are bounded too, so memory stays bounded.

With `--method stereo` it pairs that camera with a second one (`--right`, default cam1): both cameras'
events, held until poses cover them, feed the stereo mapper (`etam map --method stereo`'s) instead, with
the rig's geometry from their CameraInfo (`T_body_cam`).

With `--build mosaic` the same events and poses feed the mosaic's gradient filter instead (`etam
mosaic`'s), and the mosaic is published at most twice a second on ``mapper/map/mosaic`` (a 16-bit PNG
Image, 0 where never observed): its Poisson reconstruction plus the correction the fit to the event
pairs found so far, fitted a little further each time; `save` writes the mosaic fitted in full, as
`etam mosaic` does (seconds; the reply comes when it is written).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Awaitable
from pathlib import Path

import numpy as np

from services import keys
from services.kernels import load
from services.mapper.cloud import VoxelMap
from services.mapper.keyframes import Keyframe, KeyframeMapper, KeyframeParams
from services.mapper.mosaic import Mosaic, MosaicParams, to_png16
from services.mapper.offline import METHODS, write_mosaic
from services.mapper.ply import write_map
from services.mapper.stereo import StereoMapper, StereoParams, relative_pose
from services.mapper.trajectory import Trajectory
from services.mapper.warmup import warm_up
from services.messages import (
    EVENT_DTYPE, CameraInfo, Command, EventPacket, Message, PointCloud, Pose, Reply, image_from_array,
)
from services.runtime import Output, Service, ServiceOptions

log = logging.getLogger(__name__)

POSES_KEPT = 3_000  # the latest poses held (a minute at 50 Hz, many segments): older events are dropped
WORK_PERIOD_S = 0.05  # new events and poses are taken in batches at most this often
# events held per camera while they wait for poses or for a keyframe's sweep (seconds on a busy machine), 128 MB;
# the oldest go beyond
PENDING_EVENTS = 8_000_000
MOSAIC_PERIOD_S = 0.5  # the mosaic is rebuilt (Poisson, then 2 fit iterations) and published this often
LIVE_FIT_ITERATIONS, LIVE_PAIR_STRIDE = 2, 4  # ... on a quarter of the pairs
MOSAIC_DUTY = 4  # ... or less often: drawing takes at most 1 / MOSAIC_DUTY of the time
STEREO_FRAMES_PER_BATCH = 2  # a batch (WORK_PERIOD_S, longer when behind) matches at most this many stereo frames
MODES = ("depth", "mosaic")
# no pose for this long (or for 5 of the poses' usual spacing, if longer): the source had none (a tracker lost), so
# the events between have none either and are dropped, and the keyframe segment with them
POSE_GAP_US = 100_000


class MapperService(Service):
    kind = "mapper"

    def __init__(self, options: ServiceOptions, params: KeyframeParams | None = None, cam: str = "cam0",
                 poses: str = "ego", mode: str = "depth", mosaic_params: MosaicParams | None = None,
                 method: str = "sweep", right: str = "cam1", stereo: StereoParams | None = None,
                 max_rate: float = 4e5) -> None:
        super().__init__(options)
        if mode not in MODES or method not in METHODS:
            raise ValueError(f"mapper mode {mode!r} / method {method!r}: modes are {', '.join(MODES)}, "
                             f"methods {', '.join(METHODS)}")
        if max_rate < 0:
            raise ValueError(f"--max-rate must be >= 0 (0: every event), got {max_rate / 1e6}")
        if method == "stereo" and (mode != "depth" or right == cam):
            raise ValueError(f"stereo maps depth from two cameras: --right ({right}) must differ from --cam ({cam})")
        self.map_params, self.mosaic_params = params or KeyframeParams(), mosaic_params or MosaicParams()
        self.stereo_params = stereo or StereoParams()
        self.cam, self.poses, self.mode, self.method = cam, poses, mode, method
        self.max_rate = max_rate  # events per second of stream the sweep takes at most (0: all)
        self.cams = (cam, right) if method == "stereo" else (cam,)
        self.mosaic: Mosaic | None = None
        self._mosaic_due = 0.0  # when the next mosaic may be drawn
        self._mosaic_correction: np.ndarray | None = None  # what the live fit adds to the Poisson reconstruction
        self._mosaic_lock = asyncio.Lock()  # the mosaic's arrays: folded in, or read for a save, in worker threads
        self.cameras: dict[str, CameraInfo] = {}
        self.cloud = VoxelMap()
        self.mapper: KeyframeMapper | StereoMapper | None = None
        self._rows: collections.deque[np.ndarray] = collections.deque(maxlen=POSES_KEPT)
        self._pending = {c: collections.deque() for c in self.cams}
        self._n_pending = dict.fromkeys(self.cams, 0)
        self._received_us = dict.fromkeys(self.cams, -1)  # each camera's latest event time so far
        self._floor_us = -1  # events before this have no pose (a gap in the poses): never mapped
        self._gap = False  # a gap came since the last batch: the segment held spans it
        self._cut_us: int | None = None  # a keyframe was asked for: the segment ends once mapped up to here
        self._wake = asyncio.Event()
        self.status = {"mode": mode, "method": method, "poses": poses, "camera": "+".join(self.cams), "keyframes": 0,
                       "map_points": 0, "dropped_events": 0}

    def pose_key(self) -> str:
        if self.poses == "truth":
            return keys.key(self.rig, "camera", self.cam, "truth/pose")
        return keys.key(self.rig, "tracker", "ego", "pose")

    async def main(self) -> None:
        if self.mode == "depth":
            # before any event can queue up
            await asyncio.to_thread(load, f"the mapper ({self.method})", lambda: warm_up(self.method))
        self.serve("all", self._whole_map)
        await asyncio.gather(*(self._events(cam) for cam in self.cams), self._follow_poses(), self._work(),
                             self.follow_cameras("*", self.cameras, lambda: not set(self.cams) <= set(self.cameras)))

    async def _events(self, cam: str) -> None:
        pending = self._pending[cam]
        async for _, msg in self.subscribe(keys.events(self.rig, cam), EventPacket, policy="fifo", maxsize=4096):
            assert isinstance(msg, EventPacket)
            if self.paused or not len(msg.events):
                continue
            pending.append(msg.events)
            self._n_pending[cam] += len(msg.events)
            self._received_us[cam] = int(msg.events["t"][-1])
            if cam == self.cam:
                self.status["received_until_us"] = self._received_us[cam]
            while self._n_pending[cam] > PENDING_EVENTS:  # no poses for a long while: the oldest go, counted
                old = pending.popleft()
                self._n_pending[cam] -= len(old)
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
            if self._rows and msg.t - self._rows[-1][0] * 1e6 > self._gap_limit_us():
                log.info("no poses from %.3f to %.3f s: the events between are not mapped", self._rows[-1][0],
                         msg.t / 1e6)
                self._floor_us, self._gap = msg.t, True
                self.status["pose_gaps"] = self.status.get("pose_gaps", 0) + 1
            self._rows.append(np.array([msg.t / 1e6, *msg.p, *msg.q]))
            self._wake.set()

    def _gap_limit_us(self) -> float:
        recent = [row[0] for row in list(self._rows)[-50:]]
        return max(POSE_GAP_US, 5e6 * float(np.median(np.diff(recent)))) if len(recent) > 2 else POSE_GAP_US

    async def _work(self) -> None:
        """Sweeps the events that poses cover, in a worker thread, and publishes each keyframe's points."""
        out, depth_out, mosaic_out = self.publisher("points"), self.publisher("depth"), self.publisher("mosaic")
        keyframe_out = self.publisher("keyframe")
        while True:
            await self._wake.wait()
            await asyncio.sleep(WORK_PERIOD_S)  # a batch, not one pass (and one trajectory) per packet
            self._wake.clear()
            infos = [self.cameras.get(c) for c in self.cams]
            if None in infos or len(self._rows) < 2:
                continue
            # up to where poses cover and every camera has delivered (a stereo pair's packets arrive apart)
            posed_us = int(round(self._rows[-1][0] * 1e6))
            until_us = min(posed_us, *self._received_us.values())
            ready = [self._take_until(c, until_us) for c in self.cams]
            self.status.update(pending_events=sum(self._n_pending.values()), posed_until_us=posed_us)
            if not any(len(r) for r in ready) or "error" in self.status:
                continue
            taken_us = max(int(r["t"][-1]) for r in ready if len(r))
            trajectory = Trajectory(np.array(self._rows))
            ready = [r[r["t"] >= max(trajectory.start_us, self._floor_us)] for r in ready]
            if self._gap:
                self._gap = False
                if self.mapper is not None:
                    self.mapper.drop()
            if self.mode == "mosaic":
                await self._fold_mosaic(ready[0], trajectory, infos[0], mosaic_out)
                self.status["mapped_until_us"] = taken_us
                continue
            if self.mapper is None:
                try:
                    self.mapper = self._new_mapper(infos)
                except ValueError as exc:  # a rig that cannot be rectified: say so, keep serving
                    log.error("cannot map with cameras %s: %s", "+".join(self.cams), exc)
                    self.status["error"] = str(exc)
                    continue
            for kf in await asyncio.to_thread(self._map, ready, trajectory):
                self._publish_keyframe(kf, out, depth_out, keyframe_out)
            if self._cut_us is not None and taken_us >= self._cut_us:
                self._cut_us = None
                # the first keyframe comes of what is held; a later one only if it can place its points (a
                # tracker asks for one as its map fails it)
                cut = self.mapper.early if self.cloud.views else self.mapper.finish
                if self.mapper.held and (kf := await asyncio.to_thread(cut, trajectory)) is not None:
                    self._publish_keyframe(kf, out, depth_out, keyframe_out)
            self.status["mapped_until_us"] = taken_us  # every event up to here is in the map (or its segment)

    def _publish_keyframe(self, kf: Keyframe, out: Output, depth_out: Output, keyframe_out: Output) -> None:
        new = self.cloud.add_keyframe(kf)
        out.publish(PointCloud(t=kf.t_us, stamp=kf.t_us, points=new, keyframe=_matrix(kf)))
        depth_out.publish(image_from_array(kf.t_us, kf.depth, "rawf32"))  # the tracker's xyz reads it
        # and its own points, not thinned by the map's voxels: what a 6-DoF tracker follows
        keyframe_out.publish(PointCloud(t=kf.t_us, stamp=kf.t_us, points=kf.points, confidence=kf.confidence,
                                        keyframe=_matrix(kf)))
        log.info("keyframe %d at %.3f s: %d points, map %d", len(self.cloud.views), kf.t_us / 1e6,
                 len(kf.points), len(self.cloud))
        self.status.update(keyframes=len(self.cloud.views), map_points=len(self.cloud))

    def _map(self, ready: list[np.ndarray], trajectory: Trajectory) -> list[Keyframe]:
        """The keyframes a batch completes, its work bounded so that the mapper keeps up with the camera:
        the sweep takes every k-th event (at most `max_rate` per second of stream), stereo matches at most
        STEREO_FRAMES_PER_BATCH frames (the time surfaces take every event)."""
        if isinstance(self.mapper, StereoMapper):
            keyframes = self.mapper.add(*ready, trajectory, max_frames=STEREO_FRAMES_PER_BATCH)
            self.status["stereo_frames_skipped"] = self.mapper.matcher.skipped
            return keyframes
        events = ready[0]
        span_s = (int(events["t"][-1]) - int(events["t"][0])) / 1e6 if len(events) else 0.0
        stride = max(1, int(np.ceil(len(events) / (span_s * self.max_rate)))) if self.max_rate and span_s > 0 else 1
        self.status["sweep_stride"] = stride
        return self.mapper.add(events[::stride], trajectory)

    def _new_mapper(self, infos: list[CameraInfo]) -> KeyframeMapper | StereoMapper:
        left = infos[0]
        if self.method == "sweep":
            return KeyframeMapper(left.K, left.width, left.height, self.map_params)
        right = infos[1]
        if (right.width, right.height) != (left.width, left.height):
            raise ValueError(f"the cameras differ in size ({left.width}x{left.height}, {right.width}x{right.height})")
        return StereoMapper(left.K, right.K, relative_pose(left.T_body_cam, right.T_body_cam), left.width,
                            left.height, self.map_params, self.stereo_params)

    async def _fold_mosaic(self, ready: np.ndarray, trajectory: Trajectory, info: CameraInfo, out) -> None:  # noqa: ANN001
        """Folds events into the mosaic (in a worker thread) and publishes it when it is due."""
        if self.mosaic is None:
            self.mosaic = Mosaic(info.K, info.width, info.height, self.mosaic_params)
        mosaic = self.mosaic
        async with self._mosaic_lock:
            await asyncio.to_thread(mosaic.add, ready, trajectory)
            if time.monotonic() < self._mosaic_due or not len(ready):
                return
            started = time.monotonic()
            image = await asyncio.to_thread(self._mosaic_view, mosaic)
            took = time.monotonic() - started  # a large mosaic is drawn less often
            self._mosaic_due = started + max(MOSAIC_PERIOD_S, MOSAIC_DUTY * took)
        t_us = int(ready["t"][-1])
        out.publish(image_from_array(t_us, image, "png"))
        self.status.update(mosaic_events=mosaic.events, mosaic_observed=round(float((image > 0).mean()), 4))

    def _mosaic_view(self, mosaic: Mosaic) -> np.ndarray:
        """The published mosaic, as `to_png16` grey levels: the Poisson reconstruction plus the correction
        the last view's fit found, fitted a little further to a sample of the event pairs (a full fit
        each time would take seconds; this one trails it by 1-3 dB on the dev seed)."""
        view = poisson = mosaic.log_intensity(fit=False)
        if mosaic.pairs and mosaic.params.fit_iterations > 0:
            start = poisson if self._mosaic_correction is None else poisson + self._mosaic_correction
            view = mosaic.fitted(start, LIVE_FIT_ITERATIONS, LIVE_PAIR_STRIDE)
            self._mosaic_correction = view - poisson
        return to_png16(view, mosaic.observed())

    def _take_until(self, cam: str, until_us: int) -> np.ndarray:
        """Camera `cam`'s pending events up to `until_us` (later ones stay pending), in time order."""
        taken, pending = [], self._pending[cam]
        while pending and pending[0]["t"][-1] <= until_us:
            taken.append(pending.popleft())
        if pending and pending[0]["t"][0] <= until_us:
            head = pending[0]
            cut = int(np.searchsorted(head["t"], until_us, side="right"))
            taken.append(head[:cut])
            pending[0] = head[cut:]
        self._n_pending[cam] -= sum(len(t) for t in taken)
        return np.concatenate(taken) if taken else np.zeros(0, EVENT_DTYPE)

    def _whole_map(self, _: Message | None) -> Message:
        points, _, conf, _ = self.cloud.points()
        t = self.cloud.views[-1][0] if self.cloud.views else 0
        return PointCloud(t=t, stamp=t, points=points, confidence=conf)

    def _clear(self) -> None:
        self.cloud.reset()
        self.mapper = None
        self.mosaic = None
        self._mosaic_correction = None
        self._rows.clear()
        self._floor_us, self._gap = -1, False
        for cam in self.cams:
            self._pending[cam].clear()
            self._n_pending[cam] = 0
            self._received_us[cam] = -1

    def on_command(self, cmd: Command) -> Reply | Awaitable[Reply] | None:
        if cmd.op == "reset":
            self._clear()
            return Reply(ok=True)
        if cmd.op == "keyframe":  # end the segment held once mapped up to `until_us` (default: now), see `_work`
            until = (cmd.args or {}).get("until_us", self.status.get("received_until_us", 0))
            if not isinstance(until, int) or self.mode != "depth":
                return Reply(ok=False, error="keyframe: a depth map's, with args {'until_us': int} or none")
            self._cut_us = until
            self._wake.set()
            return Reply(ok=True, result={"until_us": until})
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

    async def _save_mosaic(self, path: str) -> Reply:
        """The mosaic as `etam mosaic` writes it, fitted to its event pairs (seconds: the reply comes once
        it is written; events meanwhile wait in the pending queue)."""
        mosaic = self.mosaic  # a reset meanwhile starts a new one; this one is still saved
        if mosaic is None:
            return Reply(ok=False, error="save: no mosaic yet (no events with poses so far)")
        async with self._mosaic_lock:
            try:
                observed = await asyncio.to_thread(write_mosaic, Path(path), mosaic)
            except OSError as exc:
                return Reply(ok=False, error=f"save: {path}: {exc.strerror or exc}")
        return Reply(ok=True, result={"path": path, "observed": observed, "pairs": mosaic.pairs})


def _matrix(kf: Keyframe) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = kf.R, kf.p
    return T
