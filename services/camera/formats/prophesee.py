"""Prophesee recordings: RAW EVT 2.0 and EVT 3.0, and DAT (v2 2-D events).

EVT 2.0 (32-bit words) is decoded with numpy alone: TIME_HIGH words are forward-filled to every CD
event. EVT 3.0 (16-bit words) is stateful (row, vector base, time high/low, and 24-bit time that
wraps), so a small numba kernel walks the words; its state carries from block to block, so memory
stays bounded. A trailing partial word is reported with its byte offset after the good events.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numba
import numpy as np

from services.camera.formats.recording import CHUNK_EVENTS, FormatError, Recording, events_from_columns

# sensor sizes by the plugin that wrote the file, when the header has no geometry
PLUGIN_SIZES = {"gen3": (640, 480), "gen31": (640, 480), "gen41": (1280, 720), "imx636": (1280, 720),
                "imx8": (320, 320), "gen4": (1280, 720)}


def read_header(path: Path) -> tuple[dict[str, str], int]:
    """The `% key value` header lines (until `% end` or the first non-`%` byte) and its length."""
    fields: dict[str, str] = {}
    offset = 0
    with open(path, "rb") as f:
        while True:
            first = f.read(1)
            if first != b"%":
                break
            line = f.readline()
            offset += 1 + len(line)
            text = line.decode("latin-1").strip()
            if text == "end":
                break
            key, _, value = text.partition(" ")
            fields[key.lower()] = value.strip()
    return fields, offset


def _size_from_header(fields: dict[str, str]) -> tuple[int, int] | None:
    if "geometry" in fields:
        w, _, h = fields["geometry"].partition("x")
        return int(w), int(h)
    fmt = fields.get("format", "")
    w, h = re.search(r"width=(\d+)", fmt), re.search(r"height=(\d+)", fmt)
    if w and h:
        return int(w.group(1)), int(h.group(1))
    if "width" in fields and "height" in fields:
        return int(fields["width"]), int(fields["height"])
    plugin = re.search(r"hal_plugin_(gen\d+|imx\d+)", fields.get("plugin_name", ""))
    return PLUGIN_SIZES.get(plugin.group(1)) if plugin else None


class RawRecording(Recording):
    """A Metavision RAW file in EVT 2.0 or EVT 3.0."""

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self.header, self.data_offset = read_header(self.path)
        evt = self.header.get("evt") or (re.search(r"EVT(\d)", self.header.get("format", "")) or [None, ""])[1]
        version = str(evt).split(".")[0]
        if version not in ("2", "3"):
            raise FormatError(self.path, f"RAW encoding {evt or 'unknown'!r}: EVT 2.0 and 3.0 are readable")
        self.format = f"prophesee-raw-evt{version}"
        self._word = 4 if version == "2" else 2
        size = _size_from_header(self.header)
        if size is None:
            raise FormatError(self.path, "sensor size is neither in the header nor known for its plugin")
        self.width, self.height = size

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        words_per_block = max(1024, max_events // 4)
        decode = _Evt2() if self._word == 4 else _Evt3()
        offset = self.data_offset
        with open(self.path, "rb") as f:
            f.seek(offset)
            while True:
                block = f.read(words_per_block * self._word)
                if not block:
                    return
                whole = len(block) - len(block) % self._word
                events = decode(np.frombuffer(block, "<u4" if self._word == 4 else "<u2", whole // self._word))
                for start in range(0, len(events), max_events):
                    yield events[start:start + max_events]
                if whole < len(block):
                    raise FormatError(self.path, f"truncated: {len(block) - whole} bytes of a {self._word}-byte "
                                      "word at the end", offset + whole)
                offset += whole


class _Evt2:
    """EVT 2.0 words to events; remembers the last TIME_HIGH across blocks."""

    def __init__(self) -> None:
        self.time_high = 0

    def __call__(self, words: np.ndarray) -> np.ndarray:
        w = words.astype(np.int64)
        kind = w >> 28
        is_high = kind == 0x8
        idx = np.where(is_high, np.arange(len(w)), -1)
        np.maximum.accumulate(idx, out=idx)
        high = np.where(idx >= 0, w[np.maximum(idx, 0)] & 0x0FFFFFFF, self.time_high)
        if is_high.any():
            self.time_high = int(w[np.flatnonzero(is_high)[-1]] & 0x0FFFFFFF)
        cd = kind <= 1
        wc = w[cd]
        t = (high[cd] << 6) | ((wc >> 22) & 0x3F)
        return _sorted(events_from_columns(t, (wc >> 11) & 0x7FF, wc & 0x7FF, kind[cd]))


@numba.njit(cache=True)
def _evt3_kernel(words, state, t_out, x_out, y_out, p_out):  # noqa: ANN001, ANN202 - numba kernel
    y, base_x, pol, t_high, t_low, loops = state[0], state[1], state[2], state[3], state[4], state[5]
    n = 0
    for i in range(len(words)):
        w = np.int64(words[i])
        kind = w >> 12
        if kind == 0x0:  # EVT_ADDR_Y
            y = w & 0x7FF
        elif kind == 0x2:  # EVT_ADDR_X: one event
            t_out[n] = (loops << 24) | (t_high << 12) | t_low
            x_out[n], y_out[n], p_out[n] = w & 0x7FF, y, (w >> 11) & 1
            n += 1
        elif kind == 0x3:  # VECT_BASE_X
            base_x, pol = w & 0x7FF, (w >> 11) & 1
        elif kind == 0x4 or kind == 0x5:  # VECT_12 / VECT_8: a bit per pixel from base_x
            width = 12 if kind == 0x4 else 8
            t = (loops << 24) | (t_high << 12) | t_low
            for b in range(width):
                if (w >> b) & 1:
                    t_out[n], x_out[n], y_out[n], p_out[n] = t, base_x + b, y, pol
                    n += 1
            base_x += width
        elif kind == 0x6:  # EVT_TIME_LOW
            t_low = w & 0xFFF
        elif kind == 0x8:  # EVT_TIME_HIGH; 24-bit time wraps every 16.8 s
            high = w & 0xFFF
            if high < t_high and t_high - high > 0x800:
                loops += 1
            t_high = high
    state[0], state[1], state[2], state[3], state[4], state[5] = y, base_x, pol, t_high, t_low, loops
    return n


class _Evt3:
    """EVT 3.0 words to events through the numba kernel; its state carries across blocks."""

    def __init__(self) -> None:
        self.state = np.zeros(6, np.int64)

    def __call__(self, words: np.ndarray) -> np.ndarray:
        cap = 12 * len(words)
        t, x, y, p = np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64), np.empty(cap, np.int64)
        n = _evt3_kernel(words, self.state, t, x, y, p)
        return _sorted(events_from_columns(t[:n], x[:n], y[:n], p[:n]))


def _sorted(ev: np.ndarray) -> np.ndarray:
    """Sensors emit events very nearly in time order; make a block exactly so."""
    if len(ev) > 1 and np.any(np.diff(ev["t"]) < 0):
        ev = ev[np.argsort(ev["t"], kind="stable")]
    return ev


class DatRecording(Recording):
    """Prophesee DAT: header, a type and a size byte, then 8-byte events (t us, packed x y p)."""

    format = "prophesee-dat"

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self.header, offset = read_header(self.path)
        with open(self.path, "rb") as f:
            f.seek(offset)
            kind_size = f.read(2)
        if len(kind_size) < 2 or kind_size[1] != 8:
            raise FormatError(self.path, f"expected 8-byte events after the header, got {kind_size!r}", offset)
        self.data_offset = offset + 2
        size = _size_from_header(self.header)
        if size is None:  # N-CARS and similar crops carry no geometry: the events tell
            size = self._extent()
        self.width, self.height = size

    def _words(self) -> np.ndarray:
        n_bytes = self.path.stat().st_size - self.data_offset
        return np.memmap(self.path, "<u4", "r", self.data_offset, (n_bytes // 8) * 2)

    def _extent(self) -> tuple[int, int]:
        data = self._words()[1::2]
        if not len(data):
            return 1, 1
        return int((data & 0x3FFF).max()) + 1, int(((data >> 14) & 0x3FFF).max()) + 1

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        words = self._words()
        n = len(words) // 2
        for start in range(0, n, max_events):
            block = np.asarray(words[2 * start:2 * min(start + max_events, n)]).astype(np.int64)
            t, data = block[0::2], block[1::2]
            yield events_from_columns(t, data & 0x3FFF, (data >> 14) & 0x3FFF, ((data >> 28) & 0xF) > 0)
        tail = (self.path.stat().st_size - self.data_offset) % 8
        if tail:
            raise FormatError(self.path, f"truncated: {tail} bytes of an 8-byte event at the end",
                              self.data_offset + 8 * n)


def open_prophesee(path: Path) -> Recording:
    """DAT or RAW, told apart by the header."""
    fields, _ = read_header(path)
    if "data" in fields and "events" in fields["data"]:  # `% Data file containing ... events.`
        return DatRecording(path)
    return RawRecording(path)

