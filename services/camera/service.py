"""The camera service: plays an event source in real time as EventPackets, with CameraInfo and truth."""

from __future__ import annotations

import asyncio
import logging
import time

from services.camera.packetizer import Packetizer
from services.camera.sources import EventSource
from services.messages import CameraInfo, EventPacket, Tracks
from services.runtime import Service, ServiceOptions

log = logging.getLogger(__name__)


class CameraService(Service):
    """Publishes ``camera/<cam>/events`` (1 ms slices), ``info`` (each second and as a query) and
    ``truth/boxes`` when the source has ground truth."""

    kind = "camera"

    def __init__(self, options: ServiceOptions, source: EventSource, slice_us: int = 1000,
                 max_events: int = 100_000, tick_s: float = 0.005, truth_hz: float = 50.0) -> None:
        super().__init__(options)
        self.source = source
        self.packetizer = Packetizer(slice_us, max_events)
        self.tick_s = tick_s
        self.truth_period_us = int(1e6 / truth_hz)

    def info(self) -> CameraInfo:
        return CameraInfo(width=self.source.width, height=self.source.height, K=self.source.K)

    async def main(self) -> None:
        events = self.publisher("events")
        info = self.publisher("info")
        truth = self.publisher("truth/boxes")
        self.serve("info", lambda _req: self.info())
        info.publish(self.info())
        await asyncio.sleep(0)
        start = time.monotonic()
        sensor_us = next_info_us = next_truth_us = 0
        paused_us = 0
        while True:
            await asyncio.sleep(self.tick_s)
            if self.paused:
                paused_us = int((time.monotonic() - start) * 1e6) - sensor_us
                continue
            now_us = int((time.monotonic() - start) * 1e6) - paused_us
            self.packetizer.accept(self.source.advance(now_us))
            for stamp, chunk in self.packetizer.generate(now_us):
                events.publish(EventPacket(stamp=stamp, width=self.source.width, height=self.source.height,
                                           events=chunk))
            while next_truth_us <= now_us:
                boxes = self.source.truth_boxes(next_truth_us)
                if boxes is not None:
                    truth.publish(Tracks.from_boxes(next_truth_us, *boxes))
                next_truth_us += self.truth_period_us
            if now_us >= next_info_us:
                info.publish(self.info())
                next_info_us = now_us + 1_000_000
            sensor_us = now_us
