"""Limit OpenBLAS threads around many small dense operations.

The active-set NNLS does hundreds of small Cholesky factorisations and matrix-vector products.
With OpenBLAS's default of one thread per core, each of them wakes every thread, and when another
process holds a core (a `make -j` batch, a test run) the threads spin-wait on each other: measured
up to 40x slower on a 2-core machine. `blas_threads(1)` runs such a section single-threaded.
numpy and scipy each bundle their own OpenBLAS; both are found among the loaded libraries
(Linux /proc/self/maps). Elsewhere, or if no OpenBLAS is loaded, it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
from functools import lru_cache

_SUFFIXES = ("", "64_", "_64_", "_")


@lru_cache(maxsize=1)
def _controls() -> tuple:
    found = []
    try:
        with open("/proc/self/maps") as f:
            paths = sorted({line.split()[-1] for line in f if "openblas" in line.lower() and "/" in line})
    except OSError:
        return ()
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix in ("scipy_openblas", "openblas"):
            getter = setter = None
            for suffix in _SUFFIXES:
                getter = getter or getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                setter = setter or getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
            if getter is not None and setter is not None:
                getter.restype = ctypes.c_int
                setter.argtypes = [ctypes.c_int]
                found.append((getter, setter))
                break
    return tuple(found)


@contextlib.contextmanager
def blas_threads(n: int):
    """Run the block with at most `n` OpenBLAS threads (restored afterwards)."""
    import numpy  # noqa: F401  (make sure the BLAS libraries are loaded before looking for them)
    import scipy.linalg  # noqa: F401

    controls = _controls()
    before = [get() for get, _ in controls]
    try:
        for (_, set_), old in zip(controls, before):
            set_(max(1, min(n, old)))
        yield
    finally:
        for (_, set_), old in zip(controls, before):
            set_(old)
