"""Prophesee recordings: RAW EVT 2.0 and EVT 3.0, and DAT (v2 2-D events).

Both encodings are stateful (EVT 2.0: time high; EVT 3.0: row, vector base, time high/low and a
24-bit time that wraps), so numba kernels (`kernels.py`) walk the words straight into event records;
their state carries from block to block, so memory stays bounded. A trailing partial word is
reported with its byte offset after the good events.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from services import events
from services.camera.formats import kernels
from services.camera.formats.recording import CHUNK_EVENTS, FormatError, Recording, events_from_columns
from services.messages import EVENT_DTYPE

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
        words_per_block = max(1024, max_events)  # large blocks: fewer packets spanning two chunks
        decode = _Decoder(kernels.evt2, 1, 1) if self._word == 4 else _Decoder(kernels.evt3, 12, 6)
        offset = self.data_offset
        with open(self.path, "rb") as f:
            f.seek(offset)
            while True:
                block = f.read(words_per_block * self._word)
                if not block:
                    return
                whole = len(block) - len(block) % self._word
                decoded = decode(np.frombuffer(block, "<u4" if self._word == 4 else "<u2", whole // self._word))
                for start in range(0, len(decoded), max_events):
                    yield decoded[start:start + max_events]
                if whole < len(block):
                    raise FormatError(self.path, f"truncated: {len(block) - whole} bytes of a {self._word}-byte "
                                      "word at the end", offset + whole)
                offset += whole


class _Decoder:
    """Words to events through a numba kernel whose state carries from block to block."""

    def __init__(self, kernel, per_word: int, state_size: int) -> None:  # noqa: ANN001 - a numba kernel
        self.kernel, self.per_word = kernel, per_word
        self.state = np.zeros(state_size, np.int64)

    def __call__(self, words: np.ndarray) -> np.ndarray:
        out = np.empty(self.per_word * len(words), EVENT_DTYPE)
        n, unsorted = self.kernel(words, self.state, out)
        out = out[:n]
        # sensors emit events very nearly in time order; make a block exactly so
        return events.sort_by_time(out) if unsorted else out


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

