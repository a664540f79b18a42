"""Record live traffic to MCAP and replay it: payloads come back byte for byte, in order."""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from services.camera.recorder import read_mcap
from tests.conftest import ROOT, client_session, etam_argv, spawn, wait_alive, wait_for


def _record(router: str, rig: str, out: Path, seconds: float, stop: signal.Signals) -> None:
    with spawn("camera", "--connect", router, "--rig", rig, "--log-level", "WARNING"):
        with spawn("record", str(out), "--keys", f"etam/{rig}/camera/**", "--connect", router, "--rig", rig,
                   "--log-level", "WARNING") as rec, client_session(router) as s:
            wait_alive(s, rig, 2)
            time.sleep(seconds)
            rec.send_signal(stop)
            rec.wait(10)


def test_record_then_replay_reproduces_payloads_bytewise(tmp_path: Path, router: str, rig: str) -> None:
    out = tmp_path / "r.mcap"
    _record(router, rig, out, 4, signal.SIGINT)
    recorded = list(read_mcap(out))
    keys = {k for k, _, _ in recorded}
    assert {f"etam/{rig}/camera/cam0/events", f"etam/{rig}/camera/cam0/truth/boxes"} <= keys
    assert sum(k.endswith("/events") for k, _, _ in recorded) > 2000
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))

    with client_session(router) as s:
        sub = s.declare_subscriber(f"etam/{rig}/camera/**", on_sample)
        replay = subprocess.run(etam_argv("replay", str(out), "--rate", "0", "--connect", router, "--log-level",
                                          "WARNING"), cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert replay.returncode == 0, replay.stderr
        wait_for(lambda: len(got) >= len(recorded), 20, "every replayed message")
        sub.undeclare()
    for key in keys:  # per key, the same payloads in the same order
        assert [p for k, p in got if k == key] == [p for k, p, _ in recorded if k == key], key


def test_a_killed_recorder_leaves_a_readable_file(tmp_path: Path, router: str, rig: str) -> None:
    out = tmp_path / "crash.mcap"
    _record(router, rig, out, 4, signal.SIGKILL)
    messages = list(read_mcap(out))  # no summary, maybe a torn chunk: everything complete is read
    assert len(messages) > 1000
    times = [t for _, _, t in messages]
    assert times == sorted(times)


def test_a_file_cut_anywhere_replays_what_is_complete(tmp_path: Path) -> None:
    from services.camera.recorder import McapRecorder

    path = tmp_path / "whole.mcap"
    rec = McapRecorder(path)
    for i in range(3000):
        rec.write(f"etam/r/x/y/t{i % 3}", bytes([i % 251]) * 200, 1_000 + i)
        if i % 500 == 499:
            rec.flush()  # what the recorder does every half second: a chunk ends
    rec.close()
    data = path.read_bytes()
    assert len(list(read_mcap(path))) == 3000
    counts = []
    for cut in (9, 20, len(data) // 3, len(data) // 2 + 7, len(data) - 100):
        (tmp_path / "cut.mcap").write_bytes(data[:cut])
        counts.append(len(list(read_mcap(tmp_path / "cut.mcap"))))
    assert counts == sorted(counts) and counts[0] == 0 and 0 < counts[2] < 3000 and counts[-1] >= counts[3]


def test_mcap_files_have_a_summary_that_seeking_readers_use(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    from services.camera.recorder import McapRecorder
    from services.messages import EVENT_DTYPE, EventPacket

    path = tmp_path / "s.mcap"
    rec = McapRecorder(path)
    packet = EventPacket(seq=1, stamp=5, width=4, height=4, events=np.zeros(3, EVENT_DTYPE))
    rec.write("etam/r/camera/cam0/events", packet.encode(), 2_000)
    for i in range(400):  # incompressible payloads: several 1 MiB chunks
        rec.write(f"etam/r/x/y/t{i % 2}", np.random.default_rng(i).bytes(10_000), 3_000 + i)
    rec.close()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 401
        assert len(summary.chunk_indexes) >= 4 and len(summary.channels) == 3
        assert {s.name for s in summary.schemas.values()} == {"EventPacket", "unknown"}
        got = [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages(starting_at=3_100)]
    assert [t for _, t, _ in got] == list(range(3_100, 3_400))
    assert got[0][2] == np.random.default_rng(100).bytes(10_000)
