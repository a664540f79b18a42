"""`etam track` and `etam eval tracking`: the metrics on hand-made cases, and the commands end to end."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from services.camera.formats import open_recording
from services.tracker.evaluation import evaluate
from services.tracker.objects.association import iou
from tests.conftest import etam_argv


def _truth(frames: int = 50, period_us: int = 20_000) -> np.ndarray:
    """Two objects moving right, one row per object and frame: t_us, id, x, y, w, h."""
    rows = [[k * period_us, obj, 10 + 2 * k + 100 * obj, 20, 20, 30] for k in range(frames) for obj in (1, 2)]
    return np.asarray(rows, np.float64)


def test_perfect_prediction_scores_one_and_no_errors() -> None:
    truth = _truth()
    pred = truth.copy()
    pred[:, 1] += 40  # ids need not be the truth's
    s = evaluate(pred, truth)
    assert (s.op50, s.op75, s.precision20, s.false_positives_per_s, s.id_switches) == (1.0, 1.0, 1.0, 0.0, 0)
    assert s.success_auc == pytest.approx(20 / 21) and s.objects == 2 and s.truth_boxes == 100


def test_misses_false_boxes_shifts_stale_frames_and_id_switches_are_counted() -> None:
    truth = _truth()
    pred = truth.copy()
    pred[pred[:, 1] == 2, 2] += 10  # object 2 predicted half a box off: IoU 1/3, centre 10 px away
    s = evaluate(pred, truth)
    assert s.op50 == 0.5 and s.precision20 == 1.0 and s.false_positives_per_s == pytest.approx(1.0)
    switched = truth.copy()
    switched[(switched[:, 1] == 1) & (switched[:, 0] >= 500_000), 1] = 7  # object 1's track changes id once
    s = evaluate(switched, truth)
    assert s.id_switches == 1 and s.id_switch_events == [
        {"t_us": 500_000, "object": 1, "from_id": 1, "to_id": 7, "cause": "other"}]
    sparse = truth[truth[:, 0] % 100_000 == 0]  # predictions every 100 ms: older than the 20 ms allowed
    assert evaluate(sparse, truth).op50 == pytest.approx(2 / 5)  # at 3 of every 5 truth frames
    assert evaluate(np.zeros((0, 6)), truth).op50 == 0.0


def test_boxes_on_dont_care_regions_are_not_false_and_empty_frames_count() -> None:
    truth = _truth()
    one = truth[truth[:, 1] == 1]
    ignore = truth[truth[:, 1] == 2]  # object 2 is in the image but not scored (mostly hidden, say)
    pred = truth.copy()
    assert evaluate(pred, one).false_positives_per_s == pytest.approx(1.0)  # the box on object 2 is false ...
    assert evaluate(pred, one, ignore=ignore).false_positives_per_s == 0.0  # ... unless object 2 is "don't care"
    assert evaluate(pred, one).idp == pytest.approx(0.5) and evaluate(pred, one, ignore=ignore).idf1 == 1.0  # IDF1 too
    shifted = pred.copy()
    shifted[shifted[:, 1] == 2, 3] += 25  # now mostly off it: false again
    assert evaluate(shifted, one, ignore=ignore).false_positives_per_s == pytest.approx(1.0)
    gap = one[(one[:, 0] < 200_000) | (one[:, 0] >= 600_000)]  # object 1 out of view for 20 frames
    s = evaluate(pred[pred[:, 1] == 1], gap)
    assert s.frames == 50 and s.false_positives_per_s == pytest.approx(20 / 50)  # its track there is false


def test_an_object_keeps_its_matched_id_while_it_still_overlaps_as_in_clear_mot() -> None:
    # two targets one on top of the other; track 5 always on object 1, track 6 between them, nearer
    # object 1 at odd frames: Hungarian alone would swap the pairs every frame, CLEAR MOT keeps them
    k = np.arange(20)
    truth = np.concatenate([np.c_[k * 20_000, np.full(20, obj), np.full(20, x), np.full(20, 20.0),
                                  np.full(20, 40.0), np.full(20, 40.0)] for obj, x in ((1, 0.0), (2, 8.0))])
    near = np.where(k % 2, 2.0, 6.0)
    pred = np.concatenate([truth[:20].copy(), np.c_[truth[:20, :2], near, truth[:20, 3:]]])
    pred[:20, 1], pred[20:, 1] = 5, 6
    pred[:20, 2] = np.where(k % 2, 3.0, 0.0)
    s = evaluate(pred, truth)
    assert s.id_switches == 0 and s.op50 == 1.0
    pred[20:, 1] = np.where(k >= 10, 9, 6)  # the second track changes id once
    assert evaluate(pred, truth).id_switches == 1


def test_switches_are_put_down_to_crossings_and_returns_and_precision_is_split_by_crossing() -> None:
    # object 1 moves right and passes over a still object 2 (boxes overlapping from frame 16 to 34); object 3,
    # far away, is out of view (unscored) from frame 20 to 29
    k = np.arange(50)
    one = np.c_[k * 20_000, np.full(50, 1), 2.0 * k, np.full(50, 20.0), np.full(50, 20.0), np.full(50, 20.0)]
    two = np.c_[k * 20_000, np.full(50, 2), np.full(50, 50.0), np.full(50, 20.0), np.full(50, 20.0), np.full(50, 20.0)]
    three = np.c_[k * 20_000, np.full(50, 3), np.full(50, 200.0), np.full(50, 150.0), np.full(50, 20.0),
                  np.full(50, 20.0)]
    truth = np.concatenate([one, two, three[(k < 20) | (k >= 30)]])
    pred = truth.copy()
    pred[(pred[:, 1] == 1) & (pred[:, 0] >= 30 * 20_000), 1] = 7  # a new id after the crossing (frame 30)
    pred[(pred[:, 1] == 3) & (pred[:, 0] >= 30 * 20_000), 1] = 8  # and on its return
    pred[(pred[:, 1] == 8) & (pred[:, 0] >= 45 * 20_000), 1] = 9  # and once more, long after it came back
    moved = (pred[:, 1] == 2) & (pred[:, 0] >= 16 * 20_000) & (pred[:, 0] < 35 * 20_000)
    pred[moved, 2] += 30  # object 2's box 30 px off while the other touches it
    s = evaluate(pred, truth)
    causes = {e["object"]: [] for e in s.id_switch_events}
    for e in s.id_switch_events:
        causes[e["object"]].append(e["cause"])
    assert causes == {1: ["crossing"], 3: ["return", "other"]}
    assert s.id_switches_by_cause == {"crossing": 1, "return": 1, "other": 1}
    assert s.crossing_share == pytest.approx(38 / 140)  # 19 frames of two boxes overlapping, of 140 truth boxes
    assert s.precision20_crossing == pytest.approx(0.5) and s.precision20_clear == 1.0
    assert evaluate(pred, one).precision20_crossing is None  # nothing crosses: no figure, not a perfect one


def test_mota_and_idf1_agree_with_py_motmetrics() -> None:
    # three objects on crossing-free paths; the tracks jitter, miss frames, add false boxes, and two
    # swap ids for a stretch (two switches there and two back): py-motmetrics scores the same boxes
    import motmetrics as mm  # a test dependency: missing, the test fails rather than skips
    rng = np.random.default_rng(7)
    frames, period = 120, 20_000
    truth = np.asarray([[k * period, obj, 10 + 2 * k, 10 + 70 * obj, 30, 40]
                        for k in range(frames) for obj in (0, 1, 2)], np.float64)
    pred = truth.copy()
    pred[:, 1] += 10
    pred[:, 2:4] += rng.normal(0, 4, (len(pred), 2))
    swap = (pred[:, 0] >= 40 * period) & (pred[:, 0] < 70 * period) & (pred[:, 1] < 12)
    pred[swap, 1] = 21 - pred[swap, 1]  # tracks 10 and 11 swap objects
    pred = pred[rng.random(len(pred)) > 0.1]  # misses
    at = np.arange(0, frames, 7) * period
    noise = np.c_[at, np.full(len(at), 99), np.full((len(at), 2), 250.0), np.full((len(at), 2), 20.0)]
    pred = np.concatenate([pred, noise])  # false boxes away from every object
    s = evaluate(pred, truth)

    acc = mm.MOTAccumulator(auto_id=True)
    for t in np.unique(truth[:, 0]):
        gt, pr = truth[truth[:, 0] == t], pred[pred[:, 0] == t]
        overlap = iou(gt[:, 2:6], pr[:, 2:6])  # motmetrics' own iou_matrix calls np.asfarray, gone in numpy 2
        acc.update(gt[:, 1].astype(int), pr[:, 1].astype(int), np.where(overlap >= 0.5, 1 - overlap, np.nan))
    ref = mm.metrics.create().compute(acc, metrics=["mota", "idf1", "idp", "idr", "num_switches"], name="etam")
    assert s.id_switches == int(ref["num_switches"].iloc[0]) == 4
    for ours, theirs in ((s.mota, "mota"), (s.idf1, "idf1"), (s.idp, "idp"), (s.idr, "idr")):
        assert ours == pytest.approx(float(ref[theirs].iloc[0]), abs=1e-9), theirs
    assert 0.5 < s.idf1 < 0.9 and s.mota < 1.0  # the swap, misses and false boxes cost


def test_track_then_eval_on_a_simulated_sequence(tmp_path: Path) -> None:
    h5, csv = tmp_path / "o.h5", tmp_path / "tracks.csv"
    subprocess.run(etam_argv("sim", "objects", "--out", str(h5), "--duration", "4", "--seed", "3", "--json"),
                   check=True, capture_output=True, timeout=120)
    with open_recording(h5) as rec:  # targets coming in are "don't care" until a quarter is in view
        assert rec.truth.ignore.shape[1] == 6 and len(rec.truth.ignore) > 0
    png = tmp_path / "boxes.png"
    run = subprocess.run(etam_argv("track", str(h5), "--out", str(csv), "--snapshots", str(png), "--json"),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    assert summary["updates"] == 400 and summary["boxes"] > 100
    import cv2

    grid = cv2.imread(str(png))
    assert grid.shape == (2 * 260, 3 * 346, 3) and grid.any()  # six event frames with boxes
    assert csv.read_text().splitlines()[0] == "t_us,id,x,y,w,h,score"
    run = subprocess.run(etam_argv("eval", "tracking", "--pred", str(csv), "--truth", str(h5), "--json"),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    scores = json.loads(run.stdout)
    assert scores["frames"] >= 150 and scores["objects"] >= 2
    assert scores["op50"] > 0.4 and scores["precision20"] > 0.4  # a floor: the tracker finds the objects
    text = subprocess.run(etam_argv("eval", "tracking", "--pred", str(csv), "--truth", str(h5)), capture_output=True,
                          text=True, timeout=120).stdout
    assert f"precision20: {scores['precision20']:.3f}" in text  # the same figures, one per line, and each switch
    assert text.count("id switch:") == scores["id_switches"] == len(scores["id_switch_events"])
    causes = scores["id_switches_by_cause"]
    assert f"id_switches_by_cause: crossing {causes['crossing']}, return {causes['return']}" in text
    bad = subprocess.run(etam_argv("eval", "tracking", "--pred", str(h5), "--truth", str(h5)), capture_output=True,
                         text=True, timeout=60)
    assert bad.returncode == 2 and "not a tracks CSV" in bad.stderr and "Traceback" not in bad.stderr

    written = csv.stat().st_mtime_ns
    for out in (["--out", str(tmp_path / "gone" / "t.csv")], ["--out", str(csv), "--snapshots", "/nonexistent/s.png"]):
        bad = subprocess.run(etam_argv("track", str(h5), *out), capture_output=True, text=True, timeout=60)
        # a missing output folder is named before any tracking: no progress bar, the tracks above untouched
        assert bad.returncode == 2 and "does not exist" in bad.stderr and "Traceback" not in bad.stderr
        assert "o.h5:" not in bad.stderr and csv.stat().st_mtime_ns == written


def test_eval_draws_each_id_switch_before_and_at_it(tmp_path: Path) -> None:
    import cv2

    h5 = tmp_path / "o.h5"
    subprocess.run(etam_argv("sim", "objects", "--out", str(h5), "--duration", "3", "--seed", "3", "--json"),
                   check=True, capture_output=True, timeout=120)
    with open_recording(h5) as rec:
        truth = rec.truth.boxes[:, :6].astype(np.float64)
    objects = np.unique(truth[:, 1])
    pred = truth.copy()
    for obj, at in zip(objects[:2], (1_000_000, 2_000_000), strict=False):  # each of two objects changes id once
        pred[(pred[:, 1] == obj) & (pred[:, 0] >= at), 1] = 100 + obj
    csv = tmp_path / "t.csv"
    np.savetxt(csv, np.c_[pred, np.ones(len(pred))], delimiter=",", header="t_us,id,x,y,w,h,score", comments="",
               fmt=["%d", "%d", "%.2f", "%.2f", "%.2f", "%.2f", "%.3f"])
    png = tmp_path / "switches.png"
    run = subprocess.run(etam_argv("eval", "tracking", "--pred", str(csv), "--truth", str(h5), "--snapshots", str(png),
                                   "--json"), capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    scores = json.loads(run.stdout)
    n = min(len(objects), 2)
    assert scores["id_switches"] == n and scores["snapshots"] == {"file": str(png), "switches_drawn": n}
    grid = cv2.imread(str(png))
    assert grid.shape == (n * 260, 2 * 346, 3)  # a row per switch: the frame before it, and at it
    yellow = (grid[..., 0] < 60) & (grid[..., 1] > 200) & (grid[..., 2] > 200)
    assert yellow[:260, 346:].any()  # the switched object's truth box is drawn apart from the others
    run = subprocess.run(etam_argv("eval", "tracking", "--pred", str(csv), "--truth", str(h5), "--snapshots",
                                   str(png), "--most", "1"), capture_output=True, text=True, timeout=120)
    assert "drew the first 1 id switches" in run.stdout and cv2.imread(str(png)).shape == (260, 2 * 346, 3)
    clean = tmp_path / "clean.csv"
    np.savetxt(clean, np.c_[truth, np.ones(len(truth))], delimiter=",", header="t_us,id,x,y,w,h,score",
               comments="", fmt=["%d", "%d", "%.2f", "%.2f", "%.2f", "%.2f", "%.3f"])
    none = tmp_path / "none.png"
    run = subprocess.run(etam_argv("eval", "tracking", "--pred", str(clean), "--truth", str(h5), "--snapshots",
                                   str(none)), capture_output=True, text=True, timeout=120)
    assert "no id switches to draw" in run.stdout and not none.exists()
    bad = subprocess.run(etam_argv("eval", "tracking", "--pred", str(csv), "--truth", str(h5), "--most", "0"),
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "not a whole number above 0" in bad.stderr


def test_bench_tracking_scores_every_seed_and_their_mean() -> None:
    from benchmarks import tracking

    from services.tracker.objects.tracker import METHODS

    rows = tracking.run(quick=True)
    ceilings = ["association on truth boxes", "association on merged truth boxes",
                "default, blobs placed on truth boxes, hidden ones too",
                "default, blobs placed on the truth boxes of targets in view"]
    assert [r["seed"] for r in rows] == [11, 12] + ["mean"] * (len(METHODS) + 5)
    assert [r["method"] for r in rows[2:]] == [*METHODS, *ceilings, "dv MeanShiftTracker"]
    mean = rows[2]
    assert mean["op50"] == pytest.approx((rows[0]["op50"] + rows[1]["op50"]) / 2)
    for row in rows[2:]:
        assert 0 <= row["op50"] <= 1 and row["false_positives_per_s"] >= 0
    assert mean["op50"] > 0.3  # the default method finds the objects
    on_truth = {r["method"]: r for r in rows}
    # fed the truth, association finds nearly every object; merged, it meets what a blob detector meets
    assert on_truth[ceilings[0]]["op50"] > 0.95 and on_truth[ceilings[1]]["op50"] < on_truth[ceilings[0]]["op50"]


def test_bench_held_out_scores_the_default_method_on_seeds_kept_from_tuning() -> None:
    from benchmarks import suite, tracking

    from services.tracker.objects.tracker import DEFAULT_METHOD

    assert not set(tracking.HELD_OUT_SEEDS) & {11, 12, 13, 14, 15}  # apart from the seeds the bench shows
    rows = tracking.held_out(quick=True)
    assert [(r["method"], r["seed"]) for r in rows] == [(DEFAULT_METHOD, "mean of 4 (71-74)")]
    assert 0.3 < rows[0]["op50"] <= 1 and rows[0]["false_positives_per_s"] >= 0
    text = suite.format_results({"machine": {}, "tracking-held-out": rows})
    assert "tracking accuracy held out seed mean of 4 (71-74) (5 s): OP50" in text
    row = rows[0]  # where the errors are: the causes add up to the switches, precision split by crossing
    assert sum(row[f"id_switches_{c}"] for c in ("crossing", "return", "other")) == pytest.approx(
        row["id_switches_per_object_minute"])
    assert "IDsw/obj/min at crossings" in text and "P@20 crossing" in text


def test_the_placement_ceiling_puts_tracks_sharing_a_blob_on_the_truth_boxes_they_overlap() -> None:
    from benchmarks.tracking import TruthPlacement

    truth = np.float64([[0, 1, 10, 10, 20, 20], [0, 2, 40, 10, 20, 20], [50_000, 1, 12, 10, 20, 20]])
    tracker = TruthPlacement(100, 60, truth)
    tracker.generate(40_000)  # between truth times, an object in both moves on linearly, one in the first stays
    preds = np.float32([[38, 12, 20, 20], [14, 8, 20, 20], [70, 40, 10, 10]])
    placed = tracker._layout(np.zeros((60, 100), np.float32), preds, preds[:, 2:], np.ones(3))
    np.testing.assert_allclose(placed, [[40, 10, 20, 20], [11.6, 10, 20, 20], [70, 40, 10, 10]], atol=1e-5)


def test_bench_tracker_speed_rows_print_as_a_table() -> None:
    from benchmarks import suite, tracking

    from services.tracker.objects.tracker import METHODS

    rows = tracking.speed(quick=True)
    assert [r["method"] for r in rows] == [*METHODS, next(iter(METHODS)), "dv MeanShiftTracker"]
    assert [r["window_ms"] for r in rows] == [10.0] * len(METHODS) + [15.0, 10.0]
    assert all(r["events_per_s"] > 0 and r["update_ms_p50"] > 0 for r in rows)
    assert rows[0]["stream_events_per_s"] > 3e5  # the dense stream the figures are for
    text = suite.format_results({"machine": {}, "tracker": rows})
    assert text.count("tracker speed") == len(rows) and "dv MeanShiftTracker" in text


def test_bench_tracker_speed_keeps_each_trackers_fastest_round() -> None:
    from benchmarks.tracking import fastest

    rounds = [{"method": "a", "window_ms": 10.0, "events_per_s": 5.0}, {"method": "a", "window_ms": 15.0,
              "events_per_s": 1.0}, {"method": "b", "window_ms": 10.0, "events_per_s": 2.0},
              {"method": "a", "window_ms": 10.0, "events_per_s": 4.0}, {"method": "a", "window_ms": 15.0,
              "events_per_s": 3.0}, {"method": "b", "window_ms": 10.0, "events_per_s": 7.0}]
    assert fastest(rounds) == [rounds[0], rounds[4], rounds[5]]


def test_bench_latency_times_updates_of_a_running_rig() -> None:
    from benchmarks import latency, suite

    rows = latency.run(quick=True)
    assert [r["web"] for r in rows] == [False, True]
    for row in rows:
        assert "error" not in row, row
        assert row["updates"] >= 50 and row["events_per_s"] > 1e5  # ~100 updates a second of a dense stream
        assert 0 < row["latency_ms_p50"] <= row["latency_ms_p99"] <= row["latency_ms_max"]
    text = suite.format_results({"machine": {}, "latency": rows})
    assert "etam up --no-web" in text and text.count("tracking latency") == 2
