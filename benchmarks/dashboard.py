"""The dashboard's cost and rate in a running `etam up`, with one browser-like client connected.

`etam up` runs as users run it, with every service: camera, tracker, mapper and dashboard. On a
recording of the 6-DoF scene played in real time (`--map`: the camera as cheap as a real one), and
on the live simulator `sim:6dof`, whose rendering takes a core of its own (2 cores are then full).
A plug-in publishes a 100k-point map on a key of its own (the simulator's semi-dense map grows by a
few hundred points a keyframe), so the dashboard holds and shows 100k points beside the mapper's. A
client joins the dashboard's websocket as a browser does and decodes viser's wire format: it counts
the updates of the event image and the bytes it is sent; meanwhile the dashboard process's CPU time
is read from the system. A real browser costs the server the same: each client gets the same stream.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import psutil
import viser
import zstandard
from websockets.sync.client import connect

from benchmarks import free_port, join
from services.camera.offline import simulate
from services.config import ZenohSettings
from services.messages import Command, PointCloud, Reply, decode

RIG = "benchweb"
PLUGIN_POINTS = 100_000
WARMUP_S = 12.0  # processes started, kernels loaded, the first keyframes mapped


def run(quick: bool = False) -> list[dict]:
    measure_s = 5.0 if quick else 20.0
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        h5 = Path(tmp) / "6dof.h5"
        simulate("6dof", h5, WARMUP_S + measure_s + 10, seed=11, progress=False)
        return [measure(str(h5), measure_s), measure(str(h5), measure_s, clients=3), measure("sim:6dof", measure_s)]


def measure(source: str, measure_s: float, clients: int = 1) -> dict:
    endpoint, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    common = ["--rig", RIG, "--log-level", "WARNING"]
    recording = not source.startswith("sim:")
    rig = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--source", source, "--listen", endpoint,
                            "--web-port", str(port), "--duration", str(WARMUP_S + measure_s + 8), *common,
                            *(("--map",) if recording else ())], stdout=subprocess.DEVNULL)
    row: dict = {"stage": "dashboard in etam up", "source": "recording of sim:6dof" if recording else source,
                 "clients": clients}
    try:
        session = join(ZenohSettings(mode="client", connect=[endpoint]).zenoh_config(), rig)
        if session is None:
            return {**row, "error": f"no router at {endpoint}"}
        with session:
            pid = _web_pid(session)
            if pid is None:
                return {**row, "error": "the dashboard did not answer"}
            pts = np.random.default_rng(0).uniform((-3, -1.5, 1), (3, 1.5, 6), (PLUGIN_POINTS, 3)).astype(np.float32)
            session.put(f"etam/{RIG}/bench/cloud/points", PointCloud(t=0, points=pts).encode())
            viewers = [_Client(port) for _ in range(clients)]
            time.sleep(WARMUP_S)
            psutil.cpu_percent(None)
            proc = psutil.Process(pid)
            frames0 = _ping(session).get("frames", 0)
            cpu0, t0 = sum(proc.cpu_times()[:2]), time.monotonic()
            before = [(v.image_updates, v.bytes) for v in viewers]
            time.sleep(measure_s)
            cpu1, t1 = sum(proc.cpu_times()[:2]), time.monotonic()
            after = [(v.image_updates, v.bytes) for v in viewers]
            status = _ping(session)
            load = psutil.cpu_percent(None)
            for v in viewers:
                v.close()
    finally:
        rig.terminate()
        rig.wait(60)
    wall = t1 - t0
    got = [(a[0] - b[0], a[1] - b[1]) for a, b in zip(after, before, strict=True)]  # updates and bytes per client
    return {**row, "cpu_percent_of_core": 100 * (cpu1 - cpu0) / wall,
            "image_updates_per_s": min(u for u, _ in got) / wall,  # the slowest client's
            "frames_per_s": (status.get("frames", 0) - frames0) / wall,
            "client_mb_per_s": sum(b for _, b in got) / clients / wall / 1e6,
            "points_shown": status.get("points_shown", 0), "machine_cpu_percent": load, "seconds": wall}


def _ping(session) -> dict:  # noqa: ANN001 - a zenoh session
    for reply in session.get(f"etam/{RIG}/web/web/cmd", payload=Command(op="ping").encode(), timeout=3.0):
        if reply.ok is not None:
            msg = decode(reply.ok.payload.to_bytes(), Reply)
            if msg.ok:
                return msg.result or {}
    return {}


def _web_pid(session, wait_s: float = 40.0) -> int | None:  # noqa: ANN001
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        pid = _ping(session).get("pid")
        if pid:
            return int(pid)
        time.sleep(0.5)
    return None


class _Client:
    """A websocket client of the dashboard, reading everything it is sent on a thread of its own."""

    def __init__(self, port: int) -> None:
        self._ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        self._zstd = zstandard.ZstdDecompressor()
        self.image_updates = self.bytes = self.messages = 0
        self._image: str | None = None
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for frame in self._ws:
                self.bytes += len(frame)
                size, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
                body = msgspec.msgpack.decode(self._zstd.decompress(frame[16:16 + packed], max_output_size=size))
                for msg in body["messages"]:
                    self.messages += 1
                    if msg.get("type") == "GuiImageMessage" and str(msg["props"].get("label", "")).startswith("events"):
                        self._image = msg["uuid"]
                    elif msg.get("type") == "GuiUpdateMessage" and msg.get("uuid") == self._image:
                        self.image_updates += 1
        except Exception:  # noqa: BLE001 - the connection closes at the end
            return

    def close(self) -> None:
        self._ws.close()
        self._thread.join(5)
