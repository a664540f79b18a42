"""Tracking accuracy against ground-truth boxes (pure numpy): what `etam eval tracking` reports.

Boxes are rows (t_us, id, x, y, w, h). Each truth frame is compared with the latest predicted
frame at or before it (no older than `max_age_us`); boxes are matched one to one by IoU as CLEAR
MOT does (and py-motmetrics): a truth object keeps the predicted id it last matched while their
IoU stays >= 0.5, the rest are matched by Hungarian on IoU. Without that, two tracks on one pair
of overlapping targets swap matches from frame to frame and count as switches. Figures:
- OP50 / OP75: share of truth boxes whose match has IoU >= 0.5 / 0.75;
- success AUC: the mean, over IoU thresholds 0, 0.05, ..., 1, of the share matched above it;
- precision@20: share of truth boxes whose match's centre is within 20 px;
- false positives per second: predicted boxes matching no truth box at IoU >= 0.5, counted per
  truth frame and weighted by the frame period, i.e. the mean number of false boxes on screen; a
  box at least half inside a "don't care" box (an object in the image the truth does not score:
  mostly out of view or hidden, as MOT's ignore regions) is not counted. Frames with no truth box
  between the first and last count too (any box there is false);
- id switches: times the predicted id matched (IoU >= 0.5) to one truth object changes, each also
  listed (time, object, the id before and after) so that a tracker's faults can be looked up;
- where the errors are, so that a tracker's weak spot is told from a number: each switch is put down to
  a crossing (the object's box overlapped another object's, scored or not, within `CROSSING_US` before it),
  else to a return (the object was not scored for `RETURN_US` or more before it: back in view), else to
  neither; precision@20 is also given apart for truth boxes that overlap another object's box and for those
  clear of every other (occlusion-level breakdowns, as MOT benchmarks give);
- MOTA (CLEAR MOT): 1 - (misses + false boxes + id switches) / truth boxes;
- IDF1, IDP, IDR (Ristani et al. 2016): each truth object is paired with at most one track id for the
  whole sequence (the pairing that shares most frames at IoU >= 0.5); IDF1 is the F1 score of those
  shared frames. A switch that lasts a frame costs little there, a track that stays on the wrong
  object a lot, which the switch count cannot tell apart.
The figures MOTA and IDF1 agree with py-motmetrics' on the same boxes (tested).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from services.tracker.objects.association import intersection, iou

CROSSING_US = 500_000  # a switch this soon after its object's box overlapped another's is put down to the crossing
RETURN_US = 200_000  # ... else one after the object went unscored this long, to its return into view
SWITCH_CAUSES = ("crossing", "return", "other")


@dataclass
class TrackingScores:
    truth_boxes: int
    frames: int
    duration_s: float
    objects: int
    op50: float
    op75: float
    success_auc: float
    precision20: float
    false_positives_per_s: float
    id_switches: int
    id_switches_per_object_minute: float
    id_switch_events: list[dict[str, int | str]]  # t_us, object, from_id, to_id, cause (one of `SWITCH_CAUSES`)
    id_switches_by_cause: dict[str, int]
    precision20_crossing: float | None  # precision@20 of the truth boxes overlapping another object's box (None: none)
    precision20_clear: float | None  # ... and of those clear of every other
    crossing_share: float  # the share of truth boxes overlapping another object's box
    mota: float
    idf1: float
    idp: float
    idr: float

    def as_dict(self) -> dict:
        return asdict(self)


def split_frames(rows: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Frame times and the rows of each, from rows sorted or not by time."""
    times = np.unique(rows[:, 0])
    return times, _rows_at(rows, times)


def _rows_at(rows: np.ndarray, times: np.ndarray) -> list[np.ndarray]:
    """The rows at each of `times` (none where a time has none)."""
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    lo, hi = np.searchsorted(rows[:, 0], times, side="left"), np.searchsorted(rows[:, 0], times, side="right")
    return [rows[a:b] for a, b in zip(lo, hi, strict=True)]


def _match(objs: np.ndarray, idents: np.ndarray, overlap: np.ndarray,
           last_match: dict[int, int]) -> list[tuple[int, int]]:
    """Pairs (truth row, predicted row) with some overlap: each object's last matched id first, if
    they still overlap by IoU >= 0.5, then Hungarian on IoU for the rest."""
    pairs = []
    col = {int(ident): c for c, ident in enumerate(idents)}
    for r, obj in enumerate(objs):
        c = col.get(last_match.get(int(obj), -1))
        if c is not None and overlap[r, c] >= 0.5:
            pairs.append((r, c))
    rows = np.setdiff1d(np.arange(len(objs)), [r for r, _ in pairs])
    cols = np.setdiff1d(np.arange(len(idents)), [c for _, c in pairs])
    if len(rows) and len(cols):
        sub = overlap[np.ix_(rows, cols)]
        pairs += [(int(rows[r]), int(cols[c])) for r, c in zip(*linear_sum_assignment(-sub), strict=True)
                  if sub[r, c] > 0]
    return pairs


def _truth_frames(truth: np.ndarray, ignore: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """Frame times with their truth rows and "don't care" rows; frames missing from the truth's
    period between its first and last (nothing to score there) are filled in empty."""
    times = np.unique(np.concatenate([truth[:, 0], ignore[:, 0]]))
    if len(times) > 2:
        period = float(np.median(np.diff(times)))
        fill = [np.arange(a + period, b - period / 2, period) for a, b in zip(times[:-1], times[1:], strict=True)
                if b - a > 1.5 * period]
        times = np.unique(np.concatenate([times, *fill]))
    return times, _rows_at(truth, times), _rows_at(ignore, times)


def evaluate(pred: np.ndarray, truth: np.ndarray, max_age_us: int = 20_000,
             ignore: np.ndarray | None = None) -> TrackingScores:
    """Scores of predicted rows against truth rows (both N x 6: t_us, id, x, y, w, h), boxes inside
    the `ignore` rows (same layout) of their frame being neither hits nor false."""
    pred, truth = np.asarray(pred, np.float64).reshape(-1, 6), np.asarray(truth, np.float64).reshape(-1, 6)
    ignore = np.zeros((0, 6)) if ignore is None else np.asarray(ignore, np.float64).reshape(-1, 6)
    t_truth, truth_frames, ignore_frames = _truth_frames(truth, ignore)
    t_pred, pred_frames = split_frames(pred)
    ious: list[float] = []
    centre_err: list[float] = []
    false_boxes = scored_boxes = 0
    shared: dict[tuple[int, int], int] = {}  # (object, track id) -> frames they overlap at IoU >= 0.5
    last_match: dict[int, int] = {}
    switches: list[dict[str, int | str]] = []
    crossing: list[bool] = []  # per truth box, as `ious`
    last_scored: dict[int, float] = {}  # object -> the latest frame it was scored in
    last_crossed: dict[int, float] = {}  # object -> the latest frame its box overlapped another's
    for t, gt, dont_care in zip(t_truth, truth_frames, ignore_frames, strict=True):
        overlapping = _overlapping(gt, dont_care)
        crossing.extend(overlapping.tolist())
        for obj, overlaps in zip(gt[:, 1].astype(int).tolist(), overlapping.tolist(), strict=True):
            if overlaps:
                last_crossed[obj] = t
        k = np.searchsorted(t_pred, t, side="right") - 1
        pr = pred_frames[k] if k >= 0 and t - t_pred[k] <= max_age_us else np.zeros((0, 6))
        overlap = iou(gt[:, 2:6], pr[:, 2:6]) if len(pr) else np.zeros((len(gt), 0))
        best = np.zeros(len(gt))
        err = np.full(len(gt), np.inf)
        matched_pred = np.zeros(len(pr), bool)
        for r, c in _match(gt[:, 1], pr[:, 1], overlap, last_match):
            best[r] = overlap[r, c]
            centre_gt = gt[r, 2:4] + gt[r, 4:6] / 2
            centre_pr = pr[c, 2:4] + pr[c, 4:6] / 2
            err[r] = float(np.hypot(*(centre_gt - centre_pr)))
            if overlap[r, c] >= 0.5:
                matched_pred[c] = True
                obj, ident = int(gt[r, 1]), int(pr[c, 1])
                if obj in last_match and last_match[obj] != ident:
                    cause = ("crossing" if t - last_crossed.get(obj, -np.inf) <= CROSSING_US
                             else "return" if t - last_scored.get(obj, t) >= RETURN_US else "other")
                    switches.append({"t_us": int(t), "object": obj, "from_id": last_match[obj], "to_id": ident,
                                     "cause": cause})
                last_match[obj] = ident
        ious.extend(best.tolist())
        centre_err.extend(err.tolist())
        last_scored.update(dict.fromkeys(gt[:, 1].astype(int).tolist(), t))
        scored = np.ones(len(pr), bool)  # all but unmatched boxes on a "don't care" object
        if len(dont_care) and len(pr):
            inside = intersection(pr[:, 2:6], dont_care[:, 2:6]).max(axis=1) / np.maximum(pr[:, 4] * pr[:, 5], 1e-6)
            scored = matched_pred | (inside < 0.5)
        false_boxes += int((scored & ~matched_pred).sum())
        scored_boxes += int(scored.sum())
        for r, c in zip(*np.nonzero((overlap >= 0.5) & scored), strict=True):
            key = (int(gt[r, 1]), int(pr[c, 1]))
            shared[key] = shared.get(key, 0) + 1
    n = len(ious)
    iou_arr, err_arr, crossing_arr = np.asarray(ious), np.asarray(centre_err), np.asarray(crossing, bool)
    within20 = err_arr <= 20
    period_s = float(np.median(np.diff(t_truth))) / 1e6 if len(t_truth) > 1 else 0.0
    duration_s = len(t_truth) * period_s
    objects = len(np.unique(truth[:, 1])) if len(truth) else 0
    thresholds = np.linspace(0, 1, 21)
    n_switches = len(switches)
    id_tp = _id_true_positives(shared)
    return TrackingScores(
        truth_boxes=n, frames=len(t_truth), duration_s=duration_s, objects=objects,
        op50=float((iou_arr >= 0.5).mean()) if n else 0.0,
        op75=float((iou_arr >= 0.75).mean()) if n else 0.0,
        success_auc=float(np.mean([(iou_arr > th).mean() for th in thresholds])) if n else 0.0,
        precision20=float(within20.mean()) if n else 0.0,
        false_positives_per_s=false_boxes * period_s / duration_s if duration_s else 0.0,
        id_switches=n_switches,
        id_switches_per_object_minute=n_switches / objects / (duration_s / 60) if objects and duration_s else 0.0,
        id_switch_events=switches,
        id_switches_by_cause={c: sum(e["cause"] == c for e in switches) for c in SWITCH_CAUSES},
        precision20_crossing=float(within20[crossing_arr].mean()) if crossing_arr.any() else None,
        precision20_clear=float(within20[~crossing_arr].mean()) if (~crossing_arr).any() else None,
        crossing_share=float(crossing_arr.mean()) if n else 0.0,
        mota=1.0 - (int((iou_arr < 0.5).sum()) + false_boxes + n_switches) / n if n else 0.0,
        idf1=2 * id_tp / (n + scored_boxes) if n + scored_boxes else 0.0,
        idp=id_tp / scored_boxes if scored_boxes else 0.0,
        idr=id_tp / n if n else 0.0,
    )


def _overlapping(gt: np.ndarray, dont_care: np.ndarray) -> np.ndarray:
    """Per truth row of a frame, whether its box overlaps another object's box there, scored or not."""
    others = np.concatenate([gt, dont_care])
    if len(others) < 2 or not len(gt):
        return np.zeros(len(gt), bool)
    inter = intersection(gt[:, 2:6], others[:, 2:6])
    inter[gt[:, 1][:, None] == others[:, 1][None, :]] = 0  # an object does not cross itself
    return (inter > 0).any(axis=1)


def _id_true_positives(shared: dict[tuple[int, int], int]) -> int:
    """The most frames truth objects and track ids can share when each object is paired with at most
    one id and each id with one object, over the whole sequence (IDF1's IDTP)."""
    if not shared:
        return 0
    objects, row = np.unique([o for o, _ in shared], return_inverse=True)
    idents, col = np.unique([i for _, i in shared], return_inverse=True)
    counts = np.zeros((len(objects), len(idents)))
    counts[row, col] = list(shared.values())
    rows, cols = linear_sum_assignment(-counts)
    return int(counts[rows, cols].sum())
