"""Key expressions of DESIGN.md section 3: ``etam/<rig>/<service>/<name>/<topic>``."""

from __future__ import annotations

import re
import socket

ROOT = "etam"
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")


def default_rig() -> str:
    """The host name, made safe for a key expression chunk."""
    return sanitize(socket.gethostname().split(".")[0]) or "rig"


def sanitize(chunk: str) -> str:
    """Replace characters zenoh key chunks cannot hold (``/ * $ # ?`` and blanks)."""
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", chunk)


def key(rig: str, service: str, name: str, topic: str) -> str:
    """The key of one topic of one service instance, e.g. ``etam/drone1/camera/cam0/events``."""
    for label, chunk in (("rig", rig), ("service", service), ("name", name)):
        if chunk != "*" and not _CHUNK.match(chunk):
            raise ValueError(f"{label} {chunk!r} is not a valid key chunk (letters, digits, _ . -)")
    return f"{ROOT}/{rig}/{service}/{name}/{topic}"


def parse(keyexpr: str) -> tuple[str, str, str, str] | None:
    """Split a concrete ETAM key into (rig, service, name, topic), or None if it is not one."""
    parts = keyexpr.split("/", 4)
    if len(parts) != 5 or parts[0] != ROOT:
        return None
    return parts[1], parts[2], parts[3], parts[4]


def events(rig: str = "*", cam: str = "*") -> str:
    return key(rig, "camera", cam, "events")


def stats(rig: str = "*") -> str:
    return f"{ROOT}/{rig}/*/*/stats"


def alive(rig: str = "*") -> str:
    return f"{ROOT}/{rig}/*/*/alive"


def frames(rig: str = "*") -> str:
    """Every visualisation Image any service publishes."""
    return f"{ROOT}/{rig}/*/*/frame"
