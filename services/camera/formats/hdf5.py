"""ETAM HDF5 (DESIGN.md section 7), read and written, and DSEC-style HDF5, read.

ETAM: `/events/{t,x,y,p}`, root attributes width/height, optional `/calibration`, `/truth` and `/imu/{t,gyro,accel}`
(int64 us, N x 3 rad/s, N x 3 m/s^2, in the camera's frame: an addition to DESIGN.md's layout).
A rig of several cameras keeps the first at the root (so every reader sees a plain file) and each
further one in a group of the same layout named after it (`/cam1/events/t`, `/cam1/calibration/K`,
...), with `calibration/T_body_cam` (4x4) placing each camera in the rig.
DSEC: `events/{x,y,t,p}` with `t_offset` (us) added to t; sensor size 640x480 unless attributes say.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from services.camera.formats.kernels import interleave
from services.camera.formats.recording import (CHUNK_EVENTS, TRUTH_TABLES, Calibration, EventWriter, FormatError,
                                              Recording, Truth)
from services.messages import EVENT_DTYPE

MAGIC = b"\x89HDF\r\n\x1a\n"
DSEC_SIZE = (640, 480)
ROOT_CAMERA = "cam0"  # the name of the camera stored at the file's root


class H5Recording(Recording):
    """ETAM or DSEC HDF5; the layout is told by the datasets present."""

    format = "hdf5"

    def __init__(self, path: str | Path, camera: str | None = None) -> None:
        super().__init__(path)
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise FormatError(self.path, f"not a readable HDF5 file ({exc})") from None
        self.cameras = [ROOT_CAMERA] + sorted(g for g, item in self._file.items()
                                              if isinstance(item, h5py.Group) and "events" in item)
        if camera not in (None, ROOT_CAMERA) and camera not in self.cameras:
            raise FormatError(self.path, f"no camera {camera!r} (cameras: {', '.join(self.cameras)})")
        f = self._file if camera in (None, ROOT_CAMERA) else self._file[camera]
        if "events" not in f or not all(k in f["events"] for k in "txyp"):
            raise FormatError(self.path, "no events/{t,x,y,p} datasets")
        self._t_offset = int(f["t_offset"][()]) if "t_offset" in f else 0
        self.format = "dsec-hdf5" if "t_offset" in f or "ms_to_idx" in f else "etam-hdf5"
        self.width = int(f.attrs.get("width", DSEC_SIZE[0] if self.format == "dsec-hdf5" else 0))
        self.height = int(f.attrs.get("height", DSEC_SIZE[1] if self.format == "dsec-hdf5" else 0))
        self.n_events = len(f["events/t"])
        lengths = {k: len(f["events"][k]) for k in "txyp"}
        if len(set(lengths.values())) != 1:
            raise FormatError(self.path, f"events columns differ in length: {lengths}")
        if not self.width or not self.height:
            self.width = int(f["events/x"][:].max()) + 1 if self.n_events else 1
            self.height = int(f["events/y"][:].max()) + 1 if self.n_events else 1
        if "calibration/K" in f:
            dist = f["calibration/dist"] if "calibration/dist" in f else None
            self.calibration = Calibration(
                np.asarray(f["calibration/K"][:], np.float64),
                str(dist.attrs.get("model", "radtan")) if dist is not None else "none",
                np.asarray(dist[:], np.float64) if dist is not None else np.zeros(0),
                np.asarray(f["calibration/T_body_cam"][:], np.float64) if "calibration/T_body_cam" in f else None,
            )
        for name in TRUTH_TABLES:
            if f"truth/{name}" in f:
                setattr(self.truth, name, np.asarray(f[f"truth/{name}"][:]))
        if "truth/depth/t" in f and "truth/depth/maps" in f:
            self.truth.depth_t = np.asarray(f["truth/depth/t"][:], np.int64)
            self.truth.depth_maps = f["truth/depth/maps"]  # frames are read when played
        self._events = f["events"]
        self._imu = f["imu"] if all(f"imu/{k}" in f for k in ("t", "gyro", "accel")) else None

    def imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if self._imu is None:
            return None
        t, gyro, accel = (np.asarray(self._imu[k][:]) for k in ("t", "gyro", "accel"))
        if not (len(t) == len(gyro) == len(accel)) or gyro.shape[1:] != (3,) or accel.shape[1:] != (3,):
            raise FormatError(self.path, f"imu/t, imu/gyro and imu/accel must be N, N x 3 and N x 3; got "
                              f"{t.shape}, {gyro.shape} and {accel.shape}")
        return t.astype(np.int64), gyro.astype(np.float64), accel.astype(np.float64)

    def rig(self) -> list[Recording]:
        return [self] + [H5Recording(self.path, name) for name in self.cameras[1:]]

    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        """Columns read into reused buffers, then interleaved into fresh records by one kernel."""
        cols = [self._events[k] for k in "txyp"]
        bufs = [np.empty(min(max_events, self.n_events), c.dtype) for c in cols]
        for start in range(0, self.n_events, max_events):
            n = min(max_events, self.n_events - start)
            for col, buf in zip(cols, bufs, strict=True):
                col.read_direct(buf, np.s_[start:start + n], np.s_[:n])
            out = np.empty(n, EVENT_DTYPE)
            interleave(*(b[:n] for b in bufs), np.int64(self._t_offset), out)
            yield out

    def close(self) -> None:
        self._file.close()


class H5Writer(EventWriter):
    """Appends events (and at the end calibration and truth) to an ETAM HDF5 file; `add_camera`
    gives a writer for a further camera of a rig in the same file."""

    def __init__(self, path: str | Path, width: int, height: int, _group: h5py.Group | None = None) -> None:
        self.path = Path(path)
        self._owner = _group is None
        self._file = h5py.File(self.path, "w") if _group is None else _group
        self._file.attrs["width"], self._file.attrs["height"] = width, height
        grp = self._file.create_group("events")
        self._cols = {
            name: grp.create_dataset(name, (0,), dtype=dtype, maxshape=(None,), chunks=(CHUNK_EVENTS,))
            for name, dtype in (("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1"))
        }
        self.count = 0

    def write(self, events: np.ndarray) -> None:
        n = len(events)
        if not n:
            return
        for name, ds in self._cols.items():
            ds.resize((self.count + n,))
            ds[self.count:] = events[name]
        self.count += n

    def add_camera(self, name: str, width: int, height: int) -> H5Writer:
        """A writer for camera `name` of the same rig, stored in group `/name`."""
        return H5Writer(self.path, width, height, _group=self._file.create_group(name))

    def write_calibration(self, calib: Calibration) -> None:
        self._file["calibration/K"] = np.asarray(calib.K, np.float64)
        self._file["calibration/dist"] = np.asarray(calib.dist, np.float64)
        self._file["calibration/dist"].attrs["model"] = calib.dist_model
        if calib.T_body_cam is not None:
            self._file["calibration/T_body_cam"] = np.asarray(calib.T_body_cam, np.float64)

    def write_imu(self, t_us: np.ndarray, gyro: np.ndarray, accel: np.ndarray) -> None:
        """IMU samples: times (us), gyro (rad/s, N x 3) and accelerometer (m/s^2, N x 3), in this camera's frame."""
        self._file["imu/t"] = np.asarray(t_us, np.int64)
        self._file["imu/gyro"] = np.asarray(gyro, np.float64).reshape(-1, 3)
        self._file["imu/accel"] = np.asarray(accel, np.float64).reshape(-1, 3)

    def write_truth(self, name: str, rows: np.ndarray) -> None:
        self._file[f"truth/{name}"] = rows

    def copy_truth(self, truth: Truth) -> None:
        """Every ground truth `truth` holds, as read from another file."""
        for name in TRUTH_TABLES:
            if getattr(truth, name) is not None:
                self.write_truth(name, getattr(truth, name))
        if truth.depth_t is not None and truth.depth_maps is not None:
            self.write_truth("depth/t", truth.depth_t)
            self.write_truth("depth/maps", np.asarray(truth.depth_maps[:], np.float32))

    def close(self) -> None:
        if self._owner:
            self._file.close()
