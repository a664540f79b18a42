"""Whole-record event operations agree with numpy's field-by-field ones."""

from __future__ import annotations

import numpy as np

from services import events
from services.messages import EVENT_DTYPE


def _events(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = rng.integers(0, 10**9, n), rng.integers(0, 640, n), \
        rng.integers(0, 480, n), rng.integers(0, 2, n)
    return ev


def test_concat_take_copy_and_sort_match_numpy() -> None:
    a, b = _events(1000, 1), _events(17, 2)[::2]  # a strided view too
    assert np.array_equal(events.concat([a, b, a[:0]]), np.concatenate([a, b]))
    assert events.concat([]).dtype == EVENT_DTYPE and len(events.concat([])) == 0
    mask, order = a["p"] == 1, np.argsort(a["t"], kind="stable")
    assert np.array_equal(events.take(a, mask), a[mask]) and np.array_equal(events.take(a, order), a[order])
    assert np.array_equal(events.sort_by_time(a), a[order])
    c = events.copy(a)
    c["x"] += 1
    assert np.array_equal(c["x"], a["x"] + 1)  # a real copy
