"""Object tracking: accuracy on simulated sequences, and speed.

Accuracy: `etam sim objects` with noise on, several seeds, each run through `etam track` with
every method and scored by `etam eval tracking` (OP50, OP75, success AUC, precision@20, false
positives per second, id switches per object and minute), beside dv-processing's MeanShiftTracker
on the same events. That tracker reports points, not boxes; each point is scored as a box of its
own kernel (2 x bandwidth square) around it, so its precision@20 is the fair comparison.
The tracker's faults were traced on these seeds, one by one, so they flatter it; `held_out` scores
the default method on seeds no one looked at while tuning it, the honest measure of how it does on
scenes it has never seen.

Where the default method's remaining errors come from: the same association fed the simulator's
truth boxes as its detections, once as they are and once with overlapping boxes merged into their
union (what one blob of events gives a detector); and the default tracker whose tracks sharing a
blob are placed on the truth boxes their predictions overlap most, instead of by its layout: on those
of the targets in view (what a perfect layout could do: no layout sees a hidden target), and on those
of hidden ones too. None is a tracker; they bound what a better detector, one that splits touching
targets, or a better placement of the targets in one blob would reach.

Speed: every method and MeanShiftTracker on the same 10 ms packets at 346x260 (events per second
of processing on one core, ms per update), and the default method's update of a 15 ms window, with
OpenCV and BLAS held to one thread as the live service holds them. The objects scene is simulated
with a lower contrast threshold so that it streams about 1 Mev/s, the rate the issue's figures for
MeanShiftTracker (0.37 ms per 10 ms packet) were taken at. Each is
timed in `SPEED_ROUNDS` rounds that take turns with the others, and its fastest round is reported
(as `timeit` does): on a shared machine a slow round measures the neighbours, and taking turns
gives every tracker the same chance of a quiet one.
"""

from __future__ import annotations

import datetime
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from services.camera.formats import open_recording
from services.camera.offline import simulate
from services.camera.simulator import DURATION_S as SIM_DURATION_S
from services.camera.simulator import SimParams
from services.threads import one_thread
from services.tracker.offline import CSV_HEADER, eval_tracking, track
from services.tracker.evaluation import SWITCH_CAUSES, split_frames
from services.tracker.objects.association import intersection, iou, union
from services.tracker.objects.tracker import DEFAULT_METHOD, METHODS, ObjectTracker, method_params, warm_up

FIGURES = ("op50", "op75", "success_auc", "precision20", "false_positives_per_s", "id_switches_per_object_minute",
           "idf1", "mota")
DV_BANDWIDTH_PX = 20
PACKET_US = 10_000
SPEED_SIM = SimParams(contrast=0.06)  # the objects scene at about 1 Mev/s
SPEED_ROUNDS = 3
HELD_OUT_SEEDS = tuple(range(71, 111))  # never looked at while tuning: keep them so


def run(quick: bool = False, seeds: tuple[int, ...] = (11, 12, 13, 14, 15)) -> list[dict]:
    seeds = seeds[:2] if quick else seeds
    duration_s = 5.0 if quick else 20.0
    scores: dict[str, list[dict]] = {m: [] for m in (*METHODS, *CEILINGS, "dv MeanShiftTracker")}
    rows = []
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        for seed in seeds:
            h5 = Path(tmp) / f"objects{seed}.h5"
            simulate("objects", h5, duration_s, seed=seed, progress=False)
            for method in METHODS:
                csv = Path(tmp) / f"{method}{seed}.csv"
                track(h5, csv, method_params(method), progress=False)
                scores[method].append(eval_tracking(csv, h5))
            with open_recording(h5) as rec:
                truth = rec.truth.boxes[:, :6].astype(np.float64)
                in_image = np.concatenate([truth, rec.truth.ignore[:, :6].astype(np.float64)])
            for k, (name, make) in enumerate(CEILINGS.items()):
                csv = Path(tmp) / f"ceiling{k}_{seed}.csv"
                track(h5, csv, progress=False, make_tracker=lambda w, h, _, m=make, t=truth, i=in_image: m(w, h, t, i))
                scores[name].append(eval_tracking(csv, h5))
            csv = Path(tmp) / f"dv{seed}.csv"
            _dv_track(h5, csv)
            scores["dv MeanShiftTracker"].append(eval_tracking(csv, h5))
    for seed, s in zip(seeds, scores[DEFAULT_METHOD], strict=True):
        rows.append({"stage": "tracking accuracy", "method": DEFAULT_METHOD, "seed": seed, "duration_s": duration_s,
                     **{k: s[k] for k in FIGURES}})
    for method, per_seed in scores.items():
        rows.append({"stage": "tracking accuracy", "method": method, "seed": "mean", "duration_s": duration_s,
                     **_mean(per_seed)})
    return rows


def held_out(quick: bool = False) -> list[dict]:
    """The default method's mean figures on the held-out seeds, 20 s each (the scene's targets leave and come
    back in at once at its 12 s period, a hard re-identification), and as long as `etam sim` makes them by
    default (10 s: its targets come in once); the first four seeds, once, shorter, when quick."""
    seeds = HELD_OUT_SEEDS[:4] if quick else HELD_OUT_SEEDS
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        return [{"stage": "tracking accuracy held out", "method": DEFAULT_METHOD,
                 "seed": f"mean of {len(seeds)} ({seeds[0]}-{seeds[-1]})", "duration_s": duration_s,
                 **_mean([_default_scores(Path(tmp), seed, duration_s) for seed in seeds])}
                for duration_s in ((5.0,) if quick else (20.0, SIM_DURATION_S))]


def _default_scores(tmp: Path, seed: int, duration_s: float) -> dict:
    """The default method's figures on one simulated `objects` sequence (made and tracked in `tmp`)."""
    h5, csv = tmp / f"objects{seed}.h5", tmp / f"{seed}.csv"
    simulate("objects", h5, duration_s, seed=seed, progress=False)
    track(h5, csv, method_params(DEFAULT_METHOD), progress=False)
    return eval_tracking(csv, h5)


def _mean(per_seed: list[dict]) -> dict[str, float]:
    """The mean figures, with where the errors are: id switches per object-minute by cause, and precision@20
    of the truth boxes that overlap another object's and of those clear of every other."""
    rate = [s["id_switches_per_object_minute"] / max(s["id_switches"], 1) for s in per_seed]
    causes = {f"id_switches_{cause}": float(np.mean([r * s["id_switches_by_cause"][cause]
                                                     for r, s in zip(rate, per_seed, strict=True)]))
              for cause in SWITCH_CAUSES}
    split = {k: float(np.mean(v)) if (v := [s[k] for s in per_seed if s[k] is not None]) else None
             for k in ("precision20_crossing", "precision20_clear")}
    return {k: float(np.mean([s[k] for s in per_seed])) for k in FIGURES} | causes | split


class _WithTruth(ObjectTracker):
    """The default tracker that knows the simulator's truth boxes (N x 6 rows) at each time."""

    def __init__(self, width: int, height: int, truth: np.ndarray) -> None:
        super().__init__(width, height, method_params(DEFAULT_METHOD))
        self.truth_times, self.truth_rows = split_frames(truth)

    def _truth_at(self, t_us: int) -> np.ndarray:
        """The boxes at `t_us`, moved on linearly towards the next truth time: the truth comes at a lower rate
        than the updates, and a box left where it was for an update is a target that stopped, to the
        association (it halved the velocities of fast targets, whose tracks then fell behind them)."""
        k = int(np.searchsorted(self.truth_times, t_us, side="right")) - 1
        if k < 0:
            return np.zeros((0, 4), np.float32)
        rows = self.truth_rows[k][:, 1:6].astype(np.float64)
        if k + 1 < len(self.truth_times) and t_us > self.truth_times[k]:
            share = (t_us - self.truth_times[k]) / (self.truth_times[k + 1] - self.truth_times[k])
            after = {int(r[0]): r for r in self.truth_rows[k + 1][:, 1:6]}
            rows = np.asarray([r + share * (after[int(r[0])] - r) if int(r[0]) in after else r for r in rows])
        return rows.reshape(-1, 5)[:, 1:].astype(np.float32)


class TruthBoxes(_WithTruth):
    """The default tracker with the truth boxes as its detections, overlapping ones merged into their
    union if `merged` (as one blob of events would be); its events still feed the counts and layouts
    the association uses."""

    def __init__(self, width: int, height: int, truth: np.ndarray, merged: bool) -> None:
        super().__init__(width, height, truth)
        self.merged = merged

    def _detect(self, image: np.ndarray, t_us: int) -> np.ndarray:
        boxes = self._truth_at(t_us)
        return _merge_overlapping(boxes) if self.merged else boxes


class TruthPlacement(_WithTruth):
    """The default tracker whose tracks sharing a blob are placed on the truth boxes it is given (of the objects
    in view, or of every object in the image) their predictions overlap most, one to one, instead of by its layout
    (and not moved towards where their templates are)."""

    def __init__(self, width: int, height: int, truth: np.ndarray) -> None:
        super().__init__(width, height, truth)
        self.params.appearance.reach_px = 0

    def _detect(self, image: np.ndarray, t_us: int) -> np.ndarray:
        self.t_us = t_us  # the layout of this update places on the truth of this time
        return super()._detect(image, t_us)

    def _layout(self, image: np.ndarray, boxes: np.ndarray, sizes: np.ndarray, fills: np.ndarray,
                fixed: np.ndarray | None = None) -> np.ndarray:
        placed = np.asarray(boxes, np.float32).reshape(-1, 4).copy()
        truth = self._truth_at(self.t_us)
        if len(truth) and len(placed):
            overlap = iou(placed, truth)
            for i, j in zip(*linear_sum_assignment(-overlap), strict=True):
                if overlap[i, j] > 0.1:
                    placed[i] = truth[j]
        return placed


# name -> the tracker, from the sensor size, the truth boxes in view and those with every object in the image too.
# Blobs placed on the truth of the targets in view bound what a better layout could reach (no layout sees a hidden
# target); placed on every object's, they add where the hidden ones are
CEILINGS: dict[str, Callable[[int, int, np.ndarray, np.ndarray], ObjectTracker]] = {
    "association on truth boxes": lambda w, h, truth, _: TruthBoxes(w, h, truth, merged=False),
    "association on merged truth boxes": lambda w, h, truth, _: TruthBoxes(w, h, truth, merged=True),
    "default, blobs placed on truth boxes, hidden ones too": lambda w, h, _, in_image: TruthPlacement(w, h, in_image),
    "default, blobs placed on the truth boxes of targets in view": lambda w, h, truth, _: TruthPlacement(w, h, truth),
}


def _merge_overlapping(boxes: np.ndarray) -> np.ndarray:
    merged: list[tuple[float, ...]] = []
    for box in map(tuple, boxes.tolist()):
        while hit := [i for i, m in enumerate(merged) if intersection(np.float32([box]), np.float32([m]))[0, 0] > 0]:
            box = union([box, merged.pop(hit[0])])
        merged.append(box)
    return np.float32(merged).reshape(-1, 4)


def _packets(h5: Path, window_us: int = PACKET_US) -> tuple[list[tuple[int, np.ndarray]], int, int]:
    """The file's events cut into windows of `window_us`, each with its end time, and the sensor size."""
    with open_recording(h5) as rec:
        ev = np.concatenate(list(rec.chunks()))
        width, height = rec.width, rec.height
    ends = np.arange(window_us, int(ev["t"][-1]) + 1, window_us)
    cuts = np.searchsorted(ev["t"], ends)
    return list(zip(ends.tolist(), np.split(ev, cuts)[:-1], strict=True)), width, height


def _dv_track(h5: Path, out: Path) -> float:
    """dv-processing's MeanShiftTracker over 10 ms packets; its points written as tracks CSV boxes.
    Returns its processing time (s), EventStores built beforehand."""
    import dv_processing as dv

    from benchmarks.filters import dv_stores

    packets, width, height = _packets(h5)
    stores = dv_stores([p for _, p in packets])
    tracker = dv.features.MeanShiftTracker((width, height), DV_BANDWIDTH_PX, datetime.timedelta(microseconds=PACKET_US))
    tracker.setMaxTracks(10)
    rows = []
    t0 = time.perf_counter()
    results = []
    for (t_us, _), store in zip(packets, stores, strict=True):
        tracker.accept(store)
        results.append((t_us, tracker.runTracking()))
    elapsed = time.perf_counter() - t0
    side = 2 * DV_BANDWIDTH_PX
    for t_us, result in results:
        for kp in (result.keypoints if result is not None else []):
            rows.append((t_us, kp.class_id, kp.pt[0] - side / 2, kp.pt[1] - side / 2, side, side, 1.0))
    np.savetxt(out, np.asarray(rows, np.float64).reshape(-1, 7), fmt=["%d", "%d", "%.2f", "%.2f", "%.2f", "%.2f",
               "%.3f"], delimiter=",", header=CSV_HEADER, comments="")
    return elapsed


def speed(quick: bool = False) -> list[dict]:
    """Events per second of processing and ms per update, per method and for MeanShiftTracker."""
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        h5 = Path(tmp) / "objects.h5"
        duration_s = 2.0 if quick else 6.0
        simulate("objects", h5, duration_s, seed=11, progress=False, params=SPEED_SIM)
        packets, width, height = _packets(h5)
        n_events = sum(len(p) for _, p in packets)
        rounds = 1 if quick else SPEED_ROUNDS
        stream = {"stream_events_per_s": n_events / duration_s, "rounds": rounds}
        windows, _, _ = _packets(h5, 15_000)
        for method in METHODS:
            warm_up(method_params(method))  # numba kernels loaded before any timing
        timings = []
        with one_thread():  # as the live service runs them
            for _ in range(rounds):
                timed = [_time_tracker(method, packets, width, height, n_events, PACKET_US) for method in METHODS]
                timed.append(_time_tracker(DEFAULT_METHOD, windows, width, height,
                                           sum(len(w) for _, w in windows), 15_000))
                elapsed = _dv_track(h5, Path(tmp) / "dv.csv")
                timed.append({"stage": "tracker speed", "method": "dv MeanShiftTracker",
                              "window_ms": PACKET_US / 1e3, "events": n_events, "events_per_s": n_events / elapsed,
                              "update_ms_p50": elapsed / len(packets) * 1e3})
                timings.extend(timed)
    return [row | stream for row in fastest(timings)]


def fastest(timings: list[dict]) -> list[dict]:
    """Of rows timing the same tracker and window in several rounds, the fastest, in first-seen order."""
    best: dict[tuple[str, float], dict] = {}
    for row in timings:
        key = (row["method"], row["window_ms"])
        if key not in best or row["events_per_s"] > best[key]["events_per_s"]:
            best[key] = row
    return list(best.values())


def _time_tracker(method: str, packets: list[tuple[int, np.ndarray]], width: int, height: int, n_events: int,
                  window_us: int) -> dict:
    tracker = ObjectTracker(width, height, method_params(method))
    per_update = []
    t0 = time.perf_counter()
    for t_us, ev in packets:
        t1 = time.perf_counter()
        tracker.accept(ev)
        tracker.generate(t_us)
        per_update.append((time.perf_counter() - t1) * 1e3)
    wall = time.perf_counter() - t0
    return {"stage": "tracker speed", "method": method, "window_ms": window_us / 1e3, "events": n_events,
            "events_per_s": n_events / wall, "update_ms_p50": float(np.median(per_update)),
            "update_ms_p99": float(np.percentile(per_update, 99))}
