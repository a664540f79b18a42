"""A fake iniVation camera behind pyusb's backend interface, so the driver runs unchanged against it.

It answers as the reference's section 12 model says the hardware does: descriptors (VID, PID,
bcdDevice, serial string), the vendor requests 0xBF (read and write one register; module 5 keyed by
the full 16-bit wIndex on a DVXplorer) and 0xC2 (several records), read-only identity registers, and
the side effects: a timestamp reset puts a reset word in the stream and restarts the clock; data flows
only while USB, MUX and DVS run and the sensor is on (DAVIS RUN_CHIP, DVXplorer MODE = stream);
`clear_halt` drops what is queued. Its events come from a callable of a time span (the simulator, or a
list), encoded as the device would (`encode.py`); `unplug` makes every call fail as a pulled cable does.
"""

from __future__ import annotations

import array
import errno
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import usb.backend
import usb.core

from services.camera.usb import protocol as pr
from services.camera.usb.encode import RESET_WORD, encode, imu_words, time_words
from services.messages import EVENT_DTYPE

# span (us, since the last reset) -> events in it, sorted by time
EventsIn = Callable[[int, int], np.ndarray]
IMU_PERIOD_US = 5000  # 200 Hz samples while the IMU runs
IMU_SCALE_DVX, IMU_SCALE_DAVIS = 0xEA, 0xE5  # all sensors; +-4 g, +-500 deg/s (sections 5.6, 13)


@dataclass
class FakeModel:
    pid: int
    bcd_device: int
    chip_id: int
    width: int
    height: int
    imu_type: int


FAKE_MODELS = {"dvxplorer": FakeModel(pr.PID_DVXPLORER, 0x0109, 20, 640, 480, 3),
               "dvxplorer-lite": FakeModel(pr.PID_DVXPLORER, 0x0109, 19, 320, 240, 3),
               "davis346": FakeModel(pr.PID_DAVIS_FX3, 0x0106, 5, 346, 260, 1),
               "davis240": FakeModel(pr.PID_DAVIS_FX2, 0x0004, 2, 240, 180, 1)}


def _no_events(t0_us: int, t1_us: int) -> np.ndarray:
    return np.zeros(0, EVENT_DTYPE)


@dataclass
class FakeCamera:
    """One fake camera: its identity, register store and stream."""

    model: str = "dvxplorer"
    serial: str = "FAKE0001"
    events: EventsIn = _no_events
    bus: int = 1
    address: int = 4
    logic_version: int = pr.LOGIC_REQUIRED
    plugged: bool = True
    registers: dict[tuple[int, int], int] = field(default_factory=dict)
    requests: list[tuple[int, int, int, int, bytes]] = field(default_factory=list)  # OUT transfers, in order
    fifo_bytes: int = 1 << 22  # the device's buffer toward USB: a host that stops reading fills it
    generated: int = 0  # events the sensor saw
    dropped: int = 0  # ... that a full FIFO made it drop (DAVIS with DROP_DVS_ON_TRANSFER_STALL)

    def __post_init__(self) -> None:
        m = FAKE_MODELS[self.model]
        self.spec, self.dvx = m, m.pid == pr.PID_DVXPLORER
        self.identity = {(pr.SYSINFO, pr.LOGIC_VERSION): self.logic_version, (pr.SYSINFO, pr.CHIP_ID): m.chip_id,
                         (pr.SYSINFO, pr.IS_MASTER): 1, (pr.SYSINFO, pr.LOGIC_CLOCK): 100,
                         (pr.SYSINFO, pr.ADC_CLOCK): 30, (pr.SYSINFO, pr.USB_CLOCK): 80,
                         (pr.SYSINFO, pr.CLOCK_DEVIATION): 1040, (pr.SYSINFO, pr.LOGIC_PATCH): 4 if self.dvx else 1,
                         (pr.DVS, pr.DVS_COLUMNS): m.width, (pr.DVS, pr.DVS_ROWS): m.height,
                         (pr.DVS, pr.DVS_ORIENTATION): 0, (pr.IMU, pr.IMU_TYPE): m.imu_type,
                         (pr.IMU, pr.IMU_ORIENTATION): 0, (pr.EXTINPUT, pr.EXT_HAS_GENERATOR): 1}
        if not self.dvx:  # a DAVIS's logic has the DVS filters, and an APS of the DVS's size
            self.identity |= {(pr.DVS, flag): 1 for flag in (pr.DVS_HAS_PIXEL_FILTER, pr.DVS_HAS_BA_FILTER,
                                                              pr.DVS_HAS_ROI_FILTER, pr.DVS_HAS_SKIP_FILTER,
                                                              pr.DVS_HAS_POLARITY_FILTER)}
            self.identity |= {(pr.APS, 0): m.width, (pr.APS, 1): m.height, (pr.APS, 2): 0}
        self._lock = threading.Lock()
        self._queue = bytearray()
        self._clock0 = time.monotonic()  # wall time of the device's last timestamp reset
        self._sent_us = 0  # device time up to which events are queued
        self._stream_us = 0  # the stream's time after its last word (the encoder's state)
        self._next_imu_us = 0

    def unplug(self) -> None:
        self.plugged = False

    def plug(self) -> None:
        self.plugged = True
        self.registers.clear()  # powered off: volatile settings gone
        with self._lock:
            self._queue.clear()

    # the registers
    def read(self, module: int, param: int) -> int:
        if (module, param) in ((pr.MUX, pr.MUX_STAT_DVS_DROPPED), (pr.MUX, pr.MUX_STAT_DVS_DROPPED + 1)):
            return self.dropped >> 32 if param == pr.MUX_STAT_DVS_DROPPED else self.dropped & 0xFFFFFFFF
        return self.identity.get((module, param), self.registers.get((module, param), 0))

    def write(self, module: int, param: int, value: int) -> None:
        if (module, param) in self.identity:
            return  # read-only: accepted, ignored
        self.registers[module, param] = value
        if module == pr.MUX and param == pr.MUX_TS_RESET and value == 1:
            with self._lock:
                self._queue += np.array([RESET_WORD], "<u2").tobytes()
                self._clock0 = time.monotonic()
                self._sent_us = self._stream_us = self._next_imu_us = 0

    def streaming(self) -> bool:
        r = self.registers
        sensor = (r.get((pr.BIAS, pr.DVX_MODE)) == pr.DVX_MODE_STREAM if self.dvx
                  else r.get((pr.MUX, pr.MUX_RUN_CHIP)) == 1)
        return sensor and all(r.get(k) == 1 for k in ((pr.USB, pr.USB_RUN), (pr.MUX, pr.MUX_RUN), (pr.DVS, pr.DVS_RUN)))

    # the stream
    def bulk(self, size: int, timeout_ms: int) -> bytes:
        """Up to `size` bytes of the stream; waits for data up to the early-packet delay (1 ms), or the
        timeout while nothing flows."""
        deadline = time.monotonic() + timeout_ms / 1e3
        while True:
            with self._lock:
                if self.streaming():
                    self._generate()
                if self._queue:
                    n = min(size - size % 2, len(self._queue))
                    out = bytes(self._queue[:n])
                    del self._queue[:n]
                    return out
            if time.monotonic() >= deadline:
                raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
            time.sleep(0.001)

    def _generate(self) -> None:
        """Queue the words of the events (and IMU samples) up to the device's time now."""
        if self.registers.get((pr.MUX, pr.MUX_TS_RUN)) != 1:
            return
        now_us = int((time.monotonic() - self._clock0) * 1e6)
        if now_us <= self._sent_us:
            return
        events = self._cropped(self.events(self._sent_us, now_us))
        imu_on = self.registers.get((pr.IMU, pr.IMU_RUN_GYRO)) == 1
        chunks = []
        for t_imu in range(self._next_imu_us, now_us + 1, IMU_PERIOD_US) if imu_on else ():
            before = events[events["t"] < t_imu] if len(events) else events
            events = events[len(before):]
            chunks.append(self._encode(before))
            chunks.append(time_words(t_imu, self._stream_us))
            self._stream_us = t_imu
            chunks.append(imu_words(IMU_SCALE_DVX if self.dvx else IMU_SCALE_DAVIS, _still_imu()))
            self._next_imu_us = t_imu + IMU_PERIOD_US
        chunks.append(self._fit(events, 2 * sum(len(c) for c in chunks)))
        self._queue += b"".join(c.astype("<u2").tobytes() for c in chunks)
        self._sent_us = now_us

    def _cropped(self, events: np.ndarray) -> np.ndarray:
        """The events inside the region of interest its registers set: a DVXplorer's cropper (X bounds,
        Y groups with their masks), a DAVIS's DVS ROI filter."""
        r = self.registers.get
        if self.dvx:
            if r((pr.BIAS, pr.DVX_CROP_BYPASS), 1):
                return events
            xs = [r((pr.BIAS, a), 0) for a in pr.DVX_CROP_X]
            x0, x1 = xs[0] << 8 | xs[1], xs[2] << 8 | xs[3]
            g0, m0, g1, m1 = (r((pr.BIAS, a), 0) for a in pr.DVX_CROP_Y)
            y0 = 8 * g0 + (m0 & -m0).bit_length() - 1 if g0 != g1 else 8 * g0 + (m1 & -m1).bit_length() - 1
            y1 = 8 * g1 + m1.bit_length() - 1
        else:
            if (pr.DVS, pr.DVS_ROI[2]) not in self.registers:
                return events
            x0, y0, x1, y1 = (r((pr.DVS, a), 0) for a in pr.DVS_ROI)
        keep = (events["x"] >= x0) & (events["x"] <= x1) & (events["y"] >= y0) & (events["y"] <= y1)
        return events[keep]

    def _fit(self, events: np.ndarray, queued: int) -> np.ndarray:
        """The words of the events the FIFO has room for, after `queued` more bytes: the ones beyond are dropped
        and counted where the device drops on a stall (DAVIS); a DVXplorer slows its readout instead (all kept)."""
        self.generated += len(events)
        room = self.fifo_bytes - len(self._queue) - queued
        state = self._stream_us
        words = self._encode(events)
        drops = self.registers.get((pr.MUX, pr.MUX_DROP_DVS)) == 1
        if not drops or 2 * len(words) <= room or not len(events):
            return words
        keep = max(int(len(events) * max(room, 0) / (2 * len(words))), 0)
        self._stream_us = state
        self.dropped += len(events) - keep
        return self._encode(events[:keep])

    def _encode(self, events: np.ndarray) -> np.ndarray:
        words, self._stream_us = encode(events, self.dvx, self._stream_us)
        return words

    def clear_halt(self) -> None:
        with self._lock:
            self._queue.clear()


def simulated_events(width: int, height: int, seed: int = 0) -> EventsIn:
    """The simulator's moving objects, at the camera's size, as the fake camera's events."""
    from services.camera.simulator import EventSimulator, ObjectsScene

    scene = ObjectsScene(width, height, seed=seed)
    sim = EventSimulator(scene, seed=seed)
    return lambda since_us, until_us: sim.advance(until_us)


def _still_imu() -> tuple[int, ...]:
    """A camera at rest: accel A, B, Z (1 g up along z, at +-4 g), temperature 0 raw, gyro A, B, Z all zero."""
    return (0, 0, 8192, 0, 0, 0, 0)


class FakeBackend(usb.backend.IBackend):
    """pyusb's backend for the fake cameras plugged in (`cameras`); an unplugged one is not listed, and its
    handles fail with ENODEV."""

    def __init__(self, cameras: list[FakeCamera]) -> None:
        self.cameras = cameras

    def enumerate_devices(self):  # noqa: ANN201 - pyusb's interface
        return [c for c in self.cameras if c.plugged]

    def get_device_descriptor(self, dev: FakeCamera) -> SimpleNamespace:
        return SimpleNamespace(bLength=18, bDescriptorType=1, bcdUSB=0x0300, bDeviceClass=0xFF, bDeviceSubClass=0,
                               bDeviceProtocol=0, bMaxPacketSize0=9, idVendor=pr.VID, idProduct=dev.spec.pid,
                               bcdDevice=dev.spec.bcd_device, iManufacturer=1, iProduct=2, iSerialNumber=3,
                               bNumConfigurations=1, address=dev.address, bus=dev.bus, port_number=1,
                               port_numbers=(1,), speed=usb.util.SPEED_SUPER)

    def get_configuration_descriptor(self, dev: FakeCamera, config: int) -> SimpleNamespace:
        return SimpleNamespace(bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1, bConfigurationValue=1,
                               iConfiguration=0, bmAttributes=0x80, bMaxPower=250, extra_descriptors=[])

    def get_interface_descriptor(self, dev: FakeCamera, intf: int, alt: int, config: int) -> SimpleNamespace:
        return SimpleNamespace(bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0, bNumEndpoints=2,
                               bInterfaceClass=0xFF, bInterfaceSubClass=0, bInterfaceProtocol=0, iInterface=0,
                               extra_descriptors=[])

    def get_endpoint_descriptor(self, dev: FakeCamera, ep: int, intf: int, alt: int, config: int) -> SimpleNamespace:
        address, attributes, size = ((pr.EP_DATA, 2, 1024), (pr.EP_DEBUG, 3, 64))[ep]
        return SimpleNamespace(bLength=7, bDescriptorType=5, bEndpointAddress=address, bmAttributes=attributes,
                               wMaxPacketSize=size, bInterval=0 if attributes == 2 else 1, bRefresh=0, bSynchAddress=0,
                               extra_descriptors=[])

    def open_device(self, dev: FakeCamera) -> FakeCamera:
        return _alive(dev)

    def close_device(self, dev_handle: FakeCamera) -> None:
        pass

    def set_configuration(self, dev_handle: FakeCamera, config_value: int) -> None:
        _alive(dev_handle)

    def get_configuration(self, dev_handle: FakeCamera) -> int:
        return _alive(dev_handle) and 1

    def claim_interface(self, dev_handle: FakeCamera, intf: int) -> None:
        _alive(dev_handle)

    def release_interface(self, dev_handle: FakeCamera, intf: int) -> None:
        pass

    def clear_halt(self, dev_handle: FakeCamera, ep: int) -> None:
        _alive(dev_handle).clear_halt()

    def bulk_read(self, dev_handle: FakeCamera, ep: int, intf: int, buff: array.array, timeout: int) -> int:
        data = _alive(dev_handle).bulk(len(buff) * buff.itemsize, timeout or 1000)
        _alive(dev_handle)
        memoryview(buff).cast("B")[:len(data)] = data
        return len(data)

    def ctrl_transfer(self, dev_handle: FakeCamera, bmRequestType: int, bRequest: int, wValue: int,  # noqa: N803
                      wIndex: int, data: array.array, timeout: int) -> int:  # noqa: N803 - pyusb's names
        dev = _alive(dev_handle)
        raw = memoryview(data).cast("B")
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR, string
            index = wValue & 0xFF
            text = {1: "iniVation", 2: dev.spec and dev.model, 3: dev.serial}.get(index, "")
            body = b"\x09\x04" if index == 0 else text.encode("utf-16-le")
            out = bytes([2 + len(body), 3]) + body
            raw[:min(len(out), len(raw))] = out[:len(raw)]
            return min(len(out), len(raw))
        if bmRequestType == pr.REQ_IN and bRequest == pr.VR_FPGA_CONFIG:
            if len(raw) != 4:
                raise usb.core.USBError("Pipe error", -9, errno.EPIPE)  # STALL
            raw[:4] = dev.read(wValue, wIndex).to_bytes(4, "big")
            return 4
        if bmRequestType == pr.REQ_OUT and bRequest == pr.VR_FPGA_CONFIG and len(raw) == 4:
            dev.requests.append((bmRequestType, bRequest, wValue, wIndex, bytes(raw)))
            dev.write(wValue, wIndex, int.from_bytes(raw, "big"))
            return 4
        if bmRequestType == pr.REQ_OUT and bRequest == pr.VR_FPGA_CONFIG_MULTIPLE and len(raw) == 6 * wValue:
            dev.requests.append((bmRequestType, bRequest, wValue, wIndex, bytes(raw)))
            for k in range(wValue):
                rec = bytes(raw[6 * k:6 * k + 6])
                dev.write(rec[0], rec[1], int.from_bytes(rec[2:], "big"))
            return len(raw)
        raise usb.core.USBError("Pipe error", -9, errno.EPIPE)


def _alive(dev: FakeCamera) -> FakeCamera:
    if not dev.plugged:
        raise usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)
    return dev
