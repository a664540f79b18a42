"""Zenoh session settings from a JSON5 config file, then environment variables, then flags.

Multicast scouting is off by default: on a drone's network a service should join the rig it is told
to join (``--connect tcp/HOST:7447``), not whatever answers on the LAN.
"""

from __future__ import annotations

import ctypes
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from services import keys

DEFAULT_PORT = 7447

TRANSPORT_DEFAULTS = {
    # Python subscribers stall zenoh's receive thread while they wait for the GIL; give a sensor
    # stream 50 ms and 16 batches of slack before the publisher drops, instead of 1 ms and 2.
    "transport/link/tx/queue/congestion_control/drop/wait_before_drop": 50_000,
    "transport/link/tx/queue/size/data": 16,
}
"""Zenoh transport settings ETAM uses when no config file is given (a config file's own are kept)."""


class ConfigError(ValueError):
    """A setting that cannot be used; the text names the setting and the value."""


@dataclass
class ZenohSettings:
    """Where and how a process joins the zenoh network."""

    mode: str | None = None  # peer, client or router; None: the file's, else peer
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    multicast: bool | None = None  # None: the file's, else off
    config_file: str | None = None

    def zenoh_config(self) -> zenoh.Config:
        """The zenoh.Config these settings describe: the file (or ETAM's defaults), then the settings."""
        if self.mode not in (None, "peer", "client", "router"):
            raise ConfigError(f"mode: {self.mode!r} is not one of peer, client, router")
        if self.config_file:
            path = Path(self.config_file)
            if not path.is_file():
                raise ConfigError(f"config file {path} does not exist")
            try:
                conf = zenoh.Config.from_file(str(path))
            except Exception as exc:  # zenoh raises ZError with the parser's message
                raise ConfigError(f"config file {path}: {zenoh_reason(exc)}") from None
        else:
            conf = zenoh.Config()
            for path, value in {**TRANSPORT_DEFAULTS, "mode": "peer", "scouting/multicast/enabled": False}.items():
                conf.insert_json5(path, json.dumps(value))
        try:
            if self.mode is not None:
                conf.insert_json5("mode", json.dumps(self.mode))
            if self.connect:
                conf.insert_json5("connect/endpoints", json.dumps(self.connect))
            if self.listen:
                conf.insert_json5("listen/endpoints", json.dumps(self.listen))
            if self.multicast is not None:
                conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast))
        except Exception as exc:
            raise ConfigError(f"zenoh settings {self}: {zenoh_reason(exc)}") from None
        return conf


def zenoh_reason(exc: Exception) -> str:
    """zenoh's error text without the Rust source locations it appends."""
    return str(exc).split(" at /", 1)[0].replace("[", "").strip()


def _split(value: str | None) -> list[str]:
    return [v.strip() for v in (value or "").split(",") if v.strip()]


def _endpoint(value: str) -> str:
    """Accept ``HOST:PORT`` and ``HOST`` as shorthands for ``tcp/HOST:PORT``."""
    if "/" in value:
        return value
    return f"tcp/{value}" if ":" in value else f"tcp/{value}:{DEFAULT_PORT}"


def resolve(
    mode: str | None = None,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    multicast: bool | None = None,
    config_file: str | None = None,
) -> ZenohSettings:
    """Settings from flags (given here) over environment (ETAM_MODE, ETAM_CONNECT, ETAM_LISTEN,
    ETAM_MULTICAST, ETAM_ZENOH_CONFIG) over defaults."""
    env = os.environ
    env_multicast = env["ETAM_MULTICAST"].lower() in ("1", "true", "yes", "on") if "ETAM_MULTICAST" in env else None
    return ZenohSettings(
        mode=mode or env.get("ETAM_MODE") or None,
        connect=[_endpoint(c) for c in (connect or _split(env.get("ETAM_CONNECT")))],
        listen=[_endpoint(c) for c in (listen or _split(env.get("ETAM_LISTEN")))],
        multicast=env_multicast if multicast is None else multicast,
        config_file=config_file or env.get("ETAM_ZENOH_CONFIG") or None,
    )


def resolve_rig(rig: str | None) -> str:
    """The rig name: flag, then ETAM_RIG, then the host name."""
    return keys.sanitize(rig or os.environ.get("ETAM_RIG") or keys.default_rig())


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8  # glibc mallopt parameters


def tune_malloc(arena_max: int = 1, big_bytes: int = 64 << 20) -> bool:
    """Keep freed memory for reuse instead of handing it back to the kernel after every event block.

    glibc serves blocks above a few hundred kB with fresh mmaps and returns them on free, so every
    decoded chunk and packet page-faulted its memory anew (on a VM that halved file playback); with
    several threads each gets its own arena and trims it on its own. Blocks up to `big_bytes` come
    from one shared heap that is trimmed only when 4x that is free. numpy's advice to back arrays
    with huge pages is turned off too: it doubled the cost of allocating a decoder's output block.
    False where libc is not glibc.
    """
    import numpy as np

    set_hugepage = getattr(getattr(np, "_core", np).multiarray, "_set_madvise_hugepage", None)
    if set_hugepage is not None:
        set_hugepage(False)
    try:
        libc = ctypes.CDLL("libc.so.6")
        return all(libc.mallopt(param, value) == 1 for param, value in (
            (_M_ARENA_MAX, arena_max), (_M_MMAP_THRESHOLD, big_bytes), (_M_TRIM_THRESHOLD, 4 * big_bytes)))
    except (OSError, AttributeError):
        return False
