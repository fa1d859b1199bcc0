"""polycc.parallel.in_row_chunks: every row once, any chunk and thread count, the first error raised."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polycc.parallel import in_row_chunks


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
