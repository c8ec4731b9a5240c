"""BLAS threads: one for the small products this library makes, all cores for large
factorisations.

Waking a second OpenBLAS thread costs more than it saves on the small matrices of a
radar scan or a tile (the scan of ``bench/bench_core.py``, M = 500, runs fastest on one
thread) and gains on the dense factorisations of a city-scale field (M ~ 3,000); the
threshold between them is :data:`PARALLEL_MIN_HINGES`.
"""

from __future__ import annotations

import contextlib
import functools

import numpy  # noqa: F401  (loads the BLAS libraries before the controller looks for them)
import scipy.linalg  # noqa: F401
from threadpoolctl import ThreadpoolController

#: Dense factorisations of at least this many hinges use every BLAS thread.
PARALLEL_MIN_HINGES = 800

_CONTROLLER = ThreadpoolController()


def threads_for(hinges: int | None = None):
    """Context: one BLAS thread, unless ``hinges`` (the size of a dense factorisation)
    is at least :data:`PARALLEL_MIN_HINGES`.

    OpenBLAS's thread count is process-wide: threadpoolctl lets one Python thread at a time
    change it (the first to enter), the others' sections leave it alone, and leaving
    restores the count found on entry.
    """
    if hinges is not None and hinges >= PARALLEL_MIN_HINGES:
        return contextlib.nullcontext()
    return _CONTROLLER.limit(limits=1, user_api="blas")


def single_threaded(fn):
    """Decorator: run ``fn`` with one BLAS thread (small GEMMs)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with threads_for():
            return fn(*args, **kwargs)

    return wrapper
