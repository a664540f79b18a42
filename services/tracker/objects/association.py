"""Multi-object association with stable ids, a constant-velocity model and explicit track states.

The drone report (seed 003) lost slow targets, locked onto noise once its target had gone and never
knew it was lost. Here:
- a track is reported only once confirmed by several detections (`TENTATIVE` -> `TRACKED`);
- a target that stops (no more events) is held where it stopped, and a target hidden behind
  another coasts at its velocity, both still `TRACKED` for `hold_us`; one that leaves the image is
  let go at once;
- two tracks that share one detection (crossing targets) keep their sizes and move by prediction,
  nudged by a mean-shift `refine`, instead of collapsing onto the merged blob;
- small detections inside a track's box are fragments of it, not new targets; tracks that turn out
  to be one target (they share a detection and move together) merge into the oldest;
- a `LOST` track is re-found under the same id when a detection of its size appears near its
  prediction before `forget_after_us`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

TENTATIVE, TRACKED, LOST = 0, 1, 2
_GONE = -1  # merged or expired during an update; removed before it returns

Refine = Callable[[np.ndarray], np.ndarray]  # a predicted box -> the box moved onto the events


@dataclass
class AssociationParams:
    min_iou: float = 0.1
    gate: float = 0.75  # centre distance accepted without overlap, in track sizes
    redetect_gate: float = 1.5  # the same for a lost track, which may have moved unseen
    confirm_hits: int = 4
    lost_after_us: int = 50_000  # a tentative track unseen this long is dropped
    hold_us: int = 2_000_000  # a confirmed track unseen this long is lost
    forget_after_us: int = 2_000_000  # a lost track unseen this long is forgotten
    velocity_gain: float = 0.3  # weight of a new velocity measurement
    size_gain: float = 0.5  # weight of a new size measurement
    refine_gain: float = 0.3  # weight of the mean-shift correction of tracks in a shared detection
    fragment_area: float = 0.5  # a detection this much smaller than a track, inside it, is a fragment
    same_velocity_px_s: float = 40.0  # tracks in one detection moving this alike are one target
    young_us: int = 300_000  # a track younger than this merges into an older one it shares with


@dataclass
class Track:
    ident: int
    box: np.ndarray  # x, y, w, h at `t_us`
    t_us: int
    vel: np.ndarray = field(default_factory=lambda: np.zeros(2, np.float32))  # px/s of the centre
    hits: int = 1
    first_seen_us: int = 0
    last_seen_us: int = 0
    state: int = TENTATIVE
    score: float = 0.3

    def predict(self, t_us: int) -> np.ndarray:
        box = self.box.copy()
        box[:2] += self.vel * ((t_us - self.t_us) / 1e6)
        return box


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise intersection over union of boxes a (N x 4) and b (M x 4), x y w h."""
    inter = intersection(a, b)
    union = a[:, 2:3] * a[:, 3:4] + b[:, 2] * b[:, 3] - inter
    return inter / np.maximum(union, 1e-6)


def intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise intersection areas of boxes a (N x 4) and b (M x 4), x y w h."""
    iw = np.minimum(a[:, 0:1] + a[:, 2:3], b[:, 0] + b[:, 2]) - np.maximum(a[:, 0:1], b[:, 0])
    ih = np.minimum(a[:, 1:2] + a[:, 3:4], b[:, 1] + b[:, 3]) - np.maximum(a[:, 1:2], b[:, 1])
    return np.clip(iw, 0, None) * np.clip(ih, 0, None)


def _centres(boxes: np.ndarray) -> np.ndarray:
    return boxes[:, :2] + boxes[:, 2:] / 2


def _union(boxes: np.ndarray) -> np.ndarray:
    x0, y0 = boxes[:, 0].min(), boxes[:, 1].min()
    return np.array([x0, y0, (boxes[:, 0] + boxes[:, 2]).max() - x0, (boxes[:, 1] + boxes[:, 3]).max() - y0],
                    np.float32)


class MultiObjectTracker:
    """Keeps tracks from successive detections; `update` returns the tracks to report."""

    def __init__(self, params: AssociationParams | None = None, width: int = 0, height: int = 0) -> None:
        self.params = params or AssociationParams()
        self.width, self.height = width, height
        self.tracks: list[Track] = []
        self._next_id = 1

    def update(self, t_us: int, boxes: np.ndarray, refine: Refine | None = None) -> list[Track]:
        """Tracks at `t_us` given the detections (N x 4 boxes) of that time."""
        p = self.params
        boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
        pred = np.array([tr.predict(t_us) for tr in self.tracks], np.float32).reshape(-1, 4)
        inter = intersection(pred, boxes)
        track_area = np.maximum(pred[:, 2] * pred[:, 3], 1.0)[:, None]
        det_area = np.maximum(boxes[:, 2] * boxes[:, 3], 1.0)[None, :]
        live = np.array([tr.state != LOST for tr in self.tracks], bool)
        # a detection holding most of two or more live tracks is shared (crossing targets) or the
        # tracks are one target seen in pieces before: merge those, refine the rest
        inside = (inter / track_area >= 0.5) & live[:, None]
        shared: dict[int, list[int]] = {}
        for di in np.flatnonzero(inside.sum(axis=0) >= 2):
            members = self._merge_alike(t_us, [int(i) for i in np.flatnonzero(inside[:, di])])
            if len(members) >= 2:
                shared[int(di)] = members
        in_shared = {ti for members in shared.values() for ti in members}
        live &= self._states() != _GONE
        assigned = self._match(pred, boxes, exclude_tracks=in_shared, exclude_dets=set(shared))
        used = set(assigned.values()) | set(shared)
        # fragments: small detections mostly inside a track's prediction join its measurement
        pieces: dict[int, list[int]] = {ti: [di] for ti, di in assigned.items()}
        for di in range(len(boxes)):
            if di in used:
                continue
            cover = np.where(live, inter[:, di] / det_area[0, di], 0.0)
            ti = int(np.argmax(cover)) if len(cover) else -1
            if ti >= 0 and cover[ti] >= 0.6 and det_area[0, di] < p.fragment_area * track_area[ti, 0]:
                if ti in pieces and t_us - self.tracks[ti].first_seen_us < p.young_us:
                    pieces[ti].append(di)  # a target first seen in pieces: its box grows to hold them
                used.add(di)
        for ti, dets in pieces.items():
            self._correct(self.tracks[ti], _union(boxes[dets]), t_us)
        for ti in in_shared:
            self._coast(self.tracks[ti], pred[ti], t_us, refine)
        observed = pred[sorted(set(pieces) | in_shared)]
        for ti, tr in enumerate(self.tracks):
            if ti not in pieces and ti not in in_shared and tr.state != _GONE:
                self._unseen(tr, pred[ti], t_us, observed)
        self.tracks = [tr for tr in self.tracks if tr.state != _GONE]
        for di in range(len(boxes)):
            if di not in used:
                self.tracks.append(Track(self._next_id, boxes[di].copy(), t_us, first_seen_us=t_us,
                                         last_seen_us=t_us))
                self._next_id += 1
        return list(self.tracks)

    def _merge_alike(self, t_us: int, members: list[int]) -> list[int]:
        """Of tracks sharing one detection, fold each young or same-moving one into the oldest of
        them (marked `_GONE`, removed after the update); the members left."""
        p = self.params
        members.sort(key=lambda i: self.tracks[i].ident)
        keep: list[int] = []
        for i in members:
            tr = self.tracks[i]
            for k in keep:
                older = self.tracks[k]
                alike = np.linalg.norm(tr.vel - older.vel) <= p.same_velocity_px_s
                if tr.state == TENTATIVE or t_us - tr.first_seen_us < p.young_us or alike:
                    older.hits = max(older.hits, tr.hits)
                    tr.state = _GONE
                    break
            else:
                keep.append(i)
        return keep

    def _match(self, pred: np.ndarray, boxes: np.ndarray, exclude_tracks: set[int],
               exclude_dets: set[int]) -> dict[int, int]:
        """One-to-one assignment, greedy by overlap, then by centre distance within the gate; lost
        tracks also take detections of their size near their prediction (re-detection)."""
        if not len(pred) or not len(boxes):
            return {}
        p = self.params
        overlap = iou(pred, boxes)
        dist = np.linalg.norm(_centres(pred)[:, None, :] - _centres(boxes)[None, :, :], axis=2)
        size = np.maximum(pred[:, 2:].max(axis=1, keepdims=True), 1.0)
        lost = np.array([tr.state == LOST for tr in self.tracks])[:, None]
        area_ratio = (boxes[None, :, 2] * boxes[None, :, 3]) / np.maximum(pred[:, 2:3] * pred[:, 3:4], 1.0)
        similar = (area_ratio > 0.4) & (area_ratio < 2.5)
        gate = np.where(lost, p.redetect_gate, p.gate) * size
        allowed = ((overlap >= p.min_iou) | ((dist <= gate) & similar)) & (self._states()[:, None] != _GONE)
        allowed[list(exclude_tracks), :] = False
        allowed[:, list(exclude_dets)] = False
        cost = np.where(overlap >= p.min_iou, -overlap, dist / size)
        cost = cost + lost * 0.5  # live tracks first
        out: dict[int, int] = {}
        used_d: set[int] = set()
        for flat in np.argsort(np.where(allowed, cost, np.inf), axis=None):
            ti, di = divmod(int(flat), len(boxes))
            if not allowed[ti, di]:
                break
            if ti in out or di in used_d:
                continue
            out[ti] = di
            used_d.add(di)
        return out

    def _states(self) -> np.ndarray:
        return np.array([tr.state for tr in self.tracks], np.int8)

    def _correct(self, tr: Track, box: np.ndarray, t_us: int) -> None:
        """A measured box: velocity from the centre's move, size smoothed."""
        p = self.params
        dt_s = (t_us - tr.t_us) / 1e6
        if dt_s > 0 and tr.state != LOST:
            measured = (_centres(box[None])[0] - _centres(tr.box[None])[0]) / dt_s
            tr.vel = ((1 - p.velocity_gain) * tr.vel + p.velocity_gain * measured).astype(np.float32)
        elif tr.state == LOST:
            tr.vel[:] = 0
        if tr.state == LOST or tr.hits < p.confirm_hits:
            tr.box = box.astype(np.float32)
        else:
            size = (1 - p.size_gain) * tr.box[2:] + p.size_gain * box[2:]
            tr.box = np.concatenate([_centres(box[None])[0] - size / 2, size]).astype(np.float32)
        tr.hits += 1
        tr.t_us = tr.last_seen_us = t_us
        tr.score = min(1.0, 0.8 * tr.score + 0.2)
        if tr.hits >= p.confirm_hits:
            tr.state = TRACKED

    def _coast(self, tr: Track, pred: np.ndarray, t_us: int, refine: Refine | None) -> None:
        """A track inside a shared detection: its predicted box, nudged towards its events."""
        box = pred
        if refine is not None:
            moved = refine(pred)
            box = pred.copy()
            box[:2] += self.params.refine_gain * (moved[:2] - pred[:2])
        tr.box = box.astype(np.float32)
        tr.t_us = tr.last_seen_us = t_us

    def _unseen(self, tr: Track, pred: np.ndarray, t_us: int, observed: np.ndarray) -> None:
        """No detection: drop a tentative track after a while; let go of a track that left the
        image; coast one hidden behind an observed track; hold one that stopped."""
        p = self.params
        unseen_us = t_us - tr.last_seen_us
        if tr.state == TENTATIVE:
            if unseen_us > p.lost_after_us:
                tr.state = _GONE
            return
        if tr.state == LOST:
            if unseen_us > p.forget_after_us:
                tr.state = _GONE
            return
        if self._leaving(tr.box):
            tr.state = LOST
            return
        hidden = len(observed) and intersection(pred[None], observed).max() >= 0.5 * pred[2] * pred[3]
        if not hidden:
            tr.vel *= np.float32(0.5)  # a target without events has stopped: hold it
            pred = tr.predict(t_us)
        tr.box, tr.t_us = pred, t_us
        tr.score *= 0.995
        if unseen_us > p.hold_us:
            tr.state = LOST

    def _leaving(self, box: np.ndarray) -> bool:
        """True if a box touches the image border (its target may have left): unseen, it is let go."""
        if not self.width:
            return False
        return bool(box[0] <= 1 or box[1] <= 1 or box[0] + box[2] >= self.width - 1
                    or box[1] + box[3] >= self.height - 1)

    def reset(self) -> None:
        self.tracks = []
