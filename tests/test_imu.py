"""The IMU: the simulated one of the moving-camera scenes, carried in ETAM HDF5, and its gyro predicting the
6-DoF tracker's rotation with a bias learnt from the vision."""

from __future__ import annotations

import json
import subprocess

import numpy as np
from scipy.spatial.transform import Rotation

from services.camera.formats import open_recording
from services.camera.sim_imu import GRAVITY_M_S2, SimulatedImu
from services.camera.simulator import SimParams
from services.camera.sixdof_scene import SixDofScene
from services.tracker.ego.gyro import Gyro
from services.tracker.ego.sixdof import TRACKING, SixDofTracker
from tests.conftest import etam_argv
from tests.test_sixdof import K, H, W, box_edges, edge_events


def test_simulated_imu_reads_the_scenes_motion_with_noise_and_a_bias() -> None:
    """Without noise, the gyro is the scene's body rate (its truth `omega`) and the accelerometer reads gravity
    pointing up (-y) in the camera's frame plus the camera's acceleration; with the default noise, samples come
    every millisecond, off by a constant bias of some tenths of a degree per second and a white noise of
    0.01 deg/s/sqrt(Hz) (0.32 deg/s a sample at 1 kHz)."""
    scene = SixDofScene(seed=4)
    quiet = SimParams(gyro_noise=0.0, gyro_bias=0.0, accel_noise=0.0, accel_bias=0.0)
    t, gyro, accel = SimulatedImu(scene, quiet).samples(0, 2_000_000)
    assert len(t) == 2000 and t[0] == 1000 and t[-1] == 2_000_000
    truth = np.array([scene.omega(ti) for ti in t[::100]])
    assert np.abs(gyro[::100] - truth).max() < 1e-4
    h = 1e-3  # the camera's acceleration by central differences over 1 ms, rotated into its frame
    for ti in (400_000, 1_300_000):
        a = (scene.position(ti + 1e3) - 2 * scene.position(ti) + scene.position(ti - 1e3)) / h ** 2
        i = int(np.searchsorted(t, ti))
        want = scene.rotation(ti).inv().apply(a - [0.0, GRAVITY_M_S2, 0.0])
        assert np.allclose(accel[i], want, atol=1e-3)
    assert np.linalg.norm(accel, axis=1).mean() > 9.5  # gravity, the camera's motion a small part of it

    noisy = SimulatedImu(scene, SimParams(), seed=4)
    t, gyro, _ = noisy.samples(0, 4_000_000)
    off = gyro - SimulatedImu(scene, quiet).samples(0, 4_000_000)[1]
    assert np.allclose(off.mean(axis=0), noisy.gyro_bias, atol=np.radians(0.02))
    assert 0.05 < np.degrees(np.linalg.norm(noisy.gyro_bias)) < 3.0
    assert np.allclose(np.degrees(off.std(axis=0)), 0.01 * np.sqrt(1000), rtol=0.1)
    again = SimulatedImu(scene, SimParams(), seed=4).samples(0, 4_000_000)[1]
    assert np.array_equal(again, gyro)  # the same seed, the same samples


def test_sim_files_carry_the_imu_of_the_moving_camera(tmp_path) -> None:  # noqa: ANN001
    """`etam sim 6dof` writes the IMU into the file (`/imu/t`, `/imu/gyro`, `/imu/accel`), `etam info` counts it,
    a stereo rig has it on its first camera only, a copy to HDF5 keeps it, and the objects scene (a still camera)
    has none."""
    h5 = tmp_path / "6dof.h5"
    made = subprocess.run(etam_argv("sim", "6dof", "--out", str(h5), "--duration", "0.3", "--json"),
                          capture_output=True, text=True, timeout=120, check=True)
    assert json.loads(made.stdout)["imu_samples"] == 300
    info = subprocess.run(etam_argv("info", str(h5), "--json"), capture_output=True, text=True, timeout=60, check=True)
    assert json.loads(info.stdout)["imu_samples"] == 300
    with open_recording(h5) as rec:
        t, gyro, accel = rec.imu()
        truth = rec.truth.omega
    assert gyro.shape == accel.shape == (300, 3) and np.all(np.diff(t) == 1000)
    at = np.searchsorted(t, truth[:, 0] * 1e6)  # the truth's times are sample times
    assert np.degrees(np.abs(gyro[at] - truth[:, 1:]).max()) < 3.0  # bias and noise, no more

    copy = tmp_path / "copy.h5"
    subprocess.run(etam_argv("convert", str(h5), str(copy)), capture_output=True, timeout=60, check=True)
    with open_recording(copy) as rec:
        assert np.array_equal(rec.imu()[1], gyro)

    rig = tmp_path / "stereo.h5"
    subprocess.run(etam_argv("sim", "stereo", "--out", str(rig), "--duration", "0.1", "--json"), capture_output=True,
                   timeout=120, check=True)
    with open_recording(rig) as rec:
        left, right = rec.rig()
        assert len(left.imu()[0]) == 100 and right.imu() is None
    still = tmp_path / "objects.h5"
    subprocess.run(etam_argv("sim", "objects", "--out", str(still), "--duration", "0.1", "--json"),
                   capture_output=True, timeout=120, check=True)
    with open_recording(still) as rec:
        assert rec.imu() is None


def _samples(omega: np.ndarray, bias: np.ndarray, until_us: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(1000, until_us + 1, 1000, dtype=np.int64)
    return t, np.tile(omega + bias, (len(t), 1))


def test_gyro_turns_between_two_times_and_learns_its_bias_from_the_vision() -> None:
    """A turn at a steady rate: the gyro's turn over a span is the rate times its length (off by its bias until
    learnt); the turns the vision saw make the bias estimate converge on the true one; a span the samples do not
    cover (before the first, beyond the last by more than 20 ms, or across a gap) gives none."""
    omega, bias = np.radians([5.0, -20.0, 3.0]), np.radians([0.6, -0.4, 0.3])
    gyro = Gyro()
    gyro.add(*_samples(omega, bias, 3_000_000))
    turn = gyro.turn(100_000, 120_000)
    assert np.allclose(Rotation.from_matrix(turn).as_rotvec(), (omega + bias) * 0.02, atol=1e-9)
    for t0 in range(100_000, 2_900_000, 20_000):  # what a tracker following the turn without error sees
        seen = Rotation.from_rotvec(omega * 0.02).as_matrix()
        gyro.learn(t0, t0 + 20_000, seen)
    assert np.linalg.norm(gyro.bias - bias) < 0.1 * np.linalg.norm(bias)  # 140 updates at a gain of 0.02: 6 % left
    assert np.allclose(Rotation.from_matrix(gyro.turn(100_000, 120_000)).as_rotvec(), omega * 0.02, atol=2e-5)
    assert gyro.turn(0, 20_000) is None  # before the first sample
    assert gyro.turn(3_000_000, 3_030_000) is None  # the samples stop 30 ms short
    assert gyro.turn(2_990_000, 3_010_000) is not None  # 10 ms short: the last rate holds
    gappy = Gyro()
    t, w = _samples(omega, bias, 1_000_000)
    keep = (t < 400_000) | (t > 450_000)
    gappy.add(t[keep], w[keep])
    assert gappy.turn(380_000, 480_000) is None and gappy.turn(460_000, 480_000) is not None
    gappy.add(t[:10], w[:10])  # samples older than the latest are left out
    gappy.forget_before(500_000)
    assert gappy.turn(480_000, 520_000) is None and gappy.turn(500_000, 520_000) is not None


def test_the_6dof_tracker_turns_with_the_gyro_and_learns_its_bias() -> None:
    """The camera of `test_sixdof`'s scene moving sideways and turning (0.3 m/s, 10 deg/s) with a gyro 1 deg/s off:
    the tracker follows it within 1 cm, learning the bias on the way (under half of it left after 1 s); lost on
    uniform noise for 0.2 s, its prediction still turns as the gyro says (0.2 s at 10 deg/s is 2 deg) and goes on
    at the last velocity."""
    points = box_edges()
    velocity, omega = np.array([0.3, 0.0, 0.1]), np.radians([0.0, 10.0, 0.0])
    bias = np.radians([0.6, -0.6, 0.5])  # about 1 deg/s
    events = edge_events(points, velocity, omega, 1.0)
    gyro = Gyro()
    gyro.add(*_samples(omega, bias, 1_400_000))
    tracker = SixDofTracker(K, W, H, gyro=gyro)
    tracker.add_points(points)
    tracker.start(0, np.eye(3), np.zeros(3))
    estimates = [e for chunk in np.array_split(events, 200) for e in tracker.add(chunk)]
    assert len(estimates) >= 45 and all(e.state == TRACKING for e in estimates)
    assert np.linalg.norm(estimates[-1].p - velocity * estimates[-1].t_us * 1e-6) < 0.01
    assert np.linalg.norm(gyro.bias - bias) < 0.5 * np.linalg.norm(bias)

    R_last = estimates[-1].R  # camera to world
    t_last = estimates[-1].t_us
    rng = np.random.default_rng(3)
    noise = np.zeros(20_000, events.dtype)
    noise["t"] = np.sort(rng.integers(1_000_000, 1_200_000, len(noise)))
    noise["x"], noise["y"] = rng.integers(0, W, len(noise)), rng.integers(0, H, len(noise))
    tracker.add(noise)
    R0, t0, turned = tracker._predict(1_200_000)
    assert turned
    want = R_last @ Rotation.from_rotvec(omega * (1_200_000 - t_last) * 1e-6).as_matrix()
    assert np.degrees(Rotation.from_matrix(R0.T @ want.T).magnitude()) < 0.3
    (t_a, R_a, c_a), (t_b, R_b, c_b) = tracker._poses[0], tracker._poses[-1]  # the good poses kept (T_cam_world)
    centre_a, centre_b = -R_a.T @ c_a, -R_b.T @ c_b
    went = centre_b + (centre_b - centre_a) / (t_b - t_a) * (1_200_000 - t_b)  # on at their velocity
    assert np.linalg.norm(-R0.T @ t0 - went) < 1e-6 and np.linalg.norm(went - centre_b) > 0.02
