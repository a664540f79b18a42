"""Object tracker: decayed accumulation -> moving clusters -> association with ids (pure numpy)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.tracker.objects.accumulator import DecayedAccumulator
from services.tracker.objects.association import AssociationParams, MultiObjectTracker
from services.tracker.objects.clusters import ClusterParams, detect_clusters
from services.tracker.objects.meanshift import mean_shift


@dataclass
class TrackerParams:
    tau_us: float = 30_000.0
    update_us: int = 10_000  # a tracking update every 10 ms of sensor time
    clusters: ClusterParams = field(default_factory=ClusterParams)
    association: AssociationParams = field(default_factory=AssociationParams)


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
        self.accumulator = DecayedAccumulator(width, height, self.params.tau_us)
        self.association = MultiObjectTracker(self.params.association, width, height)

    def accept(self, events: np.ndarray) -> None:
        self.accumulator.accept(events)

    def generate(self, t_us: int) -> TrackSet:
        image = self.accumulator.generate(t_us)
        boxes, _mass = detect_clusters(image, self.params.clusters)
        tracks = self.association.update(t_us, boxes, refine=lambda box: mean_shift(image, box))
        return TrackSet(
            t_us=t_us,
            ids=np.array([tr.ident for tr in tracks], np.int32),
            boxes=np.array([tr.box for tr in tracks], np.float32).reshape(-1, 4),
            scores=np.array([tr.score for tr in tracks], np.float32),
            vels=np.array([tr.vel for tr in tracks], np.float32).reshape(-1, 2),
            states=np.array([tr.state for tr in tracks], np.uint8),
        )

    def reset(self) -> None:
        self.accumulator.reset()
        self.association.reset()
