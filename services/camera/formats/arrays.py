"""Formats that are arrays on disk: MATLAB `events`, numpy npz, and N-MNIST binary.

MATLAB and npz files are loaded whole (their containers are not streamable); N-MNIST is memory
mapped and decoded in chunks.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from services.camera.formats.recording import CHUNK_EVENTS, FormatError, Recording, events_from_columns

MAT_MAGIC = b"MATLAB 5.0 MAT-file"
NPZ_MAGIC = b"PK\x03\x04"


class _InMemory(Recording):
    """A recording whose events were loaded at once; chunks are views on them."""

    events: np.ndarray

    def _set_events(self, t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> None:
        order = np.argsort(t, kind="stable")
        self.events = events_from_columns(t[order], x[order], y[order], p[order])
        if len(self.events) and (x.min() < 0 or y.min() < 0):
            raise FormatError(self.path, "negative pixel coordinates")
        if not self.width:
            self.width = int(x.max()) + 1 if len(x) else 1
            self.height = int(y.max()) + 1 if len(y) else 1

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        for start in range(0, len(self.events), max_events):
            yield self.events[start:start + max_events]


class MatRecording(_InMemory):
    """MATLAB v5 with an `events` matrix N x 4 = [x y p(-1/+1 or 0/1) t_us] (rpg_event_lifetime)."""

    format = "matlab"

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        import scipy.io

        try:
            mat = scipy.io.loadmat(self.path, variable_names=["events"])
        except (ValueError, OSError, NotImplementedError) as exc:
            raise FormatError(self.path, f"unreadable MATLAB file ({exc})") from None
        ev = mat.get("events")
        if ev is None or ev.ndim != 2 or ev.shape[1] != 4:
            raise FormatError(self.path, "expected a variable `events` of N x 4 [x y p t_us]")
        ev = ev.astype(np.int64)
        if ev[:, 0].max(initial=0) < 128 and ev[:, 1].max(initial=0) < 128:
            self.width = self.height = 128  # the DVS128 these files come from
        self._set_events(ev[:, 3], ev[:, 0], ev[:, 1], ev[:, 2] > 0)


class NpzRecording(_InMemory):
    """numpy npz with arrays t (us), x, y, p, or one structured array `events` with those fields."""

    format = "npz"

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        try:
            data = np.load(self.path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise FormatError(self.path, f"unreadable npz ({exc})") from None
        cols = data["events"] if "events" in data and data["events"].dtype.names else data
        missing = [k for k in "txyp" if k not in (cols.dtype.names if hasattr(cols, "dtype") else cols)]
        if missing:
            raise FormatError(self.path, f"npz lacks {', '.join(missing)} (expected t x y p, or events)")
        for key in ("width", "height"):
            if key in getattr(data, "files", []):
                setattr(self, key, int(data[key]))
        self._set_events(*(np.asarray(cols[k]).astype(np.int64) for k in "txyp"))


def looks_like_nmnist(head: bytes) -> bool:
    """N-MNIST has no header: plausible when the first events lie in 34 x 34 with rising times."""
    b = np.frombuffer(head[: len(head) - len(head) % 5], np.uint8).reshape(-1, 5).astype(np.int64)
    t = ((b[:, 2] & 0x7F) << 16) | (b[:, 3] << 8) | b[:, 4]
    return len(b) > 0 and bool(np.all(b[:, :2] < 34) and np.all(np.diff(t) >= 0))


class NmnistRecording(Recording):
    """N-MNIST binary: 5 bytes an event (x, y, p | t[22:16], t[15:8], t[7:0]), 34 x 34 pixels."""

    format = "nmnist-bin"

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self.width = self.height = 34

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        size = self.path.stat().st_size
        raw = np.memmap(self.path, np.uint8, "r", 0, size - size % 5).reshape(-1, 5)
        for start in range(0, len(raw), max_events):
            b = np.asarray(raw[start:start + max_events]).astype(np.int64)
            t = ((b[:, 2] & 0x7F) << 16) | (b[:, 3] << 8) | b[:, 4]
            yield events_from_columns(t, b[:, 0], b[:, 1], b[:, 2] >> 7)
        if size % 5:
            raise FormatError(self.path, f"truncated: {size % 5} bytes of a 5-byte event", size - size % 5)
