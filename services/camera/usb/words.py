"""Decoding the 16-bit word stream of DAVIS and DVXplorer cameras (reference sections 5.1-5.6).

One numba pass over the words, its state (timestamp base, current row or column, the IMU sample being
read) carried from one buffer to the next, so a stream may be cut anywhere between words. Events are
written straight into the output arrays; an IMU sample is kept as its 7 raw int16 values and scale
byte, converted to SI units afterwards in numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from services.messages import EVENT_DTYPE

G = 9.80665
# state slots
_BASE, _TS, _ROW, _COL, _Y1, _Y2, _IMU_ON, _IMU_N, _IMU_CFG, _RESETS, _DROPPED, _RESET_AT = range(12)
_STATE_LEN = 12
_IMU_BYTES = 14


@dataclass
class Decoded:
    """One buffer's decode: events, IMU samples (us, rad/s, m/s^2, deg C), the counts of timestamp resets
    and of words dropped (addresses beyond the sensor, bytes of an odd-length buffer), and where the
    events after the buffer's last reset begin (a new time epoch)."""

    events: np.ndarray
    imu_t: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    gyro: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    accel: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    temperature: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    resets: int = 0
    dropped: int = 0
    reset_at: int = 0


class WordDecoder:
    """Decodes a camera's bulk stream buffer by buffer; `dvx` picks the DVXplorer layout (column and
    8-pixel groups), else DAVIS (row, then column words); `width` x `height` is the sensor's native size
    (addresses beyond it are dropped), `invert_xy` the DVS orientation's swap."""

    def __init__(self, dvx: bool, width: int, height: int, invert_xy: bool = False,
                 imu_flips: tuple[bool, bool, bool] = (False, False, False)) -> None:
        self.dvx, self.width, self.height, self.invert_xy = dvx, width, height, invert_xy
        self.imu_signs = np.where(imu_flips, -1.0, 1.0).astype(np.float32)
        self.state = np.zeros(_STATE_LEN, np.int64)
        self.state[_ROW] = self.state[_COL] = -1
        self.imu_bytes = np.zeros(_IMU_BYTES, np.int64)

    @property
    def time_us(self) -> int:
        """The stream's current timestamp (us since the last reset)."""
        return int(self.state[_TS])

    def decode(self, data: bytes | bytearray | memoryview | np.ndarray) -> Decoded:
        raw = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8)
        odd = len(raw) % 2  # the device never sends one; libcaer drops the last byte
        words = raw[:len(raw) - odd].view("<u2")
        resets0, dropped0 = int(self.state[_RESETS]), int(self.state[_DROPPED])
        self.state[_RESET_AT] = 0
        n_out = len(words) * (8 if self.dvx else 1)
        t, x, y, p = (np.empty(n_out, np.int64), np.empty(n_out, np.uint16), np.empty(n_out, np.uint16),
                      np.empty(n_out, np.uint8))
        imu = np.empty((len(words) // 16 + 1, 9), np.int64)
        kernel = _decode_dvx if self.dvx else _decode_davis
        n, n_imu = kernel(words, self.state, self.imu_bytes, self.width, self.height, self.invert_xy,
                          t, x, y, p, imu)
        events = np.empty(n, EVENT_DTYPE)
        events["t"], events["x"], events["y"], events["p"] = t[:n], x[:n], y[:n], p[:n]
        out = Decoded(events, resets=int(self.state[_RESETS]) - resets0,
                      dropped=int(self.state[_DROPPED]) - dropped0 + odd, reset_at=int(self.state[_RESET_AT]))
        if n_imu:
            self._imu_units(imu[:n_imu], out)
        return out

    def _imu_units(self, rows: np.ndarray, out: Decoded) -> None:
        """Raw IMU pairs (accel A, B, Z, temperature, gyro A, B, Z) to SI units (section 5.6)."""
        cfg = rows[:, 8]
        raw = rows[:, 1:8].astype(np.float32)
        if self.dvx:  # BMI160: accel range bits 4..3, gyro range bits 2..0 (0 = 2000 deg/s); A is y, B is x
            accel_lsb = 65536.0 / (4.0 * 2.0 ** ((cfg >> 3) & 3))
            gyro_lsb = 65536.0 / (250.0 * 2.0 ** (4 - (cfg & 7)))
            order, temp = [1, 0, 2], raw[:, 3] / 512.0 + 23.0
        else:  # MPU-6050/6150: accel bits 3..2, gyro bits 1..0; A is x, B is y
            accel_lsb = 65536.0 / (4.0 * 2.0 ** ((cfg >> 2) & 3))
            gyro_lsb = 65536.0 / (500.0 * 2.0 ** (cfg & 3))
            order, temp = [0, 1, 2], raw[:, 3] / 340.0 + 35.0
        accel = raw[:, [0, 1, 2]][:, order] / accel_lsb[:, None] * self.imu_signs
        gyro = raw[:, [4, 5, 6]][:, order] / gyro_lsb[:, None] * self.imu_signs
        out.imu_t, out.temperature = rows[:, 0], temp.astype(np.float32)
        out.accel = (accel * G).astype(np.float32)
        out.gyro = np.deg2rad(gyro).astype(np.float32)


@numba.njit(cache=True, nogil=True, inline="always")
def _common(w, code, data, state, imu_bytes, imu, n_imu):  # noqa: ANN001, ANN202 - numba kernel
    """The words both layouts share: timestamps, wraps, special events (reset, IMU start and end) and the
    IMU's MISC8 bytes. Returns the IMU sample count after it."""
    if w & 0x8000:
        state[_TS] = state[_BASE] + (w & 0x7FFF)
    elif code == 7:
        state[_BASE] += 0x8000 * data
        state[_TS] = state[_BASE]
    elif code == 0:
        if data == 1:  # timestamp reset
            state[_BASE] = 0
            state[_TS] = 0
            state[_RESETS] += 1
            state[_IMU_ON] = 0
        elif data == 5:
            state[_IMU_ON] = 1
            state[_IMU_N] = 0
        elif data == 7:
            if state[_IMU_ON] == 1 and state[_IMU_N] == _IMU_BYTES:
                imu[n_imu, 0] = state[_TS]
                for k in range(7):
                    v = (imu_bytes[2 * k] << 8) | imu_bytes[2 * k + 1]
                    imu[n_imu, 1 + k] = v - 65536 if v >= 32768 else v
                imu[n_imu, 8] = state[_IMU_CFG]
                n_imu += 1
            state[_IMU_ON] = 0
    elif code == 5 and state[_IMU_ON] == 1:
        sub, byte = (data >> 8) & 0xF, data & 0xFF
        if sub == 3:  # scale byte: which sensors follow, so where the first byte goes
            state[_IMU_CFG] = byte
            kinds = (byte >> 5) & 7
            state[_IMU_N] = 0 if kinds & 4 else (6 if kinds & 1 else 8)
        elif sub == 0 and state[_IMU_N] < _IMU_BYTES:
            imu_bytes[state[_IMU_N]] = byte
            state[_IMU_N] += 1
            kinds = (state[_IMU_CFG] >> 5) & 7
            if state[_IMU_N] == 6 and not kinds & 1:  # after accel, no temperature
                state[_IMU_N] = 8 if kinds & 2 else _IMU_BYTES
            elif state[_IMU_N] == 8 and not kinds & 2:  # after temperature, no gyro
                state[_IMU_N] = _IMU_BYTES
    return n_imu


@numba.njit(cache=True, nogil=True, inline="always")
def _emit(n, t, x, y, p, ts, ex, ey, pol, invert):  # noqa: ANN001, ANN202 - numba kernel
    t[n] = ts
    if invert:
        x[n], y[n] = ey, ex
    else:
        x[n], y[n] = ex, ey
    p[n] = pol
    return n + 1


@numba.njit(cache=True, nogil=True)
def _decode_davis(words, state, imu_bytes, width, height, invert, t, x, y, p, imu):  # noqa: ANN001, ANN202
    """DAVIS: a row word (code 1), then column words on that row (code 3 ON, code 2 OFF)."""
    n = n_imu = 0
    for i in range(len(words)):
        w = np.int64(words[i])
        code, data = (w >> 12) & 7, w & 0xFFF
        if not w & 0x8000 and (code == 2 or code == 3):
            if data < width and state[_ROW] >= 0:
                n = _emit(n, t, x, y, p, state[_TS], data, state[_ROW], code == 3, invert)
            else:
                state[_DROPPED] += 1
        elif not w & 0x8000 and code == 1:
            if data < height:
                state[_ROW] = data
            else:
                state[_DROPPED] += 1
        else:
            n_imu = _common(w, code, data, state, imu_bytes, imu, n_imu)
            if code == 0 and data == 1 and not w & 0x8000:
                state[_RESET_AT] = n
    return n, n_imu


@numba.njit(cache=True, nogil=True)
def _decode_dvx(words, state, imu_bytes, width, height, invert, t, x, y, p, imu):  # noqa: ANN001, ANN202
    """DVXplorer: a column word (code 1), group addresses (code 4), then the 8-pixel masks of group 1
    (code 3) and group 2 (code 2), polarity in bit 8 (set = OFF)."""
    n = n_imu = 0
    for i in range(len(words)):
        w = np.int64(words[i])
        code, data = (w >> 12) & 7, w & 0xFFF
        if w & 0x8000 or code in (0, 5, 7):
            n_imu = _common(w, code, data, state, imu_bytes, imu, n_imu)
            if code == 0 and data == 1 and not w & 0x8000:
                state[_RESET_AT] = n
        elif code == 1:
            col = data & 0x3FF
            if col < width:
                state[_COL] = col
            else:
                state[_DROPPED] += 1
        elif code == 4:
            g1, off = data & 0x3F, (data >> 6) & 0x1F
            g2 = g1 - off if data & 0x800 else g1 + off
            if 8 * g1 < height and 0 <= 8 * g2 < height:
                state[_Y1], state[_Y2] = 8 * g1, 8 * g2
            else:
                state[_DROPPED] += 1
        elif (code == 3 or code == 2) and state[_COL] >= 0:
            base = state[_Y1] if code == 3 else state[_Y2]
            pol = 0 if data & 0x100 else 1
            for b in range(8):
                if data & (1 << b):
                    n = _emit(n, t, x, y, p, state[_TS], state[_COL], base + b, pol, invert)
    return n, n_imu


def warm_up() -> None:
    """Loads both decoders' kernels (compiles them, the first time on a machine; see `services.kernels`) before a
    camera streams: compiled on its first buffers, the decoder would fall seconds behind, and the camera's FIFO
    fill up meanwhile. A buffer of bytes, as the reader hands over, of no event."""
    for dvx in (False, True):
        WordDecoder(dvx, 64, 48).decode(bytes(64))
