"""Numba kernels that decode camera words straight into ETAM's event records (no temporaries).

Each kernel fills `out` (EVENT_DTYPE) from the front, returns how many events it wrote and whether
their times ever went backwards, and keeps the decoder's state in a small int64 array so that a
file can be decoded block by block.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def evt2(words, state, out):  # noqa: ANN001, ANN201 - numba kernel
    """Prophesee EVT 2.0: state = [time_high]."""
    high = state[0]
    n, last, unsorted = 0, np.int64(-1), False
    for i in range(len(words)):
        w = np.int64(words[i])
        kind = w >> 28
        if kind <= 1:  # CD_OFF, CD_ON
            t = (high << 6) | ((w >> 22) & 0x3F)
            out[n].t, out[n].x, out[n].y, out[n].p = t, (w >> 11) & 0x7FF, w & 0x7FF, kind
            unsorted |= t < last
            last = t
            n += 1
        elif kind == 0x8:  # EVT_TIME_HIGH
            high = w & 0x0FFFFFFF
    state[0] = high
    return n, unsorted


@numba.njit(cache=True, nogil=True)
def evt3(words, state, out):  # noqa: ANN001, ANN201 - numba kernel
    """Prophesee EVT 3.0: state = [y, base_x, polarity, time_high, time_low, 24-bit wraps].

    Time changes only with time words, so it is composed there, not per event, and checked for order
    at the first event after a change (a TIME_HIGH before its TIME_LOW steps back briefly, harmlessly);
    vector words visit their bits only up to the highest set one."""
    y, base_x, pol, t_high, t_low, loops = state[0], state[1], state[2], state[3], state[4], state[5]
    n, unsorted, last, moved = 0, False, np.int64(-1), True
    t = (loops << 24) | (t_high << 12) | t_low
    for i in range(len(words)):
        w = np.int64(words[i])
        kind = w >> 12
        if moved and (kind == 0x2 or ((kind == 0x4 or kind == 0x5) and w & 0xFFF)):
            unsorted |= t < last
            last, moved = t, False
        if kind == 0x2:  # EVT_ADDR_X: one event
            e = out[n]
            e.t, e.x, e.y, e.p = t, w & 0x7FF, y, (w >> 11) & 1
            n += 1
        elif kind == 0x0:  # EVT_ADDR_Y
            y = w & 0x7FF
        elif kind == 0x4 or kind == 0x5:  # VECT_12 / VECT_8: a bit per pixel from base_x
            width = 12 if kind == 0x4 else 8
            bits, x = w & ((1 << width) - 1), base_x
            while bits:
                if bits & 1:
                    e = out[n]
                    e.t, e.x, e.y, e.p = t, x, y, pol
                    n += 1
                bits >>= 1
                x += 1
            base_x += width
        elif kind == 0x3:  # VECT_BASE_X
            base_x, pol = w & 0x7FF, (w >> 11) & 1
        elif kind == 0x6 or kind == 0x8:  # EVT_TIME_LOW / EVT_TIME_HIGH (24-bit time wraps every 16.8 s)
            if kind == 0x6:
                t_low = w & 0xFFF
            else:
                high = w & 0xFFF
                if high < t_high and t_high - high > 0x800:
                    loops += 1
                t_high = high
            t, moved = (loops << 24) | (t_high << 12) | t_low, True
    state[0], state[1], state[2], state[3], state[4], state[5] = y, base_x, pol, t_high, t_low, loops
    return n, unsorted


@numba.njit(cache=True, nogil=True)
def dv_events(raw, out, start):  # noqa: ANN001, ANN201 - numba kernel
    """AEDAT 4.0 event structs (t, x, y, on, padding) into `out[start:]`."""
    for i in range(len(raw)):
        r = raw[i]
        out[start + i].t, out[start + i].x, out[start + i].y, out[start + i].p = r.t, r.x, r.y, r.on
    return start + len(raw)


@numba.njit(cache=True, nogil=True)
def interleave(t, x, y, p, t_offset, out):  # noqa: ANN001, ANN201 - numba kernel
    """Columns (any integer types) into event records, adding `t_offset` to time: one pass."""
    for i in range(len(t)):
        e = out[i]
        e.t, e.x, e.y, e.p = t[i] + t_offset, x[i], y[i], p[i]


@numba.njit(cache=True, nogil=True)
def first_at_or_after(events, t_us):  # noqa: ANN001, ANN201 - numba kernel
    """Index of the first event with t >= t_us in time-sorted records (binary search in place:
    numpy's searchsorted would first copy the strided time column)."""
    lo, hi = 0, len(events)
    while lo < hi:
        mid = (lo + hi) >> 1
        if events[mid].t < t_us:
            lo = mid + 1
        else:
            hi = mid
    return lo
