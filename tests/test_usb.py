"""The pyusb driver against the fake camera: wire test vectors, round trips, discovery, streaming, unplugging."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.camera.formats import open_recording
from services.camera.usb import protocol as pr
from services.camera.usb.driver import UsbCamera, UsbError, discover
from services.camera.usb.encode import encode
from services.camera.usb.fake import FakeBackend, FakeCamera
from services.camera.usb.source import UsbSource
from services.camera.usb.words import WordDecoder
from services.messages import EVENT_DTYPE, Command

from tests.conftest import ROOT, client_session, etam_argv, free_port, wait_for
from tests.test_services import _query


def _hex(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


def _events(rows: list[tuple[int, int, int, int]]) -> np.ndarray:
    return np.array(rows, EVENT_DTYPE)


def test_davis_test_vectors_decode_as_the_reference_states() -> None:
    d = WordDecoder(False, 346, 260)
    out = d.decode(_hex("01 00  64 80  32 10  C8 30  C9 20  FF FF  01 70  05 80  03 11  59 31"))  # TV-1
    assert out.resets == 1 and out.dropped == 0
    np.testing.assert_array_equal(out.events, _events([(100, 200, 50, 1), (100, 201, 50, 0), (32773, 345, 259, 1)]))
    out = WordDecoder(False, 346, 260).decode(_hex("03 70 34 92 05 10 07 30"))  # TV-2: the wrap multiplier
    np.testing.assert_array_equal(out.events, _events([(102964, 7, 5, 1)]))


def test_dvxplorer_test_vector_decodes_as_the_reference_states() -> None:
    out = WordDecoder(True, 640, 480).decode(_hex("0A 80  11 18  85 40  05 30  80 21  12 10  CA 48  FF 31"))  # TV-3
    expected = [(10, 17, 40, 1), (10, 17, 42, 1), (10, 17, 63, 0)] + [(10, 18, y, 0) for y in range(80, 88)]
    np.testing.assert_array_equal(out.events, _events(expected))


@pytest.mark.parametrize("dvx, scale, accel_g, gyro_deg_s, temp_c", [
    (False, "E5", (1, 0, -1), (9.9945, 0, -9.9945), 35.0),  # TV-4: MPU-6050, a is x
    (True, "EA", (0, 1, -1), (0, 9.9945, -9.9945), 23.0),  # TV-5: BMI160, libcaer's mapping (a is y)
])
def test_imu_test_vectors_decode_as_the_reference_states(dvx: bool, scale: str, accel_g: tuple, gyro_deg_s: tuple,
                                                         temp_c: float) -> None:
    words = (f"05 00 {scale} 53 20 50 00 50 00 50 00 50 E0 50 00 50 00 50 00 50 02 50 8F 50 00 50"
             " 00 50 FD 50 71 50 07 00")
    out = WordDecoder(dvx, 346, 260).decode(_hex(words))
    np.testing.assert_allclose(out.accel[0] / 9.80665, accel_g, atol=1e-4)
    np.testing.assert_allclose(np.rad2deg(out.gyro[0]), gyro_deg_s, atol=1e-3)
    assert out.temperature[0] == pytest.approx(temp_c)


def test_addresses_beyond_the_sensor_and_an_odd_byte_are_dropped_and_counted() -> None:
    out = WordDecoder(False, 346, 260).decode(_hex("64 80  32 10  5A 31  C8 30  07"))  # x = 346: off the sensor
    np.testing.assert_array_equal(out.events, _events([(100, 200, 50, 1)]))
    assert out.dropped == 2


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.integers(1, 3000), st.lists(st.integers(0, 200), max_size=8))
def test_random_events_encoded_as_the_fake_does_decode_to_the_same_events(seed: int, dvx: bool, n: int,
                                                                          cuts: list[int]) -> None:
    rng = np.random.default_rng(seed)
    width, height = (640, 480) if dvx else (346, 260)
    ev = np.zeros(n, EVENT_DTYPE)
    # gaps up to 20 s: many wraps, some of several thousand at once
    ev["t"] = np.cumsum(rng.choice([0, 1, 7, 40_000, 20_000_000], n, p=[0.5, 0.3, 0.15, 0.04, 0.01]))
    ev["x"], ev["y"], ev["p"] = rng.integers(0, width, n), rng.integers(0, height, n), rng.integers(0, 2, n)
    if dvx:  # one readout reports a pixel once
        ev = np.unique(ev)
    words, _ = encode(ev, dvx)
    data = words.tobytes()
    decoder = WordDecoder(dvx, width, height)
    bounds = sorted({0, len(data), *(2 * (c * len(words) // 201) for c in cuts)})  # cut anywhere between words
    got = np.concatenate([decoder.decode(data[a:b]).events for a, b in zip(bounds, bounds[1:], strict=False)])
    order = ["t", "x", "y", "p"]
    np.testing.assert_array_equal(np.sort(got, order=order), np.sort(ev, order=order))


def _fake(model: str = "dvxplorer", serial: str = "DXA00001", events=None, **kw) -> FakeCamera:  # noqa: ANN001
    cam = FakeCamera(model=model, serial=serial, **kw)
    if events is not None:
        cam.events = events
    return cam


def _listed(events: np.ndarray):  # noqa: ANN202 - EventsIn
    """A fake camera's events: the listed ones, each sent once its time has come."""
    return lambda since, until: events[(events["t"] > since) & (events["t"] <= until)]


def test_discovery_names_model_serial_versions_and_what_stops_a_camera() -> None:
    found = discover(FakeBackend([_fake(), _fake("davis346", "DAV00002", address=5),
                                  _fake("davis240", "OLD00003", address=6, logic_version=17)]))
    assert [(d.model, d.serial, d.width, d.height, d.firmware, d.logic_version) for d in found] == [
        ("DVXplorer", "DXA00001", 640, 480, 9, 18), ("DAVIS346", "DAV00002", 346, 260, 6, 18),
        ("DAVIS240C", "OLD00003", 240, 180, 4, 17)]
    assert found[0].problem is None and found[1].problem is None
    assert "logic version 17" in found[2].problem and "update its firmware" in found[2].problem
    with pytest.raises(UsbError, match="logic version 17"):
        UsbCamera("OLD00003", FakeBackend([_fake("davis240", "OLD00003", logic_version=17)])).open()


def test_opening_an_absent_serial_names_the_cameras_found() -> None:
    with pytest.raises(UsbError, match="no camera with serial NOPE.*found: DXA00001"):
        UsbCamera("NOPE", FakeBackend([_fake()])).open()
    with pytest.raises(UsbError, match="no iniVation camera found"):
        UsbCamera(None, FakeBackend([])).open()


def test_the_control_transfers_are_the_reference_ones() -> None:
    cam = _fake()
    camera = UsbCamera(None, FakeBackend([cam]))
    camera.open()
    camera.start()
    camera.close()
    sent = [(r, i, v, data) for _, r, v, i, data in cam.requests]
    # TV-8: DVS run, the timestamp-reset pulse, the OFF bias of the default preset, MODE = stream, and the
    # early-packet delay of 1 ms at the fake's 80 MHz x 1.040 USB clock
    assert (pr.VR_FPGA_CONFIG, 3, 1, _hex("00 00 00 01")) in sent
    assert (pr.VR_FPGA_CONFIG_MULTIPLE, 0, 2, _hex("00 02 00 00 00 01  00 02 00 00 00 00")) in sent
    assert (pr.VR_FPGA_CONFIG, 0x1E, 5, _hex("00 00 00 08")) in sent
    assert (pr.VR_FPGA_CONFIG, 0x3000, 5, _hex("00 00 00 02")) in sent
    assert (pr.VR_FPGA_CONFIG, 1, 9, _hex("00 01 45 00")) in sent
    assert (pr.VR_FPGA_CONFIG, 5, 4, _hex("00 00 04 10")) in sent  # trigger pulse length 10 us at 100 MHz x 1.040
    # the read-modify-write registers after the defaults: global hold on and reset off, compression kept and
    # polarity options off, subsampling and area blocking bypassed; then the readout restarted
    assert [cam.registers[pr.BIAS, r] for r in (0x3255, 0x3067, 0x3200, 0x3204, pr.DVX_DTAG)] == [0x0D, 0x80, 0x06,
                                                                                                  0, 2]
    # stopped: the sensor is off and back in reset
    assert cam.registers[pr.BIAS, pr.DVX_MODE] == 0 and cam.registers[pr.MUX, pr.MUX_RUN_CHIP] == 0


def test_a_davis_gets_its_biases_filters_and_the_lite_its_subsampling_code() -> None:
    davis = _fake("davis346")
    UsbCamera(None, FakeBackend([davis])).open()
    sent = [(v, i, data) for _, r, v, i, data in davis.requests if r == pr.VR_FPGA_CONFIG]
    assert (5, 11, _hex("00 00 5F FF")) in sent  # TV-8: DAVIS346 ONBN = N 5/255
    assert [davis.registers[pr.DVS, p] for p in (*pr.DVS_ROI, 31, 32)] == [0, 0, 345, 259, 1, 8]
    lite = _fake("dvxplorer-lite")
    UsbCamera(None, FakeBackend([lite])).open()
    assert lite.registers[pr.BIAS, pr.DVX_SUBSAMPLE] == 0x09 and (pr.BIAS, pr.DVX_DUAL_BINNING) not in lite.registers


def _collect(camera: UsbCamera, n: int, timeout_s: float = 20.0) -> np.ndarray:
    got, deadline = [], time.monotonic() + timeout_s
    while sum(len(g) for g in got) < n and time.monotonic() < deadline:
        got += [d.events for d in camera.read()]
        time.sleep(0.01)
    return np.concatenate(got) if got else np.zeros(0, EVENT_DTYPE)


@pytest.mark.parametrize("model", ["dvxplorer", "davis346"])
def test_a_camera_streams_the_fakes_events_through_the_driver_unchanged(model: str) -> None:
    rng = np.random.default_rng(3)
    n = 5000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(1, 300_000, n))
    ev["x"], ev["y"], ev["p"] = rng.integers(0, 240, n), rng.integers(0, 180, n), rng.integers(0, 2, n)
    ev = np.unique(ev)
    cam = _fake(model, events=_listed(ev))
    camera = UsbCamera(None, FakeBackend([cam]))
    camera.open()
    camera.start()
    try:
        got = _collect(camera, len(ev))
    finally:
        camera.close()
    order = ["t", "x", "y", "p"]
    np.testing.assert_array_equal(np.sort(got, order=order), np.sort(ev, order=order))
    assert camera.dropped_buffers == 0 and camera.failure is None


def test_imu_samples_arrive_with_gravity() -> None:
    camera = UsbCamera(None, FakeBackend([_fake("davis346")]))
    camera.open()
    camera.start()
    deadline, accel = time.monotonic() + 20, []
    while not accel and time.monotonic() < deadline:
        accel += [d.accel for d in camera.read() if len(d.accel)]
        time.sleep(0.02)
    camera.close()
    np.testing.assert_allclose(accel[0][0], (0, 0, 9.80665), atol=1e-3)


def test_an_unplugged_camera_is_reported_and_found_again_when_it_is_back(caplog) -> None:  # noqa: ANN001
    caplog.set_level(logging.INFO)
    cam = _fake(events=lambda since, until: _events([(until, 1, 2, 1)]))
    source = UsbSource("usb:DXA00001", backend_=FakeBackend([cam]))
    try:
        first = _advance_until(source, lambda ev: len(ev) > 0)
        cam.unplug()
        _advance_until(source, lambda ev: source.camera.failure is not None, keep=False)
        assert "unplugged" in caplog.text
        cam.plug()
        later = _advance_until(source, lambda ev: len(ev) > 0)
        assert "reconnected" in caplog.text
        assert later["t"][0] > first["t"][-1]  # time goes on rising across the new session
    finally:
        source.close()


def _advance_until(source: UsbSource, done, keep: bool = True, timeout_s: float = 20.0) -> np.ndarray:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ev = source.advance(0)
        if done(ev):
            return ev
        time.sleep(0.02)
    raise AssertionError("timed out")


def test_usb_decode_writes_a_dump_as_an_event_file(tmp_path: Path) -> None:
    dump = tmp_path / "dump.bin"
    dump.write_bytes(_hex("01 00  64 80  32 10  C8 30  C9 20  FF FF  01 70  05 80  03 11  59 31"))
    out = subprocess.run(etam_argv("usb-decode", "--model", "davis346", str(dump), "--out", str(tmp_path / "e.h5"),
                                   "--json"), cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["events"] == 3
    with open_recording(tmp_path / "e.h5") as rec:
        assert (rec.width, rec.height) == (346, 260)
        np.testing.assert_array_equal(np.concatenate(list(rec.chunks()))["x"], [200, 201, 345])
    bad = subprocess.run(etam_argv("usb-decode", "--model", "davis999", str(dump), "--out", str(tmp_path / "x.h5")),
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr


def test_devices_lists_the_fake_cameras() -> None:
    env = {**os.environ, "ETAM_FAKE_USB": "dvxplorer:DXA00001,davis346"}
    out = subprocess.run(etam_argv("devices", "--json"), cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert [(d["model"], d["serial"]) for d in json.loads(out.stdout)] == [("DVXplorer", "DXA00001"),
                                                                          ("DAVIS346", "FAKE0002")]


@pytest.mark.slow
def test_up_streams_a_usb_camera_to_the_tracker_and_the_dashboard(tmp_path: Path, rig: str) -> None:
    report, endpoint = tmp_path / "r.json", f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "ETAM_FAKE_USB": "davis346"}
    with subprocess.Popen(etam_argv("up", "--source", "usb", "--duration", "12", "--web-port", str(free_port()),
                                    "--report", str(report), "--rig", rig, "--listen", endpoint,
                                    "--log-level", "WARNING"),
                          cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as proc:
        time.sleep(1.0)  # the router listens
        with client_session(endpoint) as session:
            def dashboard_events() -> int:
                reply = _query(session, f"etam/{rig}/web/web/cmd", Command(op="ping"))
                return reply.result.get("events_received", 0) if reply is not None and reply.ok else 0

            wait_for(lambda: dashboard_events() > 10_000, 60, "the dashboard receiving the USB camera's events")
            status = _query(session, f"etam/{rig}/camera/cam0/cmd", Command(op="ping")).result
            assert status["usb_state"] == "streaming" and status["usb_device_dropped_events"] == 0
            assert status["source"].startswith("usb:FAKE0001 (DAVIS346)")
        _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    keys = json.loads(report.read_text())["keys"]
    events, tracks = keys[f"etam/{rig}/camera/cam0/events"], keys[f"etam/{rig}/tracker/objects/tracks"]
    assert events["events"] > 100_000 and events["dropped"] == 0 and tracks["msg_rate"] > 50
    assert keys[f"etam/{rig}/camera/cam0/imu"]["msg_rate"] > 50
    assert "dropped" not in err


@pytest.mark.parametrize("model, roi", [("dvxplorer", (100, 60, 539, 419)), ("davis346", (20, 30, 150, 101))])
def test_a_region_of_interest_is_cropped_on_the_device(model: str, roi: tuple[int, int, int, int]) -> None:
    rng = np.random.default_rng(4)
    n = 4000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(1, 200_000, n))
    ev["x"], ev["y"], ev["p"] = rng.integers(0, 346, n), rng.integers(0, 260, n), 1
    ev = np.unique(ev)
    cam = _fake(model, events=_listed(ev))
    camera = UsbCamera(None, FakeBackend([cam]), roi=roi)
    camera.open()
    if model == "dvxplorer":  # TV-9: the cropper's registers for x 100..539, y 60..419
        assert [cam.registers[pr.BIAS, a] for a in (*pr.DVX_CROP_X, *pr.DVX_CROP_Y, pr.DVX_CROP_BYPASS)] == [
            0x00, 0x64, 0x02, 0x1B, 7, 0xF0, 52, 0x0F, 0]
    x0, y0, x1, y1 = roi
    inside = ev[(ev["x"] >= x0) & (ev["x"] <= x1) & (ev["y"] >= y0) & (ev["y"] <= y1)]
    camera.start()
    try:
        got = _collect(camera, len(inside), timeout_s=10)
        time.sleep(0.3)
        got = np.concatenate([got, *[d.events for d in camera.read()]])
    finally:
        camera.close()
    order = ["t", "x", "y", "p"]
    np.testing.assert_array_equal(np.sort(got, order=order), np.sort(inside, order=order))


def test_a_bad_preset_or_roi_is_refused_by_name_and_the_camera_released() -> None:
    cam = _fake("davis346")
    with pytest.raises(UsbError, match="bias preset 'very_high' is not one of low, default, high"):
        UsbCamera(None, FakeBackend([cam]), bias="very_high").open()
    with pytest.raises(UsbError, match="reaches beyond its 346x260"):
        UsbCamera(None, FakeBackend([cam]), roi=(0, 0, 400, 10)).open()
    env = {**os.environ, "ETAM_FAKE_USB": "davis346"}
    out = subprocess.run(etam_argv("camera", "--source", "usb", "--usb-roi", "5,5,1"), cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--usb-roi takes X0,Y0,X1,Y1" in out.stderr
    out = subprocess.run(etam_argv("camera", "--source", "usb", "--usb-bias", "loud"), cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "bias preset 'loud'" in out.stderr and "Traceback" not in out.stderr


def test_a_davis_whose_host_reads_too_slowly_drops_events_and_the_count_is_told(caplog) -> None:  # noqa: ANN001
    caplog.set_level(logging.INFO)
    rng = np.random.default_rng(5)

    def dense(since: int, until: int) -> np.ndarray:  # some 2 Mev/s
        n = (until - since) * 2
        ev = np.zeros(n, EVENT_DTYPE)
        ev["t"] = np.sort(rng.integers(since + 1, until + 1, n))
        ev["x"], ev["y"], ev["p"] = rng.integers(0, 346, n), rng.integers(0, 260, n), 1
        return ev

    cam = _fake("davis346", events=dense, fifo_bytes=1 << 16)
    source = UsbSource("usb", backend_=FakeBackend([cam]))
    decode = source.camera.decoder.decode
    source.camera.decoder.decode = lambda data: (time.sleep(0.05), decode(data))[1]  # a host that lags
    try:
        got = 0
        deadline = time.monotonic() + 20
        while source.device_dropped == 0 and time.monotonic() < deadline:
            got += len(source.advance(0))
            time.sleep(0.05)
    finally:
        source.close()
    assert source.device_dropped > 0 and "the camera dropped" in caplog.text
    assert source.health()["usb_device_dropped_events"] == source.device_dropped
    assert cam.dropped >= source.device_dropped  # told as the device counts them, none invented


def test_a_timestamp_reset_midway_starts_a_new_epoch_and_times_go_on_rising() -> None:
    cam = _fake(events=lambda since, until: _events([(until, 3, 4, 1)]))
    source = UsbSource("usb", backend_=FakeBackend([cam]))
    try:
        before = _advance_until(source, lambda ev: len(ev) > 0 and ev["t"][-1] > 200_000)
        cam.write(pr.MUX, pr.MUX_TS_RESET, 1)  # as a master camera's reset arrives over the sync cable
        after = np.concatenate([_advance_until(source, lambda ev: len(ev) > 0) for _ in range(5)])
    finally:
        source.close()
    assert after["t"][0] > before["t"][-1] and np.all(np.diff(after["t"]) >= 0)
    assert after["t"][0] - before["t"][-1] < 100_000  # the new epoch follows on, not from 0
