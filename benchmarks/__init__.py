"""The performance suite run by `etam bench`."""

import socket
import subprocess
import time

import zenoh


def free_port() -> int:
    """A TCP port on loopback that nothing listens on now (for a zenoh endpoint of one run)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def join(conf: zenoh.Config, rig: subprocess.Popen, wait_s: float = 30.0) -> zenoh.Session | None:
    """A client session on the rig's router once it listens (its start takes seconds on a busy
    machine); None if the rig exits or does not listen in `wait_s`."""
    deadline = time.monotonic() + wait_s
    while rig.poll() is None and time.monotonic() < deadline:
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            time.sleep(0.2)
    return None
