"""Stereo mapping (ESVO style): time surfaces, rectification, matching along rows, fusion, `etam map` on a rig."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from services.mapper.stereo import Rectifier, StereoParams, TimeSurface, fuse, match
from services.messages import EVENT_DTYPE
from tests.conftest import etam_argv

K = np.array([[300.0, 0, 170], [0, 300.0, 130], [0, 0, 1]])
W, H = 346, 260


def test_time_surface_keeps_each_pixels_latest_event() -> None:
    ts = TimeSurface(4, 3)
    ev = np.zeros(3, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"] = [1_000, 5_000, 3_000], [1, 1, 2], [0, 0, 2]  # pixel (1, 0) twice
    ts.add(ev)
    image = ts.image(5_000, tau_ms=2.0)
    assert image[0, 1] == 1.0 and np.isclose(image[2, 2], np.exp(-1.0)) and image[1, 1] == 0.0
    late = np.zeros(1, EVENT_DTYPE)
    late["t"], late["x"], late["y"] = 2_000, 1, 0  # older than what the pixel has: kept out
    ts.add(late)
    assert ts.image(5_000, tau_ms=2.0)[0, 1] == 1.0


def _texture(seed: int, period_px: int = 0) -> np.ndarray:
    """A smooth random image (or stripes of `period_px` along x), values in 0..1, float32."""
    if period_px:
        return (0.5 + 0.5 * np.sin(2 * np.pi * np.arange(W) / period_px))[None].repeat(H, 0).astype(np.float32)
    noise = np.random.default_rng(seed).random((H // 4, W // 4)).astype(np.float32)
    return cv2.resize(noise, (W, H), interpolation=cv2.INTER_CUBIC).clip(0, 1)


def _shifted(image: np.ndarray, d: float) -> np.ndarray:
    """What a camera d pixels to the right sees: the scene moved left by d."""
    return cv2.warpAffine(image, np.float32([[1, 0, -d], [0, 1, 0]]), (W, H), flags=cv2.INTER_CUBIC)


def test_match_finds_the_disparity_to_a_tenth_of_a_pixel_and_rejects_a_repeated_texture() -> None:
    left = _texture(3)
    mask = np.zeros((H, W), bool)
    mask[40:220:7, 80:330:9] = True
    ys, xs, d = match(left, _shifted(left, 12.4), mask, 3.0, 60.0, StereoParams())
    assert len(d) > 0.8 * mask.sum()
    assert np.median(np.abs(d - 12.4)) < 0.1 and np.mean(np.abs(d - 12.4) < 0.5) > 0.95
    assert mask[ys, xs].all()
    stripes = _texture(0, period_px=10)  # equally good 10 px apart along the row: no answer is better than a wrong one
    _, _, d = match(stripes, _shifted(stripes, 12.4), mask, 3.0, 60.0, StereoParams())
    assert len(d) < 0.05 * mask.sum()


def _blob(center: np.ndarray) -> np.ndarray:
    image = np.zeros((H, W), np.float32)
    cv2.circle(image, tuple(int(round(c * 16)) for c in center), 48, 1.0, -1, cv2.LINE_AA, shift=4)
    return cv2.GaussianBlur(image, (0, 0), 1.5)


def _centroid(image: np.ndarray) -> np.ndarray:
    ys, xs = np.mgrid[0:H, 0:W]
    return np.array([(xs * image).sum(), (ys * image).sum()]) / image.sum()


def test_rectifier_puts_a_point_on_one_row_at_the_disparity_of_its_depth() -> None:
    """A rig whose right camera is turned and offset a little: after rectification a point's two images
    share a row, and their disparity gives back the point in the left camera's frame."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("yx", [2.0, -1.0], degrees=True).as_matrix()
    T[:3, 3] = [0.12, 0.004, -0.003]
    K_right = K + np.array([[4.0, 0, -3], [0, 4.0, 2], [0, 0, 0]])
    rect = Rectifier(K, K_right, T, W, H)
    assert rect.maps is not None and np.isclose(rect.baseline_m, np.linalg.norm(T[:3, 3]))
    for point in ([0.2, -0.1, 2.0], [-0.3, 0.2, 3.5]):
        P = np.array(point)
        seen = [K @ P, K_right @ (T[:3, :3].T @ (P - T[:3, 3]))]
        left, right = (rect.apply(_blob(s[:2] / s[2]), i) for i, s in enumerate(seen))
        (xl, yl), (xr, yr) = _centroid(left), _centroid(right)
        assert abs(yl - yr) < 0.2
        z = rect.K[0, 0] * rect.baseline_m / (xl - xr)
        fx, fy, cx, cy = rect.K[0, 0], rect.K[1, 1], rect.K[0, 2], rect.K[1, 2]
        back = rect.R_left @ np.array([(xl - cx) / fx * z, (yl - cy) / fy * z, z])
        assert np.linalg.norm(back - P) < 0.02 * P[2]
    straight = np.eye(4)
    straight[0, 3] = 0.1
    assert Rectifier(K, K, straight, W, H).maps is None  # already rectified: used as it is


def test_fusion_averages_agreeing_estimates_and_drops_outliers() -> None:
    pixel = np.array([5, 5, 5, 5, 5, 9, 9])
    rho = np.array([0.50, 0.51, 0.49, 0.50, 0.90, 0.25, 0.26])
    inv, count = fuse(pixel, rho, np.full(7, 0.01), gate=2.0, n_pixels=12)
    assert count[5] == 4 and np.isclose(inv[5], 0.5)  # 0.90 is 40 sigmas off the median
    assert count[9] == 2 and np.isclose(inv[9], 0.255) and count.sum() == 6


def test_map_command_maps_a_stereo_rig(tmp_path: Path) -> None:
    """`etam sim stereo` -> `etam map` (stereo, the default for a rig) -> `etam eval map`, as a user runs them."""
    h5, ply = tmp_path / "rig.h5", tmp_path / "cloud.ply"
    subprocess.run(etam_argv("sim", "stereo", "--out", str(h5), "--duration", "2", "--seed", "5", "--json"),
                   check=True, capture_output=True, timeout=300)
    made = subprocess.run(etam_argv("map", str(h5), "--out", str(ply), "--json"), capture_output=True, text=True,
                          timeout=300)
    assert made.returncode == 0, made.stderr
    summary = json.loads(made.stdout)
    assert summary["method"] == "stereo" and summary["keyframes"] >= 1 and summary["points"] > 2000
    scored = subprocess.run(etam_argv("eval", "map", "--cloud", str(ply), "--truth", str(h5), "--json"),
                            capture_output=True, text=True, timeout=120)
    assert scored.returncode == 0, scored.stderr
    scores = json.loads(scored.stdout)
    assert scores["median_error_pct_of_range"] < 3 and scores["within_5pct"] > 0.85 and scores["completeness"] > 0.5

    mono = tmp_path / "mono.h5"
    subprocess.run(etam_argv("sim", "6dof", "--out", str(mono), "--duration", "0.2", "--json"), check=True,
                   capture_output=True, timeout=120)
    bad = subprocess.run(etam_argv("map", str(mono), "--method", "stereo"), capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "two cameras" in bad.stderr and "Traceback" not in bad.stderr
