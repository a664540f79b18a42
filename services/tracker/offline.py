"""Offline tracking commands: `etam track` (a recording to a tracks CSV), `etam odom` (a recording to a
TUM trajectory), `etam eval tracking` and `etam eval odometry`."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from services import events as ev_ops
from services.camera.filters import Undistort
from services.camera.formats import FormatError, Recording, open_recording
from services.camera.formats.kernels import first_at_or_after
from services.mapper.trajectory import Trajectory, read_tum, write_tum
from services.tracker.ego import ODOMETRY_MODES
from services.tracker.ego.evaluation import evaluate_odometry
from services.tracker.ego.gyro import Gyro
from services.mapper.offline import map_method, stereo_mapper
from services.messages import EVENT_DTYPE
from services.tracker.ego.loop import LoopParams, MappedOdometry, loop_params
from services.tracker.ego.rotation import LOST, STILL, RotationParams, RotationTracker
from services.tracker.evaluation import evaluate, split_frames
from services.tracker.objects.association import TRACKED
from services.tracker.objects.tracker import ObjectTracker, TrackerParams

CSV_HEADER = "t_us,id,x,y,w,h,score"  # DESIGN.md section 7


def track(src: Path, out: Path, params: TrackerParams | None = None, progress: bool = True,
          make_tracker: Callable[[int, int, TrackerParams | None], ObjectTracker] = ObjectTracker) -> dict[str, Any]:
    """Run the object tracker (or a variant of it, as the benchmark's) over a recording, one update
    per `update_us` of sensor time, and write the tracked boxes of each update as CSV rows."""
    rows: list[np.ndarray] = []
    with open_recording(src) as rec:
        tracker = make_tracker(rec.width, rec.height, params)
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


def odometry(src: Path, out: Path, params: RotationParams | None = None, progress: bool = True,
             mode: str = "rotation", bootstrap_s: float = 1.5, start: Path | None = None,
             loop_params: LoopParams | None = None, method: str | None = None, imu: bool = True) -> dict[str, Any]:
    """Run the ego-motion tracker over a recording's first camera (undistorted where calibrated so) and write
    its poses (T_world_cam) as a TUM file: `rotation` (the world frame being the camera's at the first
    event), or `6dof` (the tracking-mapping loop, its first map from the first `bootstrap_s` of known poses:
    `start`'s, else the file's truth; the world frame is theirs), mapped by `method`: the space sweep of the
    first camera, or stereo of the first two (the default for a file of two cameras), its rotation told by the
    file's gyro if it has one and `imu`. Lost updates give no pose, and are counted."""
    if mode not in ODOMETRY_MODES:
        raise ValueError(f"odometry mode {mode!r} is not one of {', '.join(ODOMETRY_MODES)}")
    rows = []
    with open_recording(src) as rec, contextlib.ExitStack() as others:
        rig = [rec, *(others.enter_context(r) for r in rec.rig()[1:])] if mode == "6dof" else [rec]
        method = map_method(src, rig, method)
        cameras = rig[:2] if method == "stereo" else rig[:1]
        if mode == "6dof":
            gyro = recorded_gyro(rec) if imu else None
            tracker: RotationTracker | MappedOdometry = _loop(rec, src, cameras, bootstrap_s, start, loop_params,
                                                              gyro)
        else:
            tracker = RotationTracker(rec.K_or_default(), rec.width, rec.height, params)
        n_events = still = lost = 0
        with tqdm(unit="ev", unit_scale=True, desc=src.name, disable=not progress) as bar:
            for chunks in _camera_chunks(cameras):
                n = sum(len(c) for c in chunks)
                n_events += n
                bar.update(n)
                for est in tracker.add(*chunks):
                    lost += est.state == LOST
                    if est.state != LOST:
                        rows.append(est.tum_row())
                        still += est.state == STILL
    write_tum(str(out), np.asarray(rows).reshape(-1, 8))
    summary = {"input": str(src), "output": str(out), "mode": mode, "events": n_events, "poses": len(rows),
               "still": still, "lost": lost}
    if isinstance(tracker, MappedOdometry):
        summary |= {"rate_hz": 1e6 / tracker.params.tracker.step_us, "bootstrap_s": bootstrap_s, "method": method,
                    "gyro": tracker.tracker.gyro is not None,
                    "keyframes": len(tracker.keyframes), "map_points": sum(len(k.points) for k in tracker.keyframes)}
    else:
        summary["rate_hz"] = 1e6 / tracker.params.step_us
    return summary


def _camera_chunks(cameras: list[Recording]) -> Iterator[tuple[np.ndarray, ...]]:
    """The cameras' events (undistorted where calibrated so) in chunks: the first camera's, with the second's
    up to the same time."""
    streams = [_undistorted(rec) for rec in cameras]
    if len(streams) == 1:
        return ((chunk,) for chunk in streams[0])
    return ev_ops.paired(*streams)


def _undistorted(rec: Recording) -> Iterator[np.ndarray]:
    undistort = Undistort.of(rec)
    for chunk in rec.chunks():
        yield undistort(chunk) if undistort is not None else chunk


def _loop(rec: Recording, src: Path, cameras: list[Recording], bootstrap_s: float, start: Path | None,
          params: LoopParams | None, gyro: Gyro | None) -> MappedOdometry:
    """The 6-DoF tracking-mapping loop of the first camera, mapped by stereo when given two."""
    stereo = len(cameras) > 1
    params = params or loop_params(stereo)
    return MappedOdometry(rec.K_or_default(), rec.width, rec.height, _known_start(rec, src, bootstrap_s, start),
                          params, stereo_mapper(src, cameras, params.keyframes) if stereo else None, gyro)


def recorded_gyro(rec: Recording) -> Gyro | None:
    """The recording's gyro samples, if it has any (what `etam odom` and the bench's speed run predict with)."""
    imu = rec.imu()
    if imu is None or not len(imu[0]):
        return None
    gyro = Gyro()
    gyro.add(*imu[:2])
    return gyro


def _known_start(rec: Recording, src: Path, bootstrap_s: float, start: Path | None) -> Trajectory:
    """The known poses of the first `bootstrap_s` (of `start`'s TUM file, else the recording's truth)."""
    if bootstrap_s <= 0:
        raise ValueError(f"--bootstrap must be positive, got {bootstrap_s}")
    if start is not None:
        rows = read_tum(str(start))
    elif rec.truth.poses is not None:
        rows = np.asarray(rec.truth.poses, np.float64)
    else:
        raise ValueError(f"{src}: 6-DoF odometry needs known poses for its first {bootstrap_s:g} s, to build its "
                         "first map: give --start traj.tum, or a recording with /truth/poses")
    rows = rows[rows[:, 0] <= rows[0, 0] + bootstrap_s + 1e-9]
    if len(rows) < 2:
        raise ValueError(f"{start or src}: fewer than 2 known poses in the first {bootstrap_s:g} s")
    return Trajectory(rows)


def eval_odometry(pred: Path, truth: Path, align: str = "auto") -> dict[str, Any]:
    """`etam eval odometry`: the scores of a TUM trajectory against a recording's truth poses (and angular
    velocity, where it has it) or a TUM ground-truth file (`.txt`, `.tum`)."""
    estimate = read_tum(str(pred))
    omega = None
    if truth.suffix in (".txt", ".tum"):
        poses = read_tum(str(truth))
    else:
        try:
            with open_recording(truth) as rec:
                poses, omega = rec.truth.poses, rec.truth.omega
        except FormatError as exc:
            raise ValueError(str(exc)) from None
        if poses is None:
            raise ValueError(f"{truth}: has no ground-truth poses (/truth/poses)")
    try:
        scores = evaluate_odometry(estimate, poses, omega, align)
    except ValueError as exc:
        raise ValueError(f"{pred} against {truth}: {exc}") from None
    return {"pred": str(pred), "truth": str(truth), **scores}


def _rows(tracker: ObjectTracker, t_us: int) -> np.ndarray:
    ts = tracker.generate(t_us)
    keep = ts.states == TRACKED  # confirmed tracks only
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
            boxes, ignore = rec.truth.boxes, rec.truth.ignore
    except FormatError as exc:
        raise ValueError(str(exc)) from None
    if boxes is None:
        raise ValueError(f"{truth}: has no ground-truth boxes (/truth/boxes)")
    return {"pred": str(pred), "truth": str(truth), **evaluate(predicted, boxes, ignore=ignore).as_dict()}


def snapshots(src: Path, tracks: np.ndarray, out: Path, n: int = 6, window_us: int = 30_000) -> None:
    """A PNG of `n` event frames, evenly spread over the recording, with the tracked boxes and ids
    of the nearest update drawn on them (ON events white, OFF grey)."""
    ev, width, height, _ = _recorded(src)
    times = np.linspace(int(ev["t"][0]) + window_us, int(ev["t"][-1]), n).astype(np.int64)
    updates = split_frames(tracks)
    tiles = [_frame(ev, width, height, int(t), window_us, updates, caption=f"{t / 1e6:.3f} s") for t in times]
    _write_grid(tiles, min(3, n), out)


def switch_snapshots(src: Path, tracks: np.ndarray, switches: list[dict], out: Path, most: int = 8,
                     before_us: int = 200_000, window_us: int = 30_000) -> int:
    """A PNG with a row per id switch (the first `most`): the event frame `before_us` before it and the one
    at it, the truth boxes in green (the switched object's yellow; labelled o<object>) under the tracked
    boxes and ids; what `etam eval tracking --snapshots` draws, so that a switch is seen, not only listed.
    The number of switches drawn."""
    ev, width, height, truth = _recorded(src)
    updates, objects = split_frames(tracks), split_frames(truth)
    tiles = []
    for e in switches[:most]:
        t = int(e["t_us"])
        for at in (t - before_us, t):
            caption = (f"{at / 1e6:.3f} s  o{e['object']}: {e['from_id']} -> {e['to_id']}"
                       + (f" ({e['cause']})" if at == t and "cause" in e else ""))
            tiles.append(_frame(ev, width, height, at, window_us, updates, objects, e["object"], caption))
    if tiles:
        _write_grid(tiles, 2, out)
    return len(tiles) // 2


def _recorded(src: Path) -> tuple[np.ndarray, int, int, np.ndarray]:
    """A recording's events (all of them, in time order), its size and its truth boxes (none: 0 rows)."""
    with open_recording(src) as rec:
        ev = np.concatenate([c for c in rec.chunks() if len(c)] or [np.zeros(0, EVENT_DTYPE)])
        truth = rec.truth.boxes if rec.truth.boxes is not None else np.zeros((0, 6))
        width, height = rec.width, rec.height
    if not len(ev):
        raise ValueError(f"{src}: no events to draw")
    return ev, width, height, truth


Frames = tuple[np.ndarray, list[np.ndarray]]  # rows split by time (`split_frames`)


def _frame(ev: np.ndarray, width: int, height: int, t: int, window_us: int, updates: Frames,
           truth: Frames | None = None, highlight: int | None = None, caption: str = "") -> np.ndarray:
    """The events of `window_us` up to `t` (ON white, OFF grey) with the truth boxes of the latest truth
    frame at or before `t` (green, `highlight`'s yellow) and the tracked boxes of the latest update (each id
    its colour)."""
    import cv2

    frame = ev[np.searchsorted(ev["t"], t - window_us, side="right"):np.searchsorted(ev["t"], t, side="right")]
    img = np.zeros((height, width, 3), np.uint8)
    img[frame["y"], frame["x"]] = np.where(frame["p"][:, None] > 0, 255, 110).astype(np.uint8)
    for frames, is_truth in ((truth, True), (updates, False)):
        times, rows = frames if frames is not None else (np.zeros(0), [])
        k = np.searchsorted(times, t, side="right") - 1
        for row in rows[k] if k >= 0 else []:
            x, y, w, h = (int(round(v)) for v in row[2:6])
            ident = int(row[1])
            if is_truth:  # the switched object's yellow and thicker
                colour, thick = ((0, 230, 255), 2) if ident == highlight else ((0, 170, 0), 1)
                cv2.putText(img, f"o{ident}", (x + 2, y + h - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1)
            else:
                colour = tuple(int(c) for c in np.random.default_rng(ident).integers(80, 256, 3))
                thick = 1
                cv2.putText(img, str(ident), (x + 2, y + 11), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1)
            cv2.rectangle(img, (x, y), (x + w, y + h), colour, thick)
    cv2.putText(img, caption, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 200, 255), 1)
    return img


def _write_grid(tiles: list[np.ndarray], cols: int, out: Path) -> None:
    import cv2

    tiles = tiles + [np.zeros_like(tiles[0])] * (-len(tiles) % cols)
    grid = np.vstack([np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)])
    if not cv2.imwrite(str(out), grid):
        raise ValueError(f"{out}: cannot write the image")
