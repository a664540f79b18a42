"""`etam record` and `etam replay`: live traffic to MCAP and back, payloads byte for byte.

MCAP layout: one channel per key (message encoding `msgpack`, schema = the ETAM message type),
`log_time` = receive time (ns), `publish_time` = the message's `sent`. Chunks are zstd-compressed
(`mcap_writer.py`) and closed every FLUSH_S, so a crash loses at most the last half second; Ctrl-C
and SIGTERM close the file with its summary. Replay reads records in order and tolerates a file cut
short by a crash.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import time
from collections.abc import Iterator
from pathlib import Path

from mcap.exceptions import McapError
from mcap.stream_reader import StreamReader

from services.camera.mcap_writer import McapWriter
from services.messages import peek
from services.runtime import Output, Service, ServiceOptions

log = logging.getLogger(__name__)

FLUSH_S = 0.5


def _header(payload: bytes) -> dict:
    """The payload's type and send time if it is an ETAM message; a recorder stores garbage too."""
    try:
        return peek(payload)
    except Exception:  # noqa: BLE001 - whatever msgpack raises on garbage: recorded as `unknown`
        return {}


class McapRecorder:
    """Appends (key, payload, receive time) to an MCAP file; channels and schemas made on first sight."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._writer = McapWriter(path, profile="etam")
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}

    @property
    def messages(self) -> int:
        return self._writer.messages

    def write(self, key: str, payload: bytes, receive_ns: int) -> None:
        head = _header(payload)
        channel = self._channels.get(key)
        if channel is None:
            kind = str(head.get("type", "unknown"))
            schema = self._schemas.get(kind)
            if schema is None:
                schema = self._schemas[kind] = self._writer.add_schema(kind)
            channel = self._channels[key] = self._writer.add_channel(key, "msgpack", schema)
        sent = head.get("sent")
        publish_ns = sent if isinstance(sent, int) and 0 <= sent < 1 << 64 else receive_ns
        self._writer.add_message(channel, receive_ns, payload, publish_ns, self.messages)

    def flush(self) -> None:
        """Put everything received on disk: a crash after this loses nothing before it."""
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()


def read_mcap(path: Path) -> Iterator[tuple[str, bytes, int]]:
    """(key, payload, log_time ns) of every message in file order; stops quietly at a cut-off end."""
    channels: dict[int, str] = {}
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                kind = type(record).__name__
                if kind == "Channel":
                    channels[record.id] = record.topic
                elif kind == "Message":
                    yield channels[record.channel_id], record.data, record.log_time
        except (McapError, EOFError, ValueError, struct.error) as exc:
            log.warning("%s ends early (%s): replaying what is complete", path, type(exc).__name__)


class RecordService(Service):
    """Subscribes losslessly to `keys` and writes every message to an MCAP file."""

    kind = "recorder"

    def __init__(self, options: ServiceOptions, out: Path, keys_expr: str) -> None:
        super().__init__(options)
        self.out, self.keys_expr = out, keys_expr
        self.status["file"] = str(out)

    async def main(self) -> None:
        recorder = McapRecorder(self.out)
        inp = self.subscribe(self.keys_expr, policy="lossless", maxsize=4096)
        last_flush = time.monotonic()
        log.info("recording %s to %s", self.keys_expr, self.out)
        try:
            while True:
                key, payload = await inp.raw()
                if key.endswith(f"/{self.kind}/{self.name}/stats"):
                    continue  # not our own heartbeat
                recorder.write(key, payload, time.time_ns())
                if time.monotonic() - last_flush > FLUSH_S:
                    recorder.flush()
                    last_flush = time.monotonic()
        finally:
            recorder.close()
            log.info("wrote %d messages to %s", recorder.messages, self.out)


MATCH_WAIT_S = 1.0


class ReplayService(Service):
    """Publishes an MCAP recording's payloads on their keys with the original timing (or `rate`;
    0 = as fast as possible, blocking rather than dropping), then ends (or starts over with `loop`)."""

    kind = "replay"

    def __init__(self, options: ServiceOptions, path: Path, rate: float = 1.0, loop: bool = False) -> None:
        super().__init__(options)
        self.path, self.rate, self.loop = path, rate, loop
        self.status["file"] = str(path)

    @staticmethod
    async def _await_listener(out: Output) -> None:
        """Give subscribers already listening a moment to be routed to a new key's publisher."""
        deadline = time.monotonic() + MATCH_WAIT_S
        while not out.matched and time.monotonic() < deadline:
            await asyncio.sleep(0.02)

    async def main(self) -> None:
        outputs: dict[str, Output] = {}
        while True:
            start_wall, start_log, sent = time.monotonic(), None, 0
            for key, payload, log_ns in read_mcap(self.path):
                start_log = log_ns if start_log is None else start_log
                if self.rate > 0:
                    due = start_wall + (log_ns - start_log) / 1e9 / self.rate
                    delay = due - time.monotonic()
                    if delay > 0:
                        await asyncio.sleep(delay)
                elif sent % 256 == 0:
                    await asyncio.sleep(0)
                out = outputs.get(key)
                if out is None:
                    out = outputs[key] = self.publisher(key, block=self.rate == 0)
                    await self._await_listener(out)
                out.publish_raw(payload)
                sent += 1
            log.info("replayed %d messages of %s", sent, self.path)
            if not self.loop:
                await asyncio.sleep(0.5)  # let the last messages leave before the session closes
                return
