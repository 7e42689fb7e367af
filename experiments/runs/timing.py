"""How the experiments time things: JAX's dispatch, repeated calls, their statistics, and the
machine the numbers were measured on."""

from __future__ import annotations

import itertools
import os
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np


def set_dispatch(cfg: Mapping[str, Any]) -> None:
    """Apply ``cfg['sync_dispatch']`` (default true): run JAX CPU computations on the calling
    thread. JAX otherwise runs them on a worker thread, and waking the caller afterwards adds a
    noisy latency per call comparable to a mean prediction (the README's real-time quick start
    says how much)."""
    jax.config.update("jax_cpu_enable_async_dispatch", not cfg.get("sync_dispatch", True))


def block(x):
    """Wait for every array in ``x`` (JAX dispatch is asynchronous)."""
    return jax.block_until_ready(x)


def time_calls(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> np.ndarray:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls."""
    for _ in range(warmup):
        block(fn())
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        block(fn())
        out[i] = time.perf_counter() - t0
    return out


def stats(seconds: np.ndarray) -> dict[str, float]:
    """Median, 5th and 95th percentile and mean, in seconds."""
    return {
        "median_s": float(np.median(seconds)),
        "p05_s": float(np.percentile(seconds, 5)),
        "p95_s": float(np.percentile(seconds, 95)),
        "mean_s": float(np.mean(seconds)),
        "n": int(seconds.size),
    }


def latency(fn: Callable[..., Any], args_list: Sequence[tuple], n: int) -> dict[str, float]:
    """:func:`stats` of ``n`` calls ``fn(*args)`` cycling through ``args_list``, after 3
    untimed warm-up calls."""
    calls = itertools.cycle(args_list)
    return stats(time_calls(lambda: fn(*next(calls)), n, warmup=3))


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
    }
