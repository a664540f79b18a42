"""Finding, opening and streaming iniVation cameras over pyusb (reference sections 1-4, 10, 11).

`discover` lists the cameras plugged in, with what stops one from opening (permissions, firmware).
`UsbCamera` opens one (by serial), checks its versions, sends its configuration and start sequence,
and reads the bulk stream on a thread of its own with large reads, back to back (the reference's
pitfall 1: the camera's FIFO overflows when the host leaves gaps), handing each buffer to a decoding
thread (numba releases the GIL). A decoder that falls behind blocks the reader once `RAW_BUFFERS`
wait, so the camera's own FIFO fills and it drops and counts (`device_dropped`); decoded buffers
wait for their consumer in a bounded queue too, and one too slow for them makes them dropped and
counted. Nothing is lost silently. Data before the timestamp reset sent at start is discarded (it may be
left over from an earlier session). An unplugged camera ends the thread with `failure` set.
"""

from __future__ import annotations

import array
import errno
import logging
import os
import queue
import threading
import time
from dataclasses import asdict, dataclass

import usb.core
import usb.util

from services.camera.usb import protocol as pr
from services.camera.usb.words import Decoded, WordDecoder

log = logging.getLogger(__name__)

READ_BYTES = 1 << 17  # 128 KiB bulk reads, a multiple of every wMaxPacketSize
READ_TIMEOUT_MS = 100
RAW_BUFFERS = 1024  # read, waiting to be decoded
QUEUE_BUFFERS = 4096  # some 4 s of the ~1 ms buffers a camera sends (early-packet delay) before any is dropped
FAKE_ENV = "ETAM_FAKE_USB"  # MODEL[:SERIAL],... : fake cameras instead of the USB bus (tests, demos)
UDEV_HINT = ("no permission to open it: install the udev rule (sudo cp deploy/udev/65-etam-inivation.rules "
             "/etc/udev/rules.d/ && sudo udevadm control --reload-rules && sudo udevadm trigger), then replug it")
GONE_ERRNOS = (errno.ENODEV, errno.EIO, errno.EPIPE, errno.ESHUTDOWN)


class UsbError(RuntimeError):
    """A camera that cannot be found, opened or read; the text says which and why."""


@dataclass
class DeviceInfo:
    model: str
    serial: str
    bus: int
    address: int
    firmware: int
    logic_version: int | None
    logic_patch: int | None
    usb_speed: str
    width: int | None
    height: int | None
    problem: str | None = None  # why it cannot be opened, if it cannot

    def as_dict(self) -> dict:
        return asdict(self)


def backend() -> usb.backend.IBackend | None:
    """The fake cameras named in $ETAM_FAKE_USB (streaming the simulator), else None: pyusb's own backend."""
    spec = os.environ.get(FAKE_ENV)
    if not spec:
        return None
    from services.camera.usb.fake import FakeBackend, FakeCamera, simulated_events

    cameras = []
    for k, item in enumerate(spec.split(",")):
        model, _, serial = item.partition(":")
        cam = FakeCamera(model=model, serial=serial or f"FAKE{k + 1:04d}", address=4 + k)
        cam.events = simulated_events(cam.spec.width, cam.spec.height, seed=k)
        cameras.append(cam)
    return FakeBackend(cameras)


_SPEEDS = {usb.util.SPEED_LOW: "low (1.5 Mb/s)", usb.util.SPEED_FULL: "full (12 Mb/s)",
           usb.util.SPEED_HIGH: "high (480 Mb/s)", usb.util.SPEED_SUPER: "super (5 Gb/s)"}


def _find(backend_: usb.backend.IBackend | None) -> list[usb.core.Device]:
    try:
        found = usb.core.find(find_all=True, idVendor=pr.VID, backend=backend_)
        return [d for d in found if d.idProduct in pr.PIDS]
    except usb.core.NoBackendError:
        raise UsbError("no USB backend: install libusb 1.0 (Debian/Ubuntu: sudo apt install libusb-1.0-0)") from None


def _serial(dev: usb.core.Device) -> str:
    """Its serial string (at most 8 characters), or libcaer's temporary one from bus and address."""
    text = usb.util.get_string(dev, dev.iSerialNumber) if dev.iSerialNumber else None
    return text[:8] if text else f"TMP{(dev.bus << 8) | dev.address:05d}"


def _read(dev: usb.core.Device, module: int, param: int) -> int:
    return int.from_bytes(dev.ctrl_transfer(pr.REQ_IN, pr.VR_FPGA_CONFIG, module, param, 4, pr.TIMEOUT_MS), "big")


def _model(dev: usb.core.Device) -> tuple[str, int, int]:
    """Its model (from the chip id: the PID names only a family), native width and height."""
    family = pr.FAMILIES[dev.idProduct]
    chip = _read(dev, pr.SYSINFO, pr.CHIP_ID)
    name = (pr.DVX_CHIPS if family.dvx else pr.DAVIS_CHIPS).get(chip, f"{family.name} (chip {chip})")
    width, height = _read(dev, pr.DVS, pr.DVS_COLUMNS), _read(dev, pr.DVS, pr.DVS_ROWS)
    if _read(dev, pr.DVS, pr.DVS_ORIENTATION) & 0x4:  # invertXY
        width, height = height, width
    return name, width, height


def _problem(dev: usb.core.Device, logic: int) -> str | None:
    """What stops the driver from using it: a DVXplorer Mini (32-bit words), or logic other than 18."""
    if dev.idProduct == pr.PID_DVXPLORER and dev.bcdDevice >> 8 == pr.BCD_MINI:
        return "a DVXplorer Mini (CX3 bridge, 32-bit words): not supported by this driver yet"
    if logic != pr.LOGIC_REQUIRED:
        return f"FPGA logic version {logic}, this driver speaks version {pr.LOGIC_REQUIRED}: update its firmware in DV"
    return None


def discover(backend_: usb.backend.IBackend | None = None) -> list[DeviceInfo]:
    """The iniVation cameras plugged in, each with its identity or what keeps it from opening."""
    out = []
    for dev in _find(backend_):
        speed = _SPEEDS.get(dev.speed, "unknown")
        base = dict(bus=dev.bus, address=dev.address, firmware=dev.bcdDevice & 0xFF, usb_speed=speed)
        try:
            serial = _serial(dev)
            logic, patch = _read(dev, pr.SYSINFO, pr.LOGIC_VERSION), _read(dev, pr.SYSINFO, pr.LOGIC_PATCH)
            model, width, height = _model(dev)
        except (usb.core.USBError, ValueError) as exc:
            denied = isinstance(exc, ValueError) or getattr(exc, "errno", None) == errno.EACCES
            out.append(DeviceInfo(pr.FAMILIES[dev.idProduct].name, "?", logic_version=None, logic_patch=None,
                                  width=None, height=None, problem=UDEV_HINT if denied else f"unreadable: {exc}",
                                  **base))
            continue
        out.append(DeviceInfo(model, serial, logic_version=logic, logic_patch=patch, width=width, height=height,
                              problem=_problem(dev, logic), **base))
    return out


class UsbCamera:
    """One camera, opened by serial (or the first that opens); `start` streams, `read` returns the
    decoded buffers so far, `stop` and `close` end it cleanly. `bias`: a sensitivity preset
    (very_low, low, default, high, very_high on a DVXplorer; low, default, high on a DAVIS);
    `roi`: x0, y0, x1, y1 (inclusive) kept by the camera, the rest cropped away on the device."""

    def __init__(self, serial: str | None = None, backend_: usb.backend.IBackend | None = None,
                 bias: str = "default", roi: tuple[int, int, int, int] | None = None) -> None:
        self.serial_wanted, self.backend, self.bias, self.roi = serial, backend_, bias, roi
        self._queue: queue.Queue[Decoded] = queue.Queue(QUEUE_BUFFERS)
        self._threads: list[threading.Thread] = []
        self._raw: queue.Queue[bytes | None] = queue.Queue(RAW_BUFFERS)
        self._running = threading.Event()
        self.failure: str | None = None  # why streaming stopped on its own (unplugged)
        self.dropped_buffers = self.dropped_events = self.bad_words = 0
        self._warn_at = 0.0  # drops are told at most every 5 s
        self.dev: usb.core.Device | None = None

    def open(self) -> DeviceInfo:
        """Finds and claims the camera, checks it and sends its configuration; UsbError names what failed."""
        candidates = _find(self.backend)
        if not candidates:
            raise UsbError("no iniVation camera found on USB (is it plugged in? `etam devices` lists what is seen)")
        errors = []
        for dev in candidates:
            try:
                serial = _serial(dev)
                if self.serial_wanted and serial != self.serial_wanted[:8]:
                    continue
                return self._open(dev, serial)
            except ValueError:
                errors.append(f"bus {dev.bus} address {dev.address}: {UDEV_HINT}")
            except usb.core.USBError as exc:
                busy = exc.errno == errno.EBUSY
                errors.append(f"bus {dev.bus} address {dev.address}: "
                              + ("in use by another program" if busy else UDEV_HINT if exc.errno == errno.EACCES
                                 else str(exc)))
        wanted = f" with serial {self.serial_wanted}" if self.serial_wanted else ""
        raise UsbError(f"no camera{wanted} could be opened" + (f" ({'; '.join(errors)})" if errors else
                       f"; found: {', '.join(_serial(d) for d in candidates)}"))

    def _open(self, dev: usb.core.Device, serial: str) -> DeviceInfo:
        family = pr.FAMILIES[dev.idProduct]
        if dev.get_active_configuration().bConfigurationValue != 1:
            dev.set_configuration(1)
        usb.util.claim_interface(dev, 0)
        logic, patch = _read(dev, pr.SYSINFO, pr.LOGIC_VERSION), _read(dev, pr.SYSINFO, pr.LOGIC_PATCH)
        if (problem := _problem(dev, logic)) is not None:
            usb.util.release_interface(dev, 0)
            raise UsbError(f"camera {serial}: {problem}")
        firmware = dev.bcdDevice & 0xFF
        if firmware < family.min_firmware:
            log.warning("camera %s: USB firmware %d is older than the %d this driver was written for; update it in DV",
                        serial, firmware, family.min_firmware)
        self.dev, self.dvx = dev, family.dvx
        model, width, height = _model(dev)
        invert = bool(_read(dev, pr.DVS, pr.DVS_ORIENTATION) & 0x4)
        flips = _read(dev, pr.IMU, pr.IMU_ORIENTATION)
        native = (height, width) if invert else (width, height)
        self.decoder = WordDecoder(family.dvx, *native, invert_xy=invert,
                                   imu_flips=(bool(flips & 4), bool(flips & 2), bool(flips & 1)))
        self.info = DeviceInfo(model, serial, dev.bus, dev.address, firmware, logic, patch,
                               _SPEEDS.get(dev.speed, "unknown"), width, height)
        try:
            if self.roi is not None and not (self.roi[2] < width and self.roi[3] < height):
                raise UsbError(f"camera {serial}: ROI {self.roi} reaches beyond its {width}x{height} pixels")
            self._configure()
        except BaseException:
            usb.util.release_interface(dev, 0)
            usb.util.dispose_resources(dev)
            self.dev = None
            raise
        return self.info

    # control transfers
    def write(self, module: int, param: int, value: int) -> None:
        self.dev.ctrl_transfer(pr.REQ_OUT, pr.VR_FPGA_CONFIG, module, param, int(value).to_bytes(4, "big"),
                               pr.TIMEOUT_MS)

    def _writes(self, writes: list[tuple[int, int, int]]) -> None:
        for module, param, value in writes:
            self.write(module, param, value)

    def _timestamp_reset(self) -> None:
        records = bytes([pr.MUX, pr.MUX_TS_RESET, 0, 0, 0, 1, pr.MUX, pr.MUX_TS_RESET, 0, 0, 0, 0])
        self.dev.ctrl_transfer(pr.REQ_OUT, pr.VR_FPGA_CONFIG_MULTIPLE, 2, 0, records, pr.TIMEOUT_MS)

    def _configure(self) -> None:
        """The sensor's power-up, biases and default settings (sections 4.1 A-B, 4.4 B, 7, 8)."""
        B = pr.BIAS
        presets = pr.DVX_BIAS_PRESETS if self.dvx else pr.DAVIS_SENSITIVITY
        if self.bias not in presets:
            raise UsbError(f"bias preset {self.bias!r} is not one of {', '.join(presets)}")
        usb_delay = round(8 * 125 * self._clock_mhz(pr.USB_CLOCK))  # 1 ms early-packet delay
        if self.dvx:
            self.write(pr.MUX, pr.MUX_RUN_CHIP, 1)
            time.sleep(0.01)
            lite = self.info.model == pr.DVX_CHIPS[19]
            lsb, sf, on, off = pr.DVX_BIAS_PRESETS[self.bias]
            self._writes([(B, r, v) for r, v in pr.DVX_SENSOR_INIT])
            self._writes([(pr.MUX, pr.MUX_DROP_EXT, 1), (pr.MUX, pr.MUX_DROP_DVS, 0),  # DVS back-pressured, not dropped
                          *((pr.IMU, k, v) for k, v in pr.DVX_IMU), *self._extinput(),
                          (pr.USB, pr.USB_EARLY_PACKET_DELAY, usb_delay),
                          (B, 0x0018, 0x04), (B, 0x000C, 0x14), (B, 0x000B, lsb), (B, 0x0012, sf),
                          (B, 0x001C, on), (B, 0x001E, off), (B, pr.DVX_DTAG, 0)])  # readout stopped to set it
            for reg, on_bits, off_bits in pr.DVX_UPDATES:
                self.write(B, reg, (_read(self.dev, B, reg) | on_bits) & ~off_bits & 0xFF)
            self._writes([*(((B, pr.DVX_DUAL_BINNING, 0),) if not lite else ()),
                          (B, pr.DVX_SUBSAMPLE, 0x09 if lite else 0x00),  # no subsampling (the Lite's (v<<1)|1)
                          *((B, r, v) for r, v in pr.DVX_READOUT)])
            self._dvx_crop()
            self.write(B, pr.DVX_DTAG, 2)  # readout restart
        else:
            biases = dict(pr.DAVIS240_BIASES if self.info.width == 240 else pr.DAVIS346_BIASES)
            if self.info.width != 240:
                biases[11], biases[12] = pr.DAVIS_SENSITIVITY[self.bias]
            has = {flag: _read(self.dev, pr.DVS, flag) for flag in (
                pr.DVS_HAS_PIXEL_FILTER, pr.DVS_HAS_BA_FILTER, pr.DVS_HAS_ROI_FILTER, pr.DVS_HAS_SKIP_FILTER,
                pr.DVS_HAS_POLARITY_FILTER)}
            cols, rows = _read(self.dev, pr.DVS, pr.DVS_COLUMNS), _read(self.dev, pr.DVS, pr.DVS_ROWS)
            x0, y0, x1, y1 = self.roi or (0, 0, cols - 1, rows - 1)
            if self.roi is not None and not has[pr.DVS_HAS_ROI_FILTER]:
                raise UsbError(f"camera {self.info.serial}: its logic has no ROI filter")
            aps_cols, aps_rows = _read(self.dev, pr.APS, 0), _read(self.dev, pr.APS, 1)
            adc = self._clock_mhz(pr.ADC_CLOCK)
            self._writes([*((B, k, v) for k, v in biases.items()), *((B, k, v) for k, v in pr.DAVIS_CHIP),
                          *(((B, k, v) for k, v in pr.DAVIS_CHIP_346) if self.info.width != 240 else ()),
                          (pr.MUX, pr.MUX_DROP_EXT, 1), (pr.MUX, pr.MUX_DROP_DVS, 1), (pr.DVS, 4, 0), (pr.DVS, 5, 0),
                          # hot-pixel slots at an address beyond the sensor: off
                          *(((pr.DVS, 11 + 2 * n, rows) for n in range(8)) if has[pr.DVS_HAS_PIXEL_FILTER] else ()),
                          *(((pr.DVS, 12 + 2 * n, cols) for n in range(8)) if has[pr.DVS_HAS_PIXEL_FILTER] else ()),
                          *(((pr.DVS, k, v) for k, v in pr.DVS_BA_FILTER) if has[pr.DVS_HAS_BA_FILTER] else ()),
                          *(zip((pr.DVS,) * 4, pr.DVS_ROI, (x0, y0, x1, y1), strict=True)
                            if has[pr.DVS_HAS_ROI_FILTER] else ()),
                          *(((pr.DVS, k, v) for k, v in pr.DVS_SKIP_FILTER) if has[pr.DVS_HAS_SKIP_FILTER] else ()),
                          *(((pr.DVS, k, v) for k, v in pr.DVS_POLARITY_FILTER) if has[pr.DVS_HAS_POLARITY_FILTER]
                            else ()),
                          # APS (left off: DVS only) with its whole frame, 4 ms exposure, 40 ms frame interval
                          (pr.APS, 5, 1), (pr.APS, 8, 0), (pr.APS, 9, 0), (pr.APS, 10, max(aps_cols - 1, 0)),
                          (pr.APS, 11, max(aps_rows - 1, 0)), (pr.APS, 12, round(4000 * adc)),
                          (pr.APS, 13, round(40000 * adc)),
                          *((pr.IMU, k, v) for k, v in pr.DAVIS_IMU), *self._extinput(),
                          (pr.USB, pr.USB_EARLY_PACKET_DELAY, usb_delay)])

    def _extinput(self) -> list[tuple[int, int, int]]:
        """The trigger detector's defaults (pulses, active high, 10 us), and the generator's where there is one."""
        logic = self._clock_mhz(pr.LOGIC_CLOCK)
        E = pr.EXTINPUT
        out = [(E, 1, 0), (E, 2, 0), (E, 3, 1), (E, 4, 1), (E, 5, round(10 * logic))]
        if _read(self.dev, E, pr.EXT_HAS_GENERATOR):
            out += [(E, 11, 0), (E, 12, 1), (E, 13, round(10 * logic)), (E, 14, round(5 * logic)), (E, 15, 0),
                    (E, 16, 0)]
        return out

    def _clock_mhz(self, clock: int) -> float:
        """A SYSINFO clock (LOGIC_CLOCK, ADC_CLOCK, USB_CLOCK) as it really runs, with the clock deviation."""
        return _read(self.dev, pr.SYSINFO, clock) * _read(self.dev, pr.SYSINFO, pr.CLOCK_DEVIATION) / 1000

    def _dvx_crop(self) -> None:
        """The DVXplorer's cropper (section 8.2): bypassed without a ROI."""
        B = pr.BIAS
        if self.roi is None:
            self.write(B, pr.DVX_CROP_BYPASS, 1)
            return
        x0, y0, x1, y1 = self.roi
        flips = _read(self.dev, pr.DVS, pr.DVS_ORIENTATION)
        w, h = self.info.width, self.info.height
        if flips & 2:
            x0, x1 = w - 1 - x1, w - 1 - x0
        if flips & 1:
            y0, y1 = h - 1 - y1, h - 1 - y0
        start_mask, end_mask = (0xFF << (y0 % 8)) & 0xFF, 0xFF >> (7 - y1 % 8)
        if y0 // 8 == y1 // 8:
            start_mask, end_mask = 0xFF, end_mask & start_mask
        self._writes([(B, r, v) for r, v in zip(pr.DVX_CROP_X, (x0 >> 8, x0 & 0xFF, x1 >> 8, x1 & 0xFF), strict=True)]
                     + [(B, r, v) for r, v in zip(pr.DVX_CROP_Y, (y0 // 8, start_mask, y1 // 8, end_mask), strict=True)]
                     + [(B, pr.DVX_CROP_BYPASS, 0)])

    def _stop_all(self) -> None:
        runs = [(pr.DVS, pr.DVS_RUN, 0), (pr.IMU, pr.IMU_RUN_ACCEL, 0), (pr.IMU, pr.IMU_RUN_GYRO, 0),
                (pr.IMU, pr.IMU_RUN_TEMP, 0), (pr.EXTINPUT, 0, 0), (pr.MUX, pr.MUX_RUN, 0), (pr.MUX, pr.MUX_TS_RUN, 0),
                (pr.USB, pr.USB_RUN, 0)]
        if self.dvx:
            runs.insert(0, (pr.BIAS, pr.DVX_MODE, 0))
        else:
            runs.insert(1, (pr.APS, 4, 0))
        self._writes(runs)

    def start(self) -> None:
        """The start sequence (sections 4.1 C, 4.4 C), the reader thread, then a timestamp reset: what
        comes before it is discarded."""
        self.failure = None
        self._stop_all()
        if not self.dvx:
            self.write(pr.MUX, pr.MUX_RUN_CHIP, 0)
        time.sleep(0.01)
        self.dev.clear_halt(pr.EP_DATA)
        self._synced = False
        self._running.set()
        self._raw = queue.Queue(RAW_BUFFERS)
        self._threads = [threading.Thread(target=loop, name=f"usb-{self.info.serial}-{loop.__name__[1:]}", daemon=True)
                         for loop in (self._read_loop, self._decode_loop)]
        for thread in self._threads:
            thread.start()
        if not self.dvx:
            self.write(pr.MUX, pr.MUX_RUN_CHIP, 1)
            time.sleep(0.2)  # biases settle
        self._writes([(pr.USB, pr.USB_RUN, 1), (pr.MUX, pr.MUX_TS_RUN, 1), (pr.MUX, pr.MUX_RUN, 1)])
        time.sleep(0.05)
        self._writes([(pr.DVS, pr.DVS_RUN, 1), (pr.IMU, pr.IMU_RUN_ACCEL, 1), (pr.IMU, pr.IMU_RUN_GYRO, 1),
                      (pr.IMU, pr.IMU_RUN_TEMP, 1)])
        if self.dvx:
            self._writes([(pr.BIAS, pr.DVX_TS_RESET, 1), (pr.BIAS, pr.DVX_TS_RESET, 0),
                          (pr.BIAS, pr.DVX_MODE, pr.DVX_MODE_STREAM)])
        self._timestamp_reset()

    def _read_loop(self) -> None:
        buf = array.array("B", bytes(READ_BYTES))
        view = memoryview(buf)
        while self._running.is_set():
            try:
                n = self.dev.read(pr.EP_DATA, buf, READ_TIMEOUT_MS)
            except usb.core.USBTimeoutError:
                continue
            except usb.core.USBError as exc:
                if not self._running.is_set():
                    break
                gone = exc.errno in GONE_ERRNOS or "No such device" in str(exc)
                self.failure = ("the camera was unplugged (or its cable failed)" if gone else f"USB read failed: {exc}")
                log.error("camera %s: %s", self.info.serial, self.failure)
                break
            chunk = bytes(view[:n])
            while self._running.is_set():
                try:
                    self._raw.put(chunk, timeout=READ_TIMEOUT_MS / 1e3)
                    break
                except queue.Full:  # the decoder is behind: the camera's FIFO takes the wait
                    continue
        self._raw.put(None)  # the decoder ends after what was read

    def _decode_loop(self) -> None:
        while (chunk := self._raw.get()) is not None:
            self._accept(self.decoder.decode(chunk))

    def _accept(self, d: Decoded) -> None:
        self.bad_words += d.dropped
        if not self._synced:  # data left over from before the reset is not this session's
            if not d.resets:
                return
            self._synced = True
            d.events, d.resets, d.reset_at = d.events[d.reset_at:], 0, 0
            d.imu_t, d.gyro, d.accel, d.temperature = d.imu_t[:0], d.gyro[:0], d.accel[:0], d.temperature[:0]
        try:
            self._queue.put_nowait(d)
        except queue.Full:
            self.dropped_buffers += 1
            self.dropped_events += len(d.events)
            if time.monotonic() >= self._warn_at:
                self._warn_at = time.monotonic() + 5.0
                log.warning("camera %s: %d buffers (%d events) dropped: their consumer is too slow",
                            self.info.serial, self.dropped_buffers, self.dropped_events)

    def read(self) -> list[Decoded]:
        """The buffers decoded since the last call, oldest first."""
        out = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out

    def device_dropped(self) -> int:
        """DVS events the device dropped (DAVIS drops them when USB stalls; a DVXplorer slows its readout)."""
        hi = _read(self.dev, pr.MUX, pr.MUX_STAT_DVS_DROPPED)
        return hi << 32 | _read(self.dev, pr.MUX, pr.MUX_STAT_DVS_DROPPED + 1)

    def stop(self) -> None:
        """The stop sequence, then the reader thread ends."""
        if self.dev is None:
            return
        try:
            if self.failure is None:
                self._stop_all()
        finally:
            self._running.clear()
            for thread in self._threads:
                thread.join(timeout=2)
            self._threads = []

    def close(self) -> None:
        """Stops, puts the sensor back into reset and releases the camera."""
        if self.dev is None:
            return
        try:
            self.stop()
            if self.failure is None:
                self.write(pr.MUX, pr.MUX_RUN_CHIP, 0)
                usb.util.release_interface(self.dev, 0)
        except usb.core.USBError as exc:
            log.info("camera %s: not released cleanly (%s)", self.info.serial, exc)
        finally:
            usb.util.dispose_resources(self.dev)
            self.dev = None
