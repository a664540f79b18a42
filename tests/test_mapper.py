"""Mapper: space sweep, keyframes, voxel map, PLY files, and `etam map` / `etam eval map` end to end."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.mapper.cloud import VoxelMap
from services.mapper.evaluation import depth_errors
from services.mapper.keyframes import KeyframeMapper, KeyframeParams
from services.mapper.ply import PlyError, read_ply, write_ply
from services.mapper.trajectory import Trajectory
from services.messages import EVENT_DTYPE
from tests.conftest import etam_argv

K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
W, H = 160, 120


def _slide(duration_s: float = 1.0) -> np.ndarray:
    """TUM rows of a camera sliding 0.6 m to the right while turning a little."""
    t = np.linspace(0, duration_s, 51)
    q = Rotation.from_euler("y", (0.05 * t / duration_s)[:, None]).as_quat()
    return np.column_stack([t, 0.6 * t / duration_s, 0 * t, 0 * t, q])


def _events_of(points: np.ndarray, trajectory: Trajectory, times_us: np.ndarray) -> np.ndarray:
    """Each point seen at each time: an event at its rounded pixel (a sensor's), where it is in view."""
    R, p = trajectory.at(times_us)
    out = []
    for Ri, pi, t in zip(R, p, times_us, strict=True):
        cam = (points - pi) @ Ri
        u, v = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2], K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
        ok = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        ev = np.zeros(int(ok.sum()), EVENT_DTYPE)
        ev["t"], ev["x"], ev["y"], ev["p"] = t, np.round(u[ok]), np.round(v[ok]), 1
        out.append(ev)
    return np.concatenate(out)


def test_sweep_finds_the_depth_of_two_planes_from_a_sliding_camera() -> None:
    """Points on planes at 2 m and 4 m, seen by a sliding camera: the keyframe's points lie on them."""
    rng = np.random.default_rng(1)
    near = np.column_stack([rng.uniform(-0.9, 0.3, 150), rng.uniform(-0.5, 0.5, 150), np.full(150, 2.0)])
    far = np.column_stack([rng.uniform(-1.2, 2.0, 150), rng.uniform(-1.0, 1.0, 150), np.full(150, 4.0)])
    trajectory = Trajectory(_slide())
    events = _events_of(np.vstack([near, far]), trajectory, np.arange(0, 1_000_000, 5_000))
    # 0.6 m of travel: short of a segment (0.5 of the first guess of depth, 2 m), enough for the last one
    mapper = KeyframeMapper(K, W, H, KeyframeParams(baseline_share=0.5))
    assert mapper.add(events, trajectory) == []
    kf = mapper.flush(trajectory)
    assert kf is not None and len(kf.points) > 100
    R, p = kf.R, kf.p
    z = ((kf.points - p) @ R)[:, 2]
    off = np.minimum(np.abs(z - 2.0) / 2.0, np.abs(z - 4.0) / 4.0)
    assert np.median(off) < 0.02 and np.mean(off < 0.05) > 0.7  # a few land between (the median filter at overlaps)
    assert np.any(np.abs(z - 2.0) < 0.1) and np.any(np.abs(z - 4.0) < 0.2)  # both planes found


def test_keyframes_end_by_travel_and_a_short_tail_is_dropped() -> None:
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-1, 2, 500), rng.uniform(-1, 1, 500), np.full(500, 3.0)])
    trajectory = Trajectory(_slide())
    events = _events_of(points, trajectory, np.arange(0, 1_000_000, 5_000))
    mapper = KeyframeMapper(K, W, H, KeyframeParams(baseline_share=0.07))
    mapper.scene_depth = 3.0  # so a keyframe every 0.21 m, about 0.35 s of the slide
    done = []
    for chunk in np.array_split(events, 7):
        done += mapper.add(chunk, trajectory)
    assert 2 <= len(done) <= 3
    assert all(a.t_us < b.t_us for a, b in zip(done, done[1:], strict=False))
    assert sum(kf.events for kf in done) < len(events)  # the rest waits for more travel


def test_keyframes_end_also_by_time_where_a_span_is_set() -> None:
    """A segment may also end by time (stereo depth needs no travel): a camera that only turns still gets
    keyframes; without the limit it gets none."""
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(-1, 2, 500), rng.uniform(-1, 1, 500), np.full(500, 3.0)])
    t = np.linspace(0, 1.0, 51)
    q = Rotation.from_euler("y", (0.1 * t)[:, None]).as_quat()
    turning = Trajectory(np.column_stack([t, 0 * t, 0 * t, 0 * t, q]))
    events = _events_of(points, turning, np.arange(0, 1_000_000, 5_000))
    spans = {}
    for span_us in (0, 300_000):
        mapper = KeyframeMapper(K, W, H, KeyframeParams(max_span_us=span_us))
        spans[span_us] = [kf for chunk in np.array_split(events, 5) for kf in mapper.add(chunk, turning)]
    assert spans[0] == [] and len(spans[300_000]) == 3
    middles = np.array([kf.t_us for kf in spans[300_000]])  # each segment's reference view: its middle time
    assert abs(middles[0] - 150_000) < 15_000 and np.all(np.abs(np.diff(middles) - 300_000) < 15_000)


def test_trajectory_interpolates_and_clamps() -> None:
    rows = np.array([[0.0, 0, 0, 0, *Rotation.identity().as_quat()],
                     [1.0, 2, 0, 0, *Rotation.from_euler("z", 90, degrees=True).as_quat()]])
    R, p = Trajectory(rows).at(np.array([500_000, 2_000_000]))
    assert np.allclose(p, [[1, 0, 0], [2, 0, 0]])
    assert np.isclose(Rotation.from_matrix(R[0]).magnitude(), np.pi / 4)
    with pytest.raises(ValueError, match="at least 2 poses"):
        Trajectory(rows[:1])


def test_voxel_map_fuses_repeated_points_and_forgets_the_oldest_over_its_cap() -> None:
    cloud = VoxelMap(voxel_m=0.1, max_points=3, min_neighbours=0)  # lone voxels shown: support is tested below
    cloud.add(np.array([[0.01, 0, 0], [1.01, 0, 0]]), np.ones(2), keyframe=0)
    cloud.add(np.array([[0.03, 0, 0]]), np.ones(1), keyframe=1)  # the same voxel as the first
    points, counts, _, last = cloud.points()
    assert len(cloud) == 2 and sorted(counts.tolist()) == [1, 2]
    assert np.allclose(points[np.argmax(counts)], [0.02, 0, 0])
    cloud.add(np.array([[2.0, 0, 0], [3.0, 0, 0]]), np.ones(2), keyframe=2)
    points, _, _, last = cloud.points()
    assert len(cloud) == 3 and 0 not in last.tolist()  # the voxel only keyframe 0 saw went first
    assert not np.any(np.isclose(points[:, 0], 1.01))


def test_voxel_map_shows_voxels_with_neighbours_and_hides_lone_ones() -> None:
    """An edge (a line of voxels) is shown but for its two ends (one neighbour each), a lone voxel (a wrong
    peak) is held but not shown, and shows once a later keyframe puts points beside it; what a keyframe
    adds is reported only where supported."""
    cloud = VoxelMap(voxel_m=0.1, min_neighbours=2)
    edge = np.stack([np.arange(6) * 0.1 + 0.05, np.full(6, 0.05), np.full(6, 0.05)], 1)
    lone = np.array([[2.05, 2.05, 2.05]])
    new = cloud.add(np.vstack([edge, lone]), np.ones(7), keyframe=0)
    assert len(cloud) == 7 and np.allclose(np.sort(new[:, 0]), edge[1:-1, 0])
    points, *_ = cloud.points()
    assert np.allclose(np.sort(points[:, 0]), edge[1:-1, 0])
    new = cloud.add(np.array([[2.15, 2.05, 2.05], [2.05, 2.15, 2.05]]), np.ones(2), keyframe=1)
    assert len(new) == 2  # each has the lone voxel and the other beside it
    points, *_ = cloud.points()
    assert len(points) == 7 and np.any(np.all(np.isclose(points, lone), axis=1))
    assert len(VoxelMap(voxel_m=0.1, min_neighbours=0).add(lone, np.ones(1), keyframe=0)) == 1  # 0: no filter


def test_ply_round_trip_ascii_and_truncated(tmp_path: Path) -> None:
    pts = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    path = tmp_path / "c.ply"
    write_ply(path, pts, {"keyframe": np.arange(50, dtype=np.uint32)}, ["keyframe 0 5 0 0 0 0 0 0 1"])
    back, fields, comments = read_ply(path)
    assert np.array_equal(back, pts) and np.array_equal(fields["keyframe"], np.arange(50))
    assert comments == ["keyframe 0 5 0 0 0 0 0 0 1"]
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(PlyError, match="truncated"):
        read_ply(path)
    text = tmp_path / "a.ply"
    text.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n1 2 3\n4 5 6\n")
    assert np.array_equal(read_ply(text)[0], [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "n.ply").write_text("hello")
    with pytest.raises(PlyError, match="not a PLY"):
        read_ply(tmp_path / "n.ply")


def test_depth_errors_score_points_against_the_true_surface() -> None:
    """A wall 3 m ahead: points on it score 0, points 10 cm in front of it score -0.1."""
    rows = np.array([[0.0, 0, 0, 0, 0, 0, 0, 1], [1.0, 0, 0, 0, 0, 0, 0, 1]])
    wall = np.full((H, W), 3.0, np.float32)
    pts = np.array([[0.0, 0, 3.0], [0.5, 0.2, 3.0], [0.1, 0, 2.9], [0, 0, -1.0]])
    err, true, _ = depth_errors(pts, np.zeros(4, np.int64), Trajectory(rows), np.array([0]), lambda k: wall, K)
    assert np.allclose(err, [0, 0, -0.1]) and np.allclose(true, 3.0)  # the point behind the camera is left out


def test_map_and_eval_map_commands(tmp_path: Path) -> None:
    """`etam sim 6dof` -> `etam map` -> `etam eval map`, as a user runs them; and their errors."""
    h5, ply = tmp_path / "room.h5", tmp_path / "cloud.ply"
    subprocess.run(etam_argv("sim", "6dof", "--out", str(h5), "--duration", "4", "--seed", "5", "--json"),
                   check=True, capture_output=True, timeout=120)
    made = subprocess.run(etam_argv("map", str(h5), "--out", str(ply), "--json"), capture_output=True, text=True,
                          timeout=120)
    assert made.returncode == 0, made.stderr
    summary = json.loads(made.stdout)
    assert summary["keyframes"] >= 1 and summary["points"] > 100 and summary["poses"] == "truth"
    scored = subprocess.run(etam_argv("eval", "map", "--cloud", str(ply), "--truth", str(h5), "--json"),
                            capture_output=True, text=True, timeout=120)
    assert scored.returncode == 0, scored.stderr
    scores = json.loads(scored.stdout)
    assert scores["points_scored"] > 100
    assert scores["median_error_pct_of_range"] < 4 and scores["within_5pct"] > 0.7
    assert 0 < scores["completeness"] <= 1

    objects = tmp_path / "objects.h5"
    subprocess.run(etam_argv("sim", "objects", "--out", str(objects), "--duration", "0.3", "--json"), check=True,
                   capture_output=True, timeout=120)
    for argv, says in ((("map", str(objects)), "no poses to map with"),
                       (("map", str(h5), "--depth-range", "5,1"), "--depth-range"),
                       (("eval", "map", "--cloud", str(h5), "--truth", str(h5)), "not a PLY"),
                       (("eval", "map", "--cloud", str(ply), "--truth", str(objects)), "no truth depth")):
        bad = subprocess.run(etam_argv(*argv), capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and says in bad.stderr and "Traceback" not in bad.stderr, (argv, bad.stderr)
