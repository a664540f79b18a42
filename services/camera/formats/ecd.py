"""Event Camera Dataset text (`events.txt`: `t[s] x y p` per line), with calib.txt and groundtruth.txt.

Parsed in blocks of whole lines with one vectorised `np.fromstring` per block, so memory stays
bounded and a bad line is reported with its byte offset after the good lines before it.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from services.camera.formats.recording import (
    CHUNK_EVENTS, Calibration, EventWriter, FormatError, Recording, events_from_columns,
)
from services.messages import EVENT_DTYPE

ECD_SIZE = (240, 180)  # DAVIS240C, the sensor of every ECD sequence (sensor.txt beside may say otherwise)
BLOCK_BYTES = 8 << 20


def looks_like(head: bytes) -> bool:
    """True if the first line is four numbers with a decimal time: `0.000001 12 34 1`."""
    line = head.split(b"\n", 1)[0].split()
    if len(line) != 4:
        return False
    try:
        float(line[0])
        return all(int(v) >= 0 for v in line[1:])
    except ValueError:
        return False


class EcdRecording(Recording):
    """A folder with events.txt (or the file itself); calibration and ground truth beside it."""

    format = "ecd-text"

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        folder = self.path if self.path.is_dir() else self.path.parent
        self.events_path = folder / "events.txt" if self.path.is_dir() else self.path
        if not self.events_path.is_file():
            raise FormatError(self.path, "no events.txt in this folder")
        self.width, self.height = ECD_SIZE
        sensor = folder / "sensor.txt"
        if sensor.is_file():
            try:
                self.width, self.height = (int(v) for v in sensor.read_text().split()[:2])
            except ValueError:
                raise FormatError(sensor, "expected `width height`") from None
        calib = folder / "calib.txt"
        if calib.is_file():
            values = np.array(calib.read_text().split(), np.float64)
            if len(values) < 4:
                raise FormatError(calib, "expected `fx fy cx cy [k1 k2 p1 p2 k3]`")
            fx, fy, cx, cy = values[:4]
            K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
            dist = values[4:9]
            self.calibration = Calibration(K, "radtan" if len(dist) else "none", dist)
        truth = folder / "groundtruth.txt"
        if truth.is_file():
            self.truth.poses = np.loadtxt(truth, ndmin=2)

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        block = max(BLOCK_BYTES, max_events * 24)
        offset = 0
        with open(self.events_path, "rb") as f:
            rest = b""
            while True:
                data = f.read(block)
                buf = rest + data
                if not buf:
                    return
                cut = buf.rfind(b"\n") + 1 if data else len(buf)
                lines, rest = buf[:cut], buf[cut:]
                if lines:
                    events, error = self._parse(lines, offset)
                    for start in range(0, len(events), max_events):
                        yield events[start:start + max_events]
                    if error is not None:
                        raise error
                    offset += len(lines)
                if not data:
                    return

    def _parse(self, lines: bytes, offset: int) -> tuple[np.ndarray, FormatError | None]:
        """The events of whole `lines`; at a bad line, those before it and the error naming it."""
        try:
            values = np.fromstring(lines, dtype=np.float64, sep=" ")  # the fast vectorised text parser
        except ValueError:
            values = None
        if values is None or len(values) % 4 or not np.all(np.isfinite(values)):
            bad_at, reason = self._find_bad_line(lines)
            good, _ = self._parse(lines[:bad_at], offset) if bad_at else (np.empty(0, EVENT_DTYPE), None)
            return good, FormatError(self.events_path, reason, offset + bad_at)
        rows = values.reshape(-1, 4)
        x, y, p = rows[:, 1], rows[:, 2], rows[:, 3]
        bad = (x < 0) | (x >= self.width) | (y < 0) | (y >= self.height) | ((p != 0) & (p != 1))
        if bad.any():
            line = int(np.flatnonzero(bad)[0])
            bad_at = sum(len(s) + 1 for s in lines.split(b"\n")[:line])
            good, _ = self._parse(lines[:bad_at], offset) if bad_at else (np.empty(0, EVENT_DTYPE), None)
            return good, FormatError(self.events_path, f"event outside {self.width}x{self.height} or with "
                                     "polarity other than 0/1", offset + bad_at)
        return events_from_columns(np.round(rows[:, 0] * 1e6).astype(np.int64), x, y, p), None

    @staticmethod
    def _find_bad_line(lines: bytes) -> tuple[int, str]:
        """Byte offset (within `lines`) and description of the first line that is not `t x y p`."""
        pos = 0
        for line in lines.split(b"\n"):
            parts = line.split()
            ok = len(parts) == 4
            if ok:
                try:
                    ok = all(np.isfinite(float(v)) for v in parts)
                except ValueError:
                    ok = False
            if line.strip() and not ok:
                return pos, f"bad line {line[:60]!r}: expected `t x y p`"
            pos += len(line) + 1
        return 0, "unreadable text"


class EcdWriter(EventWriter):
    """Writes `events.txt` (t in seconds with 9 decimals, x, y, p), `calib.txt` when calibrated, and
    `sensor.txt` (`width height`, an ETAM addition: ECD text has no place for the sensor size)."""

    def __init__(self, path: str | Path, width: int, height: int, calibration: Calibration | None = None) -> None:
        path = Path(path)
        if path.suffix.lower() != ".txt":
            path.mkdir(parents=True, exist_ok=True)
            path = path / "events.txt"
        self.path = path
        (path.parent / "sensor.txt").write_text(f"{width} {height}\n")
        if calibration is not None:
            k, d = calibration.K, np.zeros(5)
            d[: min(5, len(calibration.dist))] = calibration.dist[:5]
            values = [k[0, 0], k[1, 1], k[0, 2], k[1, 2], *d]
            (path.parent / "calib.txt").write_text(" ".join(f"{v:.12g}" for v in values) + "\n")
        self._file = open(path, "w")
        self.count = 0

    def write(self, events: np.ndarray) -> None:
        seconds, micros = np.divmod(events["t"], 1_000_000)
        rows = np.column_stack([seconds, micros, events["x"], events["y"], events["p"]])
        np.savetxt(self._file, rows, fmt="%d.%06d000 %d %d %d")
        self.count += len(events)

    def close(self) -> None:
        self._file.close()
