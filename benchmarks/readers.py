"""File decoding into numpy: ETAM's readers against the peer libraries, on the same bytes, same run.

Test files are made in a temporary folder: Prophesee EVT 2.0 / 3.0 from the real samples' data
repeated (the header once), AEDAT 4.0 written by ETAM from simulated events. Peers: dv-processing
(AEDAT 4.0), aedat (AEDAT 4.0), expelliarmus (EVT 2.0, EVT 3.0), evt3 (EVT 3.0). A peer that is not
installed is reported as missing.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.camera.formats import open_recording
from services.camera.formats.aedat4 import Aedat4Writer
from services.camera.formats.prophesee import read_header

SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "prophesee_samples"


def _ours(path: Path) -> int:
    return sum(len(chunk) for chunk in open_recording(path).chunks())


def _expelliarmus(encoding: str) -> Callable[[Path], int]:
    def read(path: Path) -> int:
        from expelliarmus import Wizard

        return len(Wizard(encoding=encoding, fpath=str(path)).read())
    return read


def _evt3(path: Path) -> int:
    import evt3

    return len(evt3.decode_file(str(path)).x)


def _dv(path: Path) -> int:
    import dv_processing as dv

    rec, n = dv.io.MonoCameraRecording(str(path)), 0
    while (batch := rec.getNextEventBatch()) is not None:
        n += len(batch.numpy())
    return n


def _aedat(path: Path) -> int:
    import aedat

    return sum(len(p["events"]) for p in aedat.Decoder(str(path)) if "events" in p)


def _repeat_raw(src: Path, dst: Path, times: int, word: str, high_bits: int) -> None:
    """The sample's data `times` over, each lap's TIME_HIGH words moved on so that time keeps rising
    (a realistic longer recording, not one whose clock jumps back)."""
    _, offset = read_header(src)
    data = src.read_bytes()
    words = np.frombuffer(data[offset:], word)
    shift = 28 if word == "<u4" else 12
    is_high = (words >> shift) == 0x8
    highs = words[is_high] & ((1 << high_bits) - 1)
    span = int(highs.max()) - int(highs.min()) + 1
    laps = []
    for k in range(times):
        lap = words.copy()
        lap[is_high] = (0x8 << shift) | ((highs + k * span) & ((1 << high_bits) - 1))
        laps.append(lap)
    dst.write_bytes(data[:offset] + np.concatenate(laps).tobytes())


def _aedat4_file(dst: Path, n_events: int) -> None:
    from services.camera.simulator import EventSimulator, ObjectsScene

    sim = EventSimulator(ObjectsScene())
    with Aedat4Writer(dst, 346, 260) as writer:
        t, written = 0, 0
        while written < n_events:
            t += 100_000
            ev = sim.advance(t)
            writer.write(ev, max_per_packet=4096)
            written += len(ev)


def _rate(read: Callable[[Path], int], path: Path) -> tuple[float | None, int, str | None]:
    """One decode rate (events/s), the count, and an error if the decoder failed."""
    try:
        t0 = time.perf_counter()
        count = read(path)
        return count / (time.perf_counter() - t0), count, None
    except ImportError as exc:
        return None, 0, f"not installed ({exc.name})"
    except Exception as exc:  # a peer failing on a file is a result to report, not a crash
        return None, 0, f"{type(exc).__name__}: {exc}"


def _best_rates(readers: dict[str, Callable[[Path], int]], path: Path,
                repeats: int) -> dict[str, tuple[float | None, int, str | None]]:
    """Best of `repeats` rates of each reader, taking turns (ETAM, peer, ETAM, peer, ...) so that
    a slow spell of a shared machine does not fall on one side only."""
    best: dict[str, tuple[float | None, int, str | None]] = {}
    for _ in range(repeats):
        for name, read in readers.items():
            rate, count, error = _rate(read, path)
            previous = best.get(name)
            if previous is None or (rate is not None and (previous[0] is None or rate > previous[0])):
                best[name] = (rate, count, error)
    return best


def run(quick: bool = False) -> list[dict]:
    repeats = 2 if quick else 5
    rows = []
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        files = []
        if SAMPLES.is_dir():
            _repeat_raw(SAMPLES / "gen3_sparklers_evt2.raw", Path(tmp) / "evt2.raw", 2 if quick else 10, "<u4", 28)
            _repeat_raw(SAMPLES / "gen41_driving_evt3.raw", Path(tmp) / "evt3.raw", 4 if quick else 20, "<u2", 12)
            files += [("EVT 2.0", Path(tmp) / "evt2.raw", {"expelliarmus": _expelliarmus("evt2")}),
                      ("EVT 3.0", Path(tmp) / "evt3.raw", {"expelliarmus": _expelliarmus("evt3"), "evt3": _evt3})]
        _aedat4_file(Path(tmp) / "sim.aedat4", 500_000 if quick else 3_000_000)
        files.append(("AEDAT 4.0 (LZ4)", Path(tmp) / "sim.aedat4", {"dv-processing": _dv, "aedat": _aedat}))
        for fmt, path, peers in files:
            _ours(path)  # warm: numba kernels compiled, file in the page cache
            rates = _best_rates({"etam": _ours, **peers}, path, repeats)
            ours, count, _ = rates["etam"]
            for peer in peers:
                rate, peer_count, error = rates[peer]
                rows.append({"stage": f"read {fmt}", "events": count, "bytes_per_event": path.stat().st_size / count,
                             "etam_events_per_s": ours, "peer": peer, "peer_events_per_s": rate,
                             "peer_events": peer_count, "ratio": ours / rate if rate else None, "peer_error": error})
    return rows
