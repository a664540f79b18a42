"""The tracker service: object tracks from the camera's event packets (``tracker/objects/tracks``)."""

from __future__ import annotations

import logging

from services import keys
from services.messages import Command, EventPacket, Reply, Tracks
from services.runtime import Service, ServiceOptions
from services.tracker.objects.tracker import ObjectTracker, TrackerParams

log = logging.getLogger(__name__)


class TrackerService(Service):
    """Subscribes to every camera's events (fifo, drop-oldest) and publishes Tracks every update."""

    kind = "tracker"

    def __init__(self, options: ServiceOptions, params: TrackerParams | None = None, cam: str = "*") -> None:
        super().__init__(options)
        self.tracker_params = params or TrackerParams()
        self.cam = cam
        self.trackers: dict[str, ObjectTracker] = {}
        self.params = {"update_us": self.tracker_params.update_us,
                       "density": self.tracker_params.clusters.density,
                       "min_area_px": self.tracker_params.clusters.min_area_px}

    async def main(self) -> None:
        out = self.publisher("tracks")
        next_update: dict[str, int] = {}
        async for key, msg in self.subscribe(keys.events(self.rig, self.cam), EventPacket, policy="fifo", maxsize=1024):
            assert isinstance(msg, EventPacket)
            tracker = self._tracker_for(key, msg)
            if self.paused:
                continue
            tracker.accept(msg.events)
            due = next_update.setdefault(key, msg.stamp)
            if msg.stamp >= due:
                tracks = tracker.generate(msg.stamp)
                out.publish(Tracks(t=tracks.t_us, stamp=tracks.t_us, id=tracks.ids, box=tracks.boxes,
                                   score=tracks.scores, vel=tracks.vels, state=tracks.states))
                next_update[key] = due + int(self.params["update_us"])
                if msg.stamp - next_update[key] > 1_000_000:  # source jumped (replay, restart): resync
                    next_update[key] = msg.stamp

    def _tracker_for(self, key: str, msg: EventPacket) -> ObjectTracker:
        tracker = self.trackers.get(key)
        if tracker is None or (tracker.width, tracker.height) != (msg.width, msg.height):
            tracker = ObjectTracker(msg.width, msg.height, self.tracker_params)
            self.trackers[key] = tracker
            log.info("tracking %s (%dx%d)", key, msg.width, msg.height)
        p = self.tracker_params
        p.clusters.density = float(self.params["density"])
        p.clusters.min_area_px = int(self.params["min_area_px"])
        return tracker

    def on_command(self, cmd: Command) -> Reply | None:
        if cmd.op == "reset":
            for tracker in self.trackers.values():
                tracker.reset()
            return Reply(ok=True)
        return None
