"""Cut a stream of events into time slices (default 1 ms), each capped at a maximum count."""

from __future__ import annotations

import numpy as np

from services import events
from services.camera.formats.kernels import first_at_or_after


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
        self._chunks: list[np.ndarray] = []  # accepted arrays, kept as given: slices are views on them
        self._next_end: int | None = None

    def accept(self, events: np.ndarray) -> None:
        if len(events):
            self._chunks.append(events)

    def generate(self, now_us: int) -> list[tuple[int, np.ndarray]]:
        """All complete slices whose end is at or before `now_us`."""
        if self._next_end is None:
            first = int(self._chunks[0]["t"][0]) if self._chunks else now_us
            self._next_end = (first // self.slice_us + 1) * self.slice_us
        out: list[tuple[int, np.ndarray]] = []
        end = self._next_end
        while end <= now_us:  # slice k holds t in [end - slice_us, end)
            part = self._take_before(end)
            chunks = [part[i:i + self.max_events] for i in range(0, max(len(part), 1), self.max_events)]
            out.extend((int(c["t"][-1]), c) for c in chunks[:-1])
            out.append((end, chunks[-1]))
            end += self.slice_us
        self._next_end = end
        return out

    def _take_before(self, end_us: int) -> np.ndarray:
        """Remove and return the events before `end_us`: a view when they lie in one array."""
        pieces = []
        while self._chunks:
            chunk = self._chunks[0]
            cut = first_at_or_after(chunk, end_us)
            if cut:
                pieces.append(chunk[:cut])
            if cut < len(chunk):
                self._chunks[0] = chunk[cut:]
                break
            self._chunks.pop(0)
        return pieces[0] if len(pieces) == 1 else events.concat(pieces)
