"""Writing events: ETAM's MCAP recorder (live payloads as they travel) and ETAM's AEDAT 4.0 writer,
against dv-processing's AEDAT 4.0 (LZ4) writer, on the same simulated 346x260 events in 10 ms packets
(6 s of sim:objects with noise, 8 laps: about 7 million events).
Figures: events/s and bytes per event on disk. dv-processing's EventStores are built before timing.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.filters import PACKET_US, _packets, dv_stores, labelled_events
from services.camera.formats.aedat4 import Aedat4Writer
from services.camera.recorder import McapRecorder
from services.messages import EventPacket

WIDTH, HEIGHT = 346, 260


def _mcap(packets: list[np.ndarray], path: Path) -> float:
    payloads = [EventPacket(seq=i + 1, stamp=(i + 1) * PACKET_US, width=WIDTH, height=HEIGHT, events=p).encode()
                for i, p in enumerate(packets)]  # what the recorder receives
    t0 = time.perf_counter()
    rec = McapRecorder(path)
    for payload in payloads:
        rec.write("etam/bench/camera/cam0/events", payload, time.time_ns())
    rec.close()
    return time.perf_counter() - t0


def _aedat4(packets: list[np.ndarray], path: Path) -> float:
    t0 = time.perf_counter()
    with Aedat4Writer(path, WIDTH, HEIGHT) as writer:
        for p in packets:
            writer.write(p)
    return time.perf_counter() - t0


def _dv(packets: list[np.ndarray], path: Path) -> float:
    import dv_processing as dv

    stores = dv_stores(packets)
    t0 = time.perf_counter()
    writer = dv.io.MonoCameraWriter(str(path), dv.io.MonoCameraWriter.EventOnlyConfig("bench", (WIDTH, HEIGHT)))
    for store in stores:
        writer.writeEvents(store)
    del writer  # closes the file
    return time.perf_counter() - t0


def _laps(events: np.ndarray, laps: int) -> np.ndarray:
    """The sequence played `laps` times in a row (times shifted): enough data to time the writers,
    without simulating for minutes. Chunks (1 MiB) are far smaller than a lap: no repeat to exploit."""
    span = int(events["t"][-1]) + 1
    out = np.tile(events, laps)
    out["t"] += np.repeat(np.arange(laps, dtype=np.int64) * span, len(events))
    return out


def run(quick: bool = False) -> list[dict]:
    events = _laps(labelled_events(2_000_000 if quick else 6_000_000)[0], 2 if quick else 8)
    packets = [p for p in _packets(events) if len(p)]
    n = len(events)
    rows = []
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        peer_rate = peer_bytes = None
        error = None
        try:
            peer_s = _dv(packets, Path(tmp) / "dv.aedat4")
            peer_rate, peer_bytes = n / peer_s, (Path(tmp) / "dv.aedat4").stat().st_size / n
        except ImportError as exc:
            error = f"not installed ({exc.name})"
        for stage, write, name in (("record MCAP (etam record)", _mcap, "r.mcap"),
                                   ("write AEDAT 4.0 (LZ4)", _aedat4, "e.aedat4")):
            elapsed = write(packets, Path(tmp) / name)
            rows.append({"stage": stage, "events": n, "etam_events_per_s": n / elapsed,
                         "etam_bytes_per_event": (Path(tmp) / name).stat().st_size / n,
                         "peer": "dv-processing AEDAT 4.0 (LZ4)", "peer_events_per_s": peer_rate,
                         "peer_bytes_per_event": peer_bytes,
                         "ratio": n / elapsed / peer_rate if peer_rate else None, "peer_error": error})
    return rows
