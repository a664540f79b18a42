"""Every library thread pool a process may use held to one thread.

ETAM's per-event work is numba and single calls of OpenCV on small images: pools only add spinning
threads that take the cores the other services need (two thirds of the ego tracker's CPU went to BLAS
threads spinning after small calls, on 2 cores). OpenCV's pool is its own (pthreads in the PyPI wheels,
which threadpoolctl does not see), so it is held apart: with 2 threads the object tracker used 1.2 cores
for no gain in speed.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import cv2
from threadpoolctl import threadpool_limits


@contextmanager
def one_thread() -> Iterator[None]:
    """numpy's and scipy's BLAS pools and OpenCV's held to one thread inside, as they were after."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(1):
            yield
    finally:
        cv2.setNumThreads(threads)
