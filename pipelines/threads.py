"""Limit BLAS threads around many small dense operations.

The active-set NNLS does hundreds of small Cholesky factorisations and matrix-vector products.
With a BLAS's default of one thread per core, each of them wakes every thread, and when another
process holds a core (a `make -j` batch, a test run) the threads spin-wait on each other: measured
up to 40x slower on a 2-core machine. `blas_threads(1)` runs such a section single-threaded.
threadpoolctl finds every BLAS the process has loaded (numpy's and scipy's OpenBLAS, MKL, BLIS).
"""

from __future__ import annotations

import contextlib
import threading
from functools import lru_cache


@lru_cache(maxsize=1)
def _controller():
    import numpy  # noqa: F401  (load the BLAS libraries before looking for them)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


KEEP_FREED_BYTES = 1 << 30  # `configure_malloc`: freed heap memory kept for reuse, up to this much


@lru_cache(maxsize=1)
def configure_malloc() -> bool:
    """Tune memory allocation for a solve's large, short-lived arrays; False where there is no
    glibc (the allocator unchanged; the huge-page setting below still applies). Called once at start, before the worker threads first allocate (the
    CLI calls it, so the benchmarks' solves get it, and tests/conftest.py).

    - One heap for all threads (mallopt M_ARENA_MAX = 1). glibc gives each thread that allocates its
      own arena, and what a worker thread frees stays in its arena: the block-sized temporaries of
      `parallel_blocks` (1-30 MB) held ~185 MB of teapot_sun_phong's peak RSS at R = 32 (`solve`:
      1,206 -> 1,024 MiB with one arena; spot_sun 0.78 -> 0.67 GiB and no slower). Numpy's
      temporaries are few and large, so the threads hardly wait on the one arena's lock. (A thread
      that already has an arena keeps it.)
    - Large arrays from that heap, and freed ones kept for the next (M_MMAP_THRESHOLD and
      M_TRIM_THRESHOLD = KEEP_FREED_BYTES). By default glibc maps each array above 128 kB-32 MB
      afresh and unmaps it when freed, so every new array of that size faults all its pages in
      again: a solve makes thousands (leaf sums, tree Gram matrices and their float64 copies, one
      per level, part and round), and on the 2-core test machines those page faults were an eighth
      to a quarter of a whole `solve` (medians of interleaved runs from an empty cache, the same
      lights to every digit: the sample scene 7.24 -> 6.26 s, teapot_sun_phong 35.5 -> 30.3 s).
      Peak RSS is the heap's high-water mark, as it was the mapped arrays' (593 -> 597 MiB and
      981 -> 995-1,014 MiB: freed holes a larger array cannot reuse).
    - No transparent huge pages asked for new arrays (numpy's madvise(MADV_HUGEPAGE), unless the
      user set NUMPY_MADVISE_HUGEPAGE). Where the kernel cannot hand out huge pages at once, each
      such fault tries and fails slowly: on the test machine (THP "madvise", none free) filling a
      fresh 200 MB array took 1.1-3 s against 0.11-0.16 s with 4 kB pages, and whole solves from an
      empty cache, interleaved, went bunny_sun 10.1 -> 7.5 s, the sample 9.1 -> 6.6 s, spot_overcast
      at R = 64 27.3 -> 14.6 s (the same lights and peak RSS)."""
    import ctypes
    import os
    import sys

    if "NUMPY_MADVISE_HUGEPAGE" not in os.environ:
        try:
            from numpy._core.multiarray import _set_madvise_hugepage
        except ImportError:  # (numpy's private switch moved: its default stays)
            pass
        else:
            _set_madvise_hugepage(False)

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        if not hasattr(libc, "gnu_get_libc_version"):
            return False  # (musl and others: other allocators)
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
        ok = bool(libc.mallopt(M_ARENA_MAX, 1))
        ok &= bool(libc.mallopt(M_MMAP_THRESHOLD, KEEP_FREED_BYTES))
        return ok & bool(libc.mallopt(M_TRIM_THRESHOLD, KEEP_FREED_BYTES))
    except (OSError, AttributeError):
        return False


@contextlib.contextmanager
def blas_threads(n: int):
    """Run the block with at most `n` BLAS threads (restored afterwards)."""
    with _controller().limit(limits=max(1, int(n)), user_api="blas"):
        yield


_worker = threading.local()  # .inside: this thread is one of parallel_blocks' workers


def _as_worker(run, starts):
    _worker.inside = True
    try:
        run(starts)
    finally:
        _worker.inside = False


def parallel_blocks(run, starts: list) -> None:
    """Blocked array work on the machine's cores (at most 2): `run(starts[i::k])` on thread i of k,
    with one BLAS thread each (the products in a block are small). numpy's ufuncs and BLAS release
    the GIL, so the threads run in parallel; each `run` keeps its own scratch arrays. Called from
    one of its own workers (a blocked kernel inside a blocked loop), it runs `run(starts)` on that
    thread: the cores are already busy."""
    import os

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    workers = min(2, cores, len(starts))
    if workers == 0:
        return
    if workers == 1 or getattr(_worker, "inside", False):
        run(starts)
        return
    from concurrent.futures import ThreadPoolExecutor

    with blas_threads(1), ThreadPoolExecutor(workers) as pool:
        list(pool.map(_as_worker, [run] * workers, [starts[i::workers] for i in range(workers)]))
