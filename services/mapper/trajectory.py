"""Camera poses at any time from timestamped samples (TUM rows), as rotations and positions."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


class Trajectory:
    """T_world_cam at any time inside the samples: positions interpolated linearly, orientations by
    slerp; times outside are clamped to the first or last sample (a pose is never extrapolated)."""

    def __init__(self, rows: np.ndarray) -> None:
        rows = np.asarray(rows, np.float64).reshape(-1, 8)
        if len(rows) < 2:
            raise ValueError(f"a trajectory needs at least 2 poses, got {len(rows)}")
        rows = rows[np.argsort(rows[:, 0], kind="stable")]
        keep = np.concatenate([[True], np.diff(rows[:, 0]) > 0])
        rows = rows[keep]
        self.t_us = np.round(rows[:, 0] * 1e6).astype(np.int64)
        self._positions = rows[:, 1:4]
        self._slerp = Slerp(self.t_us.astype(np.float64), Rotation.from_quat(rows[:, 4:8]))

    @property
    def start_us(self) -> int:
        return int(self.t_us[0])

    @property
    def end_us(self) -> int:
        return int(self.t_us[-1])

    def at(self, t_us: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (N x 3 x 3, camera to world) and positions (N x 3, m) at times `t_us`."""
        t = np.clip(np.atleast_1d(np.asarray(t_us, np.float64)), self.t_us[0], self.t_us[-1])
        p = np.stack([np.interp(t, self.t_us, self._positions[:, k]) for k in range(3)], axis=1)
        return self._slerp(t).as_matrix().reshape(-1, 3, 3), p


def read_tum(path: str) -> np.ndarray:
    """The rows (t_s tx ty tz qx qy qz qw) of a TUM trajectory file; '#' lines are comments."""
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a TUM trajectory (t tx ty tz qx qy qz qw per line): {exc}") from None
    if rows.shape[1] != 8:
        raise ValueError(f"{path}: a TUM trajectory has 8 columns per line (t tx ty tz qx qy qz qw), "
                         f"found {rows.shape[1]}")
    return rows


def write_tum(path: str, rows: np.ndarray) -> None:
    """TUM rows (t_s tx ty tz qx qy qz qw) as a trajectory file, with a header comment."""
    np.savetxt(path, np.asarray(rows, np.float64).reshape(-1, 8), fmt="%.6f", header="t tx ty tz qx qy qz qw")
