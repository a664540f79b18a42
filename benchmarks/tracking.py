"""Tracking accuracy on simulated sequences the tracker was not tuned on: `etam sim objects` with
noise on, several seeds, each run through `etam track` and scored by `etam eval tracking`.
Figures per seed and their mean: OP50, OP75, success AUC, precision@20, false positives per second,
id switches per object and minute.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from services.camera.offline import simulate
from services.tracker.offline import eval_tracking, track

FIGURES = ("op50", "op75", "success_auc", "precision20", "false_positives_per_s", "id_switches_per_object_minute")
METHOD = "decayed image + connected components (default)"


def run(quick: bool = False, seeds: tuple[int, ...] = (11, 12, 13, 14, 15)) -> list[dict]:
    seeds = seeds[:2] if quick else seeds
    duration_s = 5.0 if quick else 20.0
    rows = []
    with tempfile.TemporaryDirectory(prefix="etam-bench-") as tmp:
        for seed in seeds:
            h5, csv = Path(tmp) / f"objects{seed}.h5", Path(tmp) / f"tracks{seed}.csv"
            simulate("objects", h5, duration_s, seed=seed, progress=False)
            track(h5, csv, progress=False)
            scores = eval_tracking(csv, h5)
            rows.append({"stage": "tracking accuracy", "method": METHOD, "seed": seed, "duration_s": duration_s,
                         **{k: scores[k] for k in FIGURES}})
    mean = {k: sum(r[k] for r in rows) / len(rows) for k in FIGURES}
    rows.append({"stage": "tracking accuracy", "method": METHOD, "seed": "mean", "duration_s": duration_s, **mean})
    return rows
