"""Event sources the camera service plays: the built-in simulator and recorded files.

A source is pure: ``advance(until_us)`` returns the events up to that sensor time (us) and
``truth(since_us, until_us)`` the ground-truth boxes in that span; ``done`` says a file has ended.
The service decides the pacing (real time, faster, or as fast as possible).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from services import events
from services.camera.formats import Calibration, FormatError, Recording, open_recording
from services.camera.formats.kernels import first_at_or_after
from services.camera.rotation_scene import RotationScene
from services.camera.sim_imu import SimulatedImu
from services.camera.simulator import EventSimulator, ObjectsScene, SimParams
from services.camera.sixdof_scene import SixDofScene
from services.messages import EVENT_DTYPE

TRUTH_PERIOD_US = 20_000  # the simulator's boxes and poses at 50 Hz
DEPTH_PERIOD_US = 100_000  # its depth maps at 10 Hz


class SourceError(ValueError):
    """A source that cannot be opened; the text names it and says why."""


TruthBoxes = tuple[int, np.ndarray, np.ndarray, np.ndarray | None]  # t_us, ids, boxes, 3D rows (x y z m, size m)


class EventSource(Protocol):
    name: str
    width: int
    height: int
    K: np.ndarray
    calibration: Calibration | None  # with distortion, and the camera's place in a rig of several
    start_us: int
    done: bool
    error: FormatError | None  # a fault met in a file, after the good events before it

    def advance(self, until_us: int) -> np.ndarray: ...

    def truth(self, since_us: int, until_us: int) -> list[TruthBoxes]: ...

    def imu(self, since_us: int, until_us: int) -> ImuSamples | None: ...

    def poses(self, since_us: int, until_us: int) -> list[TruthPose]: ...

    def depths(self, since_us: int, until_us: int) -> list[tuple[int, np.ndarray]]: ...

    def loaded_until_us(self) -> int | None: ...


ImuSamples = tuple[np.ndarray, np.ndarray, np.ndarray]  # t_us, gyro rad/s (Nx3), accel m/s^2 (Nx3)


TruthPose = tuple[int, np.ndarray, np.ndarray, np.ndarray | None]  # t_us, p (m), q (x y z w), omega (rad/s)


class SimSource:
    """A simulator scene: `sim:objects` (static camera, moving objects, truth boxes), `sim:rotation`
    (spinning camera, truth poses and angular velocity), `sim:6dof` (moving camera, 3D structure,
    truth poses and depth maps), or one camera of `sim:stereo`."""

    done = False
    start_us = 0
    error = None

    def __init__(self, scene: ObjectsScene | RotationScene | SixDofScene, sim: EventSimulator, name: str,
                 imu: SimulatedImu | None = None) -> None:
        """`imu`: the rig's IMU, on this camera."""
        self.scene, self.sim, self.name, self._imu = scene, sim, name, imu
        self.width, self.height = scene.width, scene.height
        f = scene.focal_px
        self.K = np.array([[f, 0, self.width / 2], [0, f, self.height / 2], [0, 0, 1]], np.float64)
        self.calibration = Calibration(self.K, T_body_cam=getattr(scene, "T_body_cam", None))  # an ideal pinhole

    def advance(self, until_us: int) -> np.ndarray:
        return self.sim.advance(until_us)

    def imu(self, since_us: int, until_us: int) -> ImuSamples | None:
        if self._imu is None:
            return None
        samples = self._imu.samples(since_us, until_us)
        return samples if len(samples[0]) else None

    def loaded_until_us(self) -> int | None:
        return None  # simulated events are made on demand: nothing is loaded ahead

    def _truth_times(self, since_us: int, until_us: int) -> range:
        return range((since_us // TRUTH_PERIOD_US + 1) * TRUTH_PERIOD_US, until_us + 1, TRUTH_PERIOD_US)

    def truth(self, since_us: int, until_us: int) -> list[TruthBoxes]:
        if not isinstance(self.scene, ObjectsScene):
            return []
        return [(t, *self.scene.boxes(t)) for t in self._truth_times(since_us, until_us)]

    def unscored(self, since_us: int, until_us: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """The objects in the image that `truth` leaves out (mostly out of view or hidden): t_us, ids, boxes."""
        if not isinstance(self.scene, ObjectsScene):
            return []
        return [(t, *self.scene.unscored(t)) for t in self._truth_times(since_us, until_us)]

    def poses(self, since_us: int, until_us: int) -> list[TruthPose]:
        if not hasattr(self.scene, "pose"):
            return []
        return [(t, *self.scene.pose(t), self.scene.omega(t)) for t in self._truth_times(since_us, until_us)]

    def depths(self, since_us: int, until_us: int) -> list[tuple[int, np.ndarray]]:
        """Metric depth maps at DEPTH_PERIOD_US, for scenes with 3D structure."""
        if not hasattr(self.scene, "depth"):
            return []
        first = (since_us // DEPTH_PERIOD_US + 1) * DEPTH_PERIOD_US
        return [(t, self.scene.depth(t)) for t in range(first, until_us + 1, DEPTH_PERIOD_US)]


_END = object()


def read_ahead(chunks: Iterator[np.ndarray], depth: int = 2) -> Iterator[np.ndarray]:
    """`chunks`, decoded by a thread up to `depth` ahead of the consumer: the numba decoders release
    the GIL, so reading overlaps with publishing. An error is raised where the consumer meets it."""
    ready: queue.Queue = queue.Queue(maxsize=depth)

    def produce() -> None:
        try:
            for chunk in chunks:
                ready.put(chunk)
            ready.put(_END)
        except Exception as exc:  # noqa: BLE001 - handed over to the consumer, raised there
            ready.put(exc)

    threading.Thread(target=produce, name="read-ahead", daemon=True).start()
    while (item := ready.get()) is not _END:
        if isinstance(item, Exception):
            raise item
        yield item


class FileSource:
    """Plays a recording, read ahead on a thread; with `loop` it starts again, shifted in time so
    that time keeps rising."""

    def __init__(self, recording: Recording, loop: bool = False) -> None:
        self.recording, self.loop = recording, loop
        self.name = str(recording.path)
        self.width, self.height = recording.width, recording.height
        self.K = recording.K_or_default()
        self.calibration = recording.calibration
        self._chunks = read_ahead(recording.chunks())
        self._pending = np.empty(0, EVENT_DTYPE)
        self._shift_us = 0
        self._loaded_us: int | None = None  # time of the last event loaded, shifted
        self.done = False
        self.error: FormatError | None = None  # a fault in the file, met after the good events before it
        self._fill()
        self.start_us = int(self._pending["t"][0]) if len(self._pending) else 0
        # ground truth and IMU are small: read once, ordered by time (us) for lookups by span
        truth = recording.truth
        boxes, solid = truth.boxes, truth.boxes_3d
        order = np.argsort(boxes[:, 0], kind="stable") if boxes is not None else None
        self._truth_rows = boxes[order] if boxes is not None else None
        self._truth_3d = solid[order] if solid is not None and boxes is not None and len(solid) == len(boxes) else None
        pose_t = np.round(truth.poses[:, 0] * 1e6).astype(np.int64) if truth.poses is not None else None
        self._pose_order = np.argsort(pose_t, kind="stable") if pose_t is not None else None
        self._pose_t = pose_t[self._pose_order] if pose_t is not None else None
        self._depth_order = np.argsort(truth.depth_t, kind="stable") if truth.depth_t is not None else None
        self._depth_t = truth.depth_t[self._depth_order] if truth.depth_t is not None else None
        imu = recording.imu()
        order = np.argsort(imu[0], kind="stable") if imu is not None else None
        self._imu = tuple(a[order] for a in imu) if imu is not None else None

    def _span(self, t: np.ndarray, since_us: int, until_us: int) -> slice:
        """The entries of sorted file times `t` in (since_us, until_us] of the lap being played."""
        lo, hi = np.searchsorted(t, (since_us - self._shift_us, until_us - self._shift_us), side="right")
        return slice(int(lo), int(hi))

    def imu(self, since_us: int, until_us: int) -> ImuSamples | None:
        if self._imu is None:
            return None
        t, gyro, accel = self._imu
        sel = self._span(t, since_us, until_us)
        return (t[sel] + self._shift_us, gyro[sel], accel[sel]) if sel.stop > sel.start else None

    def _fill(self) -> bool:
        """Load the next chunk into the pending buffer; False at the end of the file or at a fault."""
        try:
            chunk = next(self._chunks, None)
        except FormatError as exc:
            self.error = exc
            return False
        if chunk is None:
            if not self.loop or self._loaded_us is None:
                return False
            self._shift_us = self._loaded_us + 1 - self.start_us  # the next lap starts just after
            self._chunks = read_ahead(self.recording.chunks())
            chunk = next(self._chunks, None)
            if chunk is None:
                return False
        if self._shift_us:
            chunk = events.copy(chunk)
            chunk["t"] += self._shift_us
        if len(chunk):
            self._loaded_us = int(chunk["t"][-1])
        self._pending = chunk  # only called once the pending events are used up
        return True

    def advance(self, until_us: int) -> np.ndarray:
        parts = []
        while True:
            if not len(self._pending) and not self._fill():
                self.done = True
                break
            cut = first_at_or_after(self._pending, until_us + 1)
            if cut:
                parts.append(self._pending[:cut])
            self._pending = self._pending[cut:]
            if len(self._pending):
                break
        if len(parts) == 1:
            return parts[0]  # a view on the chunk: no copy
        return events.concat(parts)

    def poses(self, since_us: int, until_us: int) -> list[TruthPose]:
        if self._pose_t is None:
            return []
        rows = self.recording.truth.poses  # TUM: t_s, p, q
        sel = self._span(self._pose_t, since_us, until_us)
        return [(int(t) + self._shift_us, rows[i, 1:4], rows[i, 4:8], None)
                for t, i in zip(self._pose_t[sel], self._pose_order[sel], strict=True)]

    def depths(self, since_us: int, until_us: int) -> list[tuple[int, np.ndarray]]:
        maps = self.recording.truth.depth_maps
        if self._depth_t is None or maps is None:
            return []
        sel = self._span(self._depth_t, since_us, until_us)
        return [(int(t) + self._shift_us, np.asarray(maps[i], np.float32))
                for t, i in zip(self._depth_t[sel], self._depth_order[sel], strict=True)]

    def loaded_until_us(self) -> int | None:
        """Sensor time up to which every event is already read, so advancing to it costs no copy: just
        before the last read event's time, whose fellows with the same time may open the next chunk."""
        return int(self._pending["t"][-1]) - 1 if len(self._pending) else None

    def truth(self, since_us: int, until_us: int) -> list[TruthBoxes]:
        if self._truth_rows is None:
            return []
        sel = self._span(self._truth_rows[:, 0], since_us, until_us)
        rows = self._truth_rows[sel]
        solid = self._truth_3d[sel] if self._truth_3d is not None else None
        out = []
        for tu in np.unique(rows[:, 0]):
            at = rows[:, 0] == tu
            out.append((int(tu) + self._shift_us, rows[at, 1].astype(np.int32), rows[at, 2:6],
                        solid[at] if solid is not None else None))
        return out


SIM_SCENES = ("objects", "rotation", "6dof", "stereo")
STEREO_BASELINE_M = 0.1  # the simulated stereo rig's baseline, along the left camera's x axis


def open_sources(spec: str, seed: int = 0, loop: bool = False, sim_params: SimParams | None = None,
                 scene_args: dict[str, float] | None = None, usb: dict | None = None) -> list[EventSource]:
    """Open the cameras of a source from its command-line name (``sim:objects``, ``sim:stereo``, the
    path of a recording, ``usb``, ``usb:SERIAL``): one source, or one per camera of a rig, the first
    first. `scene_args` go to a simulated scene's constructor (such as `peak_deg_s` of the rotation
    scene), `usb` to a USB camera's (`bias`, `roi`)."""
    if spec.startswith("sim:"):
        scene = spec[4:]
        if scene == "stereo":
            rig = [SixDofScene(seed=seed, baseline_m=b, **(scene_args or {})) for b in (0.0, STEREO_BASELINE_M)]
            return [SimSource(sc, EventSimulator(sc, sim_params, seed=seed + i), spec,
                              SimulatedImu(sc, sim_params, seed) if i == 0 else None) for i, sc in enumerate(rig)]
        scenes = {"objects": ObjectsScene, "rotation": RotationScene, "6dof": SixDofScene}
        if scene not in scenes:
            raise SourceError(f"source {spec!r}: unknown simulator scene {scene!r} (available: "
                              f"{', '.join('sim:' + s for s in SIM_SCENES)})")
        sc = scenes[scene](seed=seed, **(scene_args or {}))
        imu = SimulatedImu(sc, sim_params, seed) if isinstance(sc, SixDofScene) else None
        return [SimSource(sc, EventSimulator(sc, sim_params, seed=seed), spec, imu)]
    if spec == "usb" or spec.startswith("usb:"):
        from services.camera.usb.driver import UsbError
        from services.camera.usb.source import UsbSource

        try:
            return [UsbSource(spec, **(usb or {}))]
        except UsbError as exc:
            raise SourceError(f"source {spec!r}: {exc}") from None
    if not Path(spec).exists():
        raise SourceError(f"source {spec!r}: no such file, and not a known source "
                          f"({', '.join('sim:' + s for s in SIM_SCENES)}, or a recording's path)")
    try:
        return [FileSource(rec, loop=loop) for rec in open_recording(spec).rig()]
    except FormatError as exc:
        raise SourceError(f"source {spec!r}: {exc}") from None
