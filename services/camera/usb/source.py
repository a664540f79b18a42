"""A USB camera as an event source of the camera service: `usb` (the first camera) or `usb:SERIAL`.

Times are the device's, from the reset sent at start, moved on by an offset at every new epoch (a
reset from a master camera, or a reconnection), so they keep rising. An unplugged camera is reported
once, the source keeps answering (with no events) and reopens it every `RETRY_S` until it is back.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import usb.backend
import usb.core

from services.camera.formats import Calibration, FormatError
from services.camera.usb.driver import UsbCamera, UsbError, backend
from services.camera.usb.words import warm_up
from services.kernels import load
from services.messages import EVENT_DTYPE

log = logging.getLogger(__name__)
RETRY_S = 1.0
POLL_S = 1.0  # the device's drop counter is read this often


class UsbSource:
    done = False
    start_us = 0
    error: FormatError | None = None
    calibration: Calibration | None = None

    def __init__(self, spec: str, bias: str = "default", roi: tuple[int, int, int, int] | None = None,
                 backend_: usb.backend.IBackend | None = None) -> None:
        serial = spec.partition(":")[2] or None
        self.camera = UsbCamera(serial, backend_ or backend(), bias=bias, roi=roi)
        info = self.camera.open()  # UsbError: named, before the service starts; it streams from the first advance
        self._started = False
        self.name = f"usb:{info.serial} ({info.model})"
        self.width, self.height = info.width, info.height
        f = self.width / 2  # uncalibrated: 90 degrees horizontal field of view
        self.K = np.array([[f, 0, self.width / 2], [0, f, self.height / 2], [0, 0, 1]], np.float64)
        self._offset_us = 0
        self._last_us = -1
        self._imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._retry_at: float | None = None
        self._poll_at = 0.0
        self.device_dropped = 0  # DVS events the camera dropped (its USB FIFO full), over every session
        self._session_dropped = 0

    def advance(self, until_us: int) -> np.ndarray:
        """Every event that arrived (a live camera has none ahead of now)."""
        if not self._started:
            load("the USB decoder", warm_up)  # before the camera streams (not where `etam up` only checks it opens)
            self.camera.start()
            self._started = True
        if self.camera.failure is not None:
            self._reconnect()
            return np.zeros(0, EVENT_DTYPE)
        if time.monotonic() >= self._poll_at:
            self._poll_device()
        parts = []
        for d in self.camera.read():
            if d.resets:  # a new epoch from `reset_at` on: times go on from the last one
                parts.append(self._shifted(d.events[:d.reset_at]))
                self._offset_us = self._last_us + 1
                parts.append(self._shifted(d.events[d.reset_at:]))
            else:
                parts.append(self._shifted(d.events))
            if len(d.imu_t):
                self._imu.append((d.imu_t + self._offset_us, d.gyro, d.accel))
        return np.concatenate(parts) if parts else np.zeros(0, EVENT_DTYPE)

    def _poll_device(self) -> None:
        """Reads the camera's count of events it dropped; a rise is warned about."""
        self._poll_at = time.monotonic() + POLL_S
        try:
            count = self.camera.device_dropped()
        except usb.core.USBError:
            return  # unplugged: the reader thread tells
        if count > self._session_dropped:
            log.warning("%s: the camera dropped %d events (its USB buffer was full: the host read too slowly)",
                        self.name, count - self._session_dropped)
            self.device_dropped += count - self._session_dropped
            self._session_dropped = count

    def health(self) -> dict[str, object]:
        """What the camera service reports in its status: the link's state and every count of lost data."""
        cam = self.camera
        return {"usb_state": "streaming" if cam.failure is None else "unplugged",
                "usb_host_dropped_events": cam.dropped_events, "usb_device_dropped_events": self.device_dropped,
                "usb_bad_words": cam.bad_words}

    def _shifted(self, events: np.ndarray) -> np.ndarray:
        if len(events):
            events["t"] += self._offset_us
            self._last_us = max(self._last_us, int(events["t"][-1]))
        return events

    def _reconnect(self) -> None:
        now = time.monotonic()
        if self._retry_at is None:
            log.error("%s: %s; the service stays up and reopens it when it is back", self.name, self.camera.failure)
            self.camera.close()
        elif now < self._retry_at:
            return
        self._retry_at = now + RETRY_S
        try:
            self.camera.open()
            self.camera.start()
        except UsbError:
            self.camera.close()
            self.camera.failure = "not back yet"
            return
        log.info("%s: reconnected", self.name)
        self._offset_us, self._retry_at, self._session_dropped = self._last_us + 1, None, 0

    def imu(self, since_us: int, until_us: int):  # noqa: ANN201 - ImuSamples | None
        if not self._imu:
            return None
        t, gyro, accel = (np.concatenate(parts) for parts in zip(*self._imu, strict=True))
        self._imu = []
        return t, gyro, accel

    def truth(self, since_us: int, until_us: int) -> list:
        return []

    def poses(self, since_us: int, until_us: int) -> list:
        return []

    def depths(self, since_us: int, until_us: int) -> list:
        return []

    def loaded_until_us(self) -> int | None:
        return None

    def close(self) -> None:
        self.camera.close()
