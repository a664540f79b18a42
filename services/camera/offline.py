"""Offline camera commands: `etam sim` (simulate to a file) and `etam info` (what a file holds)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from services.camera.formats import open_recording
from services.camera.formats.hdf5 import H5Writer
from services.camera.formats.recording import EventWriter
from services.camera.simulator import SimParams
from services.camera.sources import SimSource, open_sources

STEP_US = 100_000


def simulate(scene: str, out: Path, duration_s: float, seed: int = 0, progress: bool = True,
             params: SimParams | None = None, scene_args: dict[str, float] | None = None) -> dict[str, Any]:
    """Simulate `scene` (its constructor given `scene_args`) for `duration_s` into an ETAM HDF5 file
    with its ground truth (a rig's further cameras in groups `/cam1`, ...)."""
    sources = open_sources(f"sim:{scene}", seed=seed, sim_params=params, scene_args=scene_args)
    end_us = int(duration_s * 1e6)
    totals = {"events": 0, "truth_boxes": 0, "truth_poses": 0, "imu_samples": 0}
    first = sources[0]
    with H5Writer(out, first.width, first.height) as writer, \
            tqdm(total=len(sources) * end_us // 1000, unit="ms", desc=f"sim:{scene}", disable=not progress) as bar:
        for i, source in enumerate(sources):
            assert isinstance(source, SimSource)
            cam_writer = writer if i == 0 else writer.add_camera(f"cam{i}", source.width, source.height)
            counts = _simulate_camera(source, cam_writer, end_us, bar)
            totals = {k: totals[k] + counts[k] for k in totals}
    return {"file": str(out), "scene": scene, "cameras": len(sources), "duration_s": duration_s, "seed": seed,
            **totals}


def _simulate_camera(source: SimSource, writer: H5Writer, end_us: int, bar: tqdm) -> dict[str, int]:
    """One camera's events and ground truth into `writer`; its counts."""
    boxes, boxes_3d, ignore, poses, omega, depth_t, depth_maps = [], [], [], [], [], [], []
    imu: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    writer.write_calibration(source.calibration)
    for since in range(0, end_us, STEP_US):
        until = min(since + STEP_US, end_us)
        writer.write(source.advance(until))
        if (samples := source.imu(since, until)) is not None:
            imu.append(samples)
        for t_us, ids, bxs, solid in source.truth(since, until):
            boxes.extend([t_us, i, *b] for i, b in zip(ids.tolist(), bxs.tolist(), strict=True))
            boxes_3d.extend(solid.tolist())
        for t_us, ids, bxs in source.unscored(since, until):
            ignore.extend([t_us, i, *b] for i, b in zip(ids.tolist(), bxs.tolist(), strict=True))
        for t_us, p, q, w in source.poses(since, until):
            poses.append([t_us / 1e6, *p, *q])
            omega.append([t_us / 1e6, *w])
        for t_us, depth in source.depths(since, until):
            depth_t.append(t_us)
            depth_maps.append(depth)
        bar.update((until - since) // 1000)
    if boxes:
        writer.write_truth("boxes", np.asarray(boxes, np.float64).reshape(-1, 6))
        writer.write_truth("boxes_3d", np.asarray(boxes_3d, np.float64).reshape(-1, 4))
        writer.write_truth("ignore", np.asarray(ignore, np.float64).reshape(-1, 6))
    if poses:
        writer.write_truth("poses", np.asarray(poses, np.float64))
        writer.write_truth("omega", np.asarray(omega, np.float64))
    if depth_maps:
        writer.write_truth("depth/t", np.asarray(depth_t, np.int64))
        writer.write_truth("depth/maps", np.stack(depth_maps).astype(np.float32))
    if imu:
        writer.write_imu(*(np.concatenate(column) for column in zip(*imu, strict=True)))
    if hasattr(source.scene, "panorama"):
        writer.write_truth("panorama", source.scene.panorama)
    return {"events": writer.count, "truth_boxes": len(boxes), "truth_poses": len(poses),
            "imu_samples": sum(len(t) for t, _, _ in imu)}


def describe(path: Path, progress: bool = True) -> dict[str, Any]:
    """Sensor size, events, duration, rate, polarity balance, IMU and ground truth of a file."""
    with open_recording(path) as rec:
        n = on = 0
        t0 = t1 = None
        with tqdm(unit="ev", unit_scale=True, desc=path.name, disable=not progress) as bar:
            for chunk in rec.chunks():
                if not len(chunk):
                    continue
                t0 = int(chunk["t"][0]) if t0 is None else t0
                t1 = int(chunk["t"][-1])
                n += len(chunk)
                on += int(chunk["p"].sum())
                bar.update(len(chunk))
        imu = rec.imu()
        duration = (t1 - t0) / 1e6 if n else 0.0
        return {
            "file": str(path), "format": rec.format, "cameras": rec.cameras, "width": rec.width, "height": rec.height,
            "events": n, "t_first_us": t0, "t_last_us": t1, "duration_s": duration,
            "event_rate": n / duration if duration > 0 else None,
            "on_fraction": on / n if n else None,
            "imu_samples": 0 if imu is None else len(imu[0]),
            "calibrated": rec.calibration is not None,
            "ground_truth": rec.truth.present(),
        }


def convert(src: Path, dst: Path, progress: bool = True) -> dict[str, Any]:
    """Copy a recording into ETAM HDF5 (.h5), AEDAT 4.0 (.aedat4) or ECD text (.txt or a folder).

    Calibration, ground truth and IMU samples go along where the output format has a place for them; of a rig of
    several cameras, the first is copied."""
    from services.camera.formats.aedat4 import Aedat4Writer
    from services.camera.formats.ecd import EcdWriter

    suffix = dst.suffix.lower()
    with open_recording(src) as rec:
        if suffix in (".h5", ".hdf5"):
            writer: EventWriter = H5Writer(dst, rec.width, rec.height)
            if rec.calibration is not None:
                writer.write_calibration(rec.calibration)
            writer.copy_truth(rec.truth)
            if (imu := rec.imu()) is not None:
                writer.write_imu(*imu)
        elif suffix == ".aedat4":
            writer = Aedat4Writer(dst, rec.width, rec.height, source=rec.path.name)
        elif suffix in (".txt", ""):
            writer = EcdWriter(dst, rec.width, rec.height, rec.calibration)
        else:
            raise ValueError(f"{dst}: unknown output format {suffix!r} (write .h5, .aedat4, .txt or a folder)")
        with writer, tqdm(unit="ev", unit_scale=True, desc=src.name, disable=not progress) as bar:
            for chunk in rec.chunks():
                writer.write(chunk)
                bar.update(len(chunk))
            count = writer.count
        return {"input": str(src), "input_format": rec.format, "output": str(dst), "events": count}
