"""What every file reader gives: sensor size, calibration, events in bounded chunks, ground truth."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from services import events
from services.messages import EVENT_DTYPE

CHUNK_EVENTS = 1 << 18  # events per chunk a reader yields: bounded memory whatever the file size


class FormatError(ValueError):
    """A file that cannot be read (further); names the file and, where known, the byte offset."""

    def __init__(self, path: str | Path, message: str, offset: int | None = None) -> None:
        where = f"{path}" + (f" at byte {offset}" if offset is not None else "")
        super().__init__(f"{where}: {message}")
        self.path, self.offset = Path(path), offset


@dataclass
class Calibration:
    """Pinhole intrinsics and distortion (`radtan`: k1 k2 p1 p2 k3; `equidistant`; `none`), and for
    rigs of several cameras this camera's pose in the rig's body frame (4x4)."""

    K: np.ndarray
    dist_model: str = "none"
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    T_body_cam: np.ndarray | None = None


TRUTH_TABLES = ("poses", "boxes", "boxes_3d", "ignore", "omega", "panorama")  # the tables of `Truth`, as named in files


@dataclass
class Truth:
    """Ground truth a file may carry (DESIGN.md section 7 layouts), each None when absent."""

    poses: np.ndarray | None = None  # N x 8 TUM rows (t_s, tx ty tz, qx qy qz qw), T_world_cam
    boxes: np.ndarray | None = None  # M x 6 (t_us, id, x, y, w, h)
    boxes_3d: np.ndarray | None = None  # M x 4 beside `boxes`: object centre x y z (m, camera frame), width (m)
    ignore: np.ndarray | None = None  # K x 6 like `boxes`: objects in the image left unscored ("don't care")
    omega: np.ndarray | None = None  # N x 4 (t_s, wx wy wz rad/s)
    panorama: np.ndarray | None = None  # H x W intensity of the scene around a rotating camera (equirectangular)
    depth_t: np.ndarray | None = None  # N frame times (us) of ...
    depth_maps: Sequence[np.ndarray] | None = None  # ... N x H x W metric depth (float32, NaN unknown), read on demand

    def present(self) -> list[str]:
        names = [name for name in TRUTH_TABLES if getattr(self, name) is not None]
        return names + (["depth"] if self.depth_t is not None else [])


class Recording(ABC):
    """An opened event file. `chunks` streams EVENT_DTYPE arrays sorted by time (us)."""

    format: ClassVar[str]

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.width = 0
        self.height = 0
        self.calibration: Calibration | None = None
        self.truth = Truth()
        self.cameras = ["cam0"]  # names of the cameras in the file (several for a stereo rig)

    @abstractmethod
    def chunks(self, max_events: int = CHUNK_EVENTS) -> Iterator[np.ndarray]:
        """Events in chunks of at most `max_events`; FormatError at the first bad byte, after
        every good event before it has been yielded."""

    def imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """IMU samples (t_us, gyro rad/s Nx3, accel m/s^2 Nx3) if the file has any."""
        return None

    def close(self) -> None:  # noqa: B027 - readers that hold no open handle need nothing here
        """Release the file."""

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def rig(self) -> list[Recording]:
        """Every camera the file holds, this one first (files of one camera: just this one)."""
        return [self]

    def read_all(self) -> np.ndarray:
        """Every event at once (for small files and tests)."""
        return events.concat(list(self.chunks()))

    def K_or_default(self) -> np.ndarray:
        """The calibrated K, or a guess (90 degrees horizontal field of view) when uncalibrated."""
        if self.calibration is not None:
            return self.calibration.K
        f = self.width / 2
        return np.array([[f, 0, self.width / 2], [0, f, self.height / 2], [0, 0, 1]], np.float64)


class EventWriter(ABC):
    """A file being written: `write` event arrays, then `close` (or use it as a context manager)."""

    count = 0

    @abstractmethod
    def write(self, events: np.ndarray) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> EventWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def events_from_columns(t_us: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> np.ndarray:
    """One EVENT_DTYPE array from four columns."""
    ev = np.empty(len(t_us), EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t_us, x, y, p
    return ev
