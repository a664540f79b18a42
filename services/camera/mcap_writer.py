"""An MCAP writer fast and compact enough for event traffic.

The `mcap` package's writer compresses each chunk on the caller's thread, with zstd at level 3
(about 13 Mev/s of event packets here) or LZ4 (8.7 bytes per event). This one builds message
records with one struct call each and compresses full chunks with zstd level 1 on worker threads
while the next chunk fills (about 4 bytes per event), writing chunks in order. `end_chunk` closes a
chunk early, so a recorder can bound what a crash loses by time as well as by size.

Schemas and channels are written inside the chunk where they first appear, so a file cut short is
readable from its start, and again in the summary with statistics and chunk indexes (no message
indexes, which are optional), so that seeking readers find everything.
"""

from __future__ import annotations

import struct
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, DataEnd, Footer, Header, Schema, Statistics, SummaryOffset

MAGIC = b"\x89MCAP0\r\n"
ZSTD_LEVEL = 1
CHUNK_BYTES = 1 << 20
MAX_PENDING = 4  # chunks compressing at once; more waits, which bounds memory
_MESSAGE = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log time, publish time
_CHUNK = struct.Struct("<BQQQQI")  # opcode, record length, start time, end time, uncompressed size, crc


def _compress(records: bytes) -> tuple[bytes, int]:
    """A chunk's zstd frame and its records' CRC32 (both release the GIL)."""
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(records), zlib.crc32(records)


def _record(rec: Header | Schema | Channel | DataEnd | Footer | Statistics | ChunkIndex | SummaryOffset) -> bytes:
    builder = RecordBuilder()
    rec.write(builder)
    return bytes(builder.end())


class McapWriter:
    """Write messages with `add_message` after `add_schema` / `add_channel`; `close` adds the summary."""

    def __init__(self, path: Path, profile: str = "", library: str = "etam", workers: int = 2) -> None:
        self._file = open(path, "wb")
        self._file.write(MAGIC + _record(Header(profile, library)))
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="mcap-zstd")
        self._pending: deque[tuple[Future[tuple[bytes, int]], int, int, int]] = deque()
        self.schemas: list[Schema] = []
        self.channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._counts: dict[int, int] = {}
        self._buf = bytearray()
        self._start: int | None = None  # log times of the chunk being filled
        self._end = 0
        self.messages = 0

    def add_schema(self, name: str, encoding: str = "", data: bytes = b"") -> int:
        schema = Schema(id=len(self.schemas) + 1, name=name, encoding=encoding, data=data)
        self.schemas.append(schema)
        self._buf += _record(schema)
        return schema.id

    def add_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = Channel(id=len(self.channels) + 1, topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata={})
        self.channels.append(channel)
        self._counts[channel.id] = 0
        self._buf += _record(channel)
        return channel.id

    def add_message(self, channel: int, log_time: int, data: bytes, publish_time: int, sequence: int) -> None:
        if self._start is None:
            self._start = log_time
        self._end = max(self._end, log_time)
        self._buf += _MESSAGE.pack(Opcode.MESSAGE, 22 + len(data), channel, sequence & 0xFFFFFFFF, log_time,
                                   publish_time)
        self._buf += data
        self._counts[channel] += 1
        self.messages += 1
        if len(self._buf) >= CHUNK_BYTES:
            self.end_chunk()

    def end_chunk(self) -> None:
        """Hand the chunk being filled to the compressors, and write those that are done."""
        if self._start is not None:
            records = bytes(self._buf)
            self._pending.append((self._pool.submit(_compress, records), self._start, self._end, len(records)))
            self._buf.clear()
            self._start, self._end = None, 0
        self._write_done(wait_for=len(self._pending) - MAX_PENDING)

    def flush(self) -> None:
        """Write every message so far to the file (closing the chunk being filled)."""
        self.end_chunk()
        self._write_done(wait_for=len(self._pending))
        self._file.flush()

    def _write_done(self, wait_for: int) -> None:
        """Write finished chunks in order, waiting for the first `wait_for` of them."""
        while self._pending and (wait_for > 0 or self._pending[0][0].done()):
            future, start, end, size = self._pending.popleft()
            wait_for -= 1
            data, crc = future.result()
            offset = self._file.tell()
            head = _CHUNK.pack(Opcode.CHUNK, 8 * 3 + 4 + 4 + 4 + 8 + len(data), start, end, size, crc)
            self._file.write(head + struct.pack("<I4sQ", 4, b"zstd", len(data)))
            self._file.write(data)
            self._chunk_indexes.append(ChunkIndex(
                message_start_time=start, message_end_time=end, chunk_start_offset=offset,
                chunk_length=self._file.tell() - offset, message_index_offsets={}, message_index_length=0,
                compression="zstd", compressed_size=len(data), uncompressed_size=size))

    def close(self) -> None:
        """Write what is left, the summary and the footer."""
        self.flush()
        self._pool.shutdown()
        self._file.write(_record(DataEnd(0)))
        summary_start = self._file.tell()
        stats = Statistics(message_count=self.messages, schema_count=len(self.schemas),
                           channel_count=len(self.channels), attachment_count=0, metadata_count=0,
                           chunk_count=len(self._chunk_indexes), channel_message_counts=self._counts,
                           message_start_time=self._chunk_indexes[0].message_start_time if self.messages else 0,
                           message_end_time=max((c.message_end_time for c in self._chunk_indexes), default=0))
        groups = [(Opcode.SCHEMA, self.schemas), (Opcode.CHANNEL, self.channels), (Opcode.STATISTICS, [stats]),
                  (Opcode.CHUNK_INDEX, self._chunk_indexes)]
        offsets = []
        for opcode, records in groups:
            start = self._file.tell()
            self._file.write(b"".join(_record(r) for r in records))
            length = self._file.tell() - start
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=start, group_length=length))
        offsets_start = self._file.tell()
        self._file.write(b"".join(_record(o) for o in offsets))
        self._file.write(_record(Footer(summary_start=summary_start, summary_offset_start=offsets_start,
                                        summary_crc=0)))
        self._file.write(MAGIC)
        self._file.close()
