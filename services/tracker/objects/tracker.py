"""Object tracker: event frame -> detections -> association with ids (pure numpy).

Every stage has the variants of the seeds, chosen by `TrackerParams`:
- frames: `decay` (a decayed accumulation image, seeds 002/003) or `adaptive` (seed 002's window
  that moves between time-based and count-based by frame quality);
- detection: `contour` (occupancy clusters, seed 003's contour method), `camshift` (seed 003's
  Canny edges + CamShift per track, clusters for new targets) or `corner` (seed 003's feature
  method: corner clusters);
- key-event sampling (seed 004) thins an update's events once they exceed `max_events`;
- a track's blob is split where its shape is two targets' (see `shapes.py`) or its points move two
  ways, and tracks sharing a blob learn their velocities from the motion of their own parts of it
  (see `motion.py`) and are found by what they looked like on their own (see `appearance.py`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from services import events as ev_ops
from services.messages import EVENT_DTYPE
from services.tracker.objects import appearance, motion, shapes
from services.tracker.objects.accumulator import DecayedAccumulator, to_uint8
from services.tracker.objects.activity import FreshCounts
from services.tracker.objects.appearance import AppearanceParams
from services.tracker.objects.association import LOST, AssociationParams, Box, MultiObjectTracker, intersection
from services.tracker.objects.clusters import ClusterParams, detect_clusters
from services.tracker.objects.corners import CornerParams, detect_corner_clusters
from services.tracker.objects.frames import AdaptiveParams, AdaptiveWindow
from services.tracker.objects.layout import LayoutParams, fit_layout, leftover
from services.tracker.objects.motion import MotionParams, ShiftParams, part_velocity, split_by_motion
from services.tracker.objects.sampling import key_events
from services.tracker.objects.shapes import ShapeParams, two_rectangles

FRAMES = ("decay", "adaptive")
DETECTORS = ("contour", "camshift", "corner")


@dataclass
class TrackerParams:
    frames: str = "decay"
    detector: str = "contour"
    tau_us: float = 30_000.0
    update_us: int = 10_000  # a tracking update every 10 ms of sensor time
    max_events: int = 0  # more events than this in one update are thinned to key events (0: never)
    sample_cell_px: int = 2
    clusters: ClusterParams = field(default_factory=ClusterParams)
    corners: CornerParams = field(default_factory=CornerParams)
    adaptive: AdaptiveParams = field(default_factory=AdaptiveParams)
    association: AssociationParams = field(default_factory=AssociationParams)
    layout: LayoutParams = field(default_factory=LayoutParams)
    motion: MotionParams = field(default_factory=MotionParams)
    shift: ShiftParams = field(default_factory=ShiftParams)
    appearance: AppearanceParams = field(default_factory=AppearanceParams)
    shapes: ShapeParams = field(default_factory=ShapeParams)

    def __post_init__(self) -> None:
        if self.frames not in FRAMES:
            raise ValueError(f"tracker frames {self.frames!r} is not one of {', '.join(FRAMES)}")
        if self.detector not in DETECTORS:
            raise ValueError(f"tracker detector {self.detector!r} is not one of {', '.join(DETECTORS)}")


# the methods compared in `etam bench tracking`
METHODS: dict[str, TrackerParams] = {
    "contour": TrackerParams(),
    "adaptive": TrackerParams(frames="adaptive"),
    # CamShift windows drift along the edges they climb: the young tracks born beside them are duplicates
    # whose velocities tell nothing, folded by overlap alone; and a window split by motion would grow a
    # track whose own window is split again (tracks multiplied without end)
    "camshift": TrackerParams(detector="camshift", motion=MotionParams(lag_us=0),
                              association=AssociationParams(take_whole=False, young_unlike_px_s=math.inf)),
    "corner": TrackerParams(detector="corner"),
    "keyevents": TrackerParams(max_events=1),
}
DEFAULT_METHOD = "contour"


def method_params(name: str) -> TrackerParams:
    """A fresh copy of the parameters of a named method; ValueError naming the known ones."""
    if name not in METHODS:
        raise ValueError(f"tracking method {name!r} is not one of {', '.join(METHODS)}")
    base = METHODS[name]
    return replace(base, clusters=replace(base.clusters), corners=replace(base.corners),
                   adaptive=replace(base.adaptive), association=replace(base.association),
                   layout=replace(base.layout), motion=replace(base.motion), shift=replace(base.shift),
                   appearance=replace(base.appearance), shapes=replace(base.shapes))


@dataclass
class TrackSet:
    """The tracks at one time, as arrays (the fields of the Tracks message)."""

    t_us: int
    ids: np.ndarray
    boxes: np.ndarray
    scores: np.ndarray
    vels: np.ndarray
    states: np.ndarray


class ObjectTracker:
    """Accepts events; `generate(t_us)` returns the TrackSet at that time (dv-processing's verbs)."""

    def __init__(self, width: int, height: int, params: TrackerParams | None = None) -> None:
        self.params = params or TrackerParams()
        self.width, self.height = width, height
        if self.params.frames == "adaptive":
            self.frames: DecayedAccumulator | AdaptiveWindow = AdaptiveWindow(width, height, self.params.adaptive)
        else:
            self.frames = DecayedAccumulator(width, height, self.params.tau_us)
        self.association = MultiObjectTracker(self.params.association, width, height)
        self._sampled: list[np.ndarray] = []
        self.fresh = FreshCounts(width, height)
        self._past: deque[tuple[int, np.ndarray]] = deque()  # (t_us, image) of recent updates, for `motion`

    def accept(self, events: np.ndarray) -> None:
        self.fresh.accept(events)
        if self.params.max_events:
            self._sampled.append(events)
        else:
            self.frames.accept(events)

    def generate(self, t_us: int) -> TrackSet:
        if self._sampled:
            self._accept_sampled()
        image = self.frames.generate(t_us)
        boxes = self._detect(image, t_us)
        earlier = self._earlier(t_us, image)
        motions = parts = None
        if earlier is not None:
            past, dt_s = earlier[1], (t_us - earlier[0]) / 1e6
            motions = lambda det: split_by_motion(past, image, det, dt_s, self.params.motion)  # noqa: E731
            parts = lambda box, others, guess: part_velocity(  # noqa: E731
                past, image, box, others, guess, dt_s, self.params.shift)
        tracks = self.association.update(
            t_us, boxes, fresh=self.fresh.count,
            layout=lambda preds, sizes, fills, fixed: self._layout(image, preds, sizes, fills, fixed),
            leftover=lambda det, boxes: leftover(image, det, boxes, self.params.layout.recent), motions=motions,
            parts=parts, looks=_Looks(image, self.params.appearance) if self.params.appearance.reach_px else None,
            shapes=lambda det: two_rectangles(image, det, self.params.clusters.recent, self.params.shapes))
        self.fresh.reset()
        return TrackSet(
            t_us=t_us,
            ids=np.array([tr.ident for tr in tracks], np.int32),
            boxes=np.array([self.association.seen_box(tr) for tr in tracks], np.float32).reshape(-1, 4),
            scores=np.array([tr.score for tr in tracks], np.float32),
            vels=np.array([tr.vel for tr in tracks], np.float32).reshape(-1, 2),
            states=np.array([self.association.reported_state(tr) for tr in tracks], np.uint8),
        )

    def _earlier(self, t_us: int, image: np.ndarray) -> tuple[int, np.ndarray] | None:
        """The latest past image at least `motion.lag_us` older than this one (with its time), if any; this
        one (a copy: the frames reuse their array) kept for the updates to come if `motion.keep_us` after the
        last one kept."""
        lag = self.params.motion.lag_us
        if lag <= 0:
            return None
        while len(self._past) >= 2 and t_us - self._past[1][0] >= lag:
            self._past.popleft()
        earlier = self._past[0] if self._past and t_us - self._past[0][0] >= lag else None
        if not self._past or t_us - self._past[-1][0] >= self.params.motion.keep_us:
            self._past.append((t_us, image.copy()))
        return earlier

    def _layout(self, image: np.ndarray, boxes: np.ndarray, sizes: np.ndarray, fills: np.ndarray,
                fixed: np.ndarray | None = None) -> np.ndarray:
        """Where the tracks sharing one blob are (their predicted boxes, own sizes and usual fills, and the other
        tracks' boxes in; boxes out)."""
        return fit_layout(image, boxes, self.params.layout, sizes, fills, fixed)

    def _accept_sampled(self) -> None:
        """This update's events, thinned to key events (each weighted by the events of its cell)
        when there are more than `max_events` of them."""
        events = ev_ops.concat(self._sampled) if len(self._sampled) > 1 else self._sampled[0]
        self._sampled = []
        if len(events) <= self.params.max_events or not isinstance(self.frames, DecayedAccumulator):
            self.frames.accept(events)
            return
        idx, weight = key_events(events, self.width, self.height, self.params.sample_cell_px)
        self.frames.accept(ev_ops.take(events, idx), weight)

    def _detect(self, image: np.ndarray, t_us: int) -> np.ndarray:
        p = self.params
        if p.detector == "corner":
            return detect_corner_clusters(image, p.corners)
        boxes = detect_clusters(image, p.clusters)
        if p.detector == "camshift":
            return self._camshift(image, boxes, t_us)
        return boxes

    def _camshift(self, image: np.ndarray, clusters: np.ndarray, t_us: int) -> np.ndarray:
        """Seed 003's contour method: CamShift on the Canny edges of the frame, from each live
        track's predicted box; clusters no CamShift box covers are new targets."""
        edges = cv2.Canny(to_uint8(image), 50, 150)
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 1.0)
        found = []
        for tr in self.association.tracks:
            if tr.state == LOST:
                continue
            x, y, w, h = (int(round(v)) for v in tr.predict(t_us))
            x, y = min(max(x, 0), self.width - 1), min(max(y, 0), self.height - 1)
            w, h = max(min(w, self.width - x), 1), max(min(h, self.height - y), 1)
            if edges[y:y + h, x:x + w].any():
                _, window = cv2.CamShift(edges, (x, y, w, h), criteria)
                if window[2] > 0 and window[3] > 0:
                    found.append(window)
        shifted = np.asarray(found, np.float32).reshape(-1, 4)
        if len(shifted) and len(clusters):
            covered = (intersection(shifted, clusters) / np.maximum(clusters[:, 2] * clusters[:, 3], 1)).max(axis=0)
            clusters = clusters[covered < 0.5]
        return np.concatenate([shifted, clusters])

    def reset(self) -> None:
        self.frames.reset()
        self.association.reset()
        self.fresh.reset()
        self._sampled = []
        self._past.clear()


class _Looks:
    """The association's `Looks` on one update's image."""

    def __init__(self, image: np.ndarray, params: AppearanceParams) -> None:
        self.image, self.params = image, params

    def capture(self, box: Box) -> np.ndarray | None:
        return appearance.template(self.image, box)

    def find(self, patch: np.ndarray, box: Box) -> tuple[float, float] | None:
        return appearance.find(self.image, patch, box, self.params)


def warm_up(params: TrackerParams | None = None) -> None:
    """Loads the numba kernels of an update (compiles them, the first time on a machine) on two small
    squares that cross, so that a live tracker's first packets wait for none of it: loading them took
    over a second on a busy machine, while the camera's packets queued up and the oldest were dropped.
    Every other packet is read-only, as packets decoded off the wire are (numba compiles such arrays
    apart); the rest are writable, as events read from a file are."""
    width, height, side = 96, 48, 12
    tracker = ObjectTracker(width, height, params)
    ys, xs = np.mgrid[:side, :side].reshape(2, -1)
    for step in range(40):
        t_us = (step + 1) * 10_000
        events = np.zeros(2 * len(xs), EVENT_DTYPE)
        for k, x0 in enumerate((4 + 2 * step, width - side - 4 - 2 * step)):
            part = events[k * len(xs):(k + 1) * len(xs)]
            part["x"], part["y"] = xs + x0, ys + 18  # x0 stays within 0..width - side
            part["t"] = t_us - 10_000 + np.arange(len(xs)) * 10_000 // len(xs)
            part["p"] = 1
        events = ev_ops.sort_by_time(events)
        events.flags.writeable = step % 2 == 0
        tracker.accept(events)
        tracker.generate(t_us)
    motion.warm_up()
    appearance.warm_up()
    shapes.warm_up()
