"""The tracker service: object tracks from the camera's event packets (``tracker/objects/tracks``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from services import keys
from services.messages import Command, EventPacket, Reply, Tracks
from services.runtime import Service, ServiceOptions
from services.tracker.objects.tracker import ObjectTracker, TrackerParams

log = logging.getLogger(__name__)


@dataclass
class _Stream:
    """One camera's tracker and the sensor time of its next update."""

    tracker: ObjectTracker
    next_update_us: int
    last_stamp_us: int


class TrackerService(Service):
    """Subscribes to every camera's events (fifo, drop-oldest) and publishes Tracks every update."""

    kind = "tracker"

    def __init__(self, options: ServiceOptions, params: TrackerParams | None = None, cam: str = "*") -> None:
        super().__init__(options)
        self.tracker_params = params or TrackerParams()
        self.cam = cam
        self.streams: dict[str, _Stream] = {}
        self.params = {"update_us": self.tracker_params.update_us,
                       "density": self.tracker_params.clusters.density,
                       "min_area_px": self.tracker_params.clusters.min_area_px}

    async def main(self) -> None:
        out = self.publisher("tracks")
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
            out.publish(Tracks(t=tracks.t_us, stamp=tracks.t_us, id=tracks.ids, box=tracks.boxes,
                               score=tracks.scores, vel=tracks.vels, state=tracks.states))
            # the next update on the update grid, skipping any slots this packet already passed
            step = int(self.params["update_us"])
            stream.next_update_us = max(stream.next_update_us + step, msg.stamp - msg.stamp % step + step)

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
            log.info("tracking %s (%dx%d)", key, msg.width, msg.height)
        stream = _Stream(ObjectTracker(msg.width, msg.height, p), msg.stamp, msg.stamp)
        self.streams[key] = stream
        return stream

    def on_command(self, cmd: Command) -> Reply | None:
        if cmd.op == "reset":
            for stream in self.streams.values():
                stream.tracker.reset()
            return Reply(ok=True)
        return None
