"""Multi-object association with stable ids, a constant-velocity model, and an explicit lost state.

The drone report (seed 003) failed by locking onto noise once its target left and by never knowing
it had lost it. Here a track must be confirmed by several detections before it is reported as
tracked, turns `lost` (and is drawn at its predicted place) when detections stop, and is re-found
under the same id if a detection reappears near its prediction before it expires.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

TENTATIVE, TRACKED, LOST = 0, 1, 2


@dataclass
class AssociationParams:
    min_iou: float = 0.1
    gate_px: float = 40.0  # centre distance accepted when boxes do not overlap
    confirm_hits: int = 3
    lost_after_us: int = 60_000
    forget_after_us: int = 1_500_000
    velocity_gain: float = 0.3  # weight of a new velocity measurement


@dataclass
class Track:
    ident: int
    box: np.ndarray  # x, y, w, h
    t_us: int
    vel: np.ndarray = field(default_factory=lambda: np.zeros(2, np.float32))  # px/s of the centre
    hits: int = 1
    last_seen_us: int = 0
    state: int = TENTATIVE
    score: float = 0.3

    def predict(self, t_us: int) -> np.ndarray:
        dt_s = (t_us - self.last_seen_us) / 1e6
        box = self.box.copy()
        box[:2] += self.vel * dt_s
        return box


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise intersection over union of boxes a (N x 4) and b (M x 4), x y w h."""
    ax0, ay0, ax1, ay1 = a[:, 0:1], a[:, 1:2], a[:, 0:1] + a[:, 2:3], a[:, 1:2] + a[:, 3:4]
    bx0, by0, bx1, by1 = b[:, 0], b[:, 1], b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]
    iw = np.clip(np.minimum(ax1, bx1) - np.maximum(ax0, bx0), 0, None)
    ih = np.clip(np.minimum(ay1, by1) - np.maximum(ay0, by0), 0, None)
    inter = iw * ih
    union = a[:, 2:3] * a[:, 3:4] + b[:, 2] * b[:, 3] - inter
    return inter / np.maximum(union, 1e-6)


def _centres(boxes: np.ndarray) -> np.ndarray:
    return boxes[:, :2] + boxes[:, 2:] / 2


class MultiObjectTracker:
    """Keeps tracks from successive detections; `update` returns the tracks to report."""

    def __init__(self, params: AssociationParams | None = None) -> None:
        self.params = params or AssociationParams()
        self.tracks: list[Track] = []
        self._next_id = 1

    def update(self, t_us: int, boxes: np.ndarray) -> list[Track]:
        p = self.params
        predicted = np.array([tr.predict(t_us) for tr in self.tracks], np.float32).reshape(-1, 4)
        matches = self._match(predicted, boxes)
        matched_det = set()
        for ti, di in matches:
            self._correct(self.tracks[ti], boxes[di], t_us)
            matched_det.add(di)
        for tr in self.tracks:
            if tr.last_seen_us != t_us:
                tr.score *= 0.9
                if t_us - tr.last_seen_us > p.lost_after_us and tr.state != TENTATIVE:
                    tr.state = LOST
        self.tracks = [
            tr for tr in self.tracks
            if not (tr.state == TENTATIVE and tr.last_seen_us != t_us and t_us - tr.last_seen_us > p.lost_after_us)
            and t_us - tr.last_seen_us <= p.forget_after_us
        ]
        for di in range(len(boxes)):
            if di not in matched_det:
                self.tracks.append(Track(self._next_id, boxes[di].astype(np.float32), t_us, last_seen_us=t_us))
                self._next_id += 1
        return list(self.tracks)

    def _match(self, predicted: np.ndarray, boxes: np.ndarray) -> list[tuple[int, int]]:
        """Greedy assignment, best overlap first, then nearest centre within the gate."""
        if not len(predicted) or not len(boxes):
            return []
        overlap = iou(predicted, boxes)
        dist = np.linalg.norm(_centres(predicted)[:, None, :] - _centres(boxes)[None, :, :], axis=2)
        size = np.maximum(predicted[:, 2:].max(axis=1, keepdims=True), boxes[None, :, 2:].max(axis=2))
        # one cost: high overlap is best; without overlap, near centres (relative to size) still match
        cost = np.where(overlap >= self.params.min_iou, -overlap, dist / np.maximum(size, 1.0))
        allowed = (overlap >= self.params.min_iou) | (dist <= self.params.gate_px)
        pairs = []
        used_t, used_d = set(), set()
        for flat in np.argsort(np.where(allowed, cost, np.inf), axis=None):
            ti, di = divmod(int(flat), len(boxes))
            if not allowed[ti, di]:
                break
            if ti in used_t or di in used_d:
                continue
            pairs.append((ti, di))
            used_t.add(ti)
            used_d.add(di)
        return pairs

    def _correct(self, tr: Track, box: np.ndarray, t_us: int) -> None:
        dt_s = (t_us - tr.last_seen_us) / 1e6
        if dt_s > 0:
            measured = (_centres(box[None])[0] - _centres(tr.box[None])[0]) / dt_s
            g = self.params.velocity_gain
            tr.vel = ((1 - g) * tr.vel + g * measured).astype(np.float32)
        tr.box = box.astype(np.float32)
        tr.hits += 1
        tr.last_seen_us = t_us
        tr.t_us = t_us
        tr.score = min(1.0, 0.8 * tr.score + 0.2 + 0.0)
        if tr.hits >= self.params.confirm_hits:
            tr.state = TRACKED

    def reset(self) -> None:
        self.tracks = []
