"""Offline mapping commands: `etam map` (a recording and poses to a PLY cloud), `etam mosaic` (a
rotating camera's recording to a panorama PNG), `etam eval map` and `etam eval mosaic`."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from services import events as ev_ops
from services.camera.filters import Undistort
from services.camera.formats import FormatError, Recording, open_recording
from services.camera.simulator import LOG_EPS
from services.mapper.cloud import VoxelMap
from services.mapper.evaluation import coverage, depth_errors, depth_scores, image_scores, project
from services.mapper.keyframes import KeyframeMapper, KeyframeParams
from services.mapper.mosaic import Mosaic, MosaicParams, from_png16
from services.mapper.ply import read_map, write_map
from services.mapper.stereo import StereoMapper, StereoParams, relative_pose
from services.mapper.trajectory import Trajectory, read_tum

EDGE_WINDOW_US = 10_000  # truth edge pixels: those that fired at least twice this near a scored frame's time
EDGE_EVENTS = 2
METHODS = ("sweep", "stereo")  # how depth is mapped: the space sweep of one camera, or stereo of two


def build_map(src: Path, out: Path, poses: Path | None = None, params: KeyframeParams | None = None,
              voxel_m: float = 0.03, progress: bool = True, method: str | None = None,
              stereo: StereoParams | None = None) -> dict[str, Any]:
    """Builds keyframes of a recording's events with the poses of `poses` (a TUM file) or the file's own
    truth poses, by the space sweep of the first camera or (`method` "stereo", the default for a file of
    two cameras) stereo matching of the first two, fuses them into a voxel map and writes it as PLY with
    the keyframes' times and poses."""
    cloud = VoxelMap(voxel_m)
    with open_recording(src) as rec, contextlib.ExitStack() as others:
        rig = [rec, *(others.enter_context(r) for r in rec.rig()[1:])]
        method = map_method(src, rig, method)
        K, trajectory = rec.K_or_default(), _trajectory(rec, src, poses)
        n_events = 0
        if method == "stereo":
            mapper = stereo_mapper(src, rig, params, stereo)
            for left, right in ev_ops.paired(_posed_chunks(rig[0], trajectory, progress),
                                             _posed_chunks(rig[1], trajectory, False)):
                n_events += len(left) + len(right)
                for kf in mapper.add(left, right, trajectory):
                    cloud.add_keyframe(kf)
        else:
            mapper = KeyframeMapper(K, rec.width, rec.height, params)
            for chunk in _posed_chunks(rec, trajectory, progress):
                n_events += len(chunk)
                for kf in mapper.add(chunk, trajectory):
                    cloud.add_keyframe(kf)
        last = mapper.flush(trajectory)
        if last is not None:
            cloud.add_keyframe(last)
    n_points = write_map(out, cloud, f"etam map of {src.name} ({method}): voxel {voxel_m} m")
    return {"input": str(src), "output": str(out), "method": method, "events": n_events,
            "keyframes": len(cloud.views), "points": n_points, "poses": str(poses) if poses else "truth"}


def map_method(src: Path, rig: list[Recording], method: str | None) -> str:
    """`method`, or the default for the file's cameras (stereo for two, else the space sweep); one the file
    cannot be mapped by is refused by name."""
    method = method or ("stereo" if len(rig) > 1 else "sweep")
    if method not in METHODS:
        raise ValueError(f"mapping method {method!r} is not one of {', '.join(METHODS)}")
    if method == "stereo" and len(rig) < 2:
        raise FormatError(src, "stereo mapping needs a file of two cameras (etam sim stereo writes one)")
    return method


def stereo_mapper(src: Path, rig: list[Recording], params: KeyframeParams | None = None,
                  stereo: StereoParams | None = None) -> StereoMapper:
    """The stereo mapper of the rig's first two cameras; a rig without their poses, or one that cannot be
    rectified, is refused by name."""
    in_rig = [r.calibration.T_body_cam if r.calibration is not None else None for r in rig[:2]]
    try:
        return StereoMapper(rig[0].K_or_default(), rig[1].K_or_default(), relative_pose(*in_rig), rig[0].width,
                            rig[0].height, params, stereo)
    except ValueError as exc:
        raise FormatError(src, str(exc)) from None


def build_mosaic(src: Path, out: Path, poses: Path | None = None, params: MosaicParams | None = None,
                 progress: bool = True) -> dict[str, Any]:
    """Folds a rotating camera's events, with the orientations of `poses` (a TUM file) or the file's truth
    poses, into a panorama's gradient map and writes its Poisson reconstruction as a 16-bit PNG."""
    with open_recording(src) as rec:
        trajectory = _trajectory(rec, src, poses)
        mosaic = Mosaic(rec.K_or_default(), rec.width, rec.height, params)
        n_events = 0
        for chunk in _posed_chunks(rec, trajectory, progress):
            n_events += len(chunk)
            mosaic.add(chunk, trajectory)
    observed = write_mosaic(out, mosaic)
    return {"input": str(src), "output": str(out), "events": n_events, "events_used": mosaic.events,
            "pairs": mosaic.pairs, "size": [mosaic.params.width, mosaic.params.height], "observed": observed,
            "poses": str(poses) if poses else "truth"}


def write_mosaic(path: Path, mosaic: Mosaic) -> float:
    """The mosaic as a 16-bit PNG (`Mosaic.image`); the share of the panorama it observed."""
    image = mosaic.image()
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: cannot write a PNG there")
    return float((image > 0).mean())


def eval_mosaic(mosaic: Path, truth: Path) -> dict[str, Any]:
    """PSNR and SSIM of a mosaic PNG against a recording's truth panorama, in log intensity (what events
    measure), over the pixels the mosaic observed, after removing offset and scale; a mosaic of another
    size is resized to the truth's."""
    image = cv2.imread(str(mosaic), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FormatError(mosaic, "not a readable image")
    try:
        estimate, observed = from_png16(image)
    except ValueError as exc:
        raise FormatError(mosaic, str(exc)) from None
    with open_recording(truth) as rec:
        if rec.truth.panorama is None:
            raise FormatError(truth, "no truth panorama (/truth/panorama, as etam sim rotation writes)")
        reference = np.log(np.asarray(rec.truth.panorama, np.float64) + LOG_EPS)
    size = reference.shape[::-1]
    if estimate.shape != reference.shape:
        estimate = cv2.resize(estimate, size, interpolation=cv2.INTER_LINEAR)
        observed = cv2.resize(observed.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    return {"mosaic": str(mosaic), "truth": str(truth), "observed": float(observed.mean()),
            **image_scores(estimate, observed, reference)}


def _trajectory(rec: Recording, src: Path, poses: Path | None) -> Trajectory:
    """The poses of `poses` (TUM), or else the recording's truth poses."""
    if poses is not None:
        return Trajectory(read_tum(str(poses)))
    if rec.truth.poses is not None:
        return Trajectory(rec.truth.poses)
    raise FormatError(src, "no poses to map with: give --poses traj.tum (e.g. from etam odom), "
                      "or a recording with /truth/poses")


def _posed_chunks(rec: Recording, trajectory: Trajectory, progress: bool) -> Iterator[np.ndarray]:
    """The recording's events inside the trajectory's span (poses are not extrapolated), undistorted where
    the file is calibrated with distortion, with a progress bar."""
    undistort = Undistort.of(rec)
    with tqdm(unit="ev", unit_scale=True, desc=rec.path.name, disable=not progress) as bar:
        for chunk in rec.chunks():
            bar.update(len(chunk))
            t = chunk["t"]
            chunk = chunk[(t >= trajectory.start_us) & (t <= trajectory.end_us)]
            yield undistort(chunk) if undistort is not None else chunk


def eval_map(cloud: Path, truth: Path) -> dict[str, Any]:
    """Depth errors of a map's points against a recording's truth depth maps, and the share of the
    truth frames' edge pixels (see `EDGE_WINDOW_US`) that the map covers."""
    points, point_t = read_map(cloud)
    with open_recording(truth) as rec:
        if rec.truth.depth_t is None or rec.truth.poses is None:
            raise FormatError(truth, "no truth depth maps and poses (/truth/depth, /truth/poses) to score a map")
        trajectory, depth_t, K = Trajectory(rec.truth.poses), np.asarray(rec.truth.depth_t), rec.K_or_default()
        maps: dict[int, np.ndarray] = {}

        def depth_map(k: int) -> np.ndarray:
            if k not in maps:
                maps[k] = np.asarray(rec.truth.depth_maps[k], np.float32)
            return maps[k]

        errors, true, frames = depth_errors(points, point_t, trajectory, depth_t, depth_map, K)
        used = np.unique(frames)
        finite = np.concatenate([depth_map(k)[np.isfinite(depth_map(k))] for k in used]) if len(used) else np.zeros(1)
        lo, hi = np.percentile(finite, [1, 99])
        scores = depth_scores(errors, true, float(hi - lo))
        edges = _edge_pixels(rec, depth_t[used])
        covered = [coverage(_on_surface(points, trajectory, int(depth_t[k]), K, depth_map(k)), e)
                   for k, e in zip(used, edges, strict=True)]
    weights = [e.sum() for e in edges]
    scores["completeness"] = float(np.average(covered, weights=weights)) if covered and sum(weights) else float("nan")
    return {"cloud": str(cloud), "truth": str(truth), "points": len(points), "depth_range_m": float(hi - lo),
            "frames_scored": len(used), **scores}


def _on_surface(points: np.ndarray, trajectory: Trajectory, t_us: int, K: np.ndarray, dmap: np.ndarray) -> np.ndarray:
    """Pixels (M x 2) where the points land in the true view at `t_us` within 5 % of the true depth there."""
    R, p = (a[0] for a in trajectory.at(t_us))
    u, v, z, true = project(points, R, p, K, dmap)
    ok = np.abs(z - true) <= 0.05 * true
    return np.stack([u[ok], v[ok]], axis=1)


def _edge_pixels(rec, times_us: np.ndarray) -> list[np.ndarray]:  # noqa: ANN001 - an open Recording
    """Per time: the pixels that fired at least `EDGE_EVENTS` times within `EDGE_WINDOW_US` of it (what
    an event camera sees as edges then), in one pass over the file."""
    counts = [np.zeros((rec.height, rec.width), np.int32) for _ in times_us]
    if not len(times_us):
        return []
    first, last = times_us.min() - EDGE_WINDOW_US, times_us.max() + EDGE_WINDOW_US
    for chunk in rec.chunks():
        if not len(chunk) or chunk["t"][-1] < first:
            continue
        if chunk["t"][0] > last:
            break
        for i, t in enumerate(times_us):
            sel = chunk[np.abs(chunk["t"] - t) <= EDGE_WINDOW_US]
            np.add.at(counts[i], (sel["y"].astype(np.int64), sel["x"].astype(np.int64)), 1)
    return [c >= EDGE_EVENTS for c in counts]
