"""The camera service: plays an event source as EventPackets, with CameraInfo and ground truth."""

from __future__ import annotations

import asyncio
import logging
import time

from services.camera.filters import FilterChain
from services.camera.packetizer import Packetizer
from services.camera.sources import EventSource
from services.messages import CameraInfo, EventPacket, ImuPacket, Pose, Tracks, image_from_array
from services.runtime import Service, ServiceOptions

log = logging.getLogger(__name__)

FAST_STEP_US = 20_000  # sensor time per step when playing as fast as possible (`rate` 0)


class CameraService(Service):
    """Publishes ``camera/<cam>/events`` (1 ms slices), ``info`` (each second and as a query),
    ``imu`` when the source has inertial samples, and ``truth/boxes`` / ``truth/pose`` when it has
    ground truth.

    `rate` 1 plays in real time, 2 twice as fast, 0 as fast as the source and the network allow
    (then it waits for a first subscriber, and publishers block rather than drop, so a subscriber
    that keeps up gets every event).
    """

    kind = "camera"

    def __init__(self, options: ServiceOptions, source: EventSource, slice_us: int = 1000,
                 max_events: int = 100_000, rate: float = 1.0, tick_s: float = 0.005,
                 filters: FilterChain | None = None) -> None:
        super().__init__(options)
        if rate < 0:
            raise ValueError(f"rate must be >= 0, got {rate}")
        self.source = source
        self.packetizer = Packetizer(slice_us, max_events)
        self.rate, self.tick_s = rate, tick_s
        self.filters = filters or FilterChain([])
        self.status["source"] = source.name

    def info(self) -> CameraInfo:
        return CameraInfo(width=self.source.width, height=self.source.height, K=self.source.K,
                          source=self.source.name)

    async def main(self) -> None:
        fast = self.rate == 0
        self._events = self.publisher("events", block=fast)
        self._truth = self.publisher("truth/boxes", block=fast)
        self._imu = self.publisher("imu", block=fast)
        self._pose = self.publisher("truth/pose", block=fast)
        self._depth = self.publisher("truth/depth", block=fast)
        info = self.publisher("info")
        self.serve("info", lambda _req: self.info())
        info.publish(self.info())
        await asyncio.sleep(0)
        if fast:  # as fast as possible is only useful to someone listening from the start
            log.info("waiting for a subscriber to %s (or its imu, truth)", self._events.key)
            while not any(out.matched for out in (self._events, self._imu, self._truth)):
                await asyncio.sleep(0.05)
        src = self.source
        sensor_us = src.start_us
        wall0, sensor0 = time.monotonic(), sensor_us
        next_info = time.monotonic() + 1.0
        while True:
            await asyncio.sleep(0 if fast and not src.done else self.tick_s)
            if time.monotonic() >= next_info:
                info.publish(self.info())
                next_info += 1.0
            if self.paused or src.done:
                wall0, sensor0 = time.monotonic(), sensor_us  # resume from here, not in a rush
                continue
            if fast:
                until = self._fast_until(sensor_us)
            else:
                until = sensor0 + int((time.monotonic() - wall0) * 1e6 * self.rate)
            self._play(sensor_us, until)
            sensor_us = until
            if src.done:
                self._play(sensor_us, sensor_us + self.packetizer.slice_us)  # flush the last slice
                self._report_end()

    def _fast_until(self, sensor_us: int) -> int:
        """The next step when playing as fast as possible: to the end of what the file reader has
        loaded (views, no copies), or FAST_STEP_US of sensor time."""
        loaded = self.source.loaded_until_us()
        return max(loaded, sensor_us + 1) if loaded is not None else sensor_us + FAST_STEP_US

    def _play(self, since_us: int, until_us: int) -> None:
        """Publish the events and truth of (since_us, until_us]."""
        self.packetizer.accept(self.filters(self.source.advance(until_us)))
        w, h = self.source.width, self.source.height
        for stamp, chunk in self.packetizer.generate(until_us):
            self._events.publish(EventPacket(stamp=stamp, width=w, height=h, events=chunk))
        for t_us, ids, boxes, solid in self.source.truth(since_us, until_us):
            extra = {} if solid is None else {"xyz": solid[:, :3].astype("<f4"), "size_m": solid[:, 3].astype("<f4")}
            self._truth.publish(Tracks.from_boxes(t_us, ids, boxes, **extra))
        for t_us, p, q, omega in self.source.poses(since_us, until_us):
            self._pose.publish(Pose(stamp=t_us, t=t_us, p=p, q=q, omega=omega, child=self.name))
        for t_us, depth in self.source.depths(since_us, until_us):
            self._depth.publish(image_from_array(t_us, depth, "rawf32"))
        imu = self.source.imu(since_us, until_us)
        if imu is not None:
            t, gyro, accel = imu
            self._imu.publish(ImuPacket(stamp=int(t[-1]), t=t, gyro=gyro, accel=accel))

    def _report_end(self) -> None:
        if self.source.error is not None:
            log.error("stopped playing: %s (every event before it was published)", self.source.error)
        else:
            log.info("end of %s: %d events published", self.source.name, self._events.counter.events)
