"""Mosaic: Poisson reconstruction, the 16-bit mosaic file, and `etam mosaic` / `etam eval mosaic` end to end."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

from services.mapper import mosaic_fit
from services.mapper.evaluation import image_scores
from services.mapper.mosaic import Mosaic, MosaicParams, from_png16, to_png16
from services.mapper.poisson import poisson
from tests.conftest import etam_argv


def _smooth(h: int = 64, w: int = 128, seed: int = 0) -> np.ndarray:
    """A smooth image that wraps around in x, as a panorama does."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w]
    img = np.zeros((h, w))
    for _ in range(6):
        k, a, ph = rng.integers(1, 4), rng.uniform(0.2, 1), rng.uniform(0, 2 * np.pi)
        img += a * np.cos(2 * np.pi * k * xs / w + ph) * np.cos(np.pi * rng.integers(0, 3) * (ys + 0.5) / h)
    return img


def test_poisson_rebuilds_an_image_from_its_gradients() -> None:
    img = _smooth()
    gx = 0.5 * (np.roll(img, -1, 1) - np.roll(img, 1, 1))
    gy = np.gradient(img, axis=0)
    out = poisson(gx, gy)
    err = (out - out.mean()) - (img - img.mean())
    assert np.abs(err).max() < 0.02 * np.ptp(img)
    assert abs(float(np.corrcoef(out.ravel(), img.ravel())[0, 1])) > 0.999


def test_fit_rebuilds_an_image_from_brightness_steps_between_far_apart_points() -> None:
    """Pairs of points up to 40 px apart, mostly along the rows (a panning camera's), with the exact step of
    the image between them: the fit recovers the image (rows too, which gradients along x alone cannot
    tie together), starting from nothing and with no gradient prior to lean on."""
    img = _smooth(seed=2)
    h, w = img.shape
    rng = np.random.default_rng(3)
    n = 60_000
    a = np.stack([rng.uniform(0, w, n), rng.uniform(0, h - 1, n)], 1)
    step = np.stack([rng.uniform(-40, 40, n), rng.uniform(-5, 5, n)], 1)
    b = a + step
    b[:, 1] = np.clip(b[:, 1], 0, h - 1)

    def sample(uv: np.ndarray) -> np.ndarray:  # bilinear, wrapping in x
        u0, v0 = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
        u1, v1 = (u0 + 1) % w, np.minimum(v0 + 1, h - 1)
        u0 %= w
        return ((1 - fu) * (1 - fv) * img[v0, u0] + fu * (1 - fv) * img[v0, u1] + (1 - fu) * fv * img[v1, u0]
                + fu * fv * img[v1, u1])

    pairs = np.concatenate([a, b], 1).astype(np.float32)
    steps = sample(b) - sample(a)
    zero, seen = np.zeros((h, w)), np.ones((h, w), bool)
    out = mosaic_fit.fit(pairs, steps, zero, zero, seen, zero, prior_weight=1e-3, iterations=60)
    err = (out - out.mean()) - (img - img.mean())
    assert np.abs(err).max() < 0.05 * np.ptp(img), np.abs(err).max()
    flipped = mosaic_fit.fit(pairs, -steps, zero, zero, seen, zero, prior_weight=1e-3, iterations=60)
    assert float(np.corrcoef(flipped.ravel(), img.ravel())[0, 1]) < -0.99  # the steps' sign is the image's


def test_mosaic_keeps_a_bounded_sample_of_event_pairs() -> None:
    """A pixel's consecutive events become pairs; when the buffer fills, every other pair goes, and the
    sample stays spread over the whole time (not just the first events)."""
    from services.mapper.trajectory import Trajectory

    K = np.array([[100.0, 0, 16], [0, 100.0, 12], [0, 0, 1]])
    mosaic = Mosaic(K, 32, 24, MosaicParams(width=256, height=128, max_pairs=1000))
    t = np.arange(0, 1_000_000, 200, dtype=np.int64)  # 5000 events, all on pixel (5, 5)
    events = np.zeros(len(t), [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    events["t"], events["x"], events["y"], events["p"] = t, 5, 5, 1
    yaw = np.linspace(0, 0.5, 101)  # a slow pan (0.5 rad/s) about the vertical axis
    quat = np.stack([np.zeros_like(yaw), np.sin(yaw / 2), np.zeros_like(yaw), np.cos(yaw / 2)], 1)
    rows = np.concatenate([np.linspace(0, 1, 101)[:, None], np.zeros((101, 3)), quat], 1)
    mosaic.add(events, Trajectory(rows))
    assert 500 <= mosaic.pairs <= 1000
    held = mosaic._pairs[:mosaic.pairs]
    du = held[:, 2] - held[:, 0]
    assert np.allclose(du, 0.5 * 200e-6 * 256 / (2 * np.pi), rtol=0.05)  # the ray's slide between events
    assert held[-1, 0] - held[0, 0] > 0.9 * 0.5 * 256 / (2 * np.pi)  # the sample spans the pan


def test_mosaic_png_round_trip_and_scores() -> None:
    img = _smooth().astype(np.float32)
    seen = np.zeros(img.shape, bool)
    seen[10:50, 20:100] = True
    back, mask = from_png16(to_png16(img, seen))
    assert np.array_equal(mask, seen)
    scores = image_scores(back, mask, img)
    assert scores["psnr_db"] > 60 and scores["ssim"] > 0.999  # 16 bits over the range: exact but for rounding
    inverted = image_scores(-back, mask, img)  # a mosaic with the gradients' sign wrong is not a fit
    assert inverted["psnr_db"] < 15 and inverted["ssim"] < 0.5
    noisy = image_scores(back + np.random.default_rng(1).normal(0, 2000, back.shape).astype(np.float32), mask, img)
    assert 10 < noisy["psnr_db"] < scores["psnr_db"] and noisy["ssim"] < scores["ssim"]


def test_mosaic_and_eval_mosaic_commands(tmp_path: Path) -> None:
    """`etam sim rotation` -> `etam mosaic` -> `etam eval mosaic`, as a user runs them; and their errors."""
    h5, png = tmp_path / "spin.h5", tmp_path / "mosaic.png"
    subprocess.run(etam_argv("sim", "rotation", "--out", str(h5), "--duration", "0.6", "--seed", "3", "--json"),
                   check=True, capture_output=True, timeout=180)
    made = subprocess.run(etam_argv("mosaic", str(h5), "--out", str(png), "--json"), capture_output=True, text=True,
                          timeout=180)
    assert made.returncode == 0, made.stderr
    summary = json.loads(made.stdout)
    assert summary["events_used"] > 0.5 * summary["events"] and 0.02 < summary["observed"] < 0.5
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint16 and image.shape == (1024, 2048)
    scored = subprocess.run(etam_argv("eval", "mosaic", "--mosaic", str(png), "--truth", str(h5), "--json"),
                            capture_output=True, text=True, timeout=120)
    assert scored.returncode == 0, scored.stderr
    scores = json.loads(scored.stdout)
    assert scores["psnr_db"] > 20 and scores["ssim"] > 0.95, scores
    assert 0 < summary["pairs"] <= MosaicParams().max_pairs

    unfitted = tmp_path / "unfitted.png"  # the gradient filter's Poisson reconstruction alone: ~7 dB worse here
    subprocess.run(etam_argv("mosaic", str(h5), "--out", str(unfitted), "--fit-iterations", "0", "--json"),
                   check=True, capture_output=True, timeout=180)
    argv = etam_argv("eval", "mosaic", "--mosaic", str(unfitted), "--truth", str(h5), "--json")
    plain = json.loads(subprocess.run(argv, capture_output=True, text=True, timeout=120, check=True).stdout)
    assert 13 < plain["psnr_db"] < scores["psnr_db"] - 3, (plain, scores)

    small = tmp_path / "small.png"  # another size is scored at the truth's
    subprocess.run(etam_argv("mosaic", str(h5), "--out", str(small), "--size", "1024x512", "--json"), check=True,
                   capture_output=True, timeout=180)
    half = json.loads(subprocess.run(etam_argv("eval", "mosaic", "--mosaic", str(small), "--truth", str(h5), "--json"),
                                     capture_output=True, text=True, timeout=120, check=True).stdout)
    assert half["psnr_db"] > 13 and 0.02 < half["observed"] < 0.5

    objects, eight_bit = tmp_path / "objects.h5", tmp_path / "grey.png"
    subprocess.run(etam_argv("sim", "objects", "--out", str(objects), "--duration", "0.2", "--json"), check=True,
                   capture_output=True, timeout=120)
    cv2.imwrite(str(eight_bit), np.zeros((8, 16), np.uint8))
    for argv, says in ((("mosaic", str(objects)), "no poses to map with"),
                       (("mosaic", str(tmp_path / "none.h5")), "no such file"),
                       (("eval", "mosaic", "--mosaic", str(png), "--truth", str(tmp_path / "none.h5")), "no such file"),
                       (("mosaic", str(h5), "--size", "big"), "--size"),
                       (("mosaic", str(h5), "--fit-iterations", "-1"), "--fit-iterations"),
                       (("mosaic", str(h5), "--out", str(tmp_path / "no" / "m.png")), "does not exist"),
                       (("eval", "mosaic", "--mosaic", str(h5), "--truth", str(h5)), "not a readable image"),
                       (("eval", "mosaic", "--mosaic", str(eight_bit), "--truth", str(h5)), "16-bit"),
                       (("eval", "mosaic", "--mosaic", str(png), "--truth", str(objects)), "no truth panorama")):
        bad = subprocess.run(etam_argv(*argv), capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and says in bad.stderr and "Traceback" not in bad.stderr, (argv, bad.stderr)
