"""USB decoding: the DVXplorer and DAVIS word streams decoded on one core, in the driver's 128 KiB reads.

The streams are the simulator's moving objects at each sensor's size, encoded as the cameras send them
(`services/camera/usb/encode.py`). No peer library on PyPI decodes these streams without the camera
itself (dv-processing and libcaer's wrappers read them only from a device), so there is none beside it.
Each is timed in rounds, and its fastest round is reported (CPU time of this process: the decoder runs
on one thread).
"""

from __future__ import annotations

import time

import numpy as np

from services.camera.simulator import EventSimulator, ObjectsScene, SimParams
from services.camera.usb.driver import READ_BYTES
from services.camera.usb.encode import encode
from services.camera.usb.protocol import MODELS
from services.camera.usb.words import WordDecoder

ROUNDS = 3


def run(quick: bool = False) -> list[dict]:
    rows = []
    seconds = 1.0 if quick else 4.0
    for model in ("dvxplorer", "davis346"):
        dvx, width, height = MODELS[model]
        scene = ObjectsScene(width, height, seed=5)
        events = EventSimulator(scene, SimParams(contrast=0.06), seed=5).advance(int(seconds * 1e6))
        if dvx:
            events = np.unique(events)  # one readout reports a pixel once
        data = encode(events, dvx)[0].tobytes()
        buffers = [memoryview(data)[k:k + READ_BYTES] for k in range(0, len(data), READ_BYTES)]
        WordDecoder(dvx, width, height).decode(buffers[0])  # kernels loaded before timing
        best = np.inf
        for _ in range(1 if quick else ROUNDS):
            decoder = WordDecoder(dvx, width, height)
            t0 = time.process_time()
            n = sum(len(decoder.decode(b).events) for b in buffers)
            best = min(best, time.process_time() - t0)
        if n != len(events):
            raise RuntimeError(f"{model}: {n} events decoded of {len(events)} encoded")
        rows.append({"stage": "usb decode", "model": model, "events": n, "bytes": len(data),
                     "bytes_per_event": len(data) / n, "events_per_s": n / best, "mb_per_s": len(data) / best / 1e6})
    return rows
