"""Map accuracy against ground-truth depth (`etam eval map`) and mosaic quality against the truth
panorama (`etam eval mosaic`), numpy in, numbers out.

Each map point is scored in the truth depth frame nearest the time of the keyframe that last saw it:
moved into that frame's true camera, projected, and its depth compared with the true depth at that
pixel. The error is thus the point's distance to the true surface along the viewing ray, whatever
poses the map was built from.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.mapper.trajectory import Trajectory


def depth_errors(points: np.ndarray, point_times_us: np.ndarray, truth: Trajectory, depth_t: np.ndarray,
                 depth_map, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # noqa: ANN001 - maps read on demand
    """Per scored point: its depth error (m, signed), true depth, and the index of the depth frame it
    was scored in; points that land outside the image or on no true surface are left out.
    `depth_map(k)` gives frame k's map."""
    frame = np.abs(depth_t[None, :] - np.asarray(point_times_us)[:, None]).argmin(axis=1) if len(points) else \
        np.zeros(0, np.int64)
    errors, depths, frames = [], [], []
    for k in np.unique(frame):
        R, p = (a[0] for a in truth.at(depth_t[k]))
        _, _, z, true = project(points[frame == k], R, p, K, depth_map(k))
        ok = np.isfinite(true)
        errors.append(z[ok] - true[ok])
        depths.append(true[ok])
        frames.append(np.full(int(ok.sum()), k))
    if not errors:
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    return np.concatenate(errors), np.concatenate(depths), np.concatenate(frames)


def project(points: np.ndarray, R: np.ndarray, p: np.ndarray, K: np.ndarray,
            dmap: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points (N x 3, world) seen from camera pose (R, p): pixel (rounded) u, v, depth z, and the true
    depth there: of the pixel it lands on and its 8 neighbours, the one nearest z (a point on an occluding
    edge lands within a rounding of either side of it); NaN off the image, behind the camera, or where the
    map knows none."""
    cam = (np.asarray(points, np.float64) - p) @ R
    z = cam[:, 2]
    front = z > 1e-6
    safe = np.where(front, z, 1.0)
    h, w = dmap.shape
    u = np.round(K[0, 0] * cam[:, 0] / safe + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * cam[:, 1] / safe + K[1, 2]).astype(np.int64)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    padded = np.pad(dmap.astype(np.float64), 1, constant_values=np.nan)
    near = np.stack([padded[v[inside] + 1 + dy, u[inside] + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1)
    gap = np.abs(near - z[inside, None])
    pick = np.nanargmin(np.where(np.isnan(gap), np.inf, gap), axis=1)
    true = np.full(len(z), np.nan)
    true[inside] = near[np.arange(len(near)), pick]
    return u, v, z, true


def depth_scores(errors: np.ndarray, true_depth: np.ndarray, depth_range_m: float) -> dict[str, float]:
    """Mean and median absolute error (m), median relative to the scene's depth range (%), mean relative to
    each point's true depth (%, ESVO's figure), and the share of points within 5 % of their true depth."""
    if not len(errors):
        return {"points_scored": 0, "mean_abs_error_m": float("nan"), "median_abs_error_m": float("nan"),
                "median_error_pct_of_range": float("nan"), "mean_relative_error_pct": float("nan"), "within_5pct": 0.0}
    err = np.abs(errors)
    return {"points_scored": int(len(err)), "mean_abs_error_m": float(err.mean()),
            "median_abs_error_m": float(np.median(err)),
            "median_error_pct_of_range": float(100 * np.median(err) / depth_range_m),
            "mean_relative_error_pct": float(100 * np.mean(err / true_depth)),
            "within_5pct": float(np.mean(err <= 0.05 * true_depth))}


def coverage(points_px: np.ndarray, edges: np.ndarray) -> float:
    """Share of edge pixels (boolean H x W) with a map point (N x 2 pixel coordinates) within one pixel."""
    if not edges.any():
        return float("nan")
    h, w = edges.shape
    hit = np.zeros((h + 2, w + 2), bool)
    u = np.round(points_px[:, 0]).astype(np.int64) + 1
    v = np.round(points_px[:, 1]).astype(np.int64) + 1
    ok = (u >= 0) & (u < w + 2) & (v >= 0) & (v < h + 2)
    hit[v[ok], u[ok]] = True
    near = np.zeros((h, w), bool)
    for dy in range(3):
        for dx in range(3):
            near |= hit[dy:dy + h, dx:dx + w]
    return float((near & edges).sum() / edges.sum())


def image_scores(estimate: np.ndarray, observed: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """PSNR (dB) and SSIM of `estimate` against `truth` over the `observed` pixels, after the offset and
    scale that fit it to the truth best (a mosaic from events knows neither); the peak is the truth's
    range there (1st to 99th percentile, so a few extreme pixels do not flatter it). SSIM: Gaussian
    window of 1.5 px (Wang et al. 2004), averaged over observed pixels whose window is all observed."""
    est, ref = estimate[observed].astype(np.float64), truth[observed].astype(np.float64)
    if len(est) < 2:
        raise ValueError("the mosaic observed fewer than 2 pixels: nothing to score")
    scale, offset = np.linalg.lstsq(np.stack([est, np.ones_like(est)], 1), ref, rcond=None)[0]
    if scale < 0:  # an inverted mosaic is wrong, not a fit: score it as a flat one
        scale, offset = 0.0, float(ref.mean())
    fitted = np.where(observed, estimate * scale + offset, truth).astype(np.float64)
    lo, hi = np.percentile(ref, [1, 99])
    peak = max(float(hi - lo), 1e-12)
    rmse = float(np.sqrt(np.mean((fitted[observed] - ref) ** 2)))
    ref_img = truth.astype(np.float64)

    def blur(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (11, 11), 1.5, borderType=cv2.BORDER_REFLECT)

    mu_x, mu_y = blur(fitted), blur(ref_img)
    var_x, var_y = blur(fitted * fitted) - mu_x ** 2, blur(ref_img * ref_img) - mu_y ** 2
    cov = blur(fitted * ref_img) - mu_x * mu_y
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    ssim = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    inner = cv2.erode(observed.astype(np.uint8), np.ones((11, 11), np.uint8), borderType=cv2.BORDER_REFLECT) > 0
    return {"psnr_db": float(20 * np.log10(peak / max(rmse, 1e-12))), "ssim": float(ssim[inner].mean())
            if inner.any() else float("nan"), "rmse": rmse, "peak": peak}
