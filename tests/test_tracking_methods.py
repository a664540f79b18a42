"""The tracker's building blocks from the seeds, and every method on a simulated scene."""

from __future__ import annotations

import numpy as np
import pytest

from services.camera.simulator import EventSimulator, ObjectsScene
from services.messages import EVENT_DTYPE
from services.tracker.objects.association import TRACKED, iou
from services.tracker.objects.frames import AdaptiveWindow, RecentEvents, frame_quality
from services.tracker.objects.position import sizes_for, xyz_from_depth, xyz_from_size
from services.tracker.objects.sampling import key_events
from services.tracker.objects.tracker import METHODS, ObjectTracker, method_params
from services.tracker.offline import track
from services.tracker.service import ObjectSizes
from tests.conftest import SHARED

PERSON = SHARED / "data" / "real" / "tonic_samples" / "sample.aedat4"  # a DVXplorer Lite recording of a person


def _events(xs, ys, ts) -> np.ndarray:  # noqa: ANN001
    ev = np.zeros(len(xs), EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"] = xs, ys, ts
    return ev


def test_key_events_keep_one_per_cell_nearest_its_centre_and_spare_sparse_regions() -> None:
    rng = np.random.default_rng(1)
    dense = _events(rng.integers(0, 40, 5000), rng.integers(0, 40, 5000), np.arange(5000))
    sparse = _events([100, 150], [100, 150], [5000, 5001])
    ev = np.concatenate([dense, sparse])
    idx, weight = key_events(ev, 200, 200, 4)
    assert np.all(np.diff(idx) > 0) and weight.sum() == len(ev)
    cells = (ev["x"][idx] // 4) * 1000 + ev["y"][idx] // 4
    assert len(np.unique(cells)) == len(idx) == 100 + 2  # 10 x 10 dense cells, and both sparse events
    keys = ev[idx]
    first = keys[(keys["x"] < 4) & (keys["y"] < 4)][0]  # cell (0, 0): none nearer its centre (1.5, 1.5)
    in_cell = ev[(ev["x"] < 4) & (ev["y"] < 4)]
    d = (in_cell["x"].astype(float) - 1.5) ** 2 + (in_cell["y"].astype(float) - 1.5) ** 2
    assert (float(first["x"]) - 1.5) ** 2 + (float(first["y"]) - 1.5) ** 2 == pytest.approx(d.min())


def test_frame_quality_prefers_a_sharp_frame_to_a_sparse_or_smeared_one() -> None:
    edge = np.zeros((60, 60), np.float32)
    edge[10:50, 30:32] = 3  # a sharp edge
    smeared = np.zeros_like(edge)
    smeared[10:50, 10:50] = 1  # the same edge dragged across the frame
    rng = np.random.default_rng(0)
    sparse = np.zeros_like(edge)
    sparse[rng.integers(0, 60, 40), rng.integers(0, 60, 40)] = 1  # too short a window: scattered events
    assert frame_quality(edge) > frame_quality(smeared) and frame_quality(edge) > frame_quality(sparse)
    assert frame_quality(np.zeros_like(edge)) == 0.0


def test_recent_events_keep_exactly_the_events_since_the_last_drop_across_regrowth() -> None:
    rng = np.random.default_rng(3)
    recent, kept = RecentEvents(capacity=16), []
    t = cut = 0
    for _ in range(60):
        n = int(rng.integers(0, 40))
        chunk = _events(rng.integers(0, 346, n), rng.integers(0, 260, n), t + np.sort(rng.integers(0, 1000, n)))
        t += 1000
        recent.append(chunk)
        kept.append(chunk)
        cut = max(cut, t - int(rng.integers(0, 5000)))  # windows only move on
        recent.drop_before(cut)
        want = np.concatenate(kept)
        want = want[want["t"] >= cut]
        got = recent.columns()
        assert all(np.array_equal(col, want[name]) for col, name in zip(got, ("t", "x", "y"), strict=True))


def _bar_events(speed_px_s: float, duration_us: int) -> np.ndarray:
    """A textured vertical bar moving right: events on its edge, 20 per pixel of travel per row."""
    ts = np.arange(0, duration_us, 50)
    xs = (20 + speed_px_s * ts / 1e6).astype(np.int64) % 150
    ys = (ts // 50) % 100
    return _events(xs, ys, ts)


def test_adaptive_window_grows_for_slow_motion_and_shrinks_for_fast() -> None:
    spans = {}
    for speed in (100.0, 2000.0):
        win = AdaptiveWindow(160, 100)
        ev = _bar_events(speed, 400_000)
        for t in range(10_000, 400_001, 10_000):
            win.accept(ev[(ev["t"] >= t - 10_000) & (ev["t"] < t)])
            win.generate(t)
        spans[speed] = win.dt_us
    assert spans[100.0] > spans[2000.0]


def test_xyz_from_size_and_from_depth() -> None:
    K = np.array([[300.0, 0, 150], [0, 300.0, 100], [0, 0, 1]])
    boxes = np.array([[140, 90, 20, 20], [0, 0, 30, 10]], np.float32)
    xyz = xyz_from_size(boxes, np.array([0.5, np.nan]), K)
    assert xyz[0] == pytest.approx([0, 0, 7.5])  # 300 * 0.5 / 20
    assert np.isnan(xyz[1]).all()
    depth = np.full((200, 300), np.nan, np.float32)
    depth[90:110, 140:160] = 4.0
    from_depth = xyz_from_depth(boxes, depth, K)
    assert from_depth[0] == pytest.approx([0, 0, 4.0]) and np.isnan(from_depth[1, 2])
    assert sizes_for(np.array([1, 7]), 0.4, {7: 1.2}) == pytest.approx([0.4, 1.2])
    sizes = ObjectSizes.parse(["0.4", "7=1.2"])
    assert sizes.default_m == 0.4 and sizes.per_id == {7: 1.2}
    with pytest.raises(ValueError, match="ID=M"):
        ObjectSizes.parse(["-1"])


def test_unknown_method_is_named() -> None:
    with pytest.raises(ValueError, match="contour"):
        method_params("kalman")


@pytest.mark.parametrize(("method", "seed", "floor"), [("contour", 0, 0.5)] + [(m, 3, 0.4) for m in METHODS])
def test_every_method_follows_simulated_objects(method: str, seed: int, floor: float) -> None:
    scene = ObjectsScene(seed=seed)
    sim = EventSimulator(scene, seed=seed)
    tracker = ObjectTracker(scene.width, scene.height, method_params(method))
    matched = total = 0
    for t in range(10_000, 3_000_001, 10_000):
        tracker.accept(sim.advance(t))
        out = tracker.generate(t)
        _, truth, _ = scene.boxes(t)
        if t > 500_000 and len(truth):
            total += len(truth)
            live = out.boxes[out.states == TRACKED]
            if len(live):
                matched += int((iou(truth, live).max(axis=1) > 0.3).sum())
    assert total > 0 and matched / total > floor


def test_warm_up_loads_every_kernel_of_a_default_update_including_the_layout_of_a_shared_blob() -> None:
    """In a fresh interpreter, as a service starts: no kernel of an update is left to load on live packets,
    which arrive decoded from the wire (read-only arrays, a type of their own to numba: compiling for it
    on the first packet of a fresh install stalled the tracker past its queue, and packets were dropped)."""
    import json
    import subprocess
    import sys

    code = """
import json
import numpy as np
from services.messages import EVENT_DTYPE, EventPacket, decode
from services.tracker.objects import accumulator, activity, clusters, layout, motion, shapes
from services.tracker.objects.tracker import ObjectTracker, warm_up
kernels = (accumulator._add, accumulator._decay, activity.count_into, activity._count_in, clusters._detect,
           layout._placed, motion._two_groups, motion._halves, motion._translation, shapes._two_rectangles)
assert not any(k.signatures for k in kernels)
warm_up()
loaded = [len(k.signatures) for k in kernels]
events = np.zeros(500, EVENT_DTYPE)
events["x"], events["y"], events["t"] = np.arange(500) % 40 + 10, np.arange(500) // 40 + 10, np.arange(500) * 10
live = decode(EventPacket(width=64, height=48, events=events).encode()).events
assert not live.flags.writeable
tracker = ObjectTracker(64, 48)
tracker.accept(live)
tracker.generate(5_000)
print(json.dumps([loaded, [len(k.signatures) for k in kernels]]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    loaded, after_live_packet = json.loads(out.stdout)
    assert all(loaded) and after_live_packet == loaded


@pytest.mark.skipif(not PERSON.exists(), reason="needs ../shared/data/real")
def test_a_person_on_a_real_recording_is_one_track_not_a_track_and_its_turning_face(tmp_path) -> None:  # noqa: ANN001
    """The edge of the person's turning face is first seen apart from the body, then in the person's blob:
    a piece of the person, folded into its track, not a second target boxed for the rest of the recording."""
    out = tmp_path / "tracks.csv"
    track(PERSON, out, progress=False)
    ids = np.loadtxt(out, delimiter=",", skiprows=1, usecols=1, ndmin=1).astype(int)
    main = np.bincount(ids).argmax()
    assert (ids == main).sum() >= 50 and (ids != main).sum() <= 5, np.unique(ids, return_counts=True)
