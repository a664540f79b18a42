"""The camera service: plays an event source as EventPackets, with CameraInfo and ground truth."""

from __future__ import annotations

import asyncio
import logging
import re
import time

from services import keys
from services.camera.filters import FilterChain
from services.camera.packetizer import Packetizer
from services.camera.sources import EventSource
from services.messages import CameraInfo, EventPacket, ImuPacket, Pose, Tracks, image_from_array
from services.runtime import Service, ServiceOptions

log = logging.getLogger(__name__)

FAST_STEP_US = 20_000  # sensor time per step when playing as fast as possible (`rate` 0)
MAX_STEP_US = 100_000  # at most this much sensor time (x rate) per step in real time: Stats keep flowing
LAG_WARN_US = 2_000_000


def camera_names(first: str, count: int) -> list[str]:
    """Names of the cameras of a rig: the service's name, then the next numbers (cam0, cam1, ...)."""
    m = re.fullmatch(r"(.*?)(\d+)", first)
    base, number = (m.group(1), int(m.group(2))) if m else (first, 0)
    return [first] + [f"{base}{number + i}" for i in range(1, count)]


class _Camera:
    """One camera of the rig the service plays: its source, filters, packetizer and publishers."""

    def __init__(self, service: CameraService, name: str, source: EventSource, filters: FilterChain,
                 slice_us: int, max_events: int, block: bool) -> None:
        self.name, self.source, self.filters = name, source, filters
        self.packetizer = Packetizer(slice_us, max_events)

        def out(topic: str, blocking: bool = block):  # noqa: ANN202 - an Output
            return service.publisher(keys.key(service.rig, service.kind, name, topic), block=blocking)

        self.events, self.truth, self.imu = out("events"), out("truth/boxes"), out("imu")
        self.pose, self.depth, self.info_out = out("truth/pose"), out("truth/depth"), out("info", False)
        service.serve(self.info_out.key, lambda _req: self.info())

    def info(self) -> CameraInfo:
        src, calib = self.source, self.source.calibration
        extra = {"dist_model": calib.dist_model, "dist": calib.dist, "T_body_cam": calib.T_body_cam} if calib else {}
        return CameraInfo(width=src.width, height=src.height, K=src.K, source=src.name, **extra)

    def play(self, since_us: int, until_us: int) -> None:
        """Publish the events and truth of (since_us, until_us]."""
        src = self.source
        self.packetizer.accept(self.filters(src.advance(until_us)))
        for stamp, chunk in self.packetizer.generate(until_us):
            self.events.publish(EventPacket(stamp=stamp, width=src.width, height=src.height, events=chunk))
        for t_us, ids, boxes, solid in src.truth(since_us, until_us):
            extra = {} if solid is None else {"xyz": solid[:, :3].astype("<f4"), "size_m": solid[:, 3].astype("<f4")}
            self.truth.publish(Tracks.from_boxes(t_us, ids, boxes, **extra))
        for t_us, p, q, omega in src.poses(since_us, until_us):
            self.pose.publish(Pose(stamp=t_us, t=t_us, p=p, q=q, omega=omega, child=self.name))
        for t_us, depth in src.depths(since_us, until_us):
            self.depth.publish(image_from_array(t_us, depth, "rawf32"))
        imu = src.imu(since_us, until_us)
        if imu is not None:
            t, gyro, accel = imu
            self.imu.publish(ImuPacket(stamp=int(t[-1]), t=t, gyro=gyro, accel=accel))

    def report_end(self) -> None:
        if self.source.error is not None:
            log.error("%s stopped playing: %s (every event before it was published)", self.name, self.source.error)
        else:
            log.info("end of %s: %d events published on %s", self.source.name, self.events.counter.events,
                     self.events.key)


class CameraService(Service):
    """Publishes ``camera/<cam>/events`` (1 ms slices), ``info`` (each second and as a query),
    ``imu`` when the source has inertial samples, and ``truth/boxes`` / ``truth/pose`` /
    ``truth/depth`` when it has ground truth. A rig of several cameras (``sim:stereo``, a stereo
    file) publishes each under its own name, in step: cam0, cam1, ...

    `rate` 1 plays in real time, 2 twice as fast, 0 as fast as the source and the network allow
    (then it waits for a first subscriber, and publishers block rather than drop, so a subscriber
    that keeps up gets every event).
    """

    kind = "camera"

    def __init__(self, options: ServiceOptions, sources: list[EventSource], slice_us: int = 1000,
                 max_events: int = 100_000, rate: float = 1.0, tick_s: float = 0.005,
                 filters: list[FilterChain] | None = None) -> None:
        super().__init__(options)
        if rate < 0:
            raise ValueError(f"rate must be >= 0, got {rate}")
        if not sources:
            raise ValueError("a camera service needs at least one source")
        self.sources = sources
        self.filters = filters or [FilterChain([]) for _ in sources]
        self.slice_us, self.max_events = slice_us, max_events
        self.rate, self.tick_s = rate, tick_s
        self.status["source"] = sources[0].name
        self._warned_lag = False

    async def main(self) -> None:
        fast = self.rate == 0
        names = camera_names(self.name, len(self.sources))
        cams = [_Camera(self, name, src, chain, self.slice_us, self.max_events, fast)
                for name, src, chain in zip(names, self.sources, self.filters, strict=True)]
        self._report(cams)
        await asyncio.sleep(0)
        if fast:  # as fast as possible is only useful to someone listening from the start
            log.info("waiting for a subscriber to %s (or its imu, truth)", cams[0].events.key)
            while not any(out.matched for cam in cams for out in (cam.events, cam.imu, cam.truth)):
                await asyncio.sleep(0.05)
        sensor_us = min(cam.source.start_us for cam in cams)
        wall0, sensor0 = time.monotonic(), sensor_us
        next_info = time.monotonic() + 1.0
        while True:
            done = all(cam.source.done for cam in cams)
            await asyncio.sleep(0 if fast and not done else self.tick_s)
            if time.monotonic() >= next_info:
                self._report(cams)
                next_info += 1.0
            if self.paused or done:
                wall0, sensor0 = time.monotonic(), sensor_us  # resume from here, not in a rush
                continue
            if fast:
                until = self._fast_until(sensor_us)
            else:  # bounded steps: a source slower than real time lags behind, the service stays responsive
                target = sensor0 + int((time.monotonic() - wall0) * 1e6 * self.rate)
                until = min(target, sensor_us + int(MAX_STEP_US * max(self.rate, 1.0)))
                self._note_lag(target - until)
            for cam in cams:
                cam.play(sensor_us, until)
            sensor_us = until
            if all(cam.source.done for cam in cams):
                for cam in cams:
                    cam.play(sensor_us, sensor_us + self.slice_us)  # flush the last slice
                    cam.report_end()

    def _report(self, cams: list[_Camera]) -> None:
        """Publishes each camera's info and puts a live camera's link state and losses in the status,
        from the start on: a ping never finds the status without them."""
        for cam in cams:
            cam.info_out.publish(cam.info())
            if hasattr(cam.source, "health"):
                self.status.update(cam.source.health())

    def _note_lag(self, behind_us: int) -> None:
        self.status["behind_s"] = round(behind_us / 1e6, 3)
        if behind_us > LAG_WARN_US and not self._warned_lag:
            self._warned_lag = True
            log.warning("%s plays slower than real time (%.1f s behind and falling back): its stream lags "
                        "the wall clock; `etam sim` writes it to a file that plays in real time",
                        self.sources[0].name, behind_us / 1e6)

    def _fast_until(self, sensor_us: int) -> int:
        """The next step when playing as fast as possible: to the end of what every file reader has
        loaded (views, no copies), or FAST_STEP_US of sensor time."""
        loaded = [t for src in self.sources if not src.done and (t := src.loaded_until_us()) is not None]
        return max(min(loaded), sensor_us + 1) if loaded else sensor_us + FAST_STEP_US
