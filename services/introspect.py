"""`etam ls`, `etam echo`, `etam hz`: look at a running rig, like `ros2 node list` / `topic echo` / `topic hz`."""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from typing import Any, TextIO

import zenoh

from services import keys
from services.messages import MessageError, Stats, decode


def list_services(session: zenoh.Session, rig: str = "*", wait_s: float = 1.5) -> list[dict[str, Any]]:
    """Live services (liveliness tokens) with their latest Stats rows, gathered over `wait_s`."""
    stats: dict[str, Stats] = {}
    lock = threading.Lock()

    def on_stats(sample: zenoh.Sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes(), Stats)
        except MessageError:
            return
        with lock:
            stats[str(sample.key_expr).rsplit("/", 1)[0]] = msg

    alive: set[str] = set()

    def on_token(sample: zenoh.Sample) -> None:
        prefix = str(sample.key_expr).rsplit("/", 1)[0]
        with lock:
            if sample.kind == zenoh.SampleKind.PUT:
                alive.add(prefix)
            else:  # the service went away during the wait
                alive.discard(prefix)

    # tokens gathered over the whole wait (those already declared come as history): one query at its
    # end missed a token now and then on a loaded machine
    subs = [session.declare_subscriber(keys.stats(rig), on_stats),
            session.liveliness().declare_subscriber(keys.alive(rig), on_token, history=True)]
    time.sleep(wait_s)
    for sub in subs:
        sub.undeclare()
    out = []
    with lock:
        prefixes = sorted(alive | set(stats))
    for prefix in prefixes:
        st = stats.get(prefix)
        out.append({
            "prefix": prefix, "alive": prefix in alive,
            "pid": st.pid if st else None, "host": st.host if st else None,
            "cpu_percent": st.cpu_percent if st else None, "rss_bytes": st.rss_bytes if st else None,
            "keys": st.keys if st else [],
        })
    return out


def format_services(services: list[dict[str, Any]]) -> str:
    if not services:
        return "no ETAM services found (is `etam up` running, or pass --connect tcp/HOST:7447)"
    lines = []
    for s in services:
        state = "alive" if s["alive"] else "no liveliness token"
        extra = f"  pid {s['pid']} on {s['host']}, {s['cpu_percent']:.0f}% cpu, {s['rss_bytes'] / 2**20:.0f} MB" \
            if s["pid"] else ""
        lines.append(f"{s['prefix']}  [{state}]{extra}")
        for row in s["keys"]:
            lines.append(f"    {row['dir']:>3} {row['key']}  {row['msg_rate']:.0f} msg/s  {row['event_rate']:.0f} ev/s"
                         f"  dropped {row['dropped']}  malformed {row['malformed']}")
    return "\n".join(lines)


def echo(session: zenoh.Session, keyexpr: str, out: TextIO, count: int | None = None,
         timeout_s: float | None = None, full: bool = False) -> int:
    """Print each message on `keyexpr` as one JSON line (arrays in full when `full`); return how many
    were printed."""
    printed = 0
    done = threading.Event()
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal printed
        try:
            msg = decode(sample.payload.to_bytes())
            body: dict[str, Any] = msg.to_dict(full)
        except MessageError as exc:
            body = {"error": str(exc)}
        with lock:
            if done.is_set():
                return
            out.write(json.dumps({"key": str(sample.key_expr), **body}, default=str) + "\n")
            out.flush()
            printed += 1
            if count is not None and printed >= count:
                done.set()

    sub = session.declare_subscriber(keyexpr, on_sample)
    try:
        done.wait(timeout_s)
    finally:
        sub.undeclare()
    return printed


def hz(session: zenoh.Session, keyexpr: str, out: TextIO, period_s: float = 1.0, reports: int | None = None,
       as_json: bool = False) -> None:
    """Print message and event rates per key every `period_s`."""
    counts: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0])  # messages, events, bytes
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        try:
            n = decode(payload).event_count()
        except MessageError:
            n = 0
        with lock:
            c = counts[str(sample.key_expr)]
            c[0] += 1
            c[1] += n
            c[2] += len(payload)

    sub = session.declare_subscriber(keyexpr, on_sample)
    try:
        done = 0
        while reports is None or done < reports:
            t = time.monotonic()
            time.sleep(period_s)
            span = time.monotonic() - t
            with lock:
                snap = dict(counts)
                counts.clear()
            rows = {k: {"msg_rate": m / span, "event_rate": e / span, "bytes_rate": b / span}
                    for k, (m, e, b) in sorted(snap.items())}
            if as_json:
                out.write(json.dumps(rows) + "\n")
            elif not rows:
                out.write(f"no messages on {keyexpr}\n")
            for k, r in ([] if as_json else rows.items()):
                out.write(f"{k}: {r['msg_rate']:.1f} msg/s, {r['event_rate']:.0f} ev/s, "
                          f"{r['bytes_rate'] / 1e6:.2f} MB/s\n")
            out.flush()
            done += 1
    finally:
        sub.undeclare()
