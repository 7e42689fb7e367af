"""Releasable square buffers, memory budgets and peak-RSS sampling."""

import gc
import mmap
import time

import numpy as np
import pytest

from gpg.linalg import memory
from gpg.linalg.tri import BlockTriangular


def test_square_buffer_release_rows(rng):
    buf = memory.square_buffer(600)
    a = buf.array
    assert a.shape == (600, 600) and a.flags.c_contiguous and a.flags.writeable
    a[...] = rng.normal(size=(600, 600))
    keep = a[400:].copy()
    buf.release_rows(0, 300)
    np.testing.assert_array_equal(a[400:], keep)  # rows outside the range are untouched
    assert np.count_nonzero(a[10:290]) == 0  # whole pages inside the range read as zeros


def test_bands_from_buffer_equal_dense(rng):
    buf = memory.square_buffer(300)
    F = np.tril(rng.normal(size=(300, 300)))
    buf.array[...] = F
    bt = BlockTriangular.from_buffer(buf, lower=True, n_blocks=5)
    np.testing.assert_array_equal(bt.to_dense(), F)
    with pytest.raises(ValueError, match="lower-triangular"):
        BlockTriangular.from_buffer(buf, lower=False)


def test_require_and_peak():
    with pytest.raises(memory.InsufficientMemory, match=r"needs about .* GiB but only .* GiB"):
        memory.require("a test", 1 << 62)
    memory.require("a test", 1 << 10)
    gc.collect()
    for _ in range(3):  # another thread (XLA's, a previous test's arrays collected) may free
        # memory at the same moment and hide the 50 MB: on a clean clone it did; a new try
        with memory.PeakRSS(interval=0.005) as p:
            before = memory.rss_bytes()
            # fresh pages from the kernel: in a long-lived worker np.ones can reuse a freed,
            # still resident heap chunk and leave the RSS unchanged (CI saw it: 5.9 GB both)
            x = mmap.mmap(-1, 50_000_000)
            np.frombuffer(x, dtype=np.uint8)[:: mmap.PAGESIZE] = 1  # every page touched
            held = memory.rss_bytes()
            # held until the sampler has seen it (a loaded machine can delay its thread by
            # more than any fixed sleep), for at most 5 s
            deadline = time.monotonic() + 5.0
            while p.peak < held and time.monotonic() < deadline:
                time.sleep(0.005)
            x.close()
        if held - before > 30_000_000 and p.peak >= held:  # shown, and seen by the sampler
            break
    assert held - before > 30_000_000
    assert p.peak >= held and p.peak_delta == p.peak - p.start
