"""Loading the numba kernels a service runs before its first events, and every service's ahead (`etam warmup`).

numba compiles a kernel on a machine's first run and caches it beside the code (`__pycache__`): the object
tracker's take about half a minute on a 2-core VM, far longer on a drone's ARM board. A live service that
compiled on its first packets held the camera's events meanwhile and dropped the oldest, so each service loads
its kernels first (`load`), and says so where that takes long: a fresh install's first `etam up` was otherwise
silent for half a minute. `etam warmup` loads them all once, after installing (a deployment image's build step).
"""

from __future__ import annotations

import importlib
import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

SLOW_S = 2.0  # a load this long is compiling: said in the log, once at its start and once at its end


def load(what: str, warm_up: Callable[[], object]) -> float:
    """Runs `warm_up`, which loads the kernels of `what` (say "the object tracker"); its seconds."""
    start = time.perf_counter()
    note = threading.Timer(SLOW_S, log.info, ("compiling %s's kernels: this machine's first run (under a minute on "
                                              "most; `etam warmup` does it ahead), cached after", what))
    note.daemon = True
    note.start()
    try:
        warm_up()
    finally:
        note.cancel()
    took = time.perf_counter() - start
    if took >= SLOW_S:
        log.info("%s's kernels ready in %.0f s", what, took)
    return took


def _object_tracker() -> None:
    from services.tracker.objects.tracker import METHODS, method_params, warm_up

    for method in METHODS:
        warm_up(method_params(method))


def _warm_up(module: str, *args: object) -> Callable[[], None]:
    """`module`'s `warm_up(*args)`, imported when run: the services import this module, so it imports none of theirs."""
    return lambda: importlib.import_module(module).warm_up(*args)


# what `etam warmup` loads: the services' own warm-ups (the mosaic loads its kernels on its first events, as do the
# simulator's and the dashboard's few small ones; the 6-DoF loop has none)
PARTS: dict[str, Callable[[], None]] = {
    "object tracker (every method)": _object_tracker,
    "rotation tracker": _warm_up("services.tracker.ego.rotation"),
    "USB decoder": _warm_up("services.camera.usb.words"),
    "mapper (sweep)": _warm_up("services.mapper.warmup", "sweep"),
    "mapper (stereo)": _warm_up("services.mapper.warmup", "stereo"),
}
