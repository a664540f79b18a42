"""Counters behind the Stats message: rates, drops, malformed payloads and latency per key."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

_RESERVOIR = 4096


@dataclass
class KeyCounter:
    """Totals and the current one-second window of one input or output key."""

    key: str
    direction: str  # "in" or "out"
    messages: int = 0
    events: int = 0
    overflow: int = 0  # dropped from a full fifo queue
    gaps: int = 0  # missing sequence numbers, including the samples `skipped` on purpose
    skipped: int = 0  # superseded unread under the `latest` policy, by design
    malformed: int = 0
    _win_messages: int = 0
    _win_events: int = 0
    _win_start: float = field(default_factory=time.monotonic)
    _latency_ms: list[float] = field(default_factory=list)
    _last_seq: dict[str, int] = field(default_factory=dict)

    def count(self, events: int, latency_ms: float | None = None) -> None:
        self.messages += 1
        self.events += events
        self._win_messages += 1
        self._win_events += events
        if latency_ms is not None and len(self._latency_ms) < _RESERVOIR:
            self._latency_ms.append(latency_ms)

    def sequence(self, source: str, seq: int) -> None:
        """Count the messages a gap in one publisher's sequence numbers says were lost."""
        last = self._last_seq.get(source)
        if last is not None and seq > last + 1:
            self.gaps += seq - last - 1
        self._last_seq[source] = seq

    @property
    def dropped(self) -> int:
        """Messages lost against the subscription's policy: overflow, and gaps not explained by skips."""
        return self.overflow + max(self.gaps - self.skipped, 0)

    def snapshot(self) -> dict:
        """The Stats row of this key; starts a new rate and latency window."""
        now = time.monotonic()
        span = max(now - self._win_start, 1e-6)
        lat = np.asarray(self._latency_ms) if self._latency_ms else None
        row = {
            "key": self.key,
            "dir": self.direction,
            "messages": self.messages,
            "events": self.events,
            "msg_rate": self._win_messages / span,
            "event_rate": self._win_events / span,
            "dropped": self.dropped,
            "skipped": self.skipped,
            "malformed": self.malformed,
            "latency_p50_ms": float(np.percentile(lat, 50)) if lat is not None else None,
            "latency_p99_ms": float(np.percentile(lat, 99)) if lat is not None else None,
        }
        self._win_messages = self._win_events = 0
        self._win_start = now
        self._latency_ms = []
        return row
