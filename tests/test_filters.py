"""Event filters: each keeps what it should and drops what it should, across packets."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.filters import labelled_events
from services.camera.filters import (
    BackgroundActivity, HotPixels, Mask, Polarity, Refractory, Undistort, parse_chain,
)
from services.messages import EVENT_DTYPE


def _ev(rows: list[tuple[int, int, int, int]]) -> np.ndarray:
    ev = np.zeros(len(rows), EVENT_DTYPE)
    for i, (t, x, y, p) in enumerate(rows):
        ev[i] = (t, x, y, p)
    return ev


def test_background_activity_keeps_supported_events_across_packets() -> None:
    ba = BackgroundActivity(10, 10, window_us=1000)
    assert len(ba(_ev([(100, 5, 5, 1)]))) == 0  # alone: noise
    kept = ba(_ev([(600, 6, 5, 1), (700, 9, 9, 0)]))  # a neighbour 500 us ago; a lone corner event
    assert kept["t"].tolist() == [600]
    assert len(ba(_ev([(5000, 5, 5, 1)]))) == 0  # its neighbour fired too long ago
    assert len(ba(_ev([(5000, 5, 5, 1), (5001, 5, 5, 1)]))) == 0  # its own pixel is no support
    assert len(ba(_ev([(9000, 12, 3, 1)]))) == 0  # outside the sensor: dropped, no crash


def test_background_activity_removes_most_noise_and_keeps_signal_on_simulated_events() -> None:
    events, is_signal = labelled_events(1_000_000, noise_hz=0.5)
    ba = BackgroundActivity(346, 260, 2000)
    kept = np.concatenate([ba(events[i:i + 3000]) for i in range(0, len(events), 3000)])
    keys = lambda e: (e["t"].astype(np.int64) << 20) | (e["y"].astype(np.int64) << 10) | e["x"]  # noqa: E731
    found = np.isin(keys(events), keys(kept))
    assert found[~is_signal].mean() < 0.05 and found[is_signal].mean() > 0.4


def test_refractory_polarity_roi_and_mask() -> None:
    ev = _ev([(0, 1, 1, 1), (100, 1, 1, 0), (600, 1, 1, 1), (650, 2, 2, 0)])
    assert Refractory(4, 4, 500)(ev)["t"].tolist() == [0, 600, 650]
    assert Polarity(0)(ev)["t"].tolist() == [100, 650]
    assert Mask.roi(4, 4, 2, 2, 2, 2)(ev)["t"].tolist() == [650]
    with pytest.raises(ValueError, match="cannot be read"):
        Mask.from_image("/nonexistent.png", 4, 4)


def test_hot_pixels_are_learnt_then_masked() -> None:
    rng = np.random.default_rng(0)
    n = 20_000
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, 2_000_000, n))
    ev["x"], ev["y"] = rng.integers(0, 64, n), rng.integers(0, 48, n)
    ev["x"][::4], ev["y"][::4] = 7, 9  # one pixel fires a quarter of all events
    hot = HotPixels(64, 48, learn_us=1_000_000)
    first = hot(ev[ev["t"] < 1_000_100])
    later = hot(ev[ev["t"] >= 1_000_100])
    assert hot.hot is not None and hot.hot.sum() == 1 and hot.hot[9 * 64 + 7]
    assert ((first["x"] == 7) & (first["y"] == 9)).any()  # learning passes everything
    assert not ((later["x"] == 7) & (later["y"] == 9)).any() and len(later) > 0.7 * (ev["t"] >= 1_000_100).sum()


def test_undistort_moves_events_to_their_undistorted_pixels() -> None:
    K = np.array([[100.0, 0, 64], [0, 100, 48], [0, 0, 1]])
    und = Undistort(128, 96, K, "radtan", np.array([-0.3, 0.1, 0, 0, 0]))
    ev = _ev([(0, 64, 48, 1), (1, 120, 90, 1)])
    out = und(ev)
    assert (out["x"][0], out["y"][0]) == (64, 48)  # the centre stays
    assert len(out) == 1 or (out["x"][1], out["y"][1]) != (120, 90)  # a corner moves (or leaves)


def test_parse_chain_builds_filters_and_names_bad_items() -> None:
    chain = parse_chain(["ba:1000", "refractory", "roi:0,0,10,10", "polarity:on", "hotpixels"], 64, 48)
    assert [type(f).__name__ for f in chain.filters] == ["BackgroundActivity", "Refractory", "Mask", "Polarity",
                                                         "HotPixels"]
    for bad, message in (("fog", "unknown filter"), ("roi:1,2", "roi:1,2"), ("polarity:up", "polarity:up"),
                         ("undistort", "no distortion calibration")):
        with pytest.raises(ValueError, match=message):
            parse_chain([bad], 64, 48)
