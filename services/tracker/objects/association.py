"""Multi-object association with stable ids, a constant-velocity model and explicit track states.

The drone report (seed 003) lost slow targets, locked onto noise once its target had gone and never
knew it was lost. Here:
- a track is reported only once confirmed by several detections (`TENTATIVE` -> `TRACKED`), and
  as tentative while a lost track may still give it its id (`reported_state`); one whose detections
  end while it is young (a remnant a target left, or noise) is let go, not held;
- a target that stops is held where it stopped, from the moment its detection has far fewer new
  events than usual (it is only the fading image of the target), not once the detection has gone,
  and a detection that overlaps it only a little (a target passing over it) does not take it away;
  a target going behind another keeps its usual size where its detection is cut by the other's box,
  and moves with the edge still seen (not the box's centre, which jumps as the size comes back);
  a target hidden behind others (their boxes cover most of it) coasts at its velocity, or in a
  blob it shares with the nearer one is still placed but counts as unseen; all stay `TRACKED` for
  `hold_us`; one that stops at a border with most of it in view is held too, but one that
  leaves the image is lost, and a target coming in at that border with its size (on the axis
  the border does not cut, measured again as more of it comes in) takes its id back, wherever
  along the border it comes in, unless two lost tracks fit about as well (seed 002 re-identifies a
  target back in view by its likeness);
- two tracks that share one detection (crossing targets; not one with a detection of its own, a
  small target seen inside a big one's box) keep their sizes instead of collapsing onto the merged
  blob (up to slow corrections towards the events), and a `layout` places them on its events (see
  `layout.py`); one hidden there takes a detection of its size apart from the blob near its
  prediction (it comes out from behind the nearer one); one that stops there, told by the new
  events in the part of its box the others leave, is held instead of laid onto the moving one's
  events;
- small detections inside a track's box are fragments of it, not new targets; tracks that turn out
  to be one target (they share a detection, move together and overlap) merge into the oldest (or, of
  two confirmed ones, the one whose box fits their detection), and a track
  left alone in a detection much bigger than itself (it held a piece or a remnant of its target)
  takes that detection whole; a detection much bigger than the one track it holds, whose events the
  track's box at its own size leaves partly unexplained beside it, holds a second target, which gets a
  detection of its own;
- a track's detection whose points move two ways (optical flow, see `motion.py`) holds two targets
  that came in or were first seen together, or that met and went on as one blob for a while: it is
  split in two, the track keeping the part its box overlaps more; the other part's track is a target of its
  own, not a young piece of the first to fold back into it;
- a `LOST` track is re-found under the same id when a detection of its size appears near its
  prediction before `forget_after_us`; a target coming out from behind a nearer one (a new track
  at the edge of that one's box) takes back the id of the track hidden there, by its size, as one
  coming back in at a border does; and a new track anywhere away from the borders (targets do not
  come from nothing there) takes the id of a track unseen since before it appeared whose size it
  fits on both axes, even one merged into another (it was a second target after all).

An update sees a handful of tracks and detections, so the boxes are plain tuples of floats: numpy's
per-call cost on arrays of three boxes was most of an update's time.
"""

from __future__ import annotations

import itertools
import math
import statistics
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

TENTATIVE, TRACKED, LOST = 0, 1, 2
LEFT, TOP, RIGHT, BOTTOM = 1, 2, 4, 8  # the image borders a box touches, as bits
CUT_X, CUT_Y = LEFT | RIGHT, TOP | BOTTOM  # borders that cut a box's width, its height
WHOLE = 0.9  # a box this share of its track's usual size or more shows the whole target
SIZE_NOW = 32  # the latest measurements of a track's size that tell its size now (a target's size changes as it moves)
# measurements kept for re-identification (some 3 s of sightings): a target's last fraction of a second in view is
# often beside another (two leave together), and its size there is theirs. On four sets of 60 dev seeds, ids
# taken back by the median of the latest 300 instead of 32 gave IDF1 +0.01-0.02 on each set, id switches per
# object-minute 2.18 -> 2.14 (up 0.05 on one set), precision@20 unchanged
SIZE_MEMORY = 300
BORDER_PX = 3  # a box this near an image border touches it: a target's edge fades out a pixel or two before it goes
PATH_UPDATES = 8  # updates of a track's centre kept, for `MultiObjectTracker.seen_box`
_GONE = -1  # merged or expired during an update; removed before it returns

Box = tuple[float, float, float, float]  # x, y, w, h
# predicted boxes (K x 4), the sizes the tracks measured on their own (K x 2), the share of their pixels the
# targets usually fire (K), the boxes of the other tracks (F x 4: their pixels are theirs) -> the boxes placed on
# the events
Layout = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]
# a detection, the boxes placed in it -> the box of its recent pixels they leave, their count, the detection's count
Leftover = Callable[[Box, np.ndarray], tuple[np.ndarray, int, int]]
# boxes (N x 4) -> the events in each since the last update
Counts = Callable[[np.ndarray], np.ndarray]
# a detection -> the boxes (2 x 4) of two targets moving apart in it, or None
Motions = Callable[[Box], np.ndarray | None]
# the two boxes of the targets whose union a detection's shape is, if it is two's (`shapes.two_rectangles`)
Shapes = Callable[[Box], np.ndarray | None]
# a box, the boxes beside it and a guess (px/s) -> the velocity (px/s) of the events in it outside those, or None
PartVelocity = Callable[[Box, list[Box], tuple[float, float]], tuple[float, float] | None]


class Looks(Protocol):
    """What a track's target looks like (`capture`: a template of the image in its box, None if it cannot be
    taken there) and where that template is about a predicted box (`find`: the shift to it, None if not found);
    see `appearance.py`."""

    def capture(self, box: Box) -> np.ndarray | None: ...

    def find(self, template: np.ndarray, box: Box) -> tuple[float, float] | None: ...


@dataclass
class AssociationParams:
    min_iou: float = 0.1
    # a still (held) track takes only a detection overlapping it this much: its target moving on again starts
    # from where it stood, while one passing over it (traced on seeds 1 and 44) took its track away
    still_min_iou: float = 0.2
    gate: float = 0.75  # centre distance accepted without overlap, in track sizes
    redetect_gate: float = 1.5  # the same for a lost track, which may have moved unseen
    confirm_hits: int = 4
    lost_after_us: int = 50_000  # a tentative track unseen this long is dropped
    hold_us: int = 2_000_000  # a confirmed track unseen this long is lost
    # a track lost this long is forgotten: a target back within it (from behind something, out of the view and in
    # again) takes its id back by its size (four dev sets of 60 seeds: id switches per object-minute 1.80 with 2 s,
    # 1.73 with 3 s, 1.72 with 4 s, 1.73 with 6 s; three fresh sets 2.29 -> 2.24, 2.58 -> 2.49, 2.53 -> 2.46)
    forget_after_us: int = 4_000_000
    # a target back through a border has its lost track's size within this ratio: sizes in the decayed image
    # include the trail a target's motion leaves (some 5-15% at usual speeds), which differs between its ways
    # out and back in
    reid_size_ratio: float = 1.25
    # of two lost tracks that fit, the better one's size error is under this share of the other's
    reid_margin: float = 0.5
    # a track coming in at a border longer along it than any of the lost tracks that left there (`_holds_two`) is
    # two of them back in one blob: it stays `entering` (reported tentative, trying for an id each update) up to this
    # long after it was first seen, not `young_us`, so that it is not shown with a new id that one of them keeps once
    # they part. On four sets of 60 seeds (200-259, 500-679) id switches per object-minute 1.790 -> 1.769
    # (1.588 -> 1.538, 2.157 -> 2.157, 1.992 -> 1.975, 1.422 -> 1.405), precision@20 0.9561 -> 0.9559, IDF1
    # 0.856 -> 0.858
    union_us: int = 1_000_000
    # a track sharing a detection with less than this share of its box outside the others' is hidden behind them
    hidden_share: float = 0.2
    # a box of recent pixels is longer than its target by about its motion over this time, and lags by half that
    # (measured on fresh simulated seeds: the excess over speed was 60-75 ms at 50-250 px/s); reported boxes, and
    # the borders a track coming in is taken to touch, drop it
    trail_us: float = 55_000.0
    velocity_gain: float = 0.3  # weight of a new velocity measurement
    # ... and of the velocity of a track's own part of a shared blob (`_learn_parts`), measured this often. On four
    # sets of 60 dev seeds id switches per object-minute 2.07 -> 1.95, precision@20 0.946 -> 0.948, false boxes
    # 0.16 -> 0.14 a second; on three fresh sets switches 2.58 -> 2.29, 2.93 -> 2.63, 2.68 -> 2.61 (gain 0.1: less)
    part_velocity_gain: float = 0.2
    part_every_us: int = 20_000
    # where a track in a shared blob found its template (`Looks`), its prediction moves there before the layout,
    # and its placed centre moves this share of the way from the layout's to there after it: two measures of where
    # it is, one by which pixels fired, one by their pattern. On four sets of 60 seeds (200-259, 500-679) id
    # switches per object-minute 1.919 -> 1.790 (on each set: 1.84 -> 1.59, 2.19 -> 2.16, 2.12 -> 1.99,
    # 1.52 -> 1.42), precision@20 0.9553 -> 0.9561, IDF1 0.848 -> 0.856 (0.7: 1.773 and 0.9554)
    look_weight: float = 0.5
    # a confirmed track's velocity changes by at most this per second: a box whose edges jump as its blob merges,
    # splits or changes shape (traced: 1400 px/s learnt from one such jump, the track then coasting off its
    # target) is not a target that turned; a target that does turn is followed within a few updates. On three sets
    # of 60 dev seeds it took id switches per object-minute from 2.50 to 2.29 (5000 and 12000: worse on one set)
    max_accel_px_s2: float = 8000.0
    size_gain: float = 0.5  # weight of a new size measurement
    fragment_area: float = 0.5  # a detection this much smaller than a track, inside it, is a fragment
    # tracks in one detection moving within this of each other are one target seen in pieces; looser, it
    # would fold two targets travelling side by side into one
    same_velocity_px_s: float = 15.0
    # ... and overlapping by this IoU: two tracks on one target overlap much, two targets side by side need not.
    # At 0.05, two targets that met and went on together were folded as one; with velocities measured on each
    # track's own part of a shared blob (`part_velocity_gain`), so were more of them
    alike_iou: float = 0.5
    # two still tracks (that moving alike tells nothing of) are one target if this share of the smaller is inside
    # the other, however they overlap: two stopped targets side by side, or one partly in front of the other, stay two
    still_inside: float = 0.8
    # a track younger than this (and not split off by motion) merges into an older one it shares with and overlaps,
    young_us: int = 300_000
    young_unlike_px_s: float = 100.0  # ... unless their velocities differ by more than this (a young one's are rough)
    # ... or whatever their velocities, if this share of its box lies inside the older one's and it overlaps no
    # other detection: a piece of that target first seen apart from it. Its velocity then came from a box still
    # growing, and stays while it is placed in the shared blob (traced on the real recording of a person,
    # shared/data/real/tonic_samples: the edge of the turning face, 150 px/s against the person's 194, was a second
    # track for 0.5 s). On four sets of 60 dev seeds false boxes per second fell on two and held on two, id
    # switches per object-minute +0.01. A target hidden behind another within 0.3 s of being first seen, with no
    # detection of its own near, is folded too, and takes its id back by its size when it comes out
    young_inside: float = 0.9
    stop_ratio: float = 0.3  # a detection with fewer new events than this share of its track's usual is fading
    # a target that stops at a border is held if its box there shows this share of its usual size on the axis the
    # border cuts (one that leaves is held, if at all, with a sliver of it in view). At 0.9, one that stopped a
    # fifth out of view was let go as gone. On four sets of 60 dev seeds precision@20 0.9489 -> 0.9510 (+0.001 to
    # +0.003 on each), on three fresh sets 0.9487 -> 0.9518; id switches per object-minute 1.72 -> 1.73 and
    # 2.40 -> 2.40, false boxes 0.138 -> 0.142 and 0.166 -> 0.169 a second
    held_share: float = 0.6
    rate_gain: float = 0.2  # weight of a new count in a track's usual count of new events
    rate_decay: float = 0.98  # per held update: a target that goes on slowly is followed again within ~0.5 s
    recent_updates: float = 3.0  # updates an event's pixel stays recent (tau 30 ms to weight 0.35 at 10 ms a step)
    # a track sharing a detection is tested for a stop on the part of its box the others leave, if this big
    alone_share: float = 0.5
    still_contrast: float = 0.1  # ... and stopped if that part has under this share of the busiest other's events/px
    # a track left alone in a detection much bigger than itself takes it whole; off where detections
    # are grown from the tracks' own predictions (CamShift), which would feed a track its own growth
    take_whole: bool = True
    # a detection this much bigger than the one confirmed track in it (placed at its size) holds a second
    # target that joined it if the recent pixels the track leaves are this share of them or more, and their
    # box covers under `split_cover` of the track's; traced on a target that moved off again beside another
    split_area: float = 1.6
    split_share: float = 0.3
    split_cover: float = 0.5
    # a confirmed track alone in a detection is tested for a second target moving otherwise in it this often at
    # most (the flow is dear): two that came in together, were first seen together, or met and went on as one blob.
    # Testing only tracks under 2 s old left such union boxes to the end: on three sets of 60 dev seeds testing
    # every one gave precision@20 +0.005 (id switches within their noise), and on the 40 unseen bench seeds it
    # took precision@20 from 0.937 to 0.947, OP50 from 0.928 to 0.937 and false boxes from 0.16 to 0.14 a second.
    # Every 100 ms it cost the speed bench 3 % (150 ms: none, with the past images kept every 20 ms)
    motion_retest_us: int = 150_000
    # ... and as late as this if its blob's width and height stay within `motion_retest_px` of those at the last test
    # (two targets moving apart in one blob stretch it): the flow was 13 % of an update's time, now 9 %; the speed
    # bench 25.4 -> 27.8 Mev/s (means of four runs). On four sets of 60 dev seeds id switches per object-minute
    # 1.769 -> 1.785, precision@20 0.9559 both ways, IDF1 0.858 -> 0.856 (1 px: no faster)
    motion_retest_max_us: int = 300_000
    motion_retest_px: float = 2.0
    # the parts of a split detection both have new events at this share of the other's rate (per pixel) at least
    split_contrast: float = 0.3
    # a split track takes the part its prediction overlaps this many times more (IoU), else the bigger one
    split_own_ratio: float = 1.5


@dataclass
class Track:
    ident: int
    box: Box  # at `t_us`
    t_us: int
    vel: tuple[float, float] = (0.0, 0.0)  # px/s of the centre
    hits: int = 1
    first_seen_us: int = 0
    last_seen_us: int = 0
    state: int = TENTATIVE
    score: float = 0.3
    rate: float = 0.0  # usual new events per update in its detection, while it moves
    own_size: tuple[float, float] | None = None  # w, h when it last had a detection of its own
    # its own widths (heights) measured while its box cleared the left and right (top and bottom) borders,
    # the latest `SIZE_MEMORY`: their median is the size it is known by when it comes back (`known_size`)
    widths: deque[float] = field(default_factory=lambda: deque(maxlen=SIZE_MEMORY))
    heights: deque[float] = field(default_factory=lambda: deque(maxlen=SIZE_MEMORY))
    entering: bool = False  # confirmed young at a border and not (yet) known as a target that left
    # first seen on a part of a blob whose points moved two ways (`_split_by_motion`): a second target, not a young
    # piece. Folded back as one while young, two targets that came in together were split and folded again and
    # again (traced on dev seed 206: one box over both for 1 s); kept, on four sets of 60 dev seeds id switches per
    # object-minute 2.13 -> 2.07, on two fresh sets 2.59 -> 2.58 and 3.11 -> 2.93, precision@20 unchanged
    moved_apart: bool = False
    path: deque[tuple[int, float, float]] = field(default_factory=lambda: deque(maxlen=PATH_UPDATES))  # t, centre
    moved_as_one_us: int = -(1 << 62)  # when its blob's points were last found moving one way (see `_split_by_motion`)
    parted_us: int = -(1 << 62)  # when its velocity was last measured on its own part of a shared blob
    template: np.ndarray | None = None  # what its target looked like when it last had a detection of its own
    tested_size: tuple[float, float] = (0.0, 0.0)  # its blob's width and height when last found moving one way

    def full_size(self, axis: int) -> float | None:
        """Its usual width (axis 0) or height (1) in full view now (its latest `SIZE_NOW` measurements), if
        ever seen so."""
        sizes = self.heights if axis else self.widths
        return statistics.median(itertools.islice(reversed(sizes), SIZE_NOW)) if sizes else None

    def known_size(self, axis: int) -> float | None:
        """The width (axis 0) or height (1) it is known by when it comes back: over all its measurements kept."""
        sizes = self.heights if axis else self.widths
        return statistics.median(sizes) if sizes else None

    def usual_size(self, axis: int) -> float:
        """Its usual width (axis 0) or height (1): in full view if ever seen so, else its box's."""
        return self.full_size(axis) or self.box[2 + axis]

    @property
    def held(self) -> bool:
        """A confirmed track held still (its target stopped)."""
        return self.state == TRACKED and self.vel == (0.0, 0.0)

    def predict(self, t_us: int) -> Box:
        dt_s = (t_us - self.t_us) / 1e6
        x, y, w, h = self.box
        return x + self.vel[0] * dt_s, y + self.vel[1] * dt_s, w, h


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise intersection over union of boxes a (N x 4) and b (M x 4), x y w h."""
    inter = intersection(a, b)
    joined = a[:, 2:3] * a[:, 3:4] + b[:, 2] * b[:, 3] - inter
    return inter / np.maximum(joined, 1e-6)


def intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise intersection areas of boxes a (N x 4) and b (M x 4), x y w h."""
    iw = np.minimum(a[:, 0:1] + a[:, 2:3], b[:, 0] + b[:, 2]) - np.maximum(a[:, 0:1], b[:, 0])
    ih = np.minimum(a[:, 1:2] + a[:, 3:4], b[:, 1] + b[:, 3]) - np.maximum(a[:, 1:2], b[:, 1])
    return np.clip(iw, 0, None) * np.clip(ih, 0, None)


def _overlap(a: Box, b: Box) -> float:
    """Their intersection's area; comparisons in line, as most pairs are apart (builtins' calls cost more)."""
    ax, ay, aw, ah = a
    bx, by, bw, bh = b
    iw = (ax + aw if ax + aw < bx + bw else bx + bw) - (ax if ax > bx else bx)
    if iw <= 0:
        return 0.0
    ih = (ay + ah if ay + ah < by + bh else by + bh) - (ay if ay > by else by)
    return iw * ih if ih > 0 else 0.0


def _cut(a: Box, b: Box) -> Box:
    """The intersection of two boxes (w or h <= 0 when they do not overlap)."""
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    return x0, y0, min(a[0] + a[2], b[0] + b[2]) - x0, min(a[1] + a[3], b[1] + b[3]) - y0


def _iou(a: Box, b: Box, inter: float | None = None) -> float:
    """Their intersection over union, from their overlap where it is known already."""
    inter = _overlap(a, b) if inter is None else inter
    return inter / max(a[2] * a[3] + b[2] * b[3] - inter, 1e-6)


def _area(box: Box) -> float:
    area = box[2] * box[3]
    return area if area > 1.0 else 1.0


def _centre(box: Box) -> tuple[float, float]:
    return box[0] + box[2] / 2, box[1] + box[3] / 2


def _alone(box: Box, others: list[Box]) -> tuple[list[Box], float]:
    """The parts of a box that other boxes cover, and the share of it they leave."""
    cuts = [c for c in (_cut(box, b) for b in others) if c[2] > 0 and c[3] > 0]
    return cuts, 1 - sum(c[2] * c[3] for c in cuts) / _area(box)


def _behind(box: Box, usual: Callable[[int], float], others: list[Box],
            sides: int) -> tuple[Box, tuple[float, float]]:
    """A detection cut on one side by another track's box (a nearer target hides that side) and
    narrower (shorter) than its track's `usual` width (height), given that size back on the hidden side;
    not on an axis where it touches the image's border (`sides`): it is leaving there. With the box, the
    point that moves with the target on each axis, as a share of the box: its seen edge where it was
    given size back (its centre jumped), else its centre."""
    x, y, w, h = box
    near = (x - 2, y - 2, w + 4, h + 4)  # an edge is cut by a box up to a pixel beyond it
    if not any(_overlap(near, o) for o in others):  # most boxes: none beside them
        return box, (0.5, 0.5)
    out = list(box)
    anchor = [0.5, 0.5]
    for axis in (0, 1):
        if sides & (CUT_X, CUT_Y)[axis]:
            continue
        lo, hi = box[axis], box[axis] + box[2 + axis]
        across = [o for o in others if o[1 - axis] < box[1 - axis] + box[3 - axis]
                  and o[1 - axis] + o[3 - axis] > box[1 - axis]]  # overlapping it on the other axis
        cut_lo = any(o[axis] < lo <= o[axis] + o[2 + axis] + 1 for o in across)
        cut_hi = any(o[axis] - 1 <= hi < o[axis] + o[2 + axis] for o in across)
        if cut_lo != cut_hi and box[2 + axis] < WHOLE * (full := usual(axis)):
            out[axis], out[2 + axis] = (hi - full if cut_lo else lo), full
            anchor[axis] = 1.0 if cut_lo else 0.0
    return (out[0], out[1], out[2], out[3]), (anchor[0], anchor[1])


def _biggest(boxes: list[Box]) -> int:
    """The index of the biggest box (the last of equal ones)."""
    return sorted(range(len(boxes)), key=lambda k: _area(boxes[k]))[-1]


def union(boxes: list[Box]) -> Box:
    """The smallest box holding all of `boxes`."""
    x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
    return x0, y0, max(b[0] + b[2] for b in boxes) - x0, max(b[1] + b[3] for b in boxes) - y0


class MultiObjectTracker:
    """Keeps tracks from successive detections; `update` returns the tracks to report."""

    def __init__(self, params: AssociationParams | None = None, width: int = 0, height: int = 0) -> None:
        self.params = params or AssociationParams()
        self.width, self.height = width, height
        self.tracks: list[Track] = []
        self._folded: list[Track] = []  # merged into others, see `_fold`
        self._next_id = 1

    def update(self, t_us: int, boxes: np.ndarray, fresh: Counts | None = None,
               layout: Layout | None = None, leftover: Leftover | None = None,
               motions: Motions | None = None, parts: PartVelocity | None = None,
               looks: Looks | None = None, shapes: Shapes | None = None) -> list[Track]:
        """Tracks at `t_us` given the detections (N x 4 boxes) of that time, if known how to count the
        new events in a box since the last update, how to place tracks that share a detection (else they
        move by prediction), how to box the events that placed tracks leave in a detection, how to
        find two targets moving apart in one and two whose union its shape is (else a detection is never
        split so), how to measure the velocity of a track's own part of a shared detection (else placed
        tracks keep theirs), and what targets look like (else tracks in a shared detection are placed by
        the layout alone)."""
        p = self.params
        dets: list[Box] = [tuple(b) for b in np.asarray(boxes, np.float64).reshape(-1, 4).tolist()]
        pred = [tr.predict(t_us) for tr in self.tracks]
        # the confirmed tracks with their predictions, built once for both splits: whose blobs may be split
        splittable = [(tr, a) for tr, a in zip(self.tracks, pred, strict=True) if tr.state == TRACKED]
        # parts of detections split by shape or motion: targets of their own, not fragments of the track beside them
        moved_apart, taken = self._split_in_two(t_us, dets, splittable, shapes, motions, fresh)
        for ti, box in taken.items():  # a split track is where its part is
            pred[ti] = box
        if layout is not None and leftover is not None:
            self._split(dets, splittable, layout, leftover)
        inter = [[_overlap(a, b) for b in dets] for a in pred]
        ious = [[_iou(a, b, o) for b, o in zip(dets, row, strict=True)] for a, row in zip(pred, inter, strict=True)]
        live = [tr.state != LOST for tr in self.tracks]
        # a detection holding most of two or more live tracks is shared (crossing targets) or the
        # tracks are one target seen in pieces before: merge those, place the rest
        shared: dict[int, list[int]] = {}
        whole: dict[int, int] = {}
        # a track with a detection of its own (the one it overlaps most, by half or more: a small target seen inside
        # a big one's) shares no other, unless the two are about the same (two tracks on one target, each with a box)
        own_det = [dets[row.index(best)] if row and (best := max(row)) >= 0.5 else None for row in ious]
        for di, det in enumerate(dets):
            inside = [ti for ti, a in enumerate(pred) if live[ti] and inter[ti][di] >= 0.5 * _area(a)
                      and (own_det[ti] is None or _iou(own_det[ti], det) >= 0.5)]
            if len(inside) >= 2:
                members = self._merge_alike(t_us, inside, pred, di, dets, inter)
                if len(members) >= 2:
                    shared[di] = members
                elif p.take_whole:  # one target after all; its box held a piece or a remnant of it
                    whole[members[0]] = di
        live = [ok and tr.state != _GONE for ok, tr in zip(live, self.tracks, strict=True)]
        emerged = self._emerging(shared, pred, dets, set(whole.values()))
        in_shared = {ti for members in shared.values() for ti in members}
        assigned = self._match(pred, dets, ious, in_shared | set(whole) | set(emerged),
                               set(shared) | set(whole.values()) | set(emerged.values()))
        assigned.update(emerged)
        used = set(assigned.values()) | set(shared) | set(whole.values())
        for ti, di in whole.items():
            self._place(self.tracks[ti], dets[di], t_us)
        # fragments: small detections mostly inside a track's prediction join its measurement
        pieces: dict[int, list[int]] = {ti: [di] for ti, di in assigned.items()}
        confirmed = [(ti, a) for ti, a in enumerate(pred) if live[ti] and self.tracks[ti].state == TRACKED]
        for di, det in enumerate(dets):
            if di in used or di in moved_apart or not pred:
                continue
            cover = [inter[ti][di] / _area(det) if live[ti] else 0.0 for ti in range(len(pred))]
            ti = max(range(len(cover)), key=cover.__getitem__)
            if cover[ti] >= 0.6 and _area(det) < p.fragment_area * _area(pred[ti]):
                if ti in pieces and t_us - self.tracks[ti].first_seen_us < p.young_us:
                    pieces[ti].append(di)  # a target first seen in pieces: its box grows to hold them
                used.add(di)
        new_in_dets = fresh(np.asarray(dets, np.float32)) if fresh is not None and dets else []
        for ti, members in pieces.items():
            tr = self.tracks[ti]
            box, anchor = union([dets[di] for di in members]), (0.5, 0.5)
            sides = self._sides(box)
            if fresh is not None:
                new_events = float(sum(new_in_dets[di] for di in members))
                if self._stopped(tr, new_events, self._in_view(tr, box, sides)):
                    self._hold(tr, t_us)
                    continue
                self._learn_rate(tr, new_events)
            if tr.state == TRACKED:  # a target going behind (or coming out from behind) another keeps its size
                box, anchor = _behind(box, tr.usual_size, [a for k, a in confirmed if k != ti], sides)
            self._correct(tr, box, t_us, anchor)
        hidden: set[int] = set()
        for members in shared.values():
            boxes = [pred[ti] for ti in members]
            alone = [_alone(box, boxes[:k] + boxes[k + 1:]) for k, box in enumerate(boxes)]
            hidden |= self._covered(members, boxes, [share for _, share in alone])
            if fresh is not None:  # one that stopped beside a moving one is held, not laid onto its events
                new_in = fresh(np.asarray(boxes, np.float32)).tolist()
                moving = []
                for k, ti in enumerate(members):
                    if self._stopped_beside(self.tracks[ti], k, boxes, new_in, alone[k], fresh):
                        self._hold(self.tracks[ti], t_us, seen=False)
                    else:
                        moving.append(ti)
                members = moving
            found = self._found(members, pred, hidden, looks) if looks is not None else {}
            boxes_in, own, fills = self._layout_inputs([(self.tracks[ti], pred[ti]) for ti in members])
            placed = (layout(boxes_in, own, fills, self._others(members, pred, t_us))
                      if layout is not None and members else boxes_in)
            placed_boxes: list[Box] = [self._toward(b, found.get(ti)) for b, ti in zip(placed.tolist(), members,
                                                                                      strict=True)]
            for ti, box in zip(members, placed_boxes, strict=True):
                if ti in hidden:  # placed, but not seen
                    self._coast(self.tracks[ti], box, t_us)
                else:
                    self._place(self.tracks[ti], box, t_us)
            if parts is not None:
                self._learn_parts(t_us, members, placed_boxes, hidden, parts)
        observed = [pred[ti] for ti in sorted(set(pieces) | in_shared)]
        for ti, tr in enumerate(self.tracks):
            if ti not in pieces and ti not in in_shared and ti not in whole and tr.state != _GONE:
                self._unseen(tr, pred[ti], t_us, observed)
        if looks is not None:  # what the targets seen on their own look like now
            for ti in pieces:
                tr = self.tracks[ti]
                if tr.state == TRACKED and tr.t_us == t_us and not tr.held:
                    tr.template = looks.capture(tr.box)
        self.tracks = [tr for tr in self.tracks if tr.state != _GONE]
        for tr in self.tracks:
            tr.path.append((t_us, *_centre(tr.box)))
        for di, det in enumerate(dets):
            if di not in used:
                self.tracks.append(Track(self._next_id, det, t_us, first_seen_us=t_us, last_seen_us=t_us,
                                         moved_apart=di in moved_apart))
                self._next_id += 1
        return list(self.tracks)

    def _split_in_two(self, t_us: int, dets: list[Box], confirmed: list[tuple[Track, Box]], shapes: Shapes | None,
                      motions: Motions | None, fresh: Counts | None) -> tuple[set[int], dict[int, Box]]:
        """Splits (in place) each detection holding most of one confirmed track in two where its shape is two
        targets' (`_shape_parts`) or, failing that, its points move two ways (`_motion_parts`): the part the
        track takes (`_taken_part`; of the flow's, the one its prediction overlaps more) stays its detection, the
        other is added at the end as a target of its own. Two targets that came in together, were first seen
        together, or met and went on side by side form one blob and so one track; here they part as soon as they
        are told apart, not once their blobs separate (the box held both until then). The indices of the parts
        added, and the part each split track (by index) took."""
        added: set[int] = set()
        taken: dict[int, Box] = {}
        for di, det in enumerate(dets[:]):
            inside = [(tr, a) for tr, a in confirmed if _overlap(a, det) >= 0.5 * _area(a)]
            if len(inside) != 1:
                continue
            tr, a = inside[0]
            parts = self._shape_parts(tr, det, shapes, fresh) if shapes is not None else None
            if parts is not None:
                own = self._taken_part(a, parts)
                taken[self.tracks.index(tr)] = parts[own]
            elif motions is not None and (parts := self._motion_parts(t_us, tr, det, motions)) is not None:
                # the flow's boxes are rough (its points' spread, clipped to the blob): the track goes on to whichever
                # its prediction matches (taking the part as for shapes: id switches per object-minute +0.017 on 360
                # dev seeds, within their noise)
                own = 0 if _iou(parts[0], a) >= _iou(parts[1], a) else 1
            else:
                continue
            dets[di] = parts[own]
            dets.append(parts[1 - own])
            added.add(len(dets) - 1)
        return added, taken

    def _shape_parts(self, tr: Track, det: Box, shapes: Shapes, fresh: Counts | None) -> list[Box] | None:
        """The two targets' boxes if the detection's shape is their union (see `shapes.py`) and both have new events
        (where the other's box leaves it) at `split_contrast` of the other's rate or more: a target that starts from
        a stop leaves its fading image beside its new place, and one that slows, fading patches in its box; those
        are no second target. None for a held track (its target stopped)."""
        found = None if tr.held else shapes(det)
        if found is None:
            return None
        parts: list[Box] = [(b[0], b[1], b[2], b[3]) for b in found.tolist()]
        if fresh is not None:
            cut = _cut(*parts)
            cut = cut if cut[2] > 0 and cut[3] > 0 else (0.0, 0.0, 0.0, 0.0)
            *counts, n_cut = fresh(np.asarray([*parts, cut], np.float32)).tolist()
            rates = [(n - n_cut) / max(_area(b) - _area(cut), 1.0) for n, b in zip(counts, parts, strict=True)]
            if min(rates) < self.params.split_contrast * max(rates):
                return None
        return parts

    def _motion_parts(self, t_us: int, tr: Track, det: Box, motions: Motions) -> list[Box] | None:
        """The two targets' boxes if the detection's points move two ways (see `motion.py`); tested at most every
        `motion_retest_us`, or `motion_retest_max_us` while the blob keeps its size (the flow is dear)."""
        p = self.params
        since = t_us - tr.moved_as_one_us
        if since < p.motion_retest_us or (since < p.motion_retest_max_us and all(
                abs(det[2 + axis] - tr.tested_size[axis]) < p.motion_retest_px for axis in (0, 1))):
            return None
        found = motions(det)
        if found is None:
            tr.moved_as_one_us = t_us
            tr.tested_size = (det[2], det[3])
            return None
        return [(b[0], b[1], b[2], b[3]) for b in found.tolist()]

    def _taken_part(self, pred: Box, parts: list[Box]) -> int:
        """Which of two parts of a split detection its track takes: the one its prediction overlaps clearly more
        (by IoU, `split_own_ratio` times), else the bigger one."""
        i0, i1 = _iou(parts[0], pred), _iou(parts[1], pred)
        if max(i0, i1) >= self.params.split_own_ratio * min(i0, i1):
            return 0 if i0 >= i1 else 1
        return 0 if _area(parts[0]) >= _area(parts[1]) else 1

    def _split(self, dets: list[Box], confirmed: list[tuple[Track, Box]], layout: Layout, leftover: Leftover) -> None:
        """Splits (in place) each detection much bigger than the one confirmed track overlapping it (whose
        box is clear of the borders: not a target still coming in) in two: a second target joined its
        blob (one that moved off again beside it, or came in at a border behind it). The track's box
        placed on the blob at its own size is one part; the recent pixels it leaves, if many and mostly
        beside it, are the other, added at the end. Tentative tracks do not count: the second target's is
        one (but one that stays young and moves with the other is still folded into it, see `_merge_alike`:
        a piece of its target)."""
        p = self.params
        for di, det in enumerate(dets[:]):  # the parts added at the end are not split again
            inside = [(tr, a, inter) for tr, a in confirmed if (inter := _overlap(a, det)) > 0]
            if len(inside) != 1:
                continue
            tr, a, inter = inside[0]
            if self._sides(a) or inter < 0.5 * _area(a) or _area(det) < p.split_area * _area(a):
                continue
            placed = layout(*self._layout_inputs([(tr, a)]), np.asarray([b for o, b in confirmed if o is not tr],
                                                                        np.float32).reshape(-1, 4))
            box, n, total = leftover(det, placed)
            own, rest = tuple(placed[0].tolist()), tuple(box.tolist())
            if n and n >= p.split_share * total and _overlap(rest, own) < p.split_cover * _area(own):
                dets[di] = own
                dets.append(rest)

    def _emerging(self, shared: dict[int, list[int]], pred: list[Box], dets: list[Box],
                  taken: set[int]) -> dict[int, int]:
        """Tracks hidden in a shared blob (others' boxes cover most of theirs) that a detection of their
        size near their prediction, apart from that blob, shows coming out from behind: each takes it
        and leaves the blob (which, left to one track, is matched as usual). Track -> detection."""
        p = self.params
        out: dict[int, int] = {}
        free = [di for di in range(len(dets)) if di not in shared and di not in taken]
        for di_shared, members in list(shared.items()) if free else []:
            boxes = [pred[ti] for ti in members]
            biggest = _biggest(boxes)
            for k, ti in enumerate(list(members)):
                tr, a = self.tracks[ti], pred[ti]
                size = max(a[2], a[3], 1.0)
                near = [(d, di) for di in free if di not in out.values()
                        and (d := math.dist(_centre(a), _centre(dets[di])) / size) <= p.gate]
                if not near or not self._hidden(k, biggest, _alone(a, boxes[:k] + boxes[k + 1:])[1]):
                    continue
                ratio = p.reid_size_ratio
                fits = [(d, di) for d, di in near if all(  # its size on both axes
                    1 / ratio < max(dets[di][2 + ax], 1.0) / max(tr.usual_size(ax), 1.0) < ratio for ax in (0, 1))]
                if fits:
                    out[ti] = min(fits)[1]
                    members.remove(ti)
            if len(members) < 2:
                del shared[di_shared]
        return out

    def _merge_alike(self, t_us: int, members: list[int], pred: list[Box], di: int, dets: list[Box],
                     overlaps: list[list[float]]) -> list[int]:
        """Of tracks sharing detection `di` (of `dets`; `overlaps`: each track's with each detection), fold
        each tentative one, each young one overlapping it (not split off by motion, and not clearly moving
        otherwise, or lying inside it and overlapping no other detection), or one moving with it and
        overlapping it, into the oldest of them (marked `_GONE`, removed after the update; but see below);
        the members left. Two still targets move alike (not at all): they are folded only if one lies
        (almost) wholly inside the other. Of two confirmed tracks found alike, the one whose box fits the
        detection better goes on: the target's own track, not one that held a piece of it or was hidden
        behind it (traced on a target that went behind a still one and was held there: its older id went
        on with the still one)."""
        p = self.params
        det = dets[di]
        members.sort(key=lambda i: self.tracks[i].ident)
        keep: list[int] = []
        for i in members:
            tr = self.tracks[i]
            only_here = not any(o > 0 for dj, o in enumerate(overlaps[i]) if dj != di)  # in no other detection
            for k in keep:
                older = self.tracks[k]
                inter = _overlap(pred[i], pred[k])
                unlike = math.dist(tr.vel, older.vel)
                still = max(math.hypot(*tr.vel), math.hypot(*older.vel)) <= p.same_velocity_px_s
                alike = unlike <= p.same_velocity_px_s and (
                    inter >= p.still_inside * min(_area(pred[i]), _area(pred[k])) if still
                    else _iou(pred[i], pred[k], inter) >= p.alike_iou)
                # a confirmed young track split off by motion, apart from the older one, or moving unlike it (and
                # not lying inside it in this detection alone) is a second target beside it (or crossing it)
                young = not tr.moved_apart and t_us - tr.first_seen_us < p.young_us and inter > 0
                piece = young and (unlike <= p.young_unlike_px_s
                                   or (inter >= p.young_inside * _area(pred[i]) and only_here))
                if tr.state == TENTATIVE or piece or alike:
                    older.hits = tr.hits = max(older.hits, tr.hits)
                    if alike and tr.state == TRACKED and _iou(pred[i], det) > _iou(pred[k], det):
                        self._fold(older)
                        keep[keep.index(k)] = i
                    else:
                        self._fold(tr)
                    break
            else:
                keep.append(i)
        return keep

    def _fold(self, tr: Track) -> None:
        """A track merged into another; a confirmed one is kept aside a while, as the second target it
        may have been after all (see `_seen_before`)."""
        if tr.state == TRACKED:
            forget = self.params.forget_after_us
            self._folded = [f for f in self._folded if tr.t_us - f.last_seen_us < forget] + [tr]
        tr.state = _GONE

    def _match(self, pred: list[Box], dets: list[Box], ious: list[list[float]], exclude_tracks: set[int],
               exclude_dets: set[int]) -> dict[int, int]:
        """One-to-one assignment, greedy by overlap, then by centre distance within the gate (a still track
        only by overlap); lost tracks (but those that left the image) also take detections of their size
        near their prediction."""
        p = self.params
        pairs = []
        for ti, (a, tr) in enumerate(zip(pred, self.tracks, strict=True)):
            lost = tr.state == LOST
            if ti in exclude_tracks or tr.state == _GONE or (lost and self._sides(tr.box)):
                continue  # one that left the image is found again by `_reidentify`, on its size
            size = max(a[2], a[3], 1.0)
            gate = (p.redetect_gate if lost else p.gate) * size
            # a target passing over a still one (which fires nothing to hold its track) is not it
            least = p.still_min_iou if tr.held else 0.0
            for di, b in enumerate(dets):
                if di in exclude_dets:
                    continue
                overlap = ious[ti][di]
                if overlap < least:
                    continue
                if overlap >= p.min_iou:
                    cost = -overlap
                else:
                    ratio = b[2] * b[3] / _area(a)
                    dist = math.dist(_centre(a), _centre(b))
                    if not (dist <= gate and 0.4 < ratio < 2.5):
                        continue
                    cost = dist / size
                pairs.append((cost + 0.5 * lost, ti, di))  # live tracks first
        out: dict[int, int] = {}
        used_d: set[int] = set()
        for _, ti, di in sorted(pairs):
            if ti not in out and di not in used_d:
                out[ti] = di
                used_d.add(di)
        return out

    def _found(self, members: list[int], pred: list[Box], hidden: set[int], looks: Looks) -> dict[int, Box]:
        """Tracks sharing a blob (`members`) that found their templates near their predictions (not the hidden
        ones, nor tracks never seen alone): their predictions moved there (in `pred`), which the layout starts from
        and is pulled towards, and those boxes by track."""
        found: dict[int, Box] = {}
        for ti in members:
            tr = self.tracks[ti]
            if ti in hidden or tr.state != TRACKED or tr.template is None:
                continue
            shift = looks.find(tr.template, pred[ti])
            if shift is not None:
                x, y, w, h = pred[ti]
                pred[ti] = found[ti] = (x + shift[0], y + shift[1], w, h)
        return found

    def _toward(self, placed: list[float], found: Box | None) -> Box:
        """A box the layout placed, its centre moved `look_weight` of the way to the centre of the one its
        template was found at (if it was)."""
        x, y, w, h = placed
        if found is not None:
            g = self.params.look_weight
            (px, py), (fx, fy) = _centre((x, y, w, h)), _centre(found)
            x, y = x + g * (fx - px), y + g * (fy - py)
        return x, y, w, h

    def _learn_parts(self, t_us: int, members: list[int], boxes: list[Box], hidden: set[int],
                     parts: PartVelocity) -> None:
        """Tracks placed in a shared blob (`members`, at their `boxes`) learn their velocities from the
        motion of their own parts of it, every `part_every_us`: the layout corrects a wrong prediction little, so
        a target that turned or started in the blob was followed on its old velocity. Not one hidden there."""
        p = self.params
        for k, ti in enumerate(members):
            tr = self.tracks[ti]
            if ti in hidden or tr.state != TRACKED or t_us - tr.parted_us < p.part_every_us:
                continue
            tr.parted_us = t_us
            measured = parts(boxes[k], boxes[:k] + boxes[k + 1:], tr.vel)
            if measured is not None:
                dt_s = (t_us - tr.path[-1][0]) / 1e6 if tr.path else 0.0
                self._learn_velocity(tr, measured, p.part_velocity_gain, max(dt_s, p.part_every_us / 1e6))

    def _learn_velocity(self, tr: Track, measured: tuple[float, float], gain: float, dt_s: float) -> None:
        """The track's velocity moved by `gain` towards a `measured` one; a confirmed track's by at most
        `max_accel_px_s2` over `dt_s`."""
        p = self.params
        change = gain * (measured[0] - tr.vel[0]), gain * (measured[1] - tr.vel[1])
        cap = p.max_accel_px_s2 * dt_s
        if tr.hits >= p.confirm_hits and (size := math.hypot(*change)) > cap:
            change = change[0] * cap / size, change[1] * cap / size
        tr.vel = (tr.vel[0] + change[0], tr.vel[1] + change[1])

    @staticmethod
    def _place(tr: Track, box: Box, t_us: int) -> None:
        """The track set on a box without learning velocity or size from it (a detection it takes whole,
        its place in a shared blob)."""
        tr.box, tr.t_us, tr.last_seen_us = box, t_us, t_us

    def _covered(self, members: list[int], boxes: list[Box], shares: list[float]) -> set[int]:
        """Of tracks sharing a detection (their predicted boxes, and the share of each the others
        leave), those whose box the others' boxes mostly cover (all but the biggest): targets gone
        behind a nearer one. They are still placed, but count as unseen, so one that stays hidden is
        lost after `hold_us` instead of riding on the nearer one's events."""
        biggest = _biggest(boxes)
        return {ti for k, ti in enumerate(members) if self._hidden(k, biggest, shares[k])}

    def _hidden(self, k: int, biggest: int, share: float) -> bool:
        """Whether the `k`th of boxes sharing a blob is hidden behind the others: it is not the biggest
        and the `share` of it they leave is small."""
        return k != biggest and share < self.params.hidden_share

    @staticmethod
    def _in_view(tr: Track, box: Box, sides: int) -> float:
        """The share of its target that a track's detection (touching the borders `sides`) shows: under 1 where
        a border cuts it. Fewer of its pixels fire there, so a target leaving through the border is not taken for
        one that stopped at it (and held at the border, where it took the next target to come in)."""
        if not sides:
            return 1.0
        return min(1.0, _area(box) / max(tr.usual_size(0) * tr.usual_size(1), 1.0))

    def _stopped(self, tr: Track, new_events: float, share: float = 1.0) -> bool:
        """Whether its detection (or the `share` of its box no other track covers) has far fewer new
        events than usual: the target stopped and what is seen there is its fading image."""
        return tr.state == TRACKED and new_events < self.params.stop_ratio * share * tr.rate

    def _hold(self, tr: Track, t_us: int, seen: bool = True) -> None:
        """The track held where it is: a stopped target; `seen` if by its own fading image."""
        tr.rate *= self.params.rate_decay
        tr.vel = (0.0, 0.0)
        if seen:
            tr.t_us = tr.last_seen_us = t_us
        else:
            self._coast(tr, tr.box, t_us)

    def _learn_rate(self, tr: Track, new_events: float) -> None:
        """The track's usual count of new events learns from its detection's, while it moves."""
        g = self.params.rate_gain
        tr.rate = new_events if tr.rate == 0 else (1 - g) * tr.rate + g * new_events

    def _layout_inputs(self, placing: list[tuple[Track, Box]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What `Layout` takes for tracks with their predicted boxes: the boxes, the sizes the tracks measured on
        their own (else their boxes'), and the share of those pixels each target usually has recent (1 while its
        rate is unknown: no event counts, or none yet)."""
        boxes = np.asarray([a for _, a in placing], np.float32).reshape(-1, 4)
        sizes = np.asarray([tr.own_size or a[2:] for tr, a in placing], np.float32).reshape(-1, 2)
        rates = np.asarray([tr.rate for tr, _ in placing], np.float64)
        fills = np.minimum(self.params.recent_updates * rates / np.maximum(sizes.prod(axis=1), 1.0), 1.0)
        return boxes, sizes, np.where(rates > 0, fills, 1.0)

    def _others(self, members: list[int], pred: list[Box], t_us: int) -> np.ndarray:
        """The boxes (F x 4) of the live tracks not among `members` (indices into the tracks, whose predictions are
        `pred`): where placed in this update already, else where predicted."""
        return np.asarray([tr.box if tr.t_us == t_us else pred[ti] for ti, tr in enumerate(self.tracks)
                           if ti not in members and tr.state in (TENTATIVE, TRACKED)], np.float32).reshape(-1, 4)

    def _stopped_beside(self, tr: Track, k: int, boxes: list[Box], new_in: list[float],
                        alone: tuple[list[Box], float], fresh: Counts) -> bool:
        """`_stopped` for the `k`th of the tracks sharing a detection (their boxes, new events, and the
        parts of its box the others cover with the share they leave): the target stopped beside a
        moving one if the part of its box no other covers (when big enough to tell) has far fewer new
        events than usual and than the busiest other, per pixel. The others' events would hide its
        stop from a count over the detection, and the layout would lay it onto them."""
        p = self.params
        box = boxes[k]
        cuts, share = alone
        if share < p.alone_share:  # too little of it left to tell: one already stopped stays so, unless
            # its box has more new events than it had itself while it moved
            return tr.held and new_in[k] < tr.rate
        own = max(new_in[k] - sum(fresh(np.asarray(cuts, np.float32).reshape(-1, 4)).tolist()), 0.0)
        busiest = max(n / _area(b) for i, (b, n) in enumerate(zip(boxes, new_in, strict=True)) if i != k)
        return own < p.still_contrast * busiest * share * _area(box) and self._stopped(tr, own, share)

    def _correct(self, tr: Track, box: Box, t_us: int, anchor: tuple[float, float] = (0.5, 0.5)) -> None:
        """A measured box: velocity from the move of its `anchor` (the share of the box on each axis that
        moves with the target: its centre, or the seen edge of one given size behind another), size smoothed
        about that same point."""
        p = self.params
        dt_s = (t_us - tr.t_us) / 1e6
        ax, ay = anchor
        if dt_s > 0 and tr.state != LOST:
            was = tr.box
            dx, dy = box[0] + ax * box[2] - (was[0] + ax * was[2]), box[1] + ay * box[3] - (was[1] + ay * was[3])
            self._learn_velocity(tr, (dx / dt_s, dy / dt_s), p.velocity_gain, dt_s)
        elif tr.state == LOST:
            tr.vel = (0.0, 0.0)
            tr.path.clear()  # found again elsewhere: it did not move there
        if tr.state == LOST or tr.hits < p.confirm_hits:
            tr.box = box
        else:
            g = p.size_gain
            w, h = (1 - g) * tr.box[2] + g * box[2], (1 - g) * tr.box[3] + g * box[3]
            tr.box = (box[0] + ax * (box[2] - w), box[1] + ay * (box[3] - h), w, h)
        tr.hits += 1
        tr.own_size = tr.box[2], tr.box[3]
        sides = self._sides(tr.box)
        if not sides & CUT_X:
            tr.widths.append(tr.box[2])
        if not sides & CUT_Y:
            tr.heights.append(tr.box[3])
        tr.t_us = tr.last_seen_us = t_us
        tr.score = min(1.0, 0.8 * tr.score + 0.2)
        if tr.hits >= p.confirm_hits:
            if tr.state == TENTATIVE or tr.entering:  # one coming in at a border may be one that left
                nearer = self._occluders(tr)
                found = self._reidentify(tr) or self._out_from_behind(tr, nearer) or self._seen_before(tr)
                age = t_us - tr.first_seen_us
                tr.entering = not found and bool(self._seen_sides(tr) or nearer) and (
                    age < p.young_us or (age < p.union_us and self._holds_two(tr)))
            tr.state = TRACKED

    def _unseen(self, tr: Track, pred: Box, t_us: int, observed: list[Box]) -> None:
        """No detection: drop a tentative track after a while; let go of a track that left the
        image or is young; coast one hidden behind an observed track; hold one that stopped."""
        p = self.params
        unseen_us = t_us - tr.last_seen_us
        if tr.state == TENTATIVE:
            if unseen_us > p.lost_after_us:
                tr.state = _GONE
            return
        if tr.state == LOST:  # since it was lost
            if t_us - tr.t_us > p.forget_after_us:
                tr.state = _GONE
            return
        # one that left the image, or a young one (a remnant a target left, or a cluster of noise) that fades, is
        # let go: it waits where it was, to be found if it comes back
        if (self._sides(tr.box) and not self._stopped_in_view(tr)) or t_us - tr.first_seen_us < p.young_us:
            tr.state, tr.vel, tr.t_us = LOST, (0.0, 0.0), t_us
            return
        hidden = _alone(pred, observed)[1] <= 0.5
        if not hidden:
            tr.vel = (0.5 * tr.vel[0], 0.5 * tr.vel[1])  # a target without events has stopped: hold it
            pred = tr.predict(t_us)
        self._coast(tr, pred, t_us)
        tr.score *= 0.995

    def seen_box(self, tr: Track) -> Box:
        """Its box without the trail its motion leaves in the image: a box of recent pixels also holds where
        the target was over the last `trail_us`, so it is longer along its path by how far its box moved in
        that time, and lags by half that. The move is measured (a velocity kept while the box was placed
        among others, not measured, may be stale); no trail where the box's trailing side is at a border
        (a target coming in: its trail is outside)."""
        trail_us = self.params.trail_us
        then = None  # the latest centre at least `trail_us` before its box's time, else the oldest before it
        for c in reversed(tr.path):
            if c[0] < tr.t_us:
                then = c
                if tr.t_us - c[0] >= trail_us:
                    break
        if then is None:
            return tr.box
        cx, cy = _centre(tr.box)
        # its move at that speed over the trail's time; a young track's shorter path is not stretched to it (a
        # box's edges jitter by a pixel or two between updates, and stretched that would be the trail)
        scale = min(trail_us / (tr.t_us - then[0]), 1.0)
        box, sides = list(tr.box), self._sides(tr.box)
        for axis, moved in ((0, cx - then[1]), (1, cy - then[2])):
            if sides & ((LEFT, TOP) if moved > 0 else (RIGHT, BOTTOM))[axis]:
                continue
            cut = min(abs(moved) * scale, 0.5 * box[2 + axis])
            box[2 + axis] -= cut
            if moved > 0:
                box[axis] += cut
        return box[0], box[1], box[2], box[3]

    def reported_state(self, tr: Track) -> int:
        """The state a track is reported in: `TENTATIVE` while it comes in (at a border, or beside another
        target) and a lost track may still give it its id, its own otherwise. An id shown and then changed a
        few updates later is one more switch for whoever follows the target; and a target may come back at
        another border than it left by, or be found only once clear of the border (`_seen_before`)."""
        if tr.state != TRACKED or not tr.entering:
            return tr.state
        return TENTATIVE if any(o.state == LOST for o in self.tracks) else tr.state

    def _stopped_in_view(self, tr: Track) -> bool:
        """Whether a track at a border is a target that stopped there, held with most of it in view
        (`held_share`; not one that left: that shrinks as it goes, and is held, if at all, with a sliver of it left)."""
        sides = self._sides(tr.box)
        return tr.held and all(
            not sides & cut or tr.box[2 + axis] >= self.params.held_share * tr.usual_size(axis)
            for axis, cut in ((0, CUT_X), (1, CUT_Y)))

    def _coast(self, tr: Track, box: Box, t_us: int) -> None:
        """A confirmed track moved to `box` without a sighting: lost once unseen for `hold_us`."""
        tr.box, tr.t_us = box, t_us
        if t_us - tr.last_seen_us > self.params.hold_us:
            tr.state = LOST

    def _sides(self, box: Box) -> int:
        """The image borders a box touches (its target may be leaving or entering), as `LEFT`... bits."""
        if not self.width:
            return 0
        m = BORDER_PX
        return ((box[0] <= m) * LEFT | (box[1] <= m) * TOP | (box[0] + box[2] >= self.width - m) * RIGHT
                | (box[1] + box[3] >= self.height - m) * BOTTOM)

    def _seen_sides(self, tr: Track) -> int:
        """The borders its box touches once its trail is dropped (`seen_box`): one beside a border, its trail
        reaching it, is not coming in there."""
        return self._sides(self.seen_box(tr))

    def _reidentify(self, new: Track) -> bool:
        """Seed 002's re-detection of a target back in view: a track coming in at a border takes the id
        of the lost track that left through that border, or of one merged into another before it appeared
        (two that leave together form one blob at the border; one hidden behind a still target was folded
        into it, and left with it), with its size (on the axis the border does
        not clip, and no bigger than it on the other); where two fit, only one that fits clearly better
        than the other (else it stays new, and is tried again on its next measurement while it comes
        in, as its size grows to the whole of it). Whether it took an id."""
        at_border = self._left_by(new)
        return at_border is not None and self._take_id(new, at_border[0], at_border[1] + self._folded_before(new))

    def _holds_two(self, tr: Track) -> bool:
        """Whether a track coming in at a border where two or more lost tracks left is longer along it (on the axis
        the border leaves whole) than any of them, by more than `reid_size_ratio`: two of them back in one blob."""
        at_border = self._left_by(tr)
        if at_border is None:
            return False
        axis, left = at_border
        known = [size for o in left if (size := o.known_size(axis))]
        return len(known) >= 2 and tr.box[2 + axis] > self.params.reid_size_ratio * max(known)

    def _left_by(self, tr: Track) -> tuple[int, list[Track]] | None:
        """For a track coming in at one border (not a corner): the axis of the size that border leaves whole (height,
        or width) and the lost tracks that left through it; else None."""
        sides = self._seen_sides(tr)
        if not sides or (sides & CUT_X and sides & CUT_Y):
            return None
        return 1 if sides & CUT_X else 0, [o for o in self.tracks if o.state == LOST and self._sides(o.box) & sides]

    def _out_from_behind(self, new: Track, nearer: list[Track]) -> bool:
        """The same for a target coming out from behind a nearer one: a new track beside a confirmed
        track's box takes the id of a track unseen since before it appeared (hidden, or lost there)
        whose box overlaps that box (where it coasted while hidden is a guess), if its size fits on the
        axis the nearer one's edge does not cut (`nearer`: its `_occluders`). Whether it took an id."""
        unseen = [tr for tr in self._unseen_since(new) if not self._sides(tr.box)] if nearer else []
        for near in nearer:
            (nx, ny), (ox, oy) = _centre(new.box), _centre(near.box)
            # beside its edge (apart more on x than on y, for their sizes), its width is cut: its height is whole
            axis = 1 if abs(nx - ox) / (near.box[2] + new.box[2]) > abs(ny - oy) / (near.box[3] + new.box[3]) else 0
            hidden = [tr for tr in unseen if tr is not near and _overlap(tr.box, near.box) > 0]
            if self._take_id(new, axis, hidden):
                return True
        return False

    def _seen_before(self, new: Track) -> bool:
        """A target does not come from nothing in the middle of the image: a new track confirmed away from
        the borders (and not found by `_out_from_behind`, which is tried first) is one seen
        before, which stopped unseen, was hidden or was merged into a blob, if a track unseen since before
        it appeared (or merged into another, within `forget_after_us`) fits its size on both axes; even one
        that left the image, which may come back in whole by the time its new track is confirmed, or
        in a blob with another. Whether it took an id."""
        unseen = self._unseen_since(new) + self._folded_before(new)
        return not self._seen_sides(new) and self._take_id(new, None, unseen)

    def _folded_before(self, new: Track) -> list[Track]:
        """The tracks merged into others (`_fold`) last seen before `new` was first seen, within `forget_after_us`."""
        since, forget = new.first_seen_us, self.params.forget_after_us
        return [tr for tr in self._folded if tr.last_seen_us < since and since - tr.last_seen_us < forget]

    def _unseen_since(self, new: Track) -> list[Track]:
        """The confirmed or lost tracks unseen since before `new` was first seen: whose target it may be."""
        return [tr for tr in self.tracks if tr is not new and tr.state in (TRACKED, LOST)
                and tr.last_seen_us < new.first_seen_us]

    def _occluders(self, new: Track) -> list[Track]:
        """Confirmed tracks whose box `new`'s touches: what it may come out from behind."""
        x, y, w, h = new.box
        m = 0.25 * max(w, h)
        grown = (x - m, y - m, w + 2 * m, h + 2 * m)
        return [tr for tr in self.tracks if tr is not new and tr.state == TRACKED and _overlap(grown, tr.box) > 0]

    def _take_id(self, new: Track, axis: int | None, lost: list[Track]) -> bool:
        """`new` takes the id of the one of `lost` whose usual size on `axis` fits its own (where two
        fit, only one that fits clearly better) and whose usual size on the other axis, which the edge
        may cut on `new`, is not much smaller than `new`'s (`axis` None: whose sizes on both axes fit,
        `new` seen whole); that one is removed (from the folded ones too), the sizes its id is known by
        going on with `new`. Only tracks once seen whole on both axes give their ids: one seen only in part
        (a piece of a target coming in beside another, lost again) is no identity to go on with. Whether it
        took an id."""
        p = self.params
        limit = math.log(p.reid_size_ratio)
        misfit = sorted((m, i) for i, tr in enumerate(lost)
                        if tr.widths and tr.heights and (m := self._misfit(new, tr, axis)) < limit)
        if len(misfit) == 1 or (len(misfit) > 1 and misfit[0][0] < p.reid_margin * misfit[1][0]):
            found = lost[misfit[0][1]]
            new.ident, found.state = found.ident, _GONE
            self._folded = [tr for tr in self._folded if tr is not found]
            # the id's sizes go on with it: a target found again on a sliver of it is still known by its whole size
            new.widths = deque([*found.widths, *new.widths], maxlen=SIZE_MEMORY)
            new.heights = deque([*found.heights, *new.heights], maxlen=SIZE_MEMORY)
            return True
        return False

    def _misfit(self, new: Track, old: Track, axis: int | None) -> float:
        """How far `new`'s size is from the one `old` is known by, as |log ratio|, on `axis` (the other, maybe cut
        on `new`, only not much bigger than `old`'s), or the worse of both axes (`axis` None); inf where
        `old` was never seen whole so."""
        if axis is None:
            return max(self._misfit(new, old, 0), self._misfit(new, old, 1))
        size, other = old.known_size(axis), old.known_size(1 - axis)
        if not size or new.box[3 - axis] > self.params.reid_size_ratio * (other or math.inf):
            return math.inf
        return abs(math.log(max(new.box[2 + axis], 1.0) / max(size, 1.0)))

    def reset(self) -> None:
        self.tracks, self._folded = [], []
