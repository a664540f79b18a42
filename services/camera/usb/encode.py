"""Writing the 16-bit word stream a DAVIS or DVXplorer sends (reference section 12), from events.

The fake device streams with it, and the tests check that decoding gives the events back. Events are
taken in time order: a wrap word when the time's upper bits grow, a timestamp word when its lower 15
bits change, then DAVIS row and column words, or DVXplorer column, group-address and mask words (the
events of one time, column, group and polarity share one mask, as the sensor's readout does).
"""

from __future__ import annotations

import numba
import numpy as np

RESET_WORD = 0x0001  # special event 1: timestamp reset


def encode(events: np.ndarray, dvx: bool, start_us: int = 0) -> tuple[np.ndarray, int]:
    """The words of `events` (sorted by time, none before `start_us`, the time of the stream's last word),
    and the stream's time after them. DVXplorer events are ordered by column and row within a time, as
    the sensor reads them out."""
    if not len(events):
        return np.zeros(0, np.uint16), start_us
    t, x, y, p = (np.ascontiguousarray(events[k]) for k in ("t", "x", "y", "p"))
    if dvx:
        order = np.lexsort((y, x, t))
        t, x, y, p = t[order], x[order], y[order], p[order]
    out = np.empty(len(t) * 4 + 64, np.uint16)
    n = (_encode_dvx if dvx else _encode_davis)(t.astype(np.int64), x, y, p, np.int64(start_us), out)
    return out[:n], int(t[-1])


def time_words(t_us: int, start_us: int) -> np.ndarray:
    """The words that move a stream at `start_us` to `t_us` (wraps, then a timestamp word)."""
    out = np.empty((t_us >> 15) // 4095 + 4, np.uint16)
    return out[:_time(np.int64(t_us), np.int64(start_us), out, 0)]


def imu_words(scale: int, raw: tuple[int, ...]) -> np.ndarray:
    """The words of one IMU sample: start, the scale byte, 14 data bytes (7 big-endian int16: accel A, B, Z,
    temperature, gyro A, B, Z; all sensors on), end."""
    data = b"".join(int(v).to_bytes(2, "big", signed=True) for v in raw)
    return np.array([0x0005, 0x5300 | scale, *(0x5000 | b for b in data), 0x0007], np.uint16)


@numba.njit(cache=True, nogil=True, inline="always")
def _time(t, now, out, n):  # noqa: ANN001, ANN202 - numba kernel
    """Wrap words (each up to 4095 wraps) and a timestamp word to move the stream from `now` to `t`."""
    wraps = (t >> 15) - (now >> 15)
    while wraps > 0:
        k = min(wraps, 4095)
        out[n] = 0x7000 | k
        n += 1
        wraps -= k
    if t & 0x7FFF or (now >> 15) == (t >> 15):
        out[n] = 0x8000 | (t & 0x7FFF)
        n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _encode_davis(t, x, y, p, now, out):  # noqa: ANN001, ANN202 - numba kernel
    n = 0
    row = -1
    for i in range(len(t)):
        if t[i] != now or n == 0:
            n = _time(t[i], now, out, n)
            now = t[i]
        if y[i] != row:
            out[n] = 0x1000 | y[i]
            n += 1
            row = y[i]
        out[n] = (0x3000 if p[i] else 0x2000) | x[i]
        n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _encode_dvx(t, x, y, p, now, out):  # noqa: ANN001, ANN202 - numba kernel
    n = 0
    col = -1
    group = -1
    i = 0
    while i < len(t):
        new_time = t[i] != now or n == 0
        if new_time:
            n = _time(t[i], now, out, n)
            now = t[i]
        if new_time or x[i] != col:
            out[n] = 0x1000 | (0x800 if new_time else 0) | x[i]
            n += 1
            col = x[i]
            group = -1
        g = y[i] >> 3
        if g != group:
            out[n] = 0x4000 | g  # group 1 at g, offset 0
            n += 1
            group = g
        mask_on = mask_off = 0
        while i < len(t) and t[i] == now and x[i] == col and (y[i] >> 3) == g:
            if p[i]:
                mask_on |= 1 << (y[i] & 7)
            else:
                mask_off |= 1 << (y[i] & 7)
            i += 1
        if mask_on:
            out[n] = 0x3000 | mask_on
            n += 1
        if mask_off:  # the same group again for the other polarity
            if mask_on:
                out[n] = 0x4000 | g
                n += 1
            out[n] = 0x3100 | mask_off
            n += 1
    return n
