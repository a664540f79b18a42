"""Cut a stream of events into time slices (default 1 ms), each capped at a maximum count."""

from __future__ import annotations

import numpy as np

from services.messages import EVENT_DTYPE


class Packetizer:
    """Accepts sorted events and generates ``(stamp_us, events)`` slices aligned to `slice_us`.

    A slice is emitted once time has passed its end; empty slices are emitted too, so consumers see
    time advance. A slice with more than `max_events` is split; each part's stamp is the time of its
    last event, the last part's the end of the window.
    """

    def __init__(self, slice_us: int = 1000, max_events: int = 100_000) -> None:
        if slice_us <= 0 or max_events <= 0:
            raise ValueError("slice_us and max_events must be positive")
        self.slice_us = slice_us
        self.max_events = max_events
        self._buf = np.empty(0, EVENT_DTYPE)
        self._next_end: int | None = None

    def accept(self, events: np.ndarray) -> None:
        if len(events):
            self._buf = np.concatenate([self._buf, events]) if len(self._buf) else events

    def generate(self, now_us: int) -> list[tuple[int, np.ndarray]]:
        """All complete slices whose end is at or before `now_us`."""
        if self._next_end is None:
            first = int(self._buf["t"][0]) if len(self._buf) else now_us
            self._next_end = (first // self.slice_us + 1) * self.slice_us
        ends = np.arange(self._next_end, now_us + 1, self.slice_us, dtype=np.int64)
        if not len(ends):
            return []
        cuts = np.searchsorted(self._buf["t"], ends, side="left")  # slice k holds t in [end_k - slice, end_k)
        out: list[tuple[int, np.ndarray]] = []
        start = 0
        for end, cut in zip(ends.tolist(), cuts.tolist(), strict=True):
            part = self._buf[start:cut]
            chunks = [part[i:i + self.max_events] for i in range(0, max(len(part), 1), self.max_events)]
            out.extend((int(c["t"][-1]), c) for c in chunks[:-1])
            out.append((end, chunks[-1]))
            start = cut
        self._buf = self._buf[start:]
        self._next_end = int(ends[-1]) + self.slice_us
        return out
