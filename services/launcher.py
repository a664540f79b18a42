"""`etam up`: a zenoh router in this process and each service as its own OS process.

The launcher restarts a service that dies (with exponential backoff, and says so), watches the
traffic of the rig to write a report, and stops every child on Ctrl-C, SIGTERM or at the end of
``--duration``. Children get PR_SET_PDEATHSIG, so even a killed launcher leaves no orphans.
"""

from __future__ import annotations

import ctypes
import functools
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import zenoh

from services import keys
from services.config import ZenohSettings, zenoh_reason
from services.messages import Command, MessageError, Reply, Stats, decode, peek

log = logging.getLogger(__name__)

BACKOFF_S = (0.5, 1.0, 2.0, 4.0, 8.0)
STABLE_S = 30.0  # a child that ran this long starts again from the shortest backoff
USAGE_ERROR = 2  # a child's exit code for a bad flag, source or config: restarting cannot help
STOP_GRACE_S = 3.0
SILENT_S = 10.0  # a running child without Stats this long is hung (a stuck loop keeps its liveliness token)
STARTUP_S = 90.0  # ... but its first Stats may take this long: imports and numba compiling on a cold cache, on
# a loaded CPU at a low priority (a dashboard killed for a slow start would never come up on a busy drone)
VIEWER_NICE = 10  # the dashboard yields the CPU to the services a robot acts on
MAPPER_NICE = 5  # ... and the mapper (keyframes every few seconds) to the tracker (tracks every 10 ms)


def _prepare_child(nice: int) -> None:
    """In the child before exec: get SIGTERM when the launcher dies, however it dies; lower its
    scheduling priority by `nice`."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:  # not Linux: Ctrl-C still reaches the process group
        pass
    if nice:
        os.nice(nice)


@dataclass
class Child:
    """One supervised service process."""

    name: str
    argv: list[str]
    nice: int = 0  # how much lower than the launcher's its scheduling priority is
    proc: subprocess.Popen | None = None
    started: float = 0.0
    restarts: int = 0
    restart_times_s: list[float] = field(default_factory=list)
    exit_codes: list[int] = field(default_factory=list)
    next_start: float = 0.0
    backoff_i: int = 0

    def start(self, t0: float) -> None:
        # children write to our stderr: stdout stays for the dashboard URL, which scripts read
        self.proc = subprocess.Popen(self.argv, preexec_fn=functools.partial(_prepare_child, self.nice),
                                     stdout=sys.stderr)
        self.started = time.monotonic()
        log.info("started %s (pid %d)", self.name, self.proc.pid)

    def check(self, t0: float) -> bool:
        """Start again a child that exited, after its backoff; False if it cannot run at all."""
        now = time.monotonic()
        if self.proc is not None and self.proc.poll() is not None:
            code = self.proc.returncode
            self.exit_codes.append(code)
            if code == USAGE_ERROR:
                log.error("%s cannot start with this configuration (see its message above); not restarting",
                          self.name)
                self.proc = None
                return False
            if now - self.started > STABLE_S:
                self.backoff_i = 0
            delay = BACKOFF_S[min(self.backoff_i, len(BACKOFF_S) - 1)]
            self.backoff_i += 1
            self.next_start = now + delay
            self.proc = None
            log.warning("%s exited with code %s; restarting in %.1f s (restart %d)",
                        self.name, code, delay, self.restarts + 1)
        if self.proc is None and now >= self.next_start:
            self.restarts += 1
            self.restart_times_s.append(round(now - t0, 3))
            self.start(t0)
        return True

    def kill_if_silent(self, last_stats: float | None) -> None:
        """Kill a child whose Stats stopped for SILENT_S, or never came in STARTUP_S; `check` restarts it."""
        if self.proc is None or self.proc.poll() is not None:
            return
        running = last_stats is not None and last_stats >= self.started  # this run of it has sent Stats
        last, limit = (last_stats, SILENT_S) if running else (self.started, STARTUP_S)
        if time.monotonic() - last > limit:
            log.warning("%s sent no Stats for %.0f s%s: it is hung; killing it", self.name, limit,
                        "" if running else " since it started")
            self.proc.kill()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)

    def kill_if_alive(self, deadline: float) -> None:
        if self.proc is None:
            return
        try:
            self.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop in %.0f s; killing it", self.name, STOP_GRACE_S)
            self.proc.kill()
            self.proc.wait()


class TrafficMonitor:
    """Counts every message of the rig per key (messages, events, seq gaps, per-second counts),
    and keeps the latest Stats of each service, from zenoh's callback thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.t0 = time.monotonic()
        self.keys: dict[str, dict[str, Any]] = {}
        self.stats: dict[str, Stats] = {}
        self.last_stats: dict[str, float] = {}  # service kind -> monotonic time of its latest Stats
        self.malformed = 0

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        try:
            body = peek(payload)
            seq = int(body.get("seq", 0))
            count = int(body.get("count", 0))
            stats = decode(payload, Stats) if body.get("type") == "Stats" else None
        except (MessageError, ValueError, TypeError, AttributeError, LookupError, msgpack.UnpackException):
            with self._lock:
                self.malformed += 1
            return
        with self._lock:
            now_s = time.monotonic() - self.t0  # read under the lock: a key's times never go backwards
            k = self.keys.get(key)
            if k is None:
                k = self.keys[key] = {"type": body.get("type"), "messages": 0, "events": 0, "seq_gaps": 0,
                                      "first_s": now_s, "last_s": now_s, "last_seq": None, "max_gap_s": 0.0,
                                      "per_second": defaultdict(int)}
            k["max_gap_s"] = max(k["max_gap_s"], now_s - k["last_s"])
            k["messages"] += 1
            k["events"] += count
            k["last_s"] = now_s
            if k["last_seq"] is not None and seq > k["last_seq"] + 1:
                k["seq_gaps"] += seq - k["last_seq"] - 1
            k["last_seq"] = seq
            k["per_second"][int(now_s)] += 1
            if stats is not None:
                self.stats[f"{stats.service}/{stats.name}"] = stats
                self.last_stats[stats.service] = time.monotonic()

    def report(self, children: list[Child], duration_s: float) -> dict[str, Any]:
        """The JSON report of `etam up --report`."""
        with self._lock:
            out_keys = {}
            for key, k in sorted(self.keys.items()):
                span = max(k["last_s"] - k["first_s"], 1e-3)
                full = [n for s, n in k["per_second"].items() if k["first_s"] + 1 <= s < int(k["last_s"])]
                out_keys[key] = {
                    "type": k["type"], "messages": k["messages"], "events": k["events"],
                    "msg_rate": k["messages"] / span, "event_rate": k["events"] / span,
                    "msg_rate_min": min(full, default=None), "msg_rate_max": max(full, default=None),
                    "max_gap_s": round(k["max_gap_s"], 3),
                    "dropped": k["seq_gaps"], "subscriber_dropped": 0, "subscriber_malformed": 0,
                }
            subs = []
            for who, st in sorted(self.stats.items()):
                for row in st.keys:
                    if row["dir"] != "in":
                        continue
                    subs.append({"service": who, "key": row["key"], "messages": row["messages"],
                                 "dropped": row["dropped"], "skipped": row.get("skipped", 0),
                                 "malformed": row["malformed"]})
                    for key, entry in out_keys.items():
                        if zenoh.KeyExpr(row["key"]).intersects(zenoh.KeyExpr(key)):
                            entry["subscriber_dropped"] += row["dropped"]
                            entry["subscriber_malformed"] += row["malformed"]
            return {
                "duration_s": round(duration_s, 3),
                "keys": out_keys,
                "subscriptions": subs,
                "malformed_seen": self.malformed,
                "services": {c.name: {"restarts": c.restarts, "restart_times_s": c.restart_times_s,
                                      "exit_codes": c.exit_codes,
                                      "pid": c.proc.pid if c.proc else None} for c in children},
            }


@dataclass
class UpOptions:
    rig: str
    source: str = "sim:objects"
    listen: str = "tcp/0.0.0.0:7447"
    web: bool = True
    web_port: int = 8080
    duration_s: float | None = None
    report: Path | None = None
    services: tuple[str, ...] = ("camera", "tracker")
    log_level: str = "INFO"
    camera_args: tuple[str, ...] = ()
    mapper_args: tuple[str, ...] = ()
    tracker_args: tuple[str, ...] = ()


def _local_endpoint(listen: str) -> str:
    proto, _, addr = listen.partition("/")
    host, _, port = addr.rpartition(":")
    if host in ("0.0.0.0", "[::]", ""):
        host = "127.0.0.1"
    return f"{proto}/{host}:{port}"


def _children(opts: UpOptions) -> list[Child]:
    common = ["--rig", opts.rig, "--connect", _local_endpoint(opts.listen), "--log-level", opts.log_level]
    out = []
    for name in opts.services:
        extra = {"camera": ["--source", opts.source, *opts.camera_args],
                 "mapper": ["--poses", "truth", *opts.mapper_args], "tracker": list(opts.tracker_args)}.get(name, [])
        out.append(Child(name, [sys.executable, "-m", "services.cli", name, *common, *extra],
                         nice=MAPPER_NICE if name == "mapper" else 0))
    if opts.web:
        out.append(Child("web", [sys.executable, "-m", "services.cli", "web", *common, "--port", str(opts.web_port)],
                         nice=VIEWER_NICE))
    return out


def _dashboard_url(session: zenoh.Session, rig: str, listen_host: str) -> str | None:
    """Ask the web service for the port it really serves on (viser moves on if the port is taken)."""
    for reply in session.get(keys.key(rig, "web", "web", "cmd"), payload=Command(op="ping").encode(), timeout=2.0):
        if reply.ok is None:
            continue
        try:
            msg = decode(reply.ok.payload.to_bytes(), Reply)
        except MessageError:
            continue
        if msg.ok and msg.result and "port" in msg.result:
            return f"http://{listen_host}:{msg.result['port']}"
    return None


def up(opts: UpOptions) -> int:
    """Run the rig until Ctrl-C / SIGTERM or `duration_s`; write the report; return the exit code."""
    router_conf = ZenohSettings(mode="router", listen=[opts.listen]).zenoh_config()
    try:
        session = zenoh.open(router_conf)
    except zenoh.ZError as exc:
        log.error("cannot start the zenoh router on %s: %s (is another `etam up` running?)", opts.listen,
                  zenoh_reason(exc))
        return USAGE_ERROR
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    monitor = TrafficMonitor()
    sub = session.declare_subscriber(f"{keys.ROOT}/{opts.rig}/**", monitor.on_sample)
    children = _children(opts)
    t0 = time.monotonic()
    log.info("zenoh router listening on %s; rig %r; source %s", opts.listen, opts.rig, opts.source)
    for child in children:
        child.start(t0)
    url_told = not opts.web
    code = 0
    try:
        while not stop.is_set():
            if opts.duration_s is not None and time.monotonic() - t0 >= opts.duration_s:
                break
            for child in children:
                if not child.check(t0):
                    code = USAGE_ERROR
                    stop.set()
                    break
                child.kill_if_silent(monitor.last_stats.get(child.name))
            if not url_told and time.monotonic() - t0 > 1.0:
                url = _dashboard_url(session, opts.rig, "localhost")
                if url:
                    print(f"Dashboard: {url}  (from another machine: http://<this host>:{url.rsplit(':', 1)[1]})",
                          flush=True)
                    url_told = True
            stop.wait(0.2)
    finally:
        log.info("stopping %d services", len(children))
        for child in children:
            child.stop()
        deadline = time.monotonic() + STOP_GRACE_S
        for child in children:
            child.kill_if_alive(deadline)
        duration = time.monotonic() - t0
        sub.undeclare()
        report = monitor.report(children, duration)
        session.close()
    if opts.report is not None:
        opts.report.write_text(json.dumps(report, indent=2))
        log.info("report written to %s", opts.report)
    return code
