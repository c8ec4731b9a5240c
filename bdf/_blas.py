"""BLAS threads: one for the small products this library makes, and for work in threads.

Waking a second OpenBLAS thread costs more than it saves on the small GEMMs of the
splat and gather kernels (:mod:`bdf.features`). The factorisations and inversions of
:mod:`bdf.sparse` run on scipy's OpenBLAS with every core, but a directional map's
classes gain more from a thread each (:func:`in_threads`).
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor

import numpy  # noqa: F401  (loads the BLAS libraries before the controller looks for them)
import scipy.linalg  # noqa: F401
from threadpoolctl import ThreadpoolController

_CONTROLLER = ThreadpoolController().select(prefix="libscipy_openblas")


def one_thread():
    """Context: one thread for numpy's and scipy's BLAS.

    OpenBLAS's thread count is process-wide: threadpoolctl lets one Python thread at a time
    change it (the first to enter), the others' sections leave it alone, and leaving
    restores the count found on entry.
    """
    return _CONTROLLER.limit(limits=1)


def single_threaded(fn):
    """Decorator: run ``fn`` with one BLAS thread (small GEMMs)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with one_thread():
            return fn(*args, **kwargs)

    return wrapper


def in_threads(tasks: list) -> list:
    """The results of ``tasks`` (callables), run side by side in a thread per core with one
    BLAS thread each: for work that releases the GIL (the factorisations and inversions of
    :mod:`bdf.sparse`), which gains more from a core per task than from two BLAS threads
    per task (the directional fit in ``bench/bench_core.py``)."""
    with one_thread(), ThreadPoolExecutor(min(len(tasks), os.cpu_count() or 1)) as pool:
        return [f.result() for f in [pool.submit(task) for task in tasks]]
