"""Event sources the camera service can play: the built-in simulator (files and USB come later).

A source is pure: ``advance(until_us)`` returns the events up to that sensor time, ``truth(t_us)``
the ground-truth boxes if it has any. The service decides the pacing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from services.camera.simulator import EventSimulator, ObjectsScene


class SourceError(ValueError):
    """A source that cannot be opened; the text names it and says why."""


class EventSource(Protocol):
    width: int
    height: int
    K: np.ndarray

    def advance(self, until_us: int) -> np.ndarray: ...

    def truth_boxes(self, t_us: int) -> tuple[np.ndarray, np.ndarray] | None: ...


@dataclass
class SimSource:
    """`sim:objects`: the simulator's static-camera scene with moving objects and truth boxes."""

    scene: ObjectsScene
    sim: EventSimulator

    @property
    def width(self) -> int:
        return self.scene.width

    @property
    def height(self) -> int:
        return self.scene.height

    @property
    def K(self) -> np.ndarray:
        f = self.scene.focal_px
        return np.array([[f, 0, self.width / 2], [0, f, self.height / 2], [0, 0, 1]], np.float64)

    def advance(self, until_us: int) -> np.ndarray:
        return self.sim.advance(until_us)

    def truth_boxes(self, t_us: int) -> tuple[np.ndarray, np.ndarray]:
        return self.scene.boxes(t_us)


SIM_SCENES = ("objects",)


def open_source(spec: str, seed: int = 0, width: int = 346, height: int = 260) -> EventSource:
    """Open a source from its command-line name (``sim:objects``, ...)."""
    if spec.startswith("sim:"):
        scene = spec[4:]
        if scene == "objects":
            sc = ObjectsScene(width, height, seed=seed)
            return SimSource(sc, EventSimulator(sc, seed=seed))
        raise SourceError(f"source {spec!r}: unknown simulator scene {scene!r} (available: "
                          f"{', '.join('sim:' + s for s in SIM_SCENES)})")
    raise SourceError(f"source {spec!r}: only the simulator ({', '.join('sim:' + s for s in SIM_SCENES)}) "
                      "is available in this version; files and USB cameras are not supported yet")
