"""The dashboard service: everything one rig publishes, in a browser (viser), rendered by message type.

One wildcard subscription (``etam/<rig>/**``) takes every message and keeps it by type and key, so a
plug-in that publishes a known type (DESIGN.md section 4) appears with no change here. A render loop
sends each view at its own rate: the event image with boxes and the camera poses at `fps`, object
markers at 10 Hz, point clouds, trajectories and other images twice a second, the health table and
plots once a second. Zenoh's threads only queue (drop-oldest, counted); viser coalesces repeated
updates of a slow browser; so a slow browser drops frames, never services' data.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser
import zenoh
from scipy.spatial.transform import Rotation

from services import keys
from services.messages import (
    EVENT_DTYPE, CameraInfo, Command, EventPacket, Image, Message, MessageError, PointCloud, Pose, Reply, Stats,
    Tracks, image_to_array,
)
from services.runtime import Input, Service, ServiceOptions
from web.cloud import COLOURINGS, Chunk, MapLayer
from web.health import Health
from web.render import draw_tracks, event_frame, track_colour, viewable

log = logging.getLogger(__name__)

MARKERS_S, SLOW_VIEWS_S, HEALTH_S = 0.1, 0.5, 1.0  # object markers; clouds, paths, images; health
FRUSTUM_IMAGE_S = 0.2  # the event image on the camera's frustum
WINDOW_MAX_MS = 200  # the accumulation window's upper bound (what is kept of each camera's events)
PATH_STEP_M, PATH_MAX = 0.01, 4000  # a trajectory keeps a point per centimetre moved, so many at most
ESTIMATE_RGB, TRUTH_RGB = (230, 60, 40), (120, 120, 120)


@dataclass
class RigState:
    """What one rig has published, by key: the latest of each kind, and recent events per camera."""

    events: dict[str, collections.deque] = field(default_factory=dict)  # (stamp, events) packets
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    tracks: dict[str, Tracks] = field(default_factory=dict)
    truth: dict[str, Tracks] = field(default_factory=dict)
    poses: dict[str, Pose] = field(default_factory=dict)
    paths: dict[str, list[np.ndarray]] = field(default_factory=dict)
    clouds: dict[str, MapLayer] = field(default_factory=dict)
    images: dict[str, Image] = field(default_factory=dict)
    infos: dict[str, CameraInfo] = field(default_factory=dict)
    health: Health = field(default_factory=Health)
    changed: set[str] = field(default_factory=set)  # keys of paths and images with news since their last send

    def main_camera(self) -> str | None:
        return min(self.events) if self.events else None

    def camera_pose(self) -> Pose | None:
        """The camera's pose for the 3D view: the newest estimate, else the truth, else none."""
        estimates = [k for k in self.poses if "/truth/" not in k]
        chosen = min(estimates) if estimates else min(self.poses, default=None)
        return self.poses.get(chosen) if chosen else None


class Every:
    """True at most once per `period_s` (a view's rate limit)."""

    def __init__(self, period_s: float) -> None:
        self.period_s, self._next = period_s, 0.0

    def __call__(self, now_s: float) -> bool:
        if now_s < self._next:
            return False
        self._next = max(self._next + self.period_s, now_s)  # a late tick keeps the rate, a very late one no burst
        return True


def _node(key: str) -> str:
    """A scene node name for a key: ``etam/r/mapper/map/points`` -> ``mapper.map.points``."""
    return ".".join(key.split("/")[2:])


def _wxyz(q_xyzw: np.ndarray) -> np.ndarray:
    return np.array([q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2]])


class WebService(Service):
    """Serves the dashboard on `port` (viser moves to the next free port if taken; see `url`)."""

    kind = "web"

    def __init__(self, options: ServiceOptions, host: str = "0.0.0.0", port: int = 8080, fps: float = 24.0) -> None:
        super().__init__(options)
        self.host, self.port, self.fps = host, port, fps
        self.server: viser.ViserServer | None = None
        self.view_rig = self.rig
        self.state = RigState()
        self.paused = False
        self.status["frames"] = 0  # event images sent, for benchmarks and tests
        self.status["events_received"] = 0
        self._rigs: set[str] = {self.rig}
        self._input: Input | None = None
        self._liveliness: zenoh.Subscriber | None = None
        self._cloud_nodes: dict[str, list[viser.PointCloudHandle]] = {}
        self._frusta: dict[str, viser.CameraFrustumHandle] = {}
        self._panels: dict[str, viser.GuiImageHandle] = {}
        self._markers: dict[int, tuple[viser.IcosphereHandle, viser.LabelHandle]] = {}
        self._handlers: dict[type[Message], Callable[[str, Any], None]] = {
            EventPacket: self._on_events, Tracks: self._on_tracks, Pose: self._on_pose, PointCloud: self._on_points,
            Image: self._on_image, CameraInfo: self._on_info, Stats: self._on_stats,
        }

    @property
    def url(self) -> str:
        port = self.server.get_port() if self.server else self.port
        return f"http://localhost:{port}"

    # ----------------------------------------------------------------------------------- run --
    async def main(self) -> None:
        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
        self.status["port"] = self.server.get_port()
        log.info("dashboard at %s", self.url)
        try:
            self._build()
            self._watch(self.view_rig)
            await asyncio.gather(self._discover_rigs(), self._render_loop())
        finally:
            self.server.stop()

    def _watch(self, rig: str) -> None:
        """Subscribe to everything of `rig` (and its liveliness tokens), dropping what another rig left."""
        if self._input is not None:
            self.unsubscribe(self._input)
        if self._liveliness is not None:
            self._liveliness.undeclare()
        self._clear_scene()
        self.view_rig, self.state = rig, RigState()
        self._input = self.subscribe(f"{keys.ROOT}/{rig}/**", None, policy="fifo", maxsize=4096)
        loop = asyncio.get_running_loop()
        health = self.state.health

        def on_token(sample: zenoh.Sample) -> None:  # zenoh's thread: hand over to the loop
            alive = sample.kind == zenoh.SampleKind.PUT
            loop.call_soon_threadsafe(health.on_liveliness, str(sample.key_expr), alive, time.monotonic())

        self._liveliness = self._session().liveliness().declare_subscriber(keys.alive(rig), on_token, history=True)
        self.server.gui.set_panel_label(f"ETAM · {rig}")
        asyncio.ensure_future(self._pump(self._input, self.state))

    async def _pump(self, inp: Input, state: RigState) -> None:
        async for key, msg in inp:
            handler = self._handlers.get(type(msg))
            if handler is not None and state is self.state:
                handler(key, msg)

    async def _discover_rigs(self) -> None:
        """Every rig whose services publish Stats, for the rig chooser."""
        async for key, _payload in _raw(self.subscribe(keys.stats("*"), None, policy="latest")):
            parts = keys.parse(key)
            if parts is not None and parts[0] not in self._rigs:
                self._rigs.add(parts[0])
                self._rig_choice.options = sorted(self._rigs)

    # ------------------------------------------------------------------------------ messages --
    def _on_events(self, key: str, msg: EventPacket) -> None:
        packets = self.state.events.setdefault(key, collections.deque())
        self.state.sizes[key] = (msg.width, msg.height)
        packets.append((msg.stamp, msg.events))
        self.status["events_received"] += len(msg.events)
        while packets and packets[0][0] < msg.stamp - WINDOW_MAX_MS * 1000:
            packets.popleft()

    def _on_tracks(self, key: str, msg: Tracks) -> None:
        (self.state.truth if "/truth/" in key else self.state.tracks)[key] = msg

    def _on_pose(self, key: str, msg: Pose) -> None:
        self.state.poses[key] = msg
        path = self.state.paths.setdefault(key, [])
        if not path or np.linalg.norm(path[-1] - msg.p) >= PATH_STEP_M:
            path.append(np.asarray(msg.p, np.float64))
            if len(path) > PATH_MAX:
                del path[::2]  # half as dense, twice as long
            self.state.changed.add(key)

    def _on_points(self, key: str, msg: PointCloud) -> None:
        layer = self.state.clouds.get(key)
        if layer is None:  # first sight: the whole map so far, when its publisher answers for it
            layer = self.state.clouds[key] = MapLayer(cap=int(self._cap.value))
            asyncio.ensure_future(self._fetch_whole_map(key, layer))
        layer.add(msg)

    async def _fetch_whole_map(self, key: str, layer: MapLayer) -> None:
        whole = key.rsplit("/", 1)[0] + "/all"
        replies = await self.query(whole, PointCloud, timeout_s=5.0)
        if replies and layer.total < len(replies[0][1].points):
            layer.replace(replies[0][1])
            self._drop_cloud_nodes(key)

    def _on_image(self, key: str, msg: Image) -> None:
        self.state.images[key] = msg
        self.state.changed.add(key)

    def _on_info(self, key: str, msg: CameraInfo) -> None:
        self.state.infos[key] = msg

    def _on_stats(self, _key: str, msg: Stats) -> None:
        self.state.health.on_stats(msg, time.monotonic())

    # ------------------------------------------------------------------------------- the GUI --
    def _build(self) -> None:
        assert self.server is not None
        gui, scene = self.server.gui, self.server.scene
        gui.configure_theme(control_width="large", show_share_button=False)
        scene.set_up_direction("-y")  # the OpenCV camera frame: x right, y down, z forward
        self.server.initial_camera.position = (0.0, -1.2, -1.8)  # behind and above the rig's start
        self.server.initial_camera.look_at = (0.0, 0.0, 3.0)
        loop = asyncio.get_running_loop()

        def on_loop(fn: Callable[..., None]) -> Callable[[Any], None]:  # viser's threads hand over to the loop
            return lambda _event: loop.call_soon_threadsafe(fn)

        self._rig_choice = gui.add_dropdown("Rig", options=[self.rig], initial_value=self.rig)
        self._rig_choice.on_update(on_loop(lambda: self._watch(self._rig_choice.value)
                                           if self._rig_choice.value != self.view_rig else None))
        blank = np.zeros((260 * 2, 346 * 2, 3), np.uint8)
        self._image = gui.add_image(blank, label="events · tracked (colour) and true (white) boxes",
                                    format="jpeg", jpeg_quality=90)
        self._pause = gui.add_button("Pause view", icon=viser.Icon.PLAYER_PAUSE)
        self._pause.on_click(on_loop(self._toggle_pause))
        with gui.add_folder("View"):
            self._window = gui.add_slider("Window (ms)", min=1, max=WINDOW_MAX_MS, step=1, initial_value=30)
            self._colouring = gui.add_dropdown("Colour points by", options=COLOURINGS, initial_value="depth")
            self._colouring.on_update(on_loop(self._recolour))
            self._point_size = gui.add_slider("Point size (m)", min=0.005, max=0.1, step=0.005, initial_value=0.04)
            self._point_size.on_update(on_loop(self._resize_points))
            self._cap = gui.add_number("Points shown at most", initial_value=100_000, min=1000, max=2_000_000,
                                       step=1000)
            self._cap.on_update(on_loop(self._recap))
            self._follow = gui.add_checkbox("Follow camera", initial_value=False)
        with gui.add_folder("Map"):
            self._map_text = gui.add_markdown("*No map yet.*")
            self._reset = gui.add_button("Reset map", icon=viser.Icon.TRASH)
            self._reset.on_click(on_loop(lambda: asyncio.ensure_future(self._map_command(Command(op="reset")))))
            self._save_path = gui.add_text("Save to (on the mapper's host)", initial_value="map.ply")
            self._save = gui.add_button("Save map", icon=viser.Icon.DEVICE_FLOPPY)
            self._save.on_click(on_loop(lambda: asyncio.ensure_future(
                self._map_command(Command(op="save", args={"path": self._save_path.value})))))
            self._reply = gui.add_markdown("")
        with gui.add_folder("Health"):
            self._status = gui.add_markdown("*Waiting for services...*")
            zero = (np.zeros(1), np.zeros(1))
            self._rate_plot = gui.add_uplot(zero, ({"label": "s"}, {"label": "Mev/s", "stroke": "#d9534f"}),
                                            title="event rate", aspect=2.5)
            self._latency_plot = gui.add_uplot(zero, ({"label": "s"}, {"label": "p99 ms", "stroke": "#337ab7"}),
                                               title="worst input latency", aspect=2.5)
        self._images_folder = gui.add_folder("Images")
        scene.add_grid("/grid", width=10, height=10, plane="xz", position=(0, 1.5, 0))
        scene.add_frame("/world", axes_length=0.3, axes_radius=0.01)

    def _toggle_pause(self) -> None:
        self.paused = not self.paused
        self._pause.label = "Resume view" if self.paused else "Pause view"
        self._pause.icon = viser.Icon.PLAYER_PLAY if self.paused else viser.Icon.PLAYER_PAUSE

    def _recolour(self) -> None:
        for key in list(self._cloud_nodes):
            self._drop_cloud_nodes(key)
            layer = self.state.clouds[key]
            if layer.chunks or layer.base:
                layer.merge()

    def _resize_points(self) -> None:
        for nodes in self._cloud_nodes.values():
            for node in nodes:
                node.point_size = float(self._point_size.value)

    def _recap(self) -> None:
        for layer in self.state.clouds.values():
            layer.cap = int(self._cap.value)
        self._recolour()

    async def _map_command(self, cmd: Command) -> None:
        """Send `cmd` to every mapper of the rig; a reset also clears the map shown here."""
        replies = await self.query(keys.key(self.view_rig, "mapper", "*", "cmd"), Reply, timeout_s=10.0, request=cmd)
        if not replies:
            self._reply.content = f"*{cmd.op}: no mapper answered*"
            return
        lines = []
        for key, reply in replies:
            who = "/".join(key.split("/")[2:4])
            lines.append(f"{who}: {cmd.op} " + ("done" if reply.ok else f"failed: {reply.error}"))
        self._reply.content = "  \n".join(lines)
        if cmd.op == "reset" and any(r.ok for _, r in replies):
            for key in [k for k in self.state.clouds if k.split("/")[2] == "mapper"]:
                self.state.clouds[key].clear()
                self._drop_cloud_nodes(key)
            self._show_map_text()

    # ------------------------------------------------------------------------------ rendering --
    async def _render_loop(self) -> None:
        """Ticks at `fps` on a fixed schedule (work done in a tick does not slow the rate); each view is sent
        when its period is due."""
        frustum_due = Every(FRUSTUM_IMAGE_S)
        markers_due, slow_due, health_due = Every(MARKERS_S), Every(SLOW_VIEWS_S), Every(HEALTH_S)
        period = 1.0 / self.fps
        tick = time.monotonic()
        while True:
            tick = max(tick + period, time.monotonic() - period)  # behind by more than a tick: no burst
            await asyncio.sleep(max(0.0, tick - time.monotonic()))
            now = time.monotonic()
            if health_due(now):
                self._show_health(now)
            if self.paused:
                continue
            frame = self._event_image()
            if frame is not None:
                self._image.image = frame
                self.status["frames"] += 1
                if frustum_due(now):
                    self._show_poses(frame)
            else:
                self._show_poses(None)
            if markers_due(now):
                self._show_markers()
                if self._follow.value:
                    self._follow_camera()
            if slow_due(now):
                self._show_clouds()
                self._show_paths()
                self._show_images()

    def _event_image(self) -> np.ndarray | None:
        cam = self.state.main_camera()
        if cam is None:
            return None
        packets = self.state.events[cam]
        newest = packets[-1][0] if packets else 0
        since = newest - int(self._window.value) * 1000
        recent = [ev for stamp, ev in packets if stamp > since]
        events = np.concatenate(recent) if recent else np.empty(0, EVENT_DTYPE)
        return draw_tracks(event_frame(events, *self.state.sizes[cam]), list(self.state.tracks.values()),
                           list(self.state.truth.values()))

    def _show_poses(self, frame: np.ndarray | None) -> None:
        """A frustum per pose key (the estimate red, the truth grey); the camera's carries the event image.
        With no pose published yet, the camera's frustum stays at the world origin."""
        assert self.server is not None
        poses = dict(self.state.poses)
        camera = self.state.camera_pose()
        if not poses:
            poses = {"camera": None}
        elif "camera" in self._frusta:  # a pose came: the placeholder at the origin goes
            self._frusta.pop("camera").remove()
        info = next(iter(self.state.infos.values()), None)
        for key, pose in poses.items():
            frustum = self._frusta.get(key)
            if frustum is None:
                frustum = self._frusta[key] = self.server.scene.add_camera_frustum(
                    f"/poses/{_node(key) or key}", fov=np.deg2rad(58), aspect=346 / 260, scale=0.3, format="jpeg",
                    color=TRUTH_RGB if "/truth/" in key else ESTIMATE_RGB)
            if info is not None:
                frustum.fov = float(2 * np.arctan2(info.height / 2, info.K[1, 1]))
                frustum.aspect = info.width / info.height
            if pose is not None:
                frustum.position, frustum.wxyz = np.asarray(pose.p), _wxyz(pose.q)
            if frame is not None and (pose is None or pose is camera):
                frustum.image = np.ascontiguousarray(frame[::2, ::2])  # a quarter of the pixels to encode: it is small

    def _show_markers(self) -> None:
        """Tracked objects with a 3D position as labelled spheres, in the world by the camera's pose."""
        assert self.server is not None
        pose = self.state.camera_pose()
        R = Rotation.from_quat(pose.q) if pose is not None else Rotation.identity()
        t = np.asarray(pose.p) if pose is not None else np.zeros(3)
        shown: set[int] = set()
        for msg in self.state.tracks.values():
            if msg.xyz is None:
                continue
            for ident, xyz, state in zip(msg.id, msg.xyz, msg.state, strict=True):
                if state == Tracks.TENTATIVE or not np.all(np.isfinite(xyz)):
                    continue
                ident = int(ident)
                world = R.apply(np.asarray(xyz, np.float64)) + t
                marker = self._markers.get(ident)
                if marker is None:
                    sphere = self.server.scene.add_icosphere(f"/objects/{ident}", radius=0.08,
                                                             color=track_colour(ident), subdivisions=2)
                    label = self.server.scene.add_label(f"/objects/{ident}/label", f"#{ident}", position=(0, -0.15, 0))
                    marker = self._markers[ident] = (sphere, label)
                marker[0].position = world
                marker[1].text = f"#{ident} · {float(np.linalg.norm(xyz)):.1f} m"
                shown.add(ident)
        for ident in [i for i in self._markers if i not in shown]:
            self._markers.pop(ident)[0].remove()

    def _follow_camera(self) -> None:
        """Every browser's view behind and above the camera, looking where it looks."""
        assert self.server is not None
        pose = self.state.camera_pose()
        if pose is None:
            return
        R = Rotation.from_quat(pose.q).as_matrix()
        p = np.asarray(pose.p)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position = p - 1.5 * R[:, 2] - 0.6 * R[:, 1]
                client.camera.look_at = p + 2.0 * R[:, 2]
                client.camera.up_direction = -R[:, 1]

    def _show_clouds(self) -> None:
        """New chunks as their own nodes; a merge (many chunks, or over the cap) re-sends one base."""
        assert self.server is not None
        for key, layer in self.state.clouds.items():
            nodes = self._cloud_nodes.setdefault(key, [])
            if layer.merge_due() or (layer.base is not None and not nodes):
                self._drop_cloud_nodes(key)
                nodes = self._cloud_nodes.setdefault(key, [])
                pending = [layer.merge()]
            else:
                pending = layer.chunks[len(nodes) - (1 if layer.base is not None else 0):]
            for chunk in pending:
                nodes.append(self._cloud_node(key, len(nodes), layer, chunk))
        self._show_map_text()

    def _show_map_text(self) -> None:
        shown, clouds = sum(layer.total for layer in self.state.clouds.values()), len(self.state.clouds)
        self._map_text.content = (f"**{shown:,}** points shown ({clouds} cloud{'s' if clouds != 1 else ''})"
                                  if shown else "*No map yet.*")
        self.status["points_shown"] = shown

    def _cloud_node(self, key: str, index: int, layer: MapLayer, chunk: Chunk) -> viser.PointCloudHandle:
        assert self.server is not None
        return self.server.scene.add_point_cloud(
            f"/clouds/{_node(key)}/{index}", points=chunk.points, colors=layer.colours(chunk, self._colouring.value),
            point_size=float(self._point_size.value), point_shape="circle")

    def _drop_cloud_nodes(self, key: str) -> None:
        for node in self._cloud_nodes.pop(key, []):
            node.remove()

    def _show_paths(self) -> None:
        assert self.server is not None
        for key in [k for k in self.state.changed if k in self.state.paths]:
            self.state.changed.discard(key)
            path = np.asarray(self.state.paths[key])
            if len(path) < 2:
                continue
            segments = np.stack([path[:-1], path[1:]], axis=1)
            self.server.scene.add_line_segments(f"/paths/{_node(key)}", segments,
                                                TRUTH_RGB if "/truth/" in key else ESTIMATE_RGB, thickness=0.01)

    def _show_images(self) -> None:
        """Every published Image (mosaic, depth, any service's frame) in a panel of its own."""
        assert self.server is not None
        for key in sorted(k for k in self.state.changed if k in self.state.images):
            self.state.changed.discard(key)
            try:
                pixels = viewable(image_to_array(self.state.images[key]))
            except MessageError as exc:
                log.warning("image on %s does not decode: %s", key, exc)
                continue
            panel = self._panels.get(key)
            if panel is None:
                with self._images_folder:
                    self._panels[key] = self.server.gui.add_image(pixels, label="/".join(key.split("/")[2:]),
                                                                  format="jpeg", jpeg_quality=85)
            else:
                panel.image = pixels

    def _show_health(self, now: float) -> None:
        health = self.state.health
        health.forget(now)
        health.sample(now)
        self._status.content = health.markdown(now)
        t, rate, p99 = health.series()
        self._rate_plot.data = (t, rate)
        self._latency_plot.data = (t, p99)

    def _clear_scene(self) -> None:
        """Remove what the rig watched so far put in the scene and the image panels."""
        for key in list(self._cloud_nodes):
            self._drop_cloud_nodes(key)
        for handle in [*self._frusta.values(), *(m[0] for m in self._markers.values()), *self._panels.values()]:
            handle.remove()
        self._frusta, self._markers, self._panels = {}, {}, {}
        if self.server is not None:
            for key in self.state.paths:
                self.server.scene.remove_by_name(f"/paths/{_node(key)}")


async def _raw(inp: Input):  # noqa: ANN202 - an async generator of (key, payload)
    while True:
        try:
            yield await inp.raw()
        except StopAsyncIteration:
            return
