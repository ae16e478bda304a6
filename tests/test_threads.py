"""The blocked-work helper: every block once, on both cores, and on the calling worker's own
thread when it is nested (a blocked kernel inside a blocked loop)."""

import os
import threading

import pytest

from pipelines.threads import parallel_blocks

two_cores = pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2 if hasattr(os, "sched_getaffinity")
                               else (os.cpu_count() or 1) < 2, reason="parallel_blocks runs serially on one core")


@two_cores
def test_every_start_is_run_once_and_nested_calls_stay_on_their_worker():
    seen, lock = [], threading.Lock()

    def inner(mine):
        with lock:
            seen.extend(("inner", s, threading.get_ident()) for s in mine)

    both = threading.Barrier(2, timeout=30)  # (a run waits for the other: two threads, or it fails)

    def outer(mine):
        both.wait()
        with lock:
            seen.extend(("outer", s, threading.get_ident()) for s in mine)
        for s in mine:
            parallel_blocks(inner, [10 * s + k for k in range(3)])

    parallel_blocks(outer, list(range(6)))
    outer_thread = {s: t for kind, s, t in seen if kind == "outer"}
    assert sorted(outer_thread) == list(range(6))
    inner_runs = [(s, t) for kind, s, t in seen if kind == "inner"]
    assert sorted(s for s, _ in inner_runs) == sorted(10 * s + k for s in range(6) for k in range(3))
    for s, t in inner_runs:
        assert t == outer_thread[s // 10]  # each nested block ran on the worker that asked for it
    assert len(set(outer_thread.values())) == 2  # (two workers)
    # and the helper uses both threads again afterwards from the main thread (not stuck in "nested" mode)
    assert len(_two_threads_ran()) == 2


def _two_threads_ran() -> set:
    """The threads a fresh parallel_blocks call ran its two blocks on (each waits for the other)."""
    both, seen = threading.Barrier(2, timeout=30), []

    def run(mine):
        both.wait()
        seen.append(threading.get_ident())

    parallel_blocks(run, [0, 1])
    return set(seen)


@two_cores
def test_a_workers_error_reaches_the_caller_and_the_next_call_runs_in_parallel():
    def fails(mine):
        if 1 in mine:
            raise ValueError("block 1")

    with pytest.raises(ValueError, match="block 1"):
        parallel_blocks(fails, [0, 1])
    after = _two_threads_ran()
    assert len(after) == 2 and threading.get_ident() not in after
