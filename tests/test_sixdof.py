"""6-DoF ego-motion: the map-to-events alignment on a scene of known edges, the lost state, and the
tracking-mapping loop as `etam odom --mode 6dof` runs it."""

from __future__ import annotations

import json
import subprocess

import numpy as np
from scipy.spatial.transform import Rotation

from services.mapper.trajectory import read_tum
from services.tracker.ego.loop import MapRefresh, MappedOdometry, RefreshParams, loop_params
from services.tracker.ego.sixdof import (LOST, TRACKING, PoseEstimate, SixDofParams, SixDofTracker, align,
                                         distance_field)
from tests.conftest import etam_argv

W, H = 346, 260
K = np.array([[311.4, 0, 173.0], [0, 311.4, 130.0], [0, 0, 1]])
EVENT_DTYPE = [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")]


def box_edges(seed: int = 0, n_boxes: int = 6, per_edge: int = 120) -> np.ndarray:
    """World points along the 12 edges of boxes 2-4 m in front of the camera at the origin."""
    rng = np.random.default_rng(seed)
    points = []
    for _ in range(n_boxes):
        lo = np.array([rng.uniform(-1.2, 0.8), rng.uniform(-0.8, 0.4), rng.uniform(2.0, 4.0)])
        hi = lo + rng.uniform(0.3, 0.6, 3)
        corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1)
                            for k in (0, 1)])
        for a in range(8):
            for b in range(a + 1, 8):
                if bin(a ^ b).count("1") == 1:  # corners differing on one axis share an edge
                    s = np.linspace(0, 1, per_edge)[:, None]
                    points.append(corners[a] + s * (corners[b] - corners[a]))
    return np.concatenate(points)


def project(points: np.ndarray, R_cw: np.ndarray, t_cw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (rounded, in the image) where world points are seen from T_cam_world."""
    X = points @ R_cw.T + t_cw
    u, v = K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2], K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]
    keep = (X[:, 2] > 0.1) & (u >= 0) & (u < W - 0.5) & (v >= 0) & (v < H - 0.5)
    return np.rint(u[keep]).astype(int), np.rint(v[keep]).astype(int)


def pose_error(R_cw: np.ndarray, t_cw: np.ndarray, R_true: np.ndarray, t_true: np.ndarray) -> tuple[float, float]:
    """Camera centre error (m) and orientation error (deg) of T_cam_world against the truth."""
    turn = np.degrees(Rotation.from_matrix(R_cw @ R_true.T).magnitude())
    return float(np.linalg.norm(R_cw.T @ t_cw - R_true.T @ t_true)), float(turn)


def test_alignment_brings_an_offset_pose_back_onto_the_edges():
    """The map's edges seen from a known pose (events at whole pixels): from 1 degree and 3 cm off, the
    alignment finds the pose within 0.25 degree (1.4 px) and 1 cm, and says the edges explain its points;
    on uniform noise it says they do not."""
    points = box_edges()
    R_true = Rotation.from_euler("YXZ", [4, -2, 1], degrees=True).as_matrix()
    t_true = np.array([0.05, -0.02, 0.1])
    u, v = project(points, R_true, t_true)
    params = SixDofParams()
    fields = [(s, distance_field(u, v, W, H, s, params.truncate_px)) for s in params.scales]
    R0 = Rotation.from_rotvec(np.radians([0.6, -0.6, 0.5])).as_matrix() @ R_true
    t0 = t_true + np.array([0.02, -0.02, 0.01])
    assert pose_error(R0, t0, R_true, t_true)[1] > 0.9
    sample = points[np.random.default_rng(1).choice(len(points), 3000, replace=False)]
    R, t, share = align(sample, R0, t0, fields, K, params)
    moved, turned = pose_error(R, t, R_true, t_true)
    assert moved < 0.01 and turned < 0.25, (moved, turned)
    assert share > 0.8
    rng = np.random.default_rng(2)
    noise = [(s, distance_field(rng.integers(0, W, len(u)), rng.integers(0, H, len(u)), W, H, s, params.truncate_px))
             for s in params.scales]
    assert align(sample, R_true, t_true, noise, K, params)[2] < params.min_inliers


def edge_events(points: np.ndarray, velocity: np.ndarray, omega: np.ndarray, duration_s: float,
                step_us: int = 1000, seed: int = 0) -> np.ndarray:
    """Events of a camera moving from the origin at `velocity` (m/s, world) turning at `omega` (rad/s): each
    step, a third of the edges' points in view fire once."""
    rng = np.random.default_rng(seed)
    chunks = []
    for t_us in range(0, int(duration_s * 1e6), step_us):
        R_wc = Rotation.from_rotvec(omega * t_us * 1e-6).as_matrix()
        u, v = project(points, R_wc.T, -R_wc.T @ (velocity * t_us * 1e-6))
        pick = rng.random(len(u)) < 0.33
        ev = np.zeros(int(pick.sum()), EVENT_DTYPE)
        ev["t"], ev["x"], ev["y"], ev["p"] = t_us + rng.integers(0, step_us, len(ev)), u[pick], v[pick], 1
        chunks.append(np.sort(ev, order="t"))
    return np.concatenate(chunks)


def test_tracker_follows_a_moving_camera_and_is_lost_on_noise():
    """Started at the true pose with the map, the tracker follows 1 s of a camera moving sideways and turning
    (0.3 m/s, 10 deg/s) within 1 cm; fed uniform noise instead, each update is lost and gives no pose."""
    points = box_edges()
    velocity, omega = np.array([0.3, 0.0, 0.1]), np.radians([0.0, 10.0, 0.0])
    events = edge_events(points, velocity, omega, 1.0)
    tracker = SixDofTracker(K, W, H)
    tracker.add_points(points)
    tracker.start(0, np.eye(3), np.zeros(3))
    estimates = [e for chunk in np.array_split(events, 200) for e in tracker.add(chunk)]
    assert len(estimates) >= 45 and all(e.state == TRACKING for e in estimates)
    last = estimates[-1]
    t_s = last.t_us * 1e-6
    assert np.linalg.norm(last.p - velocity * t_s) < 0.01
    assert np.degrees(Rotation.from_matrix(last.R.T @ Rotation.from_rotvec(omega * t_s).as_matrix()).magnitude()) < 0.5
    rng = np.random.default_rng(3)
    noise = np.zeros(len(events), EVENT_DTYPE)
    noise["t"], noise["x"], noise["y"] = events["t"] + 1_000_000, rng.integers(0, W, len(events)), \
        rng.integers(0, H, len(events))
    after = [e for chunk in np.array_split(noise, 100) for e in tracker.add(chunk)]
    lost = [e for e in after if e.t_us >= 1_020_000]  # once the window holds noise alone
    assert len(lost) >= 45 and all(e.state == LOST for e in lost)


def test_map_follower_starts_on_known_poses_and_the_first_map_then_goes_on_alone(monkeypatch):  # noqa: ANN001
    """The live loop's tracker: with known poses and no map it gives nothing (the service passes the known
    ones on); when the first part of the map comes, it starts at the last known pose, the events it held filling
    its window, and gives its own estimates from there on, within 1 cm, with the camera's angular velocity;
    known poses after that are not taken."""
    from services.tracker.ego.follow import MapFollower

    points = box_edges()
    velocity, omega = np.array([0.3, 0.0, 0.1]), np.radians([0.0, 10.0, 0.0])
    events = edge_events(points, velocity, omega, 1.0)
    follower = MapFollower(K, W, H)

    def true_pose(t_us: int) -> tuple[np.ndarray, np.ndarray]:
        return Rotation.from_rotvec(omega * t_us * 1e-6).as_quat(), velocity * t_us * 1e-6

    chunks = np.array_split(events, 200)  # 5 ms each
    for chunk in chunks[:100]:  # half a second with its known poses, no map yet
        for t_us in range(int(chunk["t"][0]) // 10_000 * 10_000, int(chunk["t"][-1]), 10_000):
            follower.known(t_us, *true_pose(t_us))
        assert follower.add(chunk) == []
    assert not follower.started
    # the first keyframe, seen at 0.3 s, comes now (its sweep took a while)
    follower.add_map(points)
    starts: list[int] = []
    start_on = SixDofTracker.start_on

    def spied(self, known, t_us):  # noqa: ANN001, ANN202
        starts.append(t_us)
        return start_on(self, known, t_us)

    monkeypatch.setattr(SixDofTracker, "start_on", spied)
    estimates = [e for chunk in chunks[100:] for e in follower.add(chunk)]
    assert follower.started and not follower.known(600_000, *true_pose(600_000))
    last_known = 490_000
    assert starts == [480_000]  # the last known pose on the update grid, not the keyframe's 0.3 s
    assert estimates[0].t_us == last_known + 10_000 and len(estimates) >= 24
    assert all(e.state == TRACKING for e in estimates)
    assert {e.t_us % 20_000 for e in estimates} == {0}
    for e in estimates:
        q, p = true_pose(e.t_us)
        assert np.linalg.norm(e.p - p) < 0.01
    assert np.allclose(estimates[-1].omega, omega, atol=np.radians(1.0))


def _odom(tmp_path, scene: str, seconds: str, *flags: str) -> tuple[dict, np.ndarray, float]:  # noqa: ANN001
    """`etam sim SCENE` -> `etam odom --mode 6dof` -> `etam eval odometry --align origin`, as a user runs them:
    the summary, the poses written, and their ATE (m, nothing fitted)."""
    h5, tum = tmp_path / f"{scene}.h5", tmp_path / "traj.tum"
    subprocess.run(etam_argv("sim", scene, "--out", str(h5), "--duration", seconds, "--seed", "1" if scene == "6dof"
                             else "2", "--json"), check=True, capture_output=True, timeout=300)
    made = subprocess.run(etam_argv("odom", str(h5), "--mode", "6dof", *flags, "--out", str(tum), "--json"),
                          capture_output=True, text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    scored = subprocess.run(etam_argv("eval", "odometry", "--pred", str(tum), "--truth", str(h5), "--align", "origin",
                                      "--json"), capture_output=True, text=True, timeout=120)
    assert scored.returncode == 0, scored.stderr
    return json.loads(made.stdout), read_tum(str(tum)), json.loads(scored.stdout)["ate_m"]


def test_odom_6dof_command_closes_the_loop_on_the_simulator(tmp_path):
    """`etam sim 6dof` -> `etam odom --mode 6dof` -> `etam eval odometry`, as a user runs them: poses from the
    end of the known start on, none lost, within 5 cm of the truth with nothing fitted, the rotation told by the
    file's gyro; and a file without
    known poses is refused with what to give."""
    summary, rows, ate_m = _odom(tmp_path, "6dof", "3", "--bootstrap", "1.5")
    assert summary["method"] == "sweep" and summary["gyro"]  # the simulated camera's IMU
    assert summary["poses"] == len(rows) >= 70 and summary["lost"] == 0 and summary["keyframes"] >= 1
    assert rows[0, 0] >= 1.5
    assert ate_m < 0.05

    objects = tmp_path / "objects.h5"
    subprocess.run(etam_argv("sim", "objects", "--out", str(objects), "--duration", "0.3", "--json"), check=True,
                   capture_output=True, timeout=120)
    refused = subprocess.run(etam_argv("odom", str(objects), "--mode", "6dof"), capture_output=True, text=True,
                             timeout=120)
    assert refused.returncode != 0 and "--start" in refused.stderr and "Traceback" not in refused.stderr
    none = subprocess.run(etam_argv("odom", str(tmp_path / "6dof.h5"), "--mode", "6dof", "--bootstrap", "0"),
                          capture_output=True, text=True, timeout=120)
    assert none.returncode != 0 and "--bootstrap must be positive" in none.stderr and "Traceback" not in none.stderr


def test_odom_6dof_on_a_stereo_rig_maps_by_stereo_and_holds(tmp_path):
    """A `sim stereo` rig's file: `etam odom --mode 6dof` maps by stereo (the default for a rig), the tracker
    following the stereo map it extends with its own poses, none lost, within 3 cm with nothing fitted; stereo
    is refused by name on a file of one camera."""
    summary, rows, ate_m = _odom(tmp_path, "stereo", "4")
    assert summary["method"] == "stereo" and summary["lost"] == 0 and summary["keyframes"] >= 3
    assert summary["poses"] == len(rows) >= 120 and ate_m < 0.03
    mono = tmp_path / "mono.h5"
    subprocess.run(etam_argv("sim", "6dof", "--out", str(mono), "--duration", "0.2", "--json"), check=True,
                   capture_output=True, timeout=120)
    bad = subprocess.run(etam_argv("odom", str(mono), "--mode", "6dof", "--method", "stereo"), capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "two cameras" in bad.stderr and "Traceback" not in bad.stderr


def _estimate(t_ms: int, share: float, state: int = TRACKING) -> PoseEstimate:
    return PoseEstimate(t_ms * 1000, np.eye(3), np.zeros(3), state, share, 1000, np.zeros(3))


def test_map_refresh_asks_for_a_keyframe_as_the_map_fails_and_when_lost() -> None:
    """Off by default; on, once an estimate explains under `weak_share` of the best share since the last
    keyframe (not sooner than `min_gap_us` after it or after the last ask), and on the first lost estimate after
    good ones."""
    never = MapRefresh()
    assert not any(never.due(_estimate(t, s)) for t, s in ((0, 0.3), (400, 0.01))) and not never.due(
        _estimate(420, 0.0, LOST))
    refresh = MapRefresh(RefreshParams(weak_share=0.6, min_gap_us=200_000))
    refresh.keyframe_at(0)
    assert [refresh.due(_estimate(t, s)) for t, s in ((20, 0.3), (40, 0.2), (60, 0.15))] == [False, False, False]
    assert refresh.due(_estimate(200, 0.17))  # under 0.6 of 0.3, 200 ms after the keyframe
    # no keyframe came: asked again 200 ms later, not at every update
    assert [refresh.due(_estimate(t, 0.17)) for t in (220, 380, 400)] == [False, False, True]
    refresh.keyframe_at(200)
    assert not refresh.due(_estimate(220, 0.17))  # the best is measured again from the keyframe on
    assert [refresh.due(_estimate(t, 0.0, LOST)) for t in (240, 260)] == [True, False]


def test_the_loop_keyframes_what_it_holds_when_its_map_fails_and_when_lost() -> None:
    """`MappedOdometry` asks its mapper for a keyframe early (`early`) where `MapRefresh` says so, and on a lost
    update, before the held segment is dropped; the keyframe's points join the tracker's map at once. The
    tracker and mapper are stand-ins that replay estimates and count what they are asked."""
    from services.mapper.keyframes import Keyframe
    from services.mapper.trajectory import Trajectory

    class Mapper:
        def __init__(self) -> None:
            self.asked: list[int] = []
            self.held = 0

        def add(self, events: np.ndarray, trajectory: Trajectory) -> list:
            self.held += len(events)
            return []

        def early(self, trajectory: Trajectory) -> Keyframe | None:
            self.asked.append(trajectory.end_us)
            if not self.held:
                return None
            self.held = 0
            return Keyframe(trajectory.end_us, np.eye(3), np.zeros(3), np.zeros((2, 2)), np.ones((7, 3)), np.ones(7),
                            0)

        def drop(self) -> None:
            self.held = 0

    class Tracker:
        params = SixDofParams()
        next_us = 1_520_000

        def __init__(self, replay: list[PoseEstimate]) -> None:
            self.replay, self.points = replay, 0

        def add(self, events: np.ndarray) -> list[PoseEstimate]:
            due = [e for e in self.replay if e.t_us <= int(events["t"][-1])]
            self.replay = self.replay[len(due):]
            return due

        def add_points(self, points: np.ndarray) -> None:
            self.points += len(points)

    known = Trajectory(np.array([[t, 0, 0, 0, 0, 0, 0, 1] for t in (1.0, 1.5)]))
    loop = MappedOdometry(np.eye(3), 64, 48, known, loop_params(stereo=True), Mapper())
    loop.started = True
    shares = [0.3, 0.3, 0.3] + [0.3] * 7 + [0.1] + [0.3] * 3
    loop.tracker = Tracker([_estimate(1520 + 20 * k, s) for k, s in enumerate(shares)] + [_estimate(1820, 0.0, LOST)])
    events = np.zeros(400, EVENT_DTYPE)
    events["t"] = np.linspace(1_500_000, 1_830_000, 400)
    loop.add(events)
    # weak at 1.72 s (0.1 under 0.6 of 0.3, 200 ms on), lost at 1.82 s: a keyframe each, of what was held up to
    # then (the last good pose, 1.78 s)
    assert loop.mapper.asked == [1_720_000, 1_780_000] and loop.tracker.points == 14 and len(loop.keyframes) == 2
