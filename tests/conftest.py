"""Helpers for tests that start real ETAM processes on loopback."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from benchmarks import free_port
from services import keys
from services.config import ZenohSettings

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


def etam_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "services.cli", *args]


@contextmanager
def spawn(*args: str, **kw) -> Iterator[subprocess.Popen]:
    """Run `etam ARGS` as a separate process; SIGTERM then SIGKILL it at the end, whatever happens."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **kw.pop("env", {})}
    proc = subprocess.Popen(etam_argv(*args), cwd=ROOT, env=env, start_new_session=True, **kw)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5)


def wait_for(predicate: Callable[[], object], timeout_s: float, what: str, period_s: float = 0.1) -> object:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def client_session(endpoint: str) -> zenoh.Session:
    return zenoh.open(ZenohSettings(mode="client", connect=[endpoint]).zenoh_config())


def wait_alive(session: zenoh.Session, rig: str, count: int, timeout_s: float = 60) -> None:
    """Until `count` services of `rig` hold their liveliness token (a clean clone's first start compiles kernels)."""
    wait_for(lambda: len(list(session.liveliness().get(keys.alive(rig), timeout=1.0))) == count,
             timeout_s, f"{count} services' liveliness tokens")


@pytest.fixture
def router() -> Iterator[str]:
    """A zenoh router process on a free loopback port; yields its endpoint."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"

    def listening() -> bool:
        with socket.socket() as s:
            return s.connect_ex(("127.0.0.1", port)) == 0

    with spawn("router", "--listen", endpoint):
        wait_for(listening, 20, f"the router on {endpoint}")
        yield endpoint


@pytest.fixture
def rig(request: pytest.FixtureRequest) -> str:
    """A rig name of this test's own, so tests never hear each other."""
    return "t" + str(abs(hash(request.node.nodeid)) % 10**8)
