"""Threads in polycc.parallel: in_row_chunks does every row once for any chunk and thread count and raises the
first error; worker processes (local pool, the budget's forks) run one BLAS thread each, this process keeps its own."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.parallel import Task, in_row_chunks, init_worker, make_runner, one_blas_thread


@settings(max_examples=60, deadline=None)
@given(n=st.integers(0, 500), chunk=st.integers(1, 80), threads=st.integers(1, 4))
def test_every_row_is_done_once(n, chunk, threads):
    hits = np.zeros(n, np.int64)
    spans = []
    lock = threading.Lock()

    def fn(s, e):
        assert 0 <= s < e <= n and e - s <= chunk
        with lock:
            spans.append((s, e))
        hits[s:e] += 1

    in_row_chunks(n, fn, chunk, threads)
    assert np.all(hits == 1)
    assert sorted(spans) == [(s, min(n, s + chunk)) for s in range(0, n, chunk)]


@pytest.mark.parametrize("threads", [1, 3])
def test_an_error_in_a_chunk_is_raised_after_every_chunk_ran(threads):
    done = []

    def fn(s, e):
        done.append(s)
        if s == 40:
            raise ValueError("chunk 40")

    with pytest.raises(ValueError, match="chunk 40"):
        in_row_chunks(100, fn, 10, threads)
    assert sorted(done) == (list(range(0, 50, 10)) if threads == 1 else list(range(0, 100, 10)))


def _blas_threads() -> tuple[list[int], None]:
    from threadpoolctl import threadpool_info

    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"], None


def test_worker_processes_run_one_blas_thread_and_this_process_keeps_its_own():
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    here = _blas_threads()[0]
    assert here, "numpy's BLAS is not visible to threadpoolctl"
    with make_runner(2) as pool:  # the local pool (forkserver)
        got = pool.run({("blas", k): Task(_blas_threads) for k in range(2)})
    assert all(v and set(v) == {1} for v in got.values())  # numpy's and scipy's own OpenBLAS, where loaded
    with ProcessPoolExecutor(1, mp_context=mp.get_context("fork"), initializer=init_worker) as ex:  # the budget's
        assert set(ex.submit(_blas_threads).result()[0]) == {1}
    with one_blas_thread():
        assert set(_blas_threads()[0]) == {1}
    assert _blas_threads()[0] == here
