"""Background-activity filtering, ETAM against dv-processing, on the same simulated events.

Signal comes from the simulator without noise; uniform background activity is added with known
labels, so each filter's selectivity is measured (signal kept, noise kept) beside its speed. Both
filters get the same 10 ms packets; dv-processing's EventStores are built before timing starts.
"""

from __future__ import annotations

import time

import numpy as np

from services.camera.filters import BackgroundActivity
from services.camera.simulator import EventSimulator, ObjectsScene, SimParams
from services.messages import EVENT_DTYPE

WIDTH, HEIGHT = 346, 260
PACKET_US = 10_000
WINDOW_US = 2000


def labelled_events(duration_us: int, noise_hz: float = 0.5, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Sorted events of sim:objects plus uniform noise, and a boolean array: True for signal."""
    signal = EventSimulator(ObjectsScene(WIDTH, HEIGHT, seed=seed), SimParams(noise_rate_hz=0.0), seed).advance(
        duration_us)
    rng = np.random.default_rng(seed)
    n = rng.poisson(noise_hz * WIDTH * HEIGHT * duration_us / 1e6)
    noise = np.empty(n, EVENT_DTYPE)
    noise["t"], noise["x"] = rng.integers(1, duration_us, n), rng.integers(0, WIDTH, n)
    noise["y"], noise["p"] = rng.integers(0, HEIGHT, n), rng.integers(0, 2, n)
    events = np.concatenate([signal, noise])
    order = np.argsort(events["t"], kind="stable")
    return events[order], (np.arange(len(events)) < len(signal))[order]


def _keys(ev: np.ndarray) -> np.ndarray:
    return (ev["t"].astype(np.int64) << 20) | (ev["y"].astype(np.int64) << 10) | ev["x"].astype(np.int64)


def _selectivity(kept: np.ndarray, events: np.ndarray, is_signal: np.ndarray) -> tuple[float, float]:
    found = np.isin(_keys(events), _keys(kept))
    return float(found[is_signal].mean()), float(found[~is_signal].mean())


def _packets(events: np.ndarray) -> list[np.ndarray]:
    cuts = np.searchsorted(events["t"], np.arange(PACKET_US, int(events["t"][-1]) + PACKET_US, PACKET_US))
    return np.split(events, cuts)


def _ours(packets: list[np.ndarray]) -> tuple[float, np.ndarray]:
    ba = BackgroundActivity(WIDTH, HEIGHT, WINDOW_US)
    ba(packets[0][:10])  # compiled before timing
    ba = BackgroundActivity(WIDTH, HEIGHT, WINDOW_US)
    t0 = time.perf_counter()
    kept = [ba(p) for p in packets]
    return time.perf_counter() - t0, np.concatenate(kept)


def dv_stores(packets: list[np.ndarray]) -> list:
    """dv-processing EventStores of the packets, built event by event (its only way in from numpy),
    from plain Python lists, the fastest way to feed it."""
    import dv_processing as dv

    stores = []
    for p in packets:
        store = dv.EventStore()
        push = store.push_back
        for t, x, y, on in zip(p["t"].tolist(), p["x"].tolist(), p["y"].tolist(), (p["p"] != 0).tolist(),
                               strict=True):
            push(t, x, y, on)
        stores.append(store)
    return stores


def _dv(packets: list[np.ndarray]) -> tuple[float, np.ndarray]:
    import datetime

    import dv_processing as dv

    stores = dv_stores(packets)
    filt = dv.noise.BackgroundActivityNoiseFilter((WIDTH, HEIGHT), datetime.timedelta(microseconds=WINDOW_US))
    out = []
    t0 = time.perf_counter()
    for store in stores:
        filt.accept(store)
        out.append(filt.generateEvents())
    elapsed = time.perf_counter() - t0
    kept = [o.numpy() for o in out if o.size()]
    arr = np.concatenate(kept) if kept else np.empty(0)
    ev = np.empty(len(arr), EVENT_DTYPE)
    if len(arr):
        ev["t"], ev["x"], ev["y"], ev["p"] = arr["timestamp"], arr["x"], arr["y"], arr["polarity"]
    return elapsed, ev


def run(quick: bool = False) -> list[dict]:
    events, is_signal = labelled_events(2_000_000 if quick else 6_000_000)
    packets = _packets(events)
    row = {"stage": "filter background activity", "events": len(events), "noise_fraction": float(1 - is_signal.mean())}
    elapsed, kept = _ours(packets)
    sig, noise = _selectivity(kept, events, is_signal)
    row.update(etam_events_per_s=len(events) / elapsed, etam_signal_kept=sig, etam_noise_kept=noise)
    try:
        elapsed, kept = _dv(packets)
        sig, noise = _selectivity(kept, events, is_signal)
        row.update(peer="dv-processing", peer_events_per_s=len(events) / elapsed, peer_signal_kept=sig,
                   peer_noise_kept=noise, ratio=row["etam_events_per_s"] * elapsed / len(events), peer_error=None)
    except ImportError as exc:
        row.update(peer="dv-processing", peer_events_per_s=None, ratio=None, peer_error=f"not installed ({exc.name})")
    return [row]
