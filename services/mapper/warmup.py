"""Loading the mapper's numba kernels before a live mapper takes its first events.

Loading them (compiling, the first time on a machine) takes seconds; a live mapper that did it on
its first batch held the camera's events meanwhile, and dropped the oldest beyond its cap.
"""

from __future__ import annotations

import numpy as np

from services.mapper.keyframes import KeyframeMapper, KeyframeParams
from services.mapper.stereo import StereoMapper
from services.mapper.trajectory import Trajectory
from services.messages import EVENT_DTYPE

WIDTH, HEIGHT = 64, 48


def warm_up(method: str) -> None:
    """Runs a keyframe of `method` ("sweep" or "stereo") on a few random events of a sliding camera."""
    K = np.array([[50.0, 0, WIDTH / 2], [0, 50.0, HEIGHT / 2], [0, 0, 1]])
    t = np.linspace(0, 0.2, 11)
    trajectory = Trajectory(np.column_stack([t, t, 0 * t, 0 * t, 0 * t, 0 * t, 0 * t, 1 + 0 * t]))
    rng = np.random.default_rng(0)
    events = np.zeros(4000, EVENT_DTYPE)
    events["t"] = np.sort(rng.integers(0, 200_000, len(events)))
    events["x"], events["y"] = rng.integers(0, WIDTH, len(events)), rng.integers(0, HEIGHT, len(events))
    if method == "stereo":
        right = np.eye(4)
        right[0, 3] = 0.1
        seen = events.copy()
        seen["x"] = np.maximum(events["x"].astype(np.int64) - 3, 0)  # a disparity of 3 px
        stereo = StereoMapper(K, K, right, WIDTH, HEIGHT)
        stereo.add(events, seen, trajectory)
        keyframes = stereo.keyframes
    else:
        keyframes = KeyframeMapper(K, WIDTH, HEIGHT, KeyframeParams())
        keyframes.add(events, trajectory)
    if keyframes.held:
        keyframes.finish(trajectory)
