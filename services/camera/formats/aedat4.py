"""iniVation AEDAT 4.0 (DV): read and written.

Layout: `#!AER-DAT4.0\\r\\n`, a size-prefixed IOHeader flatbuffer (compression, position of the data
table, and an XML info node that names each stream's type and sensor size), then packets of
(int32 stream id, int32 size, payload). A payload is an LZ4 frame, a Zstd frame, or plain; inside is
a size-prefixed flatbuffer whose first field is a vector of fixed-size structs: events
(int64 t, int16 x, int16 y, bool on, 3 bytes padding) for `EVTS` streams, viewed in place with numpy
(no per-event work in Python). `IMUS` packets hold a vector of small tables (int64 t, float
temperature, accelerometer xyz in g, gyroscope xyz in deg/s, magnetometer xyz), read one by one.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator
from pathlib import Path

import lz4.frame
import numpy as np

from services.camera.formats import kernels
from services.camera.formats.recording import CHUNK_EVENTS, EventWriter, FormatError, Recording
from services.messages import EVENT_DTYPE

MAGIC = b"#!AER-DAT4.0\r\n"
LZ4_MAGIC = b"\x04\x22\x4d\x18"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
EVENT_STRUCT = np.dtype({"names": ["t", "x", "y", "on"], "formats": ["<i8", "<i2", "<i2", "u1"],
                         "offsets": [0, 8, 10, 12], "itemsize": 16})  # 3 bytes of padding at the end
G = 9.80665


def _table_field(buf: bytes, table: int, index: int) -> int | None:
    """Absolute position of field `index` of the flatbuffer table at `table`, None if absent."""
    vtable = table - struct.unpack_from("<i", buf, table)[0]
    vt_size = struct.unpack_from("<H", buf, vtable)[0]
    if 4 + 2 * index >= vt_size:
        return None
    off = struct.unpack_from("<H", buf, vtable + 4 + 2 * index)[0]
    return table + off if off else None


def _vector(buf: memoryview) -> tuple[int, int]:
    """(start, length) of the vector in field 0 of the root table of a flatbuffer."""
    table = struct.unpack_from("<I", buf, 0)[0]
    field = _table_field(buf, table, 0)
    if field is None:
        return 0, 0
    vec = field + struct.unpack_from("<I", buf, field)[0]
    return vec + 4, struct.unpack_from("<I", buf, vec)[0]


def _struct_vector(payload: bytes, dtype: np.dtype) -> np.ndarray:
    """The struct vector in field 0 of a size-prefixed flatbuffer, viewed without copying."""
    buf = memoryview(payload)[4:]  # drop the size prefix
    start, n = _vector(buf)
    if start + n * dtype.itemsize > len(buf):
        raise ValueError(f"vector of {n} elements runs past the packet")
    return np.frombuffer(buf, dtype, n, start)


def _imu_tables(payload: bytes) -> np.ndarray:
    """Rows (t_us, temperature, ax ay az [g], gx gy gz [deg/s]) of an IMUS packet's tables."""
    buf = memoryview(payload)[4:]
    start, n = _vector(buf)
    rows = np.zeros((n, 8))
    for i in range(n):
        pos = start + 4 * i
        table = pos + struct.unpack_from("<I", buf, pos)[0]
        for j in range(8):  # timestamp, temperature, accelerometer x y z, gyroscope x y z
            field = _table_field(buf, table, j)
            if field is not None:
                rows[i, j] = struct.unpack_from("<q" if j == 0 else "<f", buf, field)[0]
    return rows


def _decompress(body: bytes) -> bytes:
    if body.startswith(LZ4_MAGIC):
        return lz4.frame.decompress(body)
    if body.startswith(ZSTD_MAGIC):
        import zstandard

        return zstandard.ZstdDecompressor().decompress(body, max_output_size=1 << 30)
    return body


class Aedat4Recording(Recording):
    """An AEDAT 4.0 file: the first event stream, IMU streams, sensor size from the info node."""

    format = "aedat4"

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        with open(self.path, "rb") as f:
            head = f.read(len(MAGIC) + 4)
            if len(head) < len(MAGIC) + 4:
                raise FormatError(self.path, "truncated AEDAT 4.0 header", 0)
            (size,) = struct.unpack_from("<i", head, len(MAGIC))
            header = f.read(size)
        if len(header) < size:
            raise FormatError(self.path, "truncated AEDAT 4.0 header", len(MAGIC))
        self.data_offset = len(MAGIC) + 4 + size
        info, self.data_table_at = self._parse_header(header)
        self.streams = self._parse_streams(info)
        events = [sid for sid, (kind, _w, _h) in self.streams.items() if kind == "EVTS"]
        if not events:
            raise FormatError(self.path, "no event stream (EVTS) in this AEDAT 4.0 file")
        self.events_stream = events[0]
        _kind, self.width, self.height = self.streams[self.events_stream]

    def _parse_header(self, header: bytes) -> tuple[str, int]:
        try:
            buf = header
            table = struct.unpack_from("<I", buf, 0)[0]
            pos_field = _table_field(buf, table, 1)
            data_table = struct.unpack_from("<q", buf, pos_field)[0] if pos_field else -1
            info_field = _table_field(buf, table, 2)
            start = info_field + struct.unpack_from("<I", buf, info_field)[0]
            n = struct.unpack_from("<I", buf, start)[0]
            return buf[start + 4:start + 4 + n].decode("utf-8", "replace"), data_table
        except (struct.error, TypeError) as exc:
            raise FormatError(self.path, f"unreadable IOHeader ({exc})", len(MAGIC) + 4) from None

    @staticmethod
    def _parse_streams(info: str) -> dict[int, tuple[str, int, int]]:
        streams = {}
        for m in re.finditer(r'<node name="(\d+)" path="[^"]*outInfo/\d+/">(.*?)\n        </node>', info, re.S):
            body = m.group(2)
            kind = re.search(r'key="typeIdentifier" type="string">(\w+)<', body)
            w = re.search(r'key="sizeX" type="int">(\d+)<', body)
            h = re.search(r'key="sizeY" type="int">(\d+)<', body)
            streams[int(m.group(1))] = (kind.group(1) if kind else "", int(w.group(1)) if w else 0,
                                        int(h.group(1)) if h else 0)
        return streams

    def _packets(self, wanted: int) -> Iterator[tuple[int, bytes]]:
        """(byte offset, decompressed payload) of each packet of stream `wanted`."""
        end = self.data_table_at if self.data_table_at > 0 else None
        with open(self.path, "rb") as f:
            offset = self.data_offset
            f.seek(offset)
            while end is None or offset < end:
                head = f.read(8)
                if not head:
                    return
                if len(head) < 8:
                    raise FormatError(self.path, "truncated packet header", offset)
                sid, size = struct.unpack("<ii", head)
                body = f.read(size)
                if size < 0 or len(body) < size:
                    raise FormatError(self.path, f"truncated packet (stream {sid}, {size} bytes)", offset)
                if sid == wanted:
                    try:
                        yield offset, _decompress(body)
                    except (RuntimeError, ValueError) as exc:
                        raise FormatError(self.path, f"corrupt packet of stream {sid} ({exc})", offset) from None
                offset += 8 + size

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        out = np.empty(max_events, EVENT_DTYPE)
        n = 0
        for offset, payload in self._packets(self.events_stream):
            try:
                raw = _struct_vector(payload, EVENT_STRUCT)
            except (struct.error, ValueError) as exc:
                raise FormatError(self.path, f"corrupt event packet ({exc})", offset) from None
            while len(raw):
                take = min(len(raw), max_events - n)
                n = kernels.dv_events(raw[:take], out, n)
                raw = raw[take:]
                if n == max_events:
                    yield out
                    out, n = np.empty(max_events, EVENT_DTYPE), 0
        if n:
            yield out[:n]

    def imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        ids = [sid for sid, (kind, _w, _h) in self.streams.items() if kind == "IMUS"]
        if not ids:
            return None
        parts = [_imu_tables(payload) for _off, payload in self._packets(ids[0])]
        rows = np.concatenate(parts) if parts else np.zeros((0, 8))
        return rows[:, 0].astype(np.int64), np.deg2rad(rows[:, 5:8]), rows[:, 2:5] * G


INFO_XML = """<dv version="2.0">
    <node name="outInfo" path="/mainloop/Recorder/outInfo/">
        <node name="0" path="/mainloop/Recorder/outInfo/0/">
            <attr key="compression" type="string">LZ4</attr>
            <attr key="originalModuleName" type="string">etam</attr>
            <attr key="originalOutputName" type="string">events</attr>
            <attr key="typeDescription" type="string">Array of events (polarity ON/OFF).</attr>
            <attr key="typeIdentifier" type="string">EVTS</attr>
            <node name="info" path="/mainloop/Recorder/outInfo/0/info/">
                <attr key="sizeX" type="int">{width}</attr>
                <attr key="sizeY" type="int">{height}</attr>
                <attr key="source" type="string">{source}</attr>
                <attr key="tsOffset" type="long">0</attr>
            </node>
        </node>
    </node>
</dv>
"""


def _io_header(info: str) -> bytes:
    """The IOHeader flatbuffer: compression LZ4, no data table, the info node."""
    text = info.encode() + b"\0"
    vtable = struct.pack("<HHHHH", 10, 24, 4, 8, 16)  # sizes, then offsets of compression, table pos, info
    head = struct.pack("<I", 24) + b"IOHE" + vtable + b"\0" * 6  # the table starts at 24, 8-aligned
    table = struct.pack("<iiqI", 24 - 8, 1, -1, 8) + b"\0" * 4  # soffset, LZ4, no table, string 8 bytes on
    return head + table + struct.pack("<I", len(text) - 1) + text


def _event_payload(events: np.ndarray) -> bytes:
    """A size-prefixed EventPacket flatbuffer around the events, laid out like DV's own."""
    elements = np.zeros(len(events), EVENT_STRUCT)
    elements["t"], elements["x"], elements["y"], elements["on"] = events["t"], events["x"], events["y"], events["p"]
    body = (struct.pack("<I", 16) + b"EVTS" + b"\0\0" + struct.pack("<HHH", 6, 8, 4)
            + struct.pack("<iII", 6, 4, len(elements)) + elements.tobytes())
    return struct.pack("<I", len(body)) + body


class Aedat4Writer(EventWriter):
    """Writes events to an AEDAT 4.0 file, one LZ4-compressed packet per `write`."""

    def __init__(self, path: str | Path, width: int, height: int, source: str = "ETAM") -> None:
        self.path = Path(path)
        self._file = open(self.path, "wb")
        header = _io_header(INFO_XML.format(width=width, height=height, source=source))
        self._file.write(MAGIC + struct.pack("<i", len(header)) + header)
        self.count = 0

    def write(self, events: np.ndarray, max_per_packet: int = 1 << 16) -> None:
        for start in range(0, len(events), max_per_packet):
            packet = lz4.frame.compress(_event_payload(events[start:start + max_per_packet]))
            self._file.write(struct.pack("<ii", 0, len(packet)) + packet)
        self.count += len(events)

    def close(self) -> None:
        self._file.close()
