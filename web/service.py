"""The dashboard service: a viser server showing events with tracked and true boxes, the camera in 3D,
and the live services with their rates and drops."""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np
import viser

from services import keys
from services.messages import EVENT_DTYPE, CameraInfo, EventPacket, Image, MessageError, Stats, Tracks, image_to_array
from services.runtime import Service, ServiceOptions
from web.render import draw_tracks, event_frame, services_markdown

log = logging.getLogger(__name__)


class WebService(Service):
    """Serves the dashboard on `port` (viser moves to the next free port if taken; see `url`)."""

    kind = "web"

    def __init__(self, options: ServiceOptions, host: str = "0.0.0.0", port: int = 8080, fps: float = 20.0) -> None:
        super().__init__(options)
        self.host, self.port, self.fps = host, port, fps
        self.server: viser.ViserServer | None = None
        self._events: list[np.ndarray] = []
        self._size = (346, 260)
        self._tracks: Tracks | None = None
        self._truth: Tracks | None = None
        self._info: CameraInfo | None = None
        self._stats: dict[str, Stats] = {}
        self._seen: dict[str, float] = {}
        self._frames: dict[str, viser.GuiImageHandle] = {}

    @property
    def url(self) -> str:
        port = self.server.get_port() if self.server else self.port
        return f"http://localhost:{port}"

    async def main(self) -> None:
        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
        self.status["port"] = self.server.get_port()
        log.info("dashboard at %s", self.url)
        try:
            self._build()
            rig = self.rig
            await asyncio.gather(
                self._pump(self.subscribe(keys.events(rig), EventPacket, policy="fifo", maxsize=1024), self._on_events),
                self._pump(self.subscribe(keys.key(rig, "tracker", "*", "tracks"), Tracks, policy="latest"),
                           self._on_tracks),
                self._pump(self.subscribe(keys.key(rig, "camera", "*", "truth/boxes"), Tracks, policy="latest"),
                           self._on_truth),
                self._pump(self.subscribe(keys.key(rig, "camera", "*", "info"), CameraInfo, policy="latest"),
                           self._on_info),
                self._pump(self.subscribe(keys.stats(rig), Stats, policy="fifo", maxsize=256), self._on_stats),
                self._pump(self.subscribe(keys.frames(rig), Image, policy="latest"), self._on_frame),
                self._render_loop(),
            )
        finally:
            self.server.stop()

    def _build(self) -> None:
        assert self.server is not None
        gui, scene = self.server.gui, self.server.scene
        gui.set_panel_label(f"ETAM · {self.rig}")
        gui.configure_theme(control_width="large", show_share_button=False)
        scene.set_up_direction("-y")  # the OpenCV camera frame: x right, y down, z forward
        blank = np.zeros((self._size[1] * 2, self._size[0] * 2, 3), np.uint8)
        self._image = gui.add_image(blank, label="events · tracked (colour) and true (white) boxes",
                                    format="jpeg", jpeg_quality=90)
        self._status = gui.add_markdown("*Waiting for services...*")
        self._frames_folder = gui.add_folder("Frames from other services")
        scene.add_grid("/grid", width=10, height=10, plane="xz", position=(0, 1.5, 0))
        scene.add_frame("/world", axes_length=0.3, axes_radius=0.01)
        self._frustum = scene.add_camera_frustum("/cam0", fov=np.deg2rad(58), aspect=346 / 260, scale=0.4,
                                                 image=blank, format="jpeg", color=(200, 60, 60))

    async def _pump(self, inp, handler) -> None:  # noqa: ANN001 - Input and a per-message callback
        async for key, msg in inp:
            handler(key, msg)

    def _on_events(self, _key: str, msg: EventPacket) -> None:
        self._size = (msg.width, msg.height)
        self._events.append(msg.events)

    def _on_tracks(self, _key: str, msg: Tracks) -> None:
        self._tracks = msg

    def _on_truth(self, _key: str, msg: Tracks) -> None:
        self._truth = msg

    def _on_info(self, _key: str, msg: CameraInfo) -> None:
        if self._info is None or (msg.width, msg.height) != (self._info.width, self._info.height):
            fov = 2 * np.arctan2(msg.height / 2, msg.K[1, 1])
            self._frustum.fov = float(fov)
            self._frustum.aspect = msg.width / msg.height
        self._info = msg

    def _on_frame(self, key: str, msg: Image) -> None:
        """Any service's ``.../frame`` Image gets a panel of its own, made on first sight."""
        try:
            pixels = image_to_array(msg)
        except MessageError as exc:
            log.warning("frame on %s does not decode: %s", key, exc)
            return
        if pixels.ndim == 3:
            pixels = np.ascontiguousarray(pixels[..., ::-1])  # BGR (OpenCV's order) to RGB
        handle = self._frames.get(key)
        if handle is None:
            assert self.server is not None
            with self._frames_folder:
                handle = self._frames[key] = self.server.gui.add_image(
                    pixels, label="/".join(key.split("/")[2:4]), format="jpeg", jpeg_quality=85)
        else:
            handle.image = pixels

    def _on_stats(self, _key: str, msg: Stats) -> None:
        who = f"{msg.service}/{msg.name}"
        self._stats[who] = msg
        self._seen[who] = time.monotonic()

    async def _render_loop(self) -> None:
        next_table = 0.0
        while True:
            await asyncio.sleep(1.0 / self.fps)
            events = np.concatenate(self._events) if self._events else np.empty(0, EVENT_DTYPE)
            self._events = []
            frame = draw_tracks(event_frame(events, *self._size), self._tracks, self._truth)
            self._image.image = frame
            self._frustum.image = frame
            now = time.monotonic()
            if now >= next_table:
                stale = [w for w, t in self._seen.items() if now - t > 10]
                for who in stale:  # a service gone for 10 s leaves the table
                    self._stats.pop(who, None)
                    self._seen.pop(who, None)
                self._status.content = services_markdown(self._stats, now, self._seen)
                next_table = now + 1.0
