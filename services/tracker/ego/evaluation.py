"""Odometry accuracy against ground truth, with evo's alignment and metrics (what `etam eval odometry`
reports).

The estimate is resampled at the truth's times (positions linearly, orientations by slerp): evo would
otherwise pair each truth pose with the nearest estimate, up to half an estimate period away, which at
1000 deg/s is degrees of error that no tracker made. Then:
- alignment: `se3` or `sim3` (Umeyama on the positions, evo's `align`), or `origin` (the first poses
  made equal, evo's `align_origin`: what a rotation-only trajectory, whose positions are all zero,
  allows); `auto` takes `se3` where the truth moves more than `MIN_TRAVEL_M`, else `origin`;
- ATE: RMS of the aligned position errors (m, and % of the distance the truth travelled), and of the
  orientation errors (deg), with the orientation error at the last pose;
- RPE over 1 s (evo's RPE between poses a second apart): rotation in deg/s and translation in cm/s;
- angular velocity: the estimate's (from its consecutive orientations) against the truth's, RMS error
  in deg/s and as a share of the truth's peak speed.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from services.mapper.trajectory import Trajectory

ALIGNMENTS = ("auto", "se3", "sim3", "origin")
MIN_TRAVEL_M = 0.01


def body_rates(rows: np.ndarray) -> np.ndarray:
    """Angular velocity (rows t_s, wx, wy, wz in rad/s, camera frame) between consecutive TUM poses,
    at their middle times."""
    rows = np.asarray(rows, np.float64)
    rot = Rotation.from_quat(rows[:, 4:8])
    dt = np.diff(rows[:, 0])
    w = (rot[:-1].inv() * rot[1:]).as_rotvec() / np.maximum(dt, 1e-9)[:, None]
    return np.column_stack([0.5 * (rows[1:, 0] + rows[:-1, 0]), w])


def evaluate_odometry(pred: np.ndarray, truth: np.ndarray, truth_omega: np.ndarray | None = None,
                      align: str = "auto") -> dict:
    """Scores of an estimated trajectory (TUM rows) against the truth (TUM rows, and angular velocity
    rows t_s, wx, wy, wz if known; else from the truth's orientations)."""
    from evo.core import metrics
    from evo.core.geometry import GeometryException
    from evo.core.trajectory import PoseTrajectory3D

    if align not in ALIGNMENTS:
        raise ValueError(f"alignment {align!r} is not one of {', '.join(ALIGNMENTS)}")
    pred, truth = np.asarray(pred, np.float64).reshape(-1, 8), np.asarray(truth, np.float64).reshape(-1, 8)
    if len(pred) < 2:
        raise ValueError(f"the estimate has {len(pred)} poses: at least 2 are needed")
    truth = truth[np.argsort(truth[:, 0], kind="stable")]
    inside = (truth[:, 0] >= pred[:, 0].min()) & (truth[:, 0] <= pred[:, 0].max())
    truth = truth[inside]
    if len(truth) < 2:
        raise ValueError("the estimate and the truth share fewer than 2 pose times")
    rot, pos = Trajectory(pred).at(np.round(truth[:, 0] * 1e6))
    quat = Rotation.from_matrix(rot).as_quat()
    travel = float(np.linalg.norm(np.diff(truth[:, 1:4], axis=0), axis=1).sum())
    if align == "auto":
        align = "se3" if travel > MIN_TRAVEL_M else "origin"

    def evo_trajectory(p: np.ndarray, q_xyzw: np.ndarray) -> PoseTrajectory3D:
        return PoseTrajectory3D(positions_xyz=p, orientations_quat_wxyz=q_xyzw[:, [3, 0, 1, 2]], timestamps=truth[:, 0])

    ref, est = evo_trajectory(truth[:, 1:4], truth[:, 4:8]), evo_trajectory(pos, quat)
    if align == "origin":
        est.align_origin(ref)
    else:
        try:
            est.align(ref, correct_scale=align == "sim3")
        except GeometryException:
            raise ValueError(f"{align} alignment needs positions that span space (the truth travels "
                             f"{travel:.3f} m); align a rotation-only trajectory by its origin") from None
    ate_t = metrics.APE(metrics.PoseRelation.translation_part)
    ate_t.process_data((ref, est))
    ate_r = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    ate_r.process_data((ref, est))
    period_s = float(np.median(np.diff(truth[:, 0])))
    second = max(int(round(1.0 / period_s)), 1)
    scores = {"alignment": align, "poses": len(truth), "duration_s": float(truth[-1, 0] - truth[0, 0]),
              "distance_m": travel, "ate_m": float(ate_t.get_statistic(metrics.StatisticsType.rmse)),
              "ate_rot_deg": float(ate_r.get_statistic(metrics.StatisticsType.rmse)),
              "final_rot_err_deg": float(ate_r.error[-1])}
    scores["ate_percent_of_distance"] = 100 * scores["ate_m"] / travel if travel > MIN_TRAVEL_M else None
    if len(truth) > second:
        rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=second, delta_unit=metrics.Unit.frames)
        rpe_r.process_data((ref, est))
        rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta=second, delta_unit=metrics.Unit.frames)
        rpe_t.process_data((ref, est))
        seconds = second * period_s
        scores["rpe_deg_per_s"] = float(rpe_r.get_statistic(metrics.StatisticsType.rmse)) / seconds
        scores["rpe_cm_per_s"] = 100 * float(rpe_t.get_statistic(metrics.StatisticsType.rmse)) / seconds
    true_w = body_rates(truth) if truth_omega is None else np.asarray(truth_omega, np.float64).reshape(-1, 4)
    est_w = body_rates(pred[np.argsort(pred[:, 0], kind="stable")])
    t = true_w[(true_w[:, 0] >= est_w[0, 0]) & (true_w[:, 0] <= est_w[-1, 0])]
    if len(t):
        at = np.column_stack([np.interp(t[:, 0], est_w[:, 0], est_w[:, k]) for k in (1, 2, 3)])
        rms = float(np.sqrt(np.mean(np.sum((at - t[:, 1:]) ** 2, axis=1))))
        peak = float(np.linalg.norm(t[:, 1:], axis=1).max())
        scores.update(omega_rms_deg_s=float(np.degrees(rms)), omega_peak_deg_s=float(np.degrees(peak)),
                      omega_rms_of_peak=rms / peak if peak > 0 else None)
    return scores
