"""jAER AEDAT 2.0: `#` header lines, then big-endian (int32 address, int32 timestamp us) records.

Address layouts (jAER's y axis points up; rows here point down, as everywhere in ETAM):
- DAVIS240C: DVS event when bit31 = 0 and bit10 = 0: x = (a>>12)&0x3FF, y = (a>>22)&0x1FF,
  polarity bit11. IMU word when bit31 = 1 and bit11 = 1: type (a>>28)&7 in the order ax ay az temp
  gx gy gz, int16 value in bits 12-27, 4096 LSB/g and 32.8 LSB per deg/s.
- DVS128: x = 127 - (a>>1)&0x7F, y = (a>>8)&0x7F, bit0 = 0 for ON (as jAER reads it). Older files
  name no chip in their header; 16-bit addresses then tell a DVS128.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from services.camera.formats.recording import CHUNK_EVENTS, FormatError, Recording, events_from_columns

MAGIC = b"#!AER-DAT2"
CHIPS = {"DAVIS240": (240, 180), "DVS128": (128, 128)}
G = 9.80665


class Aedat2Recording(Recording):
    """A jAER AEDAT 2.0 file from a DAVIS240 (events and IMU) or a DVS128."""

    format = "aedat2"

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self.data_offset, header = self._read_header()
        chip = next((c for c in CHIPS if c in header), None) or self._chip_from_addresses()
        if chip is None:
            raise FormatError(self.path, "AEDAT 2.0 from an unknown chip (readable: DAVIS240, DVS128)")
        self.chip = chip
        self.width, self.height = CHIPS[chip]

    def _chip_from_addresses(self) -> str | None:
        first = next(self._records(10_000), None)
        return "DVS128" if first is not None and len(first[1]) and first[1].max() < (1 << 16) else None

    def _read_header(self) -> tuple[int, str]:
        offset, lines = 0, []
        with open(self.path, "rb") as f:
            while True:
                pos = f.tell()
                line = f.readline()
                if not line.startswith(b"#"):
                    return pos, "".join(lines)
                lines.append(line.decode("latin-1"))
                offset += len(line)

    def _records(self, max_records: int) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(byte offset, addresses, unwrapped timestamps) per block; FormatError on a partial record."""
        wraps = 0
        last = None
        offset = self.data_offset
        with open(self.path, "rb") as f:
            f.seek(offset)
            while True:
                block = f.read(8 * max_records)
                if not block:
                    return
                whole = len(block) - len(block) % 8
                rec = np.frombuffer(block, ">i4", whole // 4).reshape(-1, 2)
                t = rec[:, 1].astype(np.int64)
                back = np.diff(t, prepend=t[0] if last is None else last) < -(1 << 31)  # int32 rolled over
                last = int(t[-1]) if len(t) else last
                t += (wraps + np.cumsum(back)) << 32
                wraps += int(back.sum())
                yield offset, rec[:, 0].astype(np.int64), t
                if whole < len(block):
                    raise FormatError(self.path, f"truncated: {len(block) - whole} bytes of an 8-byte record",
                                      offset + whole)
                offset += whole

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        for _offset, a, t in self._records(max_events):
            if self.chip == "DVS128":
                ev = events_from_columns(t, 127 - ((a >> 1) & 0x7F), 127 - ((a >> 8) & 0x7F), 1 - (a & 1))
            else:
                dvs = ((a >> 31) & 1 == 0) & ((a >> 10) & 1 == 0)
                a, t = a[dvs], t[dvs]
                ev = events_from_columns(t, (a >> 12) & 0x3FF, self.height - 1 - ((a >> 22) & 0x1FF), (a >> 11) & 1)
            if len(ev):
                yield ev

    def imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if self.chip == "DVS128":
            return None
        words, times = [], []
        for _offset, a, t in self._records(CHUNK_EVENTS):
            sel = ((a >> 31) & 1 == 1) & ((a >> 11) & 1 == 1)
            words.append(a[sel])
            times.append(t[sel])
        a, t = np.concatenate(words), np.concatenate(times)
        kind = (a >> 28) & 7
        value = ((a >> 12) & 0xFFFF).astype(np.uint16).view(np.int16).astype(np.float64)
        starts = np.flatnonzero(kind == 0)
        starts = starts[starts + 7 <= len(a)]
        complete = np.all(kind[starts[:, None] + np.arange(7)] == np.arange(7), axis=1)
        starts = starts[complete]
        if not len(starts):
            return None
        sample = value[starts[:, None] + np.arange(7)]
        accel = sample[:, 0:3] / 4096.0 * G
        gyro = np.deg2rad(sample[:, 4:7] / 32.8)
        return t[starts], gyro, accel
