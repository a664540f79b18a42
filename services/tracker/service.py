"""The tracker service: object tracks from the camera's event packets (``tracker/objects/tracks``),
and with `ego` the camera's own motion (``tracker/ego/pose``, a Pose with `omega` for every estimate):
"rotation", its orientation at 100 Hz (`ego/rotation.py`); "6dof", its pose at 50 Hz, aligned to the map
that the mapper service builds from these poses (`ego/follow.py`: the live tracking-mapping loop, started
from the camera's known poses until the mapper's first points come).

Each track gets a 3D position (`xyz`, camera frame) when it can: from the latest depth image of the
same camera (the mapper's, or a simulator's truth) where the box holds valid depth, else from a
configured object width and the camera's intrinsics (Z = fx * size / pixels).

The ego-motion follows one camera (the first to send events, or `cam` where it names one) on a
subscription of its own, in a worker thread (its kernels release the GIL), so a slow estimate delays
neither the object tracks nor the service's commands; it starts once that camera's intrinsics are
known (its events undistorted by them, as `etam odom` does a file's), and starts again (a new world
frame) where the camera's time goes back.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from dataclasses import dataclass, field

import numpy as np

from services import events as ev_ops
from services import keys
from services.camera.filters import Undistort
from services.kernels import load
from services.messages import (CameraInfo, Command, EventPacket, Image, ImuPacket, MessageError, PointCloud, Pose,
                               Reply, Tracks, image_to_array)
from services.runtime import Output, Service, ServiceOptions
from services.tracker.ego import MODES as EGO_MODES
from services.tracker.ego.follow import MapFollower
from services.tracker.ego.loop import MapRefresh, RefreshParams
from services.tracker.ego.rotation import LOST, STATES, RotationParams, RotationTracker
from services.tracker.ego.rotation import warm_up as rotation_warm_up
from services.tracker.objects.position import sizes_for, xyz_from_depth, xyz_from_size
from services.tracker.objects.tracker import ObjectTracker, TrackerParams, TrackSet, warm_up

log = logging.getLogger(__name__)

# 6-DoF: event packets (and known poses) kept while the camera's intrinsics are not known yet (seconds of them)
EARLY_PACKETS = 4_000


@dataclass
class ObjectSizes:
    """Known metric widths of targets: one for every track, and per track id."""

    default_m: float | None = None
    per_id: dict[int, float] = field(default_factory=dict)

    @classmethod
    def parse(cls, items: list[str]) -> ObjectSizes:
        """From `M` (every target) and `ID=M` items; ValueError naming a bad one."""
        sizes = cls()
        for item in items:
            ident, _, value = item.rpartition("=")
            try:
                metres = float(value)
                if not metres > 0:
                    raise ValueError
                if ident:
                    sizes.per_id[int(ident)] = metres
                else:
                    sizes.default_m = metres
            except ValueError:
                raise ValueError(f"--object-size {item!r}: expected M or ID=M with M > 0 metres") from None
        return sizes


@dataclass
class _Stream:
    """One camera's tracker and the sensor time of its next update."""

    tracker: ObjectTracker
    next_update_us: int
    last_stamp_us: int


class TrackerService(Service):
    """Subscribes to every camera's events (fifo, drop-oldest) and publishes Tracks every update."""

    kind = "tracker"

    def __init__(self, options: ServiceOptions, params: TrackerParams | None = None, cam: str = "*",
                 sizes: ObjectSizes | None = None, ego: str = "off", refresh: RefreshParams | None = None) -> None:
        """`refresh`: when the 6-DoF loop asks the mapper for a keyframe of its own (never, by default; see
        `MapRefresh`)."""
        super().__init__(options)
        if ego not in EGO_MODES:
            raise ValueError(f"ego-motion {ego!r} is not one of {', '.join(EGO_MODES)}")
        self.ego = ego
        self.motion: RotationTracker | MapFollower | None = None
        self.followed = ""  # the camera whose motion it follows
        self._asking: asyncio.Future | None = None  # the latest query for a keyframe
        self.refresh = MapRefresh(refresh)
        self._good_us = -1  # the latest good 6-DoF estimate's time
        self._early_known: collections.deque[Pose] = collections.deque(maxlen=EARLY_PACKETS)  # before intrinsics
        self.tracker_params = params or TrackerParams()
        self.cam = cam
        self.sizes = sizes or ObjectSizes()
        self.streams: dict[str, _Stream] = {}
        self.cameras: dict[str, CameraInfo] = {}  # camera name -> its size and intrinsics
        self.depth: dict[str, np.ndarray] = {}  # camera name -> latest depth image
        self.params = {"update_us": self.tracker_params.update_us,
                       "density": self.tracker_params.clusters.density,
                       "min_area_px": self.tracker_params.clusters.min_area_px,
                       "frames": self.tracker_params.frames, "detector": self.tracker_params.detector}

    async def main(self) -> None:
        ego = ()
        if self.ego != "off":
            poses = self.publisher(keys.key(self.rig, "tracker", "ego", "pose"))
            ego = (self._ego(poses),
                   *((self._known_poses(poses), self._map_parts(), self._gyro()) if self.ego == "6dof" else ()))
        await asyncio.gather(self._track(), self.follow_cameras(self.cam, self.cameras, self._missing_intrinsics),
                             self._depths(), *ego)

    def _missing_intrinsics(self) -> bool:
        """Whether a camera sending events (or none yet) has no known intrinsics."""
        return not self.streams or any(_camera(key) not in self.cameras for key in self.streams)

    async def _ego(self, out: Output) -> None:
        """Ego-motion estimates of the first camera that sends events (one, even where `cam` matches several:
        a rig moves as one), published as Poses on ``tracker/ego/pose`` (`out`)."""
        last_us, undistort = -1, None
        early: collections.deque[np.ndarray] = collections.deque(maxlen=EARLY_PACKETS)
        if self.ego == "rotation":
            await asyncio.to_thread(load, "the rotation tracker", rotation_warm_up)  # before any packet can queue up
        async for key, msg in self.subscribe(keys.events(self.rig, self.cam), EventPacket, policy="fifo",
                                             maxsize=1024):
            assert isinstance(msg, EventPacket)
            cam = _camera(key)
            self.followed = self.followed or cam
            if cam != self.followed or self.paused:
                continue
            info = self.cameras.get(cam)
            if info is None:
                if not early:
                    log.info("ego-motion of %s waits for its intrinsics", cam)
                if self.ego == "6dof":  # the first events make the first map: held for the follower to come
                    early.append(msg.events)
                continue
            if self.motion is None or msg.stamp < last_us:
                log.info("ego-motion (%s) of %s from %d us on", self.ego, cam, msg.stamp)
                self.motion = (RotationTracker(info.K, info.width, info.height, RotationParams())
                               if self.ego == "rotation" else MapFollower(info.K, info.width, info.height))
                undistort = Undistort.needed(info.width, info.height, info.K, info.dist_model, info.dist)
                if isinstance(self.motion, MapFollower):
                    log.info("6-DoF ego-motion of %s starts once the mapper's first points come; until then it "
                             "passes on the camera's known poses (%s)", cam, keys.key(self.rig, "camera", cam,
                                                                                     "truth/pose"))
                    for pose in self._early_known:
                        self.motion.known(pose.t, pose.q, pose.p)
            self._early_known.clear()
            last_us = msg.stamp
            events = ev_ops.concat([*early, msg.events]) if early else msg.events
            early.clear()
            events = undistort(events) if undistort is not None else events
            for est in await asyncio.to_thread(self.motion.add, events):
                if isinstance(self.motion, MapFollower) and self.refresh.due(est):
                    until = est.t_us if est.state != LOST else self._good_us
                    self._asking = asyncio.ensure_future(self._ask_keyframe(until, "a keyframe of the map it needs"))
                if est.state == LOST and self.status.get("ego_state") != STATES[LOST]:
                    log.warning("ego-motion of %s lost: %s", cam, "its events are no sharper for any rotation"
                                if self.ego == "rotation" else "the map does not line up with its events")
                self.status["ego_state"] = STATES[est.state]
                if est.state == LOST:  # no pose: the events say nothing of the motion (see rotation.LOST)
                    self.status["ego_lost"] = self.status.get("ego_lost", 0) + 1
                    continue
                self._good_us = est.t_us
                row = est.tum_row()  # t, position, quaternion
                out.publish(Pose(t=est.t_us, stamp=est.t_us, p=np.array(row[1:4]), q=np.array(row[4:]), child=cam,
                                 omega=est.omega))

    async def _known_poses(self, out: Output) -> None:
        """The followed camera's known poses (a simulator's truth) are the 6-DoF loop's until its map comes:
        passed on to ``tracker/ego/pose`` (`out`, the estimates' own), where the mapper sweeps its first
        keyframe with them."""
        asked = None  # the follower the first keyframe was asked for
        async for key, msg in self.subscribe(keys.key(self.rig, "camera", "*", "truth/pose"), Pose, policy="fifo",
                                             maxsize=1024):
            assert isinstance(msg, Pose)
            motion, cam = self.motion, _camera(key)
            if cam != (self.followed or cam):
                continue
            if motion is None:  # before the camera's intrinsics: kept for the follower to come, and passed on
                if self._early_known and msg.t <= self._early_known[-1].t:
                    continue
                self._early_known.append(msg)
            elif not (isinstance(motion, MapFollower) and motion.known(msg.t, msg.q, msg.p)):
                continue
            self.status["ego_state"] = "starting"
            out.publish(Pose(t=msg.t, stamp=msg.t, p=msg.p, q=msg.q, child=cam, omega=msg.omega))
            if isinstance(motion, MapFollower) and motion.wants_map and asked is not motion:
                asked = motion  # once per follower: the mapper ends its segment at this pose
                # held: a task nobody holds may go
                self._asking = asyncio.ensure_future(self._ask_keyframe(msg.t, "a first keyframe"))

    async def _ask_keyframe(self, t_us: int, what: str) -> None:
        """Asks the rig's mappers for a keyframe of the events up to `t_us` (the end of the known start, or the
        latest pose where the map fails the tracker)."""
        replies = await self.query(keys.key(self.rig, "mapper", "*", "cmd"), Reply,
                                   request=Command(op="keyframe", args={"until_us": int(t_us)}))
        if not any(isinstance(r, Reply) and r.ok for _, r in replies):
            self.status["ego_keyframes_unanswered"] = self.status.get("ego_keyframes_unanswered", 0) + 1
            (log.warning if self.status["ego_keyframes_unanswered"] == 1 else log.debug)(
                "no mapper took the request for %s: it comes at the mapper's own time", what)

    async def _gyro(self) -> None:
        """The followed camera's gyro samples (its ``imu`` key, where it has one) predict the 6-DoF tracker's
        rotation; those before the follower starts are not needed (it looks back one update at most)."""
        async for key, msg in self.subscribe(keys.key(self.rig, "camera", "*", "imu"), ImuPacket, policy="fifo",
                                             maxsize=1024):
            assert isinstance(msg, ImuPacket)
            if isinstance(self.motion, MapFollower) and _camera(key) == self.followed:
                self.motion.add_imu(msg.t, msg.gyro)
                self.status["ego_imu_samples"] = self.status.get("ego_imu_samples", 0) + len(msg.t)

    async def _map_parts(self) -> None:
        """Each keyframe's points from the mapper join the 6-DoF tracker's map."""
        async for _, msg in self.subscribe(keys.key(self.rig, "mapper", "*", "keyframe"), PointCloud,
                                           policy="fifo", maxsize=64):
            assert isinstance(msg, PointCloud)
            if isinstance(self.motion, MapFollower):
                self.motion.add_map(msg.points)
                self.refresh.keyframe_at(self._good_us)
                self.status["ego_map_parts"] = self.motion.map_parts

    async def _track(self) -> None:
        out = self.publisher("tracks")
        await asyncio.to_thread(load, "the object tracker", lambda: warm_up(self.tracker_params))  # before any packet
        events = self.subscribe(keys.events(self.rig, self.cam), EventPacket, policy="fifo", maxsize=1024)
        async for key, msg in events:
            assert isinstance(msg, EventPacket)
            stream = self._stream_for(key, msg)
            stream.last_stamp_us = msg.stamp
            if self.paused:
                continue
            stream.tracker.accept(msg.events)
            if msg.stamp < stream.next_update_us:
                continue
            tracks = stream.tracker.generate(msg.stamp)
            xyz, size_m = self._positions(_camera(key), tracks, (msg.height, msg.width))
            out.publish(Tracks(t=tracks.t_us, stamp=tracks.t_us, id=tracks.ids, box=tracks.boxes,
                               score=tracks.scores, vel=tracks.vels, state=tracks.states, xyz=xyz, size_m=size_m))
            # the next update on the update grid, skipping any slots this packet already passed
            step = int(self.params["update_us"])
            stream.next_update_us = max(stream.next_update_us + step, msg.stamp - msg.stamp % step + step)

    async def _depths(self) -> None:
        async for key, msg in self.subscribe(f"{keys.ROOT}/{self.rig}/**/depth", Image, policy="latest"):
            assert isinstance(msg, Image)
            try:
                # a camera's own (truth) depth is its; another service's (the mapper's) fits any camera of its size
                parsed = keys.parse(key)
                cam = parsed[2] if parsed and parsed[1] == "camera" else "*"
                self.depth[cam] = image_to_array(msg).astype(np.float32, copy=False)
            except (MessageError, ValueError) as exc:
                log.warning("ignoring depth image on %s: %s", key, exc)

    def _positions(self, cam: str, tracks: TrackSet,
                   shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
        """xyz per track (from depth where the box has some, else from its known width) and the
        widths used; None, None when neither a depth image nor any width is known, or the
        intrinsics are not."""
        K = self.cameras[cam].K if cam in self.cameras else None
        depth = self.depth.get(cam, self.depth.get("*"))
        if K is None or (depth is None and self.sizes.default_m is None and not self.sizes.per_id):
            return None, None
        size_m = sizes_for(tracks.ids, self.sizes.default_m, self.sizes.per_id)
        xyz = xyz_from_size(tracks.boxes, size_m, K)
        if depth is not None and depth.shape == shape:
            from_depth = xyz_from_depth(tracks.boxes, depth, K)
            known = np.isfinite(from_depth[:, 2])
            xyz[known] = from_depth[known]
        return xyz.astype("<f4"), size_m.astype("<f4")

    def _stream_for(self, key: str, msg: EventPacket) -> _Stream:
        """The stream of `key`, made anew for a new camera, a new sensor size, or time going back
        (the source restarted or a recording looped)."""
        stream = self.streams.get(key)
        p = self.tracker_params
        p.clusters.density = float(self.params["density"])
        p.clusters.min_area_px = int(self.params["min_area_px"])
        if stream is not None and (stream.tracker.width, stream.tracker.height) == (msg.width, msg.height) \
                and msg.stamp >= stream.last_stamp_us:
            return stream
        if stream is not None:
            log.info("restarting tracking of %s: its time or sensor size changed", key)
        else:
            log.info("tracking %s (%dx%d, %s frames, %s detector)", key, msg.width, msg.height, p.frames, p.detector)
        stream = _Stream(ObjectTracker(msg.width, msg.height, p), msg.stamp, msg.stamp)
        self.streams[key] = stream
        return stream

    def on_command(self, cmd: Command) -> Reply | None:
        if cmd.op == "reset":
            for stream in self.streams.values():
                stream.tracker.reset()
            self.motion = None  # ego-motion starts again from the next packet
            return Reply(ok=True)
        return None


def _camera(key: str) -> str:
    """The camera name of a camera key (etam/<rig>/camera/<name>/...)."""
    parsed = keys.parse(key)
    return parsed[2] if parsed else ""
