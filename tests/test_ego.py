"""Ego-motion: the rotation contrast's gradient, and angular velocity and orientation recovered from the
events of a camera turning at a known rate in a field of stars (points at infinity)."""

from __future__ import annotations

import json
import subprocess

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry import unit_rays
from services.mapper.trajectory import read_tum
from services.tracker.ego.contrast import RotationContrast
from services.tracker.ego.evaluation import evaluate_odometry
from services.tracker.ego.rotation import LOST, STILL, TRACKING, RotationParams, RotationTracker, warm_up
from tests.conftest import etam_argv

W, H = 240, 180
K = np.array([[200.0, 0, 120], [0, 200.0, 90], [0, 0, 1]])


def star_events(omega: np.ndarray, duration_s: float, seed: int = 0, step_us: int = 200,
                share: float = 0.3) -> np.ndarray:
    """Events of a camera turning at `omega` (rad/s, camera frame) from R = I: each step, a `share` of
    the stars in view fires one event at its pixel."""
    rng = np.random.default_rng(seed)
    stars = rng.normal(size=(6000, 3))
    stars /= np.linalg.norm(stars, axis=1, keepdims=True)
    chunks = []
    for t_us in range(0, int(duration_s * 1e6), step_us):
        cam = stars @ Rotation.from_rotvec(omega * t_us * 1e-6).as_matrix()  # R^T d for each star
        front = cam[:, 2] > 0.1
        u = K[0, 0] * cam[front, 0] / cam[front, 2] + K[0, 2]
        v = K[1, 1] * cam[front, 1] / cam[front, 2] + K[1, 2]
        seen = (u >= 0) & (u < W - 0.5) & (v >= 0) & (v < H - 0.5) & (rng.random(len(u)) < share)
        ev = np.zeros(int(seen.sum()), [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
        ev["t"], ev["x"], ev["y"], ev["p"] = t_us + rng.integers(0, step_us, len(ev)), np.rint(u[seen]), \
            np.rint(v[seen]), 1
        chunks.append(np.sort(ev, order="t"))
    return np.concatenate(chunks)


def test_contrast_gradient_matches_finite_differences_and_peaks_at_the_true_rate():
    omega = np.array([0.5, -2.0, 1.0])
    ev = star_events(omega, 0.03)
    contrast = RotationContrast(K, W, H)
    mid = ev["t"].mean()
    contrast.set_events(unit_rays(K, ev["x"], ev["y"]), (ev["t"] - mid) * 1e-6)
    for w in (omega * 0.8, omega + np.array([0.3, 0.2, -0.4])):
        value, grad = contrast(w)
        numeric = [(contrast(w + e * 1e-3)[0] - contrast(w - e * 1e-3)[0]) / 2e-3 for e in np.eye(3)]
        np.testing.assert_allclose(grad, numeric, rtol=0.1, atol=1e-3 * np.abs(numeric).max())
    assert contrast(omega)[0] > contrast(0.9 * omega)[0] > contrast(np.zeros(3))[0]


def test_tracker_recovers_the_angular_velocity_and_integrates_the_orientation():
    omega = np.array([0.5, -2.0, 1.0])  # 130 deg/s
    ev = star_events(omega, 0.3)
    tracker = RotationTracker(K, W, H, RotationParams(step_us=10_000))
    estimates = [e for k in range(0, len(ev), 5000) for e in tracker.add(ev[k:k + 5000])]
    assert len(estimates) >= 25 and all(e.state == TRACKING for e in estimates)
    times = [e.t_us for e in estimates]
    assert times == sorted(times)
    errors = [np.linalg.norm(e.omega - omega) / np.linalg.norm(omega) for e in estimates[3:]]
    assert np.median(errors) < 0.02
    last = estimates[-1]
    truth = Rotation.from_rotvec(omega * last.t_us * 1e-6)
    assert np.degrees((truth.inv() * Rotation.from_quat(last.quat)).magnitude()) < 0.5


@pytest.mark.parametrize("omega", [(0.5, -5.0, 2.0), (0.0, 0.0, 12.0), (10.0, 0.0, 0.0), (-6.0, 9.0, 4.0)])
def test_a_tracker_joining_a_fast_turn_finds_its_rate_at_once(omega):
    """A cold start on a camera already turning at 300-700 deg/s (about the optical axis too): the first
    estimate is within 2 % of the rate (sharp events from w = 0 have no slope toward it)."""
    omega = np.array(omega)
    ev = star_events(omega, 0.05)
    tracker = RotationTracker(K, W, H)
    estimates = [e for k in range(0, len(ev), 5000) for e in tracker.add(ev[k:k + 5000])]
    errors = [np.linalg.norm(e.omega - omega) / np.linalg.norm(omega) for e in estimates]
    assert len(errors) >= 4 and max(errors) < 0.02, errors


def test_noise_is_lost_not_a_rate_and_a_turn_after_it_is_found_again():
    """Uniform noise at 1 Mev/s (no motion explains it): every window is LOST with w = 0, none TRACKING
    at a made-up rate (without the state it reported 800-1100 deg/s); a turn that follows is tracked."""
    rng = np.random.default_rng(0)
    noise = np.zeros(200_000, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    noise["t"], noise["x"], noise["y"] = np.sort(rng.integers(0, 200_000, len(noise))), \
        rng.integers(0, W, len(noise)), rng.integers(0, H, len(noise))
    omega = np.array([0.5, -5.0, 2.0])
    turn = star_events(omega, 0.1)
    turn["t"] += 200_000
    tracker = RotationTracker(K, W, H)
    lost = tracker.add(noise)
    assert len(lost) >= 15 and all(e.state == LOST and not e.omega.any() for e in lost)
    found = [e for k in range(0, len(turn), 5000) for e in tracker.add(turn[k:k + 5000])]
    assert found[-1].state == TRACKING and np.linalg.norm(found[-1].omega - omega) < 0.02 * np.linalg.norm(omega)


def test_a_still_scene_is_a_still_camera():
    ev = star_events(np.zeros(3), 0.1, share=0.002)  # a few events: noise, not motion
    estimates = RotationTracker(K, W, H).add(ev)
    assert estimates and all(e.state == STILL and not e.omega.any() for e in estimates)
    np.testing.assert_allclose(estimates[-1].quat, [0, 0, 0, 1])


def _turning(rate: np.ndarray, seconds: float = 5.0, hz: float = 50.0, radius_m: float = 0.0) -> np.ndarray:
    """TUM rows of a camera turning at `rate` (rad/s) from R = I, moving on a circle of `radius_m`."""
    t = np.arange(0, seconds, 1 / hz)
    quat = Rotation.from_rotvec(np.outer(t, rate)).as_quat()
    pos = radius_m * np.column_stack([np.cos(t), np.sin(t), 0.3 * t])
    return np.column_stack([t, pos, quat])


def test_eval_odometry_scores_known_errors():
    rate = np.array([0.2, -1.0, 0.5])
    truth = _turning(rate, radius_m=1.0)
    exact = evaluate_odometry(truth, truth)
    assert exact["alignment"] == "se3" and exact["ate_m"] < 1e-9 and exact["omega_rms_deg_s"] < 1e-6
    # 2 % too fast: the rate error is 2 % of the (constant) peak, the orientation 2 % of the angle turned
    fast = _turning(1.02 * rate, radius_m=1.0)
    scores = evaluate_odometry(fast, truth, align="origin")
    assert scores["omega_rms_of_peak"] == pytest.approx(0.02, rel=0.02)
    turned = np.degrees(np.linalg.norm(rate) * truth[-1, 0])
    assert scores["final_rot_err_deg"] == pytest.approx(0.02 * turned, rel=0.02)
    assert scores["rpe_deg_per_s"] == pytest.approx(0.02 * np.degrees(np.linalg.norm(rate)), rel=0.05)
    # twice the size: only a similarity aligns it
    scaled = truth.copy()
    scaled[:, 1:4] *= 2
    assert evaluate_odometry(scaled, truth, align="se3")["ate_m"] > 0.1
    assert evaluate_odometry(scaled, truth, align="sim3")["ate_m"] < 1e-6
    with pytest.raises(ValueError, match="span space"):
        evaluate_odometry(_turning(rate), _turning(rate), align="se3")


def test_odom_and_eval_odometry_commands(tmp_path):
    h5, tum = tmp_path / "rot.h5", tmp_path / "traj.tum"
    subprocess.run(etam_argv("sim", "rotation", "--out", str(h5), "--duration", "0.5", "--seed", "4", "--json"),
                   check=True, capture_output=True, timeout=120)
    made = subprocess.run(etam_argv("odom", str(h5), "--out", str(tum), "--json"), capture_output=True, text=True,
                          timeout=120)
    assert made.returncode == 0, made.stderr
    assert json.loads(made.stdout)["poses"] == len(read_tum(str(tum))) >= 45
    scored = subprocess.run(etam_argv("eval", "odometry", "--pred", str(tum), "--truth", str(h5), "--json"),
                            capture_output=True, text=True, timeout=120)
    assert scored.returncode == 0, scored.stderr
    scores = json.loads(scored.stdout)
    assert scores["alignment"] == "origin" and scores["omega_rms_of_peak"] < 0.03 and scores["final_rot_err_deg"] < 1
    wrong = subprocess.run(etam_argv("eval", "odometry", "--pred", str(h5), "--truth", str(h5)), capture_output=True,
                           text=True, timeout=120)
    assert wrong.returncode != 0 and "not a TUM trajectory" in wrong.stderr and "Traceback" not in wrong.stderr


def test_panoramic_map_pulls_a_drifted_orientation_back():
    """A window mapped at its true orientation, then seen again with the orientation 1 degree off: aligning
    its warped events to the map brings it back within 0.2 degrees; with nothing mapped there it is kept."""
    from services.tracker.ego.panorama import PanoramaMap

    ev = star_events(np.zeros(3), 0.05, share=0.5)
    contrast = RotationContrast(K, W, H)
    contrast.set_events(unit_rays(K, ev["x"], ev["y"]), np.zeros(len(ev)))
    image = contrast.iwe(np.zeros(3)).copy()
    pano = PanoramaMap(K, W, H)
    truth = Rotation.from_euler("YXZ", [30, -10, 5], degrees=True)
    pano.insert(cv2.GaussianBlur(image, (0, 0), 1.0), truth)
    off = truth * Rotation.from_rotvec(np.radians([0.6, -0.5, 0.6]))
    rays = unit_rays(K, ev["x"], ev["y"])
    aligned = pano.align(rays, off)
    assert np.degrees((truth.inv() * off).magnitude()) > 0.9
    assert np.degrees((truth.inv() * aligned).magnitude()) < 0.2
    away = Rotation.from_euler("Y", 180, degrees=True) * off  # looking where nothing was mapped
    assert np.allclose(pano.align(rays, away).as_quat(), away.as_quat())


def test_the_rotation_warm_up_tracks_its_pan_so_every_kernel_of_an_update_loads(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The live service runs it before its first events (`services.kernels`): a scene it did not track would
    leave the panorama's kernels to compile on the camera's first turn."""
    aligned = []
    monkeypatch.setattr(RotationTracker, "_track_map", lambda self, est: aligned.append(est.state))
    warm_up()
    assert len(aligned) >= 20 and set(aligned) == {TRACKING}
