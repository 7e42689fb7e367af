"""Memory: big square buffers that can be given back row by row, budgets, and peak RSS.

At ``data=paper`` one ``K̄`` has 40000 rows, 40000² doubles: a large share of a workstation's
memory.
It is factorised in place (:mod:`gpg.linalg`), but the factor must then be copied into JAX
arrays for prediction, and two full copies do not fit. :func:`square_buffer` allocates the
matrix in an anonymous memory map whose rows can be returned to the operating system
(``madvise(MADV_DONTNEED)``) as soon as they have been copied, so the peak stays near one copy.
"""

from __future__ import annotations

import mmap
import os
import threading
import time
from dataclasses import dataclass

import numpy as np

__all__ = [
    "InsufficientMemory",
    "PeakRSS",
    "SquareBuffer",
    "available_bytes",
    "require",
    "square_buffer",
]

PAGE = mmap.PAGESIZE


class InsufficientMemory(MemoryError):
    """A model would need more memory than is available; raised before allocating it.

    Args:
        what: the step's name, which the message starts with.
        needed: bytes the step would allocate (kept as ``.needed``).
        available: bytes available (kept as ``.available``).
    """

    def __init__(self, what: str, needed: int, available: int):
        self.needed, self.available = needed, available
        super().__init__(
            f"{what} needs about {needed / 2**30:.1f} GiB but only {available / 2**30:.1f} GiB "
            "is available"
        )


@dataclass
class SquareBuffer:
    """A C-ordered ``n x n`` float64 array in an anonymous map (see :func:`release_rows`)."""

    array: np.ndarray
    _map: mmap.mmap

    def release_rows(self, start: int, stop: int) -> None:
        """Give the pages wholly inside rows ``[start, stop)`` back to the system.

        Their contents are lost (they read as zeros afterwards): call this only for rows that
        will not be read again. Pages that straddle a boundary row are kept.

        Args:
            start: first row released.
            stop: one past the last row released.
        """
        n = self.array.shape[1]
        lo = -(-start * n * 8 // PAGE) * PAGE  # first whole page inside the range
        hi = (stop * n * 8 // PAGE) * PAGE
        if hi > lo:
            self._map.madvise(mmap.MADV_DONTNEED, lo, hi - lo)


def square_buffer(n: int) -> SquareBuffer:
    """An uninitialised (zero-filled on first touch) ``n x n`` float64 buffer.

    The map is private: for a shared anonymous map (Python's default) ``MADV_DONTNEED`` frees
    nothing, and :meth:`SquareBuffer.release_rows` would not lower the peak.

    Args:
        n: rows (and columns).

    Returns:
        The buffer; its ``array`` is the C-ordered (n, n) view to write ``K̄`` into.
    """
    mm = mmap.mmap(-1, max(n * n * 8, 1), flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    return SquareBuffer(np.frombuffer(mm, dtype=np.float64, count=n * n).reshape(n, n), mm)


def available_bytes() -> int:
    """The memory available to a new allocation, as the kernel estimates it.

    Returns:
        ``MemAvailable`` from ``/proc/meminfo`` in bytes, or ``2⁶²`` where it cannot be read
        (no check then refuses).
    """
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 1 << 62


def require(what: str, needed: int, *, margin: float = 0.9) -> None:
    """Refuse, before allocating, a step that would not fit in the memory available.

    Args:
        what: the step's name in the message (``"the global α over 40000 rows"``).
        needed: bytes the step will allocate.
        margin: the share of :func:`available_bytes` it may take.

    Raises:
        InsufficientMemory: if ``needed`` exceeds ``margin`` of the memory available.
    """
    avail = available_bytes()
    if needed > margin * avail:
        raise InsufficientMemory(what, needed, avail)


def rss_bytes() -> int:
    """Resident set size of this process in bytes (0 where ``/proc`` cannot be read)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return 0


class PeakRSS:
    """Context manager sampling the resident set size in a background thread.

    ``.peak_delta`` is the highest RSS seen above the value at entry, in bytes; a peak shorter
    than ``interval`` may be missed.

    Args:
        interval: seconds between two samples.
    """

    def __init__(self, interval: float = 0.02):
        self.interval = interval
        self.start = self.peak = 0
        self._stop = threading.Event()

    def __enter__(self) -> PeakRSS:
        self.start = self.peak = rss_bytes()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_bytes())
            time.sleep(self.interval)

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss_bytes())

    @property
    def peak_delta(self) -> int:
        """The highest RSS seen above the value at entry, in bytes."""
        return self.peak - self.start
