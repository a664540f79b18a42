"""Ego-motion: rotation accuracy on `etam sim rotation` and the rotation tracker's rate.

Accuracy: three `sim:rotation` seeds no one looked at while choosing the defaults (chosen on seed 1),
10 s each, their motion scaled to peak at 600, 800 and 1000 deg/s, run through `etam odom` and scored by
`etam eval odometry` (origin alignment): the angular velocity's RMS error and its share of the peak speed,
the orientation error at the end and its RMS, and RPE per second; tracking against the panoramic map (the default)
and by integration alone. Speed: the tracker on one core (OpenCV held to one thread) over a rotation
stream of about 1 Mev/s (a higher contrast threshold), fed in 1 ms packets as the live service is:
estimates per second of the process's CPU time (the issue asks 100 Hz at 1 Mev/s: the kernels run on one
thread, so this is one core's; wall-clock time on a shared VM varied by 30 % from run to run, and is
given beside it), and ms per estimate. No peer
library on PyPI estimates camera motion from events, so no ratio is given.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_limits

from benchmarks.mapping import per_seed
from services.camera.formats import open_recording
from services.camera.offline import simulate
from services.camera.simulator import SimParams
from services.tracker.ego.rotation import RotationParams, RotationTracker
from services.tracker.offline import eval_odometry, odometry

HELD_OUT_SEEDS = (11, 12, 13)  # never looked at while choosing defaults: keep them so
PEAKS_DEG_S = {11: 600.0, 12: 800.0, 13: 1000.0}  # each seed's motion scaled to peak at this speed
FIGURES = ("omega_rms_deg_s", "omega_peak_deg_s", "omega_rms_of_peak", "final_rot_err_deg", "ate_rot_deg",
           "rpe_deg_per_s", "integrated_final_rot_err_deg", "integrated_omega_rms_of_peak")
SPEED_SIM = SimParams(contrast=0.7)  # the rotation scene at about 1 Mev/s over 4 s
PACKET_US = 1_000


def run(quick: bool = False) -> list[dict]:
    seeds = HELD_OUT_SEEDS[:1] if quick else HELD_OUT_SEEDS
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        def score(h5: Path, seed: int) -> dict:
            tum, alone = Path(tmp) / f"{seed}.tum", Path(tmp) / f"{seed}-integrated.tum"
            odometry(h5, tum, progress=False)
            odometry(h5, alone, RotationParams(panorama=False), progress=False)
            integrated = eval_odometry(alone, h5)
            return {**eval_odometry(tum, h5), "integrated_final_rot_err_deg": integrated["final_rot_err_deg"],
                    "integrated_omega_rms_of_peak": integrated["omega_rms_of_peak"]}

        rows = per_seed("odometry rotation", "rotation", seeds, 2.0 if quick else 10.0, score, FIGURES, Path(tmp),
                        {seed: {"peak_deg_s": peak} for seed, peak in PEAKS_DEG_S.items()})
        rows.extend(speed(Path(tmp) / "speed.h5", 1.0 if quick else 4.0))
    return rows


def speed(h5: Path, seconds: float) -> list[dict]:
    """The rotation tracker's estimates per CPU second on one core, fed 1 ms packets of a
    `sim:rotation` stream of about 1 Mev/s, with and without the panoramic map."""
    simulate("rotation", h5, seconds, seed=HELD_OUT_SEEDS[0], progress=False, params=SPEED_SIM)
    with open_recording(h5) as rec:
        events = np.concatenate(list(rec.chunks()))
        K, w, h = rec.K_or_default(), rec.width, rec.height
    cuts = np.searchsorted(events["t"], np.arange(events["t"][0], events["t"][-1], PACKET_US))
    packets = np.split(events, cuts[1:])
    stream_rate = len(events) / ((events["t"][-1] - events["t"][0]) * 1e-6)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    rows = []
    blas = threadpool_limits(1)  # BLAS pools held to one thread too, as the live service holds them
    try:
        for panorama in (True, False):
            tracker = RotationTracker(K, w, h, RotationParams(panorama=panorama))
            wall = cpu = 0.0
            estimates = 0
            for packet in packets:
                t0, c0 = time.perf_counter(), time.process_time()
                estimates += len(tracker.add(packet))
                wall += time.perf_counter() - t0
                cpu += time.process_time() - c0
            rows.append({"stage": "odometry rotation speed", "panorama": panorama, "events": len(events),
                         "stream_events_per_s": stream_rate, "estimates": estimates,
                         "estimates_per_s": estimates / cpu, "ms_per_estimate": 1e3 * cpu / estimates,
                         "wall_estimates_per_s": estimates / wall, "events_per_s": len(events) / cpu,
                         "realtime_factor": seconds / cpu})
    finally:
        cv2.setNumThreads(threads)
        blas.restore_original_limits()
    return rows
