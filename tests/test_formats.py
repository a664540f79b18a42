"""File readers and writers: real recordings decode to their documented counts; faults are named."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest

from services.camera.formats import Calibration, FormatError, open_recording
from services.camera.formats.hdf5 import H5Writer
from services.camera.sources import FileSource, SourceError, open_sources
from services.messages import EVENT_DTYPE
from tests.conftest import SHARED, client_session, etam_argv

REAL = SHARED / "data" / "real"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason="../shared/data/real is absent")
ECD = sorted(p.name for p in (REAL / "ecd_cuts_eventstppp").glob("*/")) if REAL.is_dir() else []


def _events(n: int, t0: int = 0) -> np.ndarray:
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = t0 + np.arange(n) * 10
    ev["x"], ev["y"], ev["p"] = np.arange(n) % 50, np.arange(n) % 40, np.arange(n) % 2
    return ev


@needs_real
@pytest.mark.parametrize("seq", ECD)
def test_ecd_sequences_decode_to_the_documented_counts(seq: str) -> None:
    with open_recording(REAL / "ecd_cuts_eventstppp" / seq) as rec:
        ev = rec.read_all()
        assert rec.format == "ecd-text" and (rec.width, rec.height) == (240, 180)
        assert rec.calibration is not None and rec.calibration.K[0, 0] == pytest.approx(199.092366542)
        assert rec.calibration.dist_model == "radtan" and len(rec.calibration.dist) == 5
    assert len(ev) == 30_000
    assert np.all(np.diff(ev["t"]) >= 0) and 5_000 <= ev["t"][-1] - ev["t"][0] <= 110_000
    assert ev["x"].max() < 240 and ev["y"].max() < 180 and set(np.unique(ev["p"])) == {0, 1}


REAL_FILES = [  # path, format, width, height, events (../shared/data/real/README.md), imu samples
    ("davis240c_imu/IMU_translBoxes.aedat", "aedat2", 240, 180, 162_771, 4_833),
    ("ethz3dv_dvs128/reveal6.aedat", "aedat2", 128, 128, 128_436, 0),
    ("ethz3dv_dvs128/reveal9.aedat", "aedat2", 128, 128, 99_628, 0),
    ("ethz3dv_dvs128/checkerboard_5.aedat", "aedat2", 128, 128, 391_136, 0),
    ("rpg_event_lifetime_dvs128/building.mat", "matlab", 128, 128, 115_839, 0),
    ("rpg_event_lifetime_dvs128/flip.mat", "matlab", 128, 128, 175_136, 0),
    ("rpg_event_lifetime_dvs128/garfield.mat", "matlab", 128, 128, 202_235, 0),
    ("rpg_event_lifetime_dvs128/stripes.mat", "matlab", 128, 128, 340_394, 0),
    ("tonic_samples/sample.aedat4", "aedat4", 320, 240, 111_954, 475),
    ("tonic_samples/sample_ncars.dat", "prophesee-dat", 78, 42, 2_009, 0),
    ("tonic_samples/sample_nmnist.bin", "nmnist-bin", 34, 34, 4_325, 0),
    ("prophesee_samples/gen3_sparklers_evt2.raw", "prophesee-raw-evt2", 640, 480, 521_252, 0),
    ("prophesee_samples/gen41_driving_evt3.raw", "prophesee-raw-evt3", 1280, 720, 219_596, 0),
    ("prophesee_samples/gen41_pedestrians_evt3.raw", "prophesee-raw-evt3", 1280, 720, 5_000, 0),
    ("prophesee_samples/ncars_obj_004397_td.dat", "prophesee-dat", 54, 61, 4_407, 0),
]


@needs_real
@pytest.mark.parametrize(("name", "fmt", "width", "height", "count", "imu"), REAL_FILES)
def test_real_files_decode_to_the_documented_counts(name: str, fmt: str, width: int, height: int, count: int,
                                                    imu: int) -> None:
    with open_recording(REAL / name) as rec:
        chunks = list(rec.chunks(max_events=50_000))
        samples = rec.imu()
    ev = np.concatenate(chunks)
    assert (rec.format, rec.width, rec.height, len(ev)) == (fmt, width, height, count)
    assert max(map(len, chunks)) <= 50_000  # bounded chunks
    assert np.all(np.diff(ev["t"]) >= 0)
    assert ev["x"].max() < width and ev["y"].max() < height and set(np.unique(ev["p"])) == {0, 1}
    assert (0 if samples is None else len(samples[0])) == imu


@needs_real
def test_davis_imu_reads_gravity_and_a_still_gyro() -> None:
    t, gyro, accel = open_recording(REAL / "davis240c_imu" / "IMU_translBoxes.aedat").imu()
    assert np.all(np.diff(t) > 0)
    assert np.linalg.norm(accel.mean(axis=0)) == pytest.approx(9.81, abs=0.5)
    assert np.abs(gyro.mean(axis=0)).max() < 0.2  # rad/s: bias only


@needs_real
@pytest.mark.parametrize(("name", "word"), [("prophesee_samples/gen3_sparklers_evt2.raw", 4),
                                            ("prophesee_samples/gen41_driving_evt3.raw", 2),
                                            ("davis240c_imu/IMU_translBoxes.aedat", 8),
                                            ("prophesee_samples/ncars_obj_004397_td.dat", 8)])
def test_truncated_files_deliver_the_good_events_then_name_the_offset(tmp_path: Path, name: str, word: int) -> None:
    data = (REAL / name).read_bytes()
    cut = len(data) - len(data) // 3
    cut -= (cut - (len(data) % word)) % word  # on a word boundary of the data, then one byte into a word
    path = tmp_path / Path(name).name
    path.write_bytes(data[:cut + 1])
    full = open_recording(REAL / name).read_all()
    got = []
    with pytest.raises(FormatError, match=rf"{path.name} at byte {cut}: truncated"):
        for chunk in open_recording(path).chunks(max_events=10_000):
            got.append(chunk)
    got = np.concatenate(got)
    assert 0.4 * len(full) < len(got) < len(full)
    assert np.isin(got["t"], full["t"]).all()


@needs_real
def test_ecd_text_matches_a_plain_parse_of_the_same_lines() -> None:
    path = REAL / "ecd_cuts_eventstppp" / "shapes_rotation" / "events.txt"
    rows = np.loadtxt(path)
    ev = open_recording(path).read_all()
    assert np.array_equal(ev["t"], np.round(rows[:, 0] * 1e6).astype(np.int64))
    assert np.array_equal(ev["x"], rows[:, 1]) and np.array_equal(ev["p"], rows[:, 3])


def test_corrupt_ecd_line_is_named_with_its_byte_offset_after_the_good_events(tmp_path: Path) -> None:
    good = "".join(f"{i * 1e-5:.9f} {i % 240} {i % 180} {i % 2}\n" for i in range(1000))
    (tmp_path / "events.txt").write_text(good + "0.5 12 oops 1\n" + good)
    rec = open_recording(tmp_path)
    got = []
    with pytest.raises(FormatError, match=rf"events.txt at byte {len(good)}: bad line b'0.5 12 oops 1'"):
        for chunk in rec.chunks(max_events=100):
            got.append(chunk)
    assert sum(map(len, got)) == 1000  # every good event before the fault was delivered


def test_h5_writer_round_trip_with_calibration_and_truth(tmp_path: Path) -> None:
    ev = _events(5000)
    K = np.array([[200.0, 0, 120], [0, 201, 90], [0, 0, 1]])
    boxes = np.array([[100, 1, 10, 20, 30, 40], [200, 1, 11, 20, 30, 40]], np.float64)
    with H5Writer(tmp_path / "a.h5", 240, 180) as w:
        w.write(ev[:3000])
        w.write(ev[3000:])
        w.write_calibration(Calibration(K, "radtan", np.array([0.1, 0.01, 0, 0, 0])))
        w.write_truth("boxes", boxes)
    with open_recording(tmp_path / "a.h5") as rec:
        assert rec.format == "etam-hdf5" and (rec.width, rec.height) == (240, 180)
        assert rec.read_all().tobytes() == ev.tobytes()
        assert [len(c) for c in rec.chunks(max_events=2000)] == [2000, 2000, 1000]
        assert np.array_equal(rec.calibration.K, K) and rec.calibration.dist_model == "radtan"
        assert np.array_equal(rec.truth.boxes, boxes) and rec.truth.present() == ["boxes"]


def test_dsec_style_h5_adds_t_offset(tmp_path: Path) -> None:
    with h5py.File(tmp_path / "d.h5", "w") as f:
        for k, v in (("x", [1, 2]), ("y", [3, 4]), ("t", [0, 5]), ("p", [1, 0])):
            f[f"events/{k}"] = np.asarray(v, {"t": "<u4", "p": "u1"}.get(k, "<u2"))
        f["t_offset"] = np.int64(1_000_000)
        f["ms_to_idx"] = np.zeros(1, np.uint64)
    rec = open_recording(tmp_path / "d.h5")
    assert rec.format == "dsec-hdf5" and (rec.width, rec.height) == (640, 480)
    assert rec.read_all()["t"].tolist() == [1_000_000, 1_000_005]


@pytest.mark.parametrize(("content", "message"), [
    (b"", "empty"), (b"\x00\x01garbage" * 10, "unknown event file format"),
    (b"\x89HDF\r\n\x1a\n" + b"\0" * 100, "not a readable HDF5 file"),
])
def test_unreadable_files_are_named(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.bin"
    path.write_bytes(content)
    with pytest.raises(FormatError, match=rf"bad.bin: .*{message}"):
        open_recording(path)
    with pytest.raises(SourceError, match="bad.bin"):
        open_sources(str(path))


def test_file_source_plays_loops_and_publishes_truth(tmp_path: Path) -> None:
    with H5Writer(tmp_path / "a.h5", 64, 48) as w:
        w.write(_events(100, t0=1_000))  # t = 1000 .. 1990
        w.write_truth("boxes", np.array([[1500, 7, 1, 2, 3, 4], [1500, 8, 5, 6, 7, 8], [1900, 7, 2, 2, 3, 4]]))
    src = FileSource(open_recording(tmp_path / "a.h5"), loop=True)
    assert src.start_us == 1000
    first = src.advance(1495)
    assert len(first) == 50 and first["t"][-1] == 1490
    (t, ids, boxes, solid), = src.truth(1000, 1600)
    assert t == 1500 and ids.tolist() == [7, 8] and boxes.shape == (2, 4)
    lap = src.advance(3000)  # the rest, then the second lap shifted to start after the first
    assert np.all(np.diff(lap["t"]) > 0) and lap["t"][50] == 1991 and not src.done
    once = FileSource(open_recording(tmp_path / "a.h5"))
    assert len(once.advance(10**9)) == 100 and once.done


def test_sim_and_info_commands(tmp_path: Path) -> None:
    out = tmp_path / "o.h5"
    sim = subprocess.run(etam_argv("sim", "objects", "--out", str(out), "--duration", "1", "--seed", "2", "--json"),
                         capture_output=True, text=True, timeout=120)
    assert sim.returncode == 0, sim.stderr
    summary = json.loads(sim.stdout)
    info = subprocess.run(etam_argv("info", str(out), "--json"), capture_output=True, text=True, timeout=60)
    facts = json.loads(info.stdout)
    assert facts["events"] == summary["events"] > 10_000 and facts["format"] == "etam-hdf5"
    assert (facts["width"], facts["height"]) == (346, 260) and facts["ground_truth"] == ["boxes", "boxes_3d", "ignore"]
    with open_recording(out) as rec:  # depth from size holds in the truth: w_px = f * size_m / z
        boxes, solid = rec.truth.boxes, rec.truth.boxes_3d
        inside = (boxes[:, 2] > 0) & (boxes[:, 2] + boxes[:, 4] < 345)  # not clipped at the image border
        f = rec.calibration.K[0, 0]
        assert len(solid) == len(boxes) and inside.any()
        assert np.allclose(boxes[inside, 4], f * solid[inside, 3] / solid[inside, 2], rtol=1e-3, atol=0.5)
    assert 0.9 < facts["duration_s"] <= 1.0 and facts["calibrated"]
    bad = subprocess.run(etam_argv("info", str(tmp_path / "nope.h5")), capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "nope.h5: no such file" in bad.stderr and "Traceback" not in bad.stderr


def test_a_file_played_as_fast_as_possible_reaches_a_subscriber_whole(tmp_path: Path, router: str, rig: str) -> None:
    from services.messages import EventPacket, Tracks, decode
    from tests.conftest import spawn, wait_for

    path = tmp_path / "o.h5"
    subprocess.run(etam_argv("sim", "objects", "--out", str(path), "--duration", "2", "--json"), check=True,
                   capture_output=True, timeout=120)
    expected = open_recording(path).read_all()
    packets: list[EventPacket] = []
    truth: list[Tracks] = []
    with client_session(router) as s:
        subs = [s.declare_subscriber(f"etam/{rig}/camera/cam0/events",
                                     lambda x: packets.append(decode(x.payload.to_bytes(), EventPacket))),
                s.declare_subscriber(f"etam/{rig}/camera/cam0/truth/boxes",
                                     lambda x: truth.append(decode(x.payload.to_bytes(), Tracks)))]
        with spawn("camera", "--source", str(path), "--rate", "0", "--connect", router, "--rig", rig):
            wait_for(lambda: sum(len(p.events) for p in packets) >= len(expected), 60, "every event of the file")
        for sub in subs:
            sub.undeclare()
    assert [p.seq for p in packets] == list(range(1, len(packets) + 1))  # no gaps
    got = np.concatenate([p.events for p in packets])
    assert got.tobytes() == expected.tobytes()
    assert len(truth) == len(np.unique(open_recording(path).truth.boxes[:, 0]))


@needs_real
def test_convert_chain_keeps_every_event_bytewise(tmp_path: Path) -> None:
    src = REAL / "tonic_samples" / "sample.aedat4"
    chain = [src, tmp_path / "a.h5", tmp_path / "b.aedat4", tmp_path / "ecd", tmp_path / "c.h5"]
    for a, b in zip(chain, chain[1:], strict=False):
        run = subprocess.run(etam_argv("convert", str(a), str(b), "--json"), capture_output=True, text=True,
                             timeout=120)
        assert run.returncode == 0, run.stderr
        assert json.loads(run.stdout)["events"] == 111_954
    original = open_recording(src).read_all()
    for path in chain[1:]:
        assert open_recording(path).read_all().tobytes() == original.tobytes(), path
    assert open_recording(tmp_path / "ecd").format == "ecd-text"


@needs_real
def test_dv_processing_reads_the_aedat4_etam_writes(tmp_path: Path) -> None:
    dv = pytest.importorskip("dv_processing")
    from services.camera.formats.aedat4 import Aedat4Writer

    events = open_recording(REAL / "prophesee_samples" / "gen41_driving_evt3.raw").read_all()
    with Aedat4Writer(tmp_path / "w.aedat4", 1280, 720) as w:
        w.write(events)
    rec = dv.io.MonoCameraRecording(str(tmp_path / "w.aedat4"))
    assert rec.getEventResolution() == (1280, 720)
    got = []
    while (batch := rec.getNextEventBatch()) is not None:
        got.append(batch.numpy())
    got = np.concatenate(got)
    assert len(got) == len(events)
    assert np.array_equal(got["timestamp"], events["t"]) and np.array_equal(got["x"], events["x"])
    assert np.array_equal(got["polarity"].astype(np.uint8), events["p"])


@needs_real
@pytest.mark.slow
def test_bench_readers_agree_with_the_peers_on_the_same_files() -> None:
    run = subprocess.run(etam_argv("bench", "--quick", "--only", "readers", "--json"), capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    rows = json.loads(run.stdout)["readers"]
    assert {r["stage"] for r in rows} == {"read EVT 2.0", "read EVT 3.0", "read AEDAT 4.0 (LZ4)"}
    for row in rows:
        if row["peer_error"] is None:  # every peer that runs decodes exactly as many events as ETAM
            assert row["peer_events"] == row["events"] > 100_000, row


@needs_real
def test_playing_a_davis_file_publishes_its_imu(router: str, rig: str) -> None:
    from services.messages import ImuPacket, decode
    from tests.conftest import spawn, wait_for

    samples: list[ImuPacket] = []
    with client_session(router) as s:
        sub = s.declare_subscriber(f"etam/{rig}/camera/cam0/imu",
                                   lambda x: samples.append(decode(x.payload.to_bytes(), ImuPacket)))
        with spawn("camera", "--source", str(REAL / "davis240c_imu" / "IMU_translBoxes.aedat"), "--rate", "0",
                   "--connect", router, "--rig", rig):
            wait_for(lambda: sum(len(p.t) for p in samples) >= 4_833, 60, "every IMU sample")
        sub.undeclare()
    t = np.concatenate([p.t for p in samples])
    accel = np.concatenate([p.accel for p in samples])
    assert len(t) == 4_833 and np.all(np.diff(t) > 0)
    assert np.linalg.norm(accel.mean(axis=0)) == pytest.approx(9.81, abs=0.5)


@pytest.mark.slow
def test_bench_writers_and_filters_run_and_report_every_figure() -> None:
    run = subprocess.run(etam_argv("bench", "--quick", "--only", "writers", "--only", "filters", "--json"),
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    results = json.loads(run.stdout)
    assert {r["stage"] for r in results["writers"]} == {"record MCAP (etam record)", "write AEDAT 4.0 (LZ4)"}
    assert all(r["etam_events_per_s"] > 0 and 0 < r["etam_bytes_per_event"] < 20 for r in results["writers"])
    (ba,) = results["filters"]
    assert ba["etam_noise_kept"] < 0.1 and ba["etam_signal_kept"] > 0.3  # selective on labelled noise


def test_sim_rotation_writes_events_poses_omega_and_panorama(tmp_path: Path) -> None:
    from scipy.spatial.transform import Rotation

    out = tmp_path / "rot.h5"
    run = subprocess.run(etam_argv("sim", "rotation", "--out", str(out), "--duration", "0.4", "--json"),
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    with open_recording(out) as rec:
        ev = rec.read_all()
        poses, omega = rec.truth.poses, rec.truth.omega
    with h5py.File(out) as f:
        assert f["truth/panorama"].shape == (1024, 2048)
    assert len(ev) > 10_000 and len(poses) == len(omega) == 20  # 50 Hz
    assert np.allclose(poses[:, 1:4], 0)  # rotation only
    # the truth is consistent: integrating omega (camera frame) reproduces the orientation change
    r = Rotation.from_quat(poses[0, 4:8])
    for i in range(1, len(poses)):
        dt = poses[i, 0] - poses[i - 1, 0]
        r = r * Rotation.from_rotvec((omega[i - 1, 1:] + omega[i, 1:]) / 2 * dt)
    err = (r.inv() * Rotation.from_quat(poses[-1, 4:8])).magnitude()
    assert np.rad2deg(err) < 0.5
    rate_early = (ev["t"] < 100_000).sum()
    rate_late = (ev["t"] > 300_000).sum()
    assert rate_late > 3 * rate_early  # the camera speeds up: more events


def test_sim_rotation_peak_scales_the_motion_and_is_checked(tmp_path: Path) -> None:
    from services.camera.rotation_scene import RotationScene

    assert np.degrees(RotationScene(seed=3).peak_speed()) == pytest.approx(616, abs=1)  # the default motion
    scene = RotationScene(seed=3, peak_deg_s=1000)
    speeds = [np.linalg.norm(scene.omega(t)) for t in np.linspace(0, scene.period_us, 2001)]
    assert np.degrees(max(speeds)) == pytest.approx(1000, rel=0.01)
    run = subprocess.run(etam_argv("sim", "6dof", "--peak", "900", "--out", str(tmp_path / "x.h5")),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode != 0 and "--peak" in run.stderr and "rotation" in run.stderr
    assert "Traceback" not in run.stderr and not (tmp_path / "x.h5").exists()


def test_live_rotation_source_publishes_truth_poses(router: str, rig: str) -> None:
    from services.messages import Pose, decode
    from tests.conftest import spawn, wait_for

    poses: list[Pose] = []
    with client_session(router) as s:
        sub = s.declare_subscriber(f"etam/{rig}/camera/cam0/truth/pose",
                                   lambda x: poses.append(decode(x.payload.to_bytes(), Pose)))
        with spawn("camera", "--source", "sim:rotation", "--connect", router, "--rig", rig):
            wait_for(lambda: len(poses) >= 5, 60, "truth poses")
        sub.undeclare()
    assert all(p.omega is not None and abs(np.linalg.norm(p.q) - 1) < 1e-9 for p in poses)
    assert [p.t for p in poses] == sorted(p.t for p in poses)


def test_sim_6dof_writes_events_poses_and_depth_maps(tmp_path: Path) -> None:
    from services.camera.sixdof_scene import SixDofScene

    out = tmp_path / "6d.h5"
    run = subprocess.run(etam_argv("sim", "6dof", "--out", str(out), "--duration", "0.3", "--json"),
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    with h5py.File(out) as f:
        t, maps = f["truth/depth/t"][:], f["truth/depth/maps"][:]
        poses = f["truth/poses"][:]
    assert json.loads(run.stdout)["events"] > 10_000
    assert t.tolist() == [100_000, 200_000, 300_000] and maps.shape == (3, 260, 346)
    assert np.isfinite(maps).all() and 0.5 < maps.min() and maps.max() < 5.5  # boxes to the back wall
    assert np.linalg.norm(poses[-1, 1:4]) > 0.01  # the camera moves
    at_rest = SixDofScene().depth(0)  # at t = 0 the camera is the world frame: the back wall is at z = 5
    assert np.isclose(at_rest.max(), 5.0, atol=1e-3)


@pytest.fixture(scope="module")
def stereo_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("stereo") / "st.h5"
    run = subprocess.run(etam_argv("sim", "stereo", "--out", str(out), "--duration", "0.2", "--json"),
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["cameras"] == 2
    return out


def test_sim_stereo_is_two_cameras_on_a_known_baseline_seeing_the_same_scene(stereo_file: Path) -> None:
    from scipy.spatial.transform import Rotation

    from services.camera.sources import STEREO_BASELINE_M

    left, right = open_recording(stereo_file).rig()
    assert (left.cameras, right.width, right.height) == (["cam0", "cam1"], 346, 260)
    assert np.allclose(right.calibration.T_body_cam[:3, 3], [STEREO_BASELINE_M, 0, 0])
    ev_l, ev_r = left.read_all(), right.read_all()
    assert len(ev_l) > 10_000 and len(ev_r) > 10_000 and ev_l.tobytes() != ev_r.tobytes()
    # the right camera's pose is the left's moved by the baseline along the left camera's x axis
    pl, pr = left.truth.poses, right.truth.poses
    assert np.allclose(pl[:, 0], pr[:, 0]) and np.allclose(pl[:, 4:], pr[:, 4:])
    offset = Rotation.from_quat(pl[:, 4:]).apply([STEREO_BASELINE_M, 0, 0])
    assert np.allclose(pr[:, 1:4] - pl[:, 1:4], offset, atol=1e-9)
    # a left depth map, moved into the right camera, agrees with the right depth map where both see it
    K = left.calibration.K
    zl, zr = left.truth.depth_maps[-1], right.truth.depth_maps[-1]
    ys, xs = np.mgrid[0:260, 0:346]
    pts = np.stack([(xs - K[0, 2]) / K[0, 0] * zl, (ys - K[1, 2]) / K[1, 1] * zl, zl], -1).reshape(-1, 3)
    pts[:, 0] -= STEREO_BASELINE_M  # same orientation: the right camera frame is shifted along x
    u = np.round(K[0, 0] * pts[:, 0] / pts[:, 2] + K[0, 2]).astype(int)
    v = np.round(K[1, 1] * pts[:, 1] / pts[:, 2] + K[1, 2]).astype(int)
    inside = (u >= 0) & (u < 346) & (v >= 0) & (v < 260)
    err = np.abs(zr[v[inside], u[inside]] - pts[inside, 2]) / pts[inside, 2]
    assert inside.mean() > 0.8 and np.median(err) < 0.01 and (err < 0.05).mean() > 0.9  # occlusion edges differ


def test_a_stereo_file_plays_both_cameras_with_calibration_and_depth(stereo_file: Path, router: str,
                                                                    rig: str) -> None:
    from services.messages import CameraInfo, EventPacket, Image, decode, image_to_array
    from tests.conftest import spawn, wait_for

    cams = open_recording(stereo_file).rig()
    packets: dict[str, list[EventPacket]] = {"cam0": [], "cam1": []}
    depth: dict[str, list[Image]] = {"cam0": [], "cam1": []}

    def on(store: dict, kind: type):  # noqa: ANN202 - a zenoh callback
        return lambda s: store[str(s.key_expr).split("/")[3]].append(decode(s.payload.to_bytes(), kind))

    with client_session(router) as s:
        subs = [s.declare_subscriber(f"etam/{rig}/camera/*/events", on(packets, EventPacket)),
                s.declare_subscriber(f"etam/{rig}/camera/*/truth/depth", on(depth, Image))]
        with spawn("camera", "--source", str(stereo_file), "--rate", "0", "--connect", router, "--rig", rig):
            wait_for(lambda: all(sum(len(p.events) for p in packets[name]) >= cam.n_events
                                 for name, cam in zip(packets, cams, strict=True)), 60, "every event of both cameras")
            wait_for(lambda: all(len(d) == 2 for d in depth.values()), 10, "both depth maps of both cameras")
            info = decode(s.get(f"etam/{rig}/camera/cam1/info").__next__().ok.payload.to_bytes(), CameraInfo)
        for sub in subs:
            sub.undeclare()
    for cam, name in zip(cams, ("cam0", "cam1"), strict=True):
        got = np.concatenate([p.events for p in packets[name]])
        assert got.tobytes() == cam.read_all().tobytes()
        assert [p.seq for p in packets[name]] == list(range(1, len(packets[name]) + 1))
        assert [d.t for d in depth[name]] == cam.truth.depth_t.tolist()
        assert np.array_equal(image_to_array(depth[name][-1]), cam.truth.depth_maps[-1], equal_nan=True)
    assert np.allclose(info.T_body_cam, cams[1].calibration.T_body_cam)


@needs_real
def test_bench_playback_delivers_every_event_of_a_dense_file() -> None:
    from benchmarks import playback

    (row,) = playback.run(quick=True)
    assert row["complete"] and row["seq_gaps"] == 0 and row["events"] == [row["file_events"]]
    assert row["file_events"] > 8_000_000 and row["events_per_s"] > 0


def test_bench_simulator_times_every_scene() -> None:
    run = subprocess.run(etam_argv("bench", "--quick", "--only", "simulator", "--json"), capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    rows = {r["stage"]: r for r in json.loads(run.stdout)["simulator"]}
    assert set(rows) == {f"camera.simulator.{s}" for s in ("objects", "rotation", "6dof", "stereo")}
    assert all(r["events"] > 1000 and r["realtime_factor"] > 0 for r in rows.values())


def test_bench_transport_sets_zenoh_beside_dv_network_transport() -> None:
    run = subprocess.run(etam_argv("bench", "--quick", "--only", "transport", "--json"), capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    rows = json.loads(run.stdout)["transport"]
    assert all(r["lost_messages"] == 0 for r in rows)
    (peer,) = [r for r in rows if r["offered_events_per_s"] == "max"]
    assert peer["peer_complete"] and peer["ratio"] > 0 and peer["ingest_ratio"] > 0
