"""Offline tracking commands: `etam track` (a recording to a tracks CSV) and `etam eval tracking`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from services.camera.formats import FormatError, open_recording
from services.camera.formats.kernels import first_at_or_after
from services.tracker.evaluation import evaluate
from services.tracker.objects.tracker import ObjectTracker, TrackerParams

CSV_HEADER = "t_us,id,x,y,w,h,score"  # DESIGN.md section 7
TRACKED = 1  # the track state written out: confirmed, seen now


def track(src: Path, out: Path, params: TrackerParams | None = None, progress: bool = True) -> dict[str, Any]:
    """Run the object tracker over a recording, one update per `update_us` of sensor time, and
    write the tracked boxes of each update as CSV rows."""
    rows: list[np.ndarray] = []
    with open_recording(src) as rec:
        tracker = ObjectTracker(rec.width, rec.height, params)
        step = tracker.params.update_us
        next_us: int | None = None
        n_events = 0
        with tqdm(unit="ev", unit_scale=True, desc=src.name, disable=not progress) as bar:
            for chunk in rec.chunks():
                if not len(chunk):
                    continue
                n_events += len(chunk)
                bar.update(len(chunk))
                if next_us is None:
                    next_us = (int(chunk["t"][0]) // step + 1) * step
                while len(chunk) and int(chunk["t"][-1]) >= next_us:
                    cut = first_at_or_after(chunk, next_us)
                    tracker.accept(chunk[:cut])
                    chunk = chunk[cut:]
                    rows.append(_rows(tracker, next_us))
                    next_us += step
                tracker.accept(chunk)
    table = np.concatenate(rows) if rows else np.zeros((0, 7))
    np.savetxt(out, table, fmt=["%d", "%d", "%.2f", "%.2f", "%.2f", "%.2f", "%.3f"], delimiter=",",
               header=CSV_HEADER, comments="")
    ids = np.unique(table[:, 1]) if len(table) else np.zeros(0)
    return {"input": str(src), "output": str(out), "events": n_events, "updates": len(rows),
            "boxes": len(table), "track_ids": len(ids)}


def _rows(tracker: ObjectTracker, t_us: int) -> np.ndarray:
    ts = tracker.generate(t_us)
    keep = ts.states == TRACKED
    n = int(keep.sum())
    return np.column_stack([np.full(n, t_us), ts.ids[keep], ts.boxes[keep], ts.scores[keep]]).astype(np.float64)


def read_tracks(path: Path) -> np.ndarray:
    """Rows (t_us, id, x, y, w, h) of a tracks CSV; ValueError naming the file if it is not one."""
    try:
        with open(path, "rb") as f:
            header = f.readline(200).decode("utf-8", "replace").strip()
        if header != CSV_HEADER:
            raise ValueError(f"{path}: not a tracks CSV (first line {header[:40]!r}, expected {CSV_HEADER!r})")
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except OSError as exc:
        raise ValueError(f"{path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise ValueError(str(exc) if str(exc).startswith(str(path)) else f"{path}: {exc}") from None
    if table.size and table.shape[1] != 7:
        raise ValueError(f"{path}: expected 7 columns ({CSV_HEADER}), got {table.shape[1]}")
    return table[:, :6] if table.size else np.zeros((0, 6))


def eval_tracking(pred: Path, truth: Path) -> dict[str, Any]:
    """`etam eval tracking`: the scores of a tracks CSV against a recording's truth boxes."""
    predicted = read_tracks(pred)
    try:
        with open_recording(truth) as rec:
            boxes = rec.truth.boxes
    except FormatError as exc:
        raise ValueError(str(exc)) from None
    if boxes is None:
        raise ValueError(f"{truth}: has no ground-truth boxes (/truth/boxes)")
    return {"pred": str(pred), "truth": str(truth), **evaluate(predicted, boxes).as_dict()}
