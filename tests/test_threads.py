"""The blocked-work helper: every block once, on both cores, and on the calling worker's own
thread when it is nested (a blocked kernel inside a blocked loop)."""

import threading

from pipelines.threads import parallel_blocks


def test_every_start_is_run_once_and_nested_calls_stay_on_their_worker():
    seen, lock = [], threading.Lock()

    def inner(mine):
        with lock:
            seen.extend(("inner", s, threading.get_ident()) for s in mine)

    def outer(mine):
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
    # and the helper is usable again from the main thread afterwards (not stuck in "nested" mode)
    after = []
    parallel_blocks(lambda mine: after.append(threading.get_ident()), [0, 1])
    assert len(after) == 2
