"""End-to-end tracking latency in a running `etam up`: from the camera's publish of an event packet
to the tracker's publish of the tracks of the update that packet closed.

`etam up` runs as users run it (router, camera, tracker, dashboard), on `sim:objects` with a lower
contrast threshold and more background activity, so that the camera streams about 1 Mev/s. This
process joins the router and subscribes to the events and the tracks; every message carries its
publisher's wall clock (`sent`, ns, the same clock on one host), and a Tracks message's `stamp` is
that of the packet that closed its update, so the latency of an update is the tracks' `sent` minus
that packet's `sent`.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import zenoh

from benchmarks import free_port, join
from services.config import ZenohSettings
from services.messages import EventPacket, Tracks, decode

RIG = "bench"
# the objects scene streams 0.1-1.6 Mev/s from second to second (0.7 on average at this contrast);
# background activity of 3.5 Hz per pixel lifts that to about 1 Mev/s on average
SIM = ("--sim-param", "contrast=0.04", "--sim-param", "noise_rate_hz=3.5")
WARMUP_S = 3.0  # processes started, numba kernels loaded, tracks confirmed


def run(quick: bool = False) -> list[dict]:
    """Latency without the dashboard (a drone's rig, viewed from another machine) and with it."""
    return [_measure(quick, web=False), _measure(quick, web=True)]


def _measure(quick: bool, web: bool) -> dict:
    measure_s = 2.0 if quick else 15.0
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sent_by_stamp: dict[int, int] = {}
    latencies: list[float] = []
    events = [0, 0.0, 0.0]  # count, first and last arrival (s)
    lock = threading.Lock()
    measuring = threading.Event()

    def on_events(sample: zenoh.Sample) -> None:
        msg = decode(sample.payload.to_bytes(), EventPacket)
        now = time.perf_counter()
        with lock:
            sent_by_stamp[msg.stamp] = msg.sent
            if measuring.is_set():
                events[0] += len(msg.events)
                events[1] = events[1] or now
                events[2] = now

    def on_tracks(sample: zenoh.Sample) -> None:
        msg = decode(sample.payload.to_bytes(), Tracks)
        with lock:
            sent = sent_by_stamp.pop(msg.stamp, None)
            if measuring.is_set() and sent is not None:
                latencies.append((msg.sent - sent) / 1e6)
            for stamp in [s for s in sent_by_stamp if s < msg.stamp]:
                del sent_by_stamp[stamp]

    argv = [sys.executable, "-m", "services.cli", "up", "--source", "sim:objects", *SIM, "--rig", RIG,
            "--listen", endpoint, "--duration", str(WARMUP_S + measure_s + 2), "--log-level", "WARNING",
            *(("--web-port", str(free_port())) if web else ("--no-web",))]
    rig = subprocess.Popen(argv, stdout=subprocess.DEVNULL)
    try:
        session = join(ZenohSettings(mode="client", connect=[endpoint]).zenoh_config(), rig)
        if session is None:
            return {"stage": "tracking latency in etam up", "web": web, "error": f"no router at {endpoint}"}
        with session:
            subs = [session.declare_subscriber(f"etam/{RIG}/camera/*/events", on_events),
                    session.declare_subscriber(f"etam/{RIG}/tracker/objects/tracks", on_tracks)]
            time.sleep(WARMUP_S)
            measuring.set()
            time.sleep(measure_s)
            measuring.clear()
            for sub in subs:
                sub.undeclare()
    finally:
        rig.wait(30)
    with lock:
        lat = np.asarray(latencies)
        rate = events[0] / max(events[2] - events[1], 1e-9)
    if not len(lat):
        return {"stage": "tracking latency in etam up", "web": web, "error": "no tracks arrived"}
    return {"stage": "tracking latency in etam up", "web": web, "events_per_s": rate, "updates": len(lat),
            "latency_ms_p50": float(np.median(lat)), "latency_ms_p99": float(np.percentile(lat, 99)),
            "latency_ms_max": float(lat.max())}
