"""A file played by the camera service as fast as possible (`--rate 0`), received in another process.

The camera runs as its own process (the real `etam camera`), reading a dense Prophesee EVT 3.0
recording (the real sample's data repeated with rising time); this process subscribes over zenoh
and counts events and sequence gaps. Figures: events/s from the first to the last packet received
(median, best and worst of three plays: this varies a lot on a shared machine), and whether every
event of every play arrived.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from benchmarks import free_port
from benchmarks.readers import SAMPLES, _repeat_raw
from services.camera.formats import open_recording
from services.config import ZenohSettings
from services.messages import EventPacket, decode


def _play(path: Path, expected: int) -> dict:
    """One `etam camera --rate 0` of `path` into a subscriber of this process."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got = {"events": 0, "packets": 0, "gaps": 0, "last_seq": 0, "first": 0.0, "last": 0.0}
    lock, done = threading.Lock(), threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        msg = decode(sample.payload.to_bytes(), EventPacket)
        now = time.perf_counter()
        with lock:
            got["first"] = got["first"] or now
            got["last"] = now
            got["events"] += len(msg.events)
            got["packets"] += 1
            got["gaps"] += max(0, msg.seq - got["last_seq"] - 1)
            got["last_seq"] = msg.seq
            if got["events"] >= expected:
                done.set()

    conf = ZenohSettings(mode="peer", listen=[endpoint]).zenoh_config()
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber("etam/bench/camera/cam0/events", on_sample)
        camera = subprocess.Popen([sys.executable, "-m", "services.cli", "camera", "--source", str(path),
                                   "--rate", "0", "--rig", "bench", "--connect", endpoint, "--log-level", "WARNING"])
        try:
            done.wait(120)
        finally:
            camera.terminate()
            camera.wait(20)
            sub.undeclare()
    got["events_per_s"] = got["events"] / max(got["last"] - got["first"], 1e-9)
    return got


def run(quick: bool = False) -> list[dict]:
    if not SAMPLES.is_dir():
        return [{"stage": "playback --rate 0", "error": "../shared/data/real is absent"}]
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        path = Path(tmp) / "dense.raw"
        _repeat_raw(SAMPLES / "gen41_driving_evt3.raw", path, 40 if quick else 200, "<u2", 12)
        expected = sum(len(c) for c in open_recording(path).chunks())
        plays = [_play(path, expected) for _ in range(1 if quick else 3)]
    rates = sorted(p["events_per_s"] for p in plays)
    return [{"stage": "playback --rate 0 to another process", "file_events": expected, "plays": len(plays),
             "events": [p["events"] for p in plays], "seq_gaps": sum(p["gaps"] for p in plays),
             "events_per_s": rates[len(rates) // 2], "best_events_per_s": rates[-1], "worst_events_per_s": rates[0],
             "complete": all(p["events"] == expected and p["gaps"] == 0 for p in plays)}]
