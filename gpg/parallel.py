"""Work over several JAX devices (and hosts): the partition's bins and blocks of queries.

The partition is the natural unit of parallel work: each bin's precompute and each block of
queries is independent. gpg places those units on the devices JAX has (``jax.device_put``
with one device per unit, round robin) and lets JAX's asynchronous dispatch run them side by
side: several GPUs, virtual CPU devices (``XLA_FLAGS=--xla_force_host_platform_device_count=4``)
or, after :func:`initialize`, the devices of every host of a cluster.

Every unit runs the same compiled program whatever the number of devices, so the results are
bit-identical to the single-device path. On the CPU the devices only overlap with JAX's
asynchronous dispatch (``jax_cpu_enable_async_dispatch``, on by default and fixed when JAX
starts; the entry points keep it on when they are given devices). A ``jax.shard_map`` over a
device mesh was tried first: its multi-device program differed from the one-device program,
and so did the results, in the last digits, for the same bins.

Multi-host: start the same command on every host (for example with ``srun`` under SLURM; see
the README) after :func:`initialize`. Each process computes the units of its own devices, and
:func:`map_units` exchanges the results so that every process holds all of them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

Devices = int | Sequence[jax.Device] | None


def initialize(**kwargs) -> None:
    """Join a multi-host run: :func:`jax.distributed.initialize` with the cluster's environment
    (SLURM, Open MPI and Kubernetes are detected; otherwise pass ``coordinator_address``,
    ``num_processes`` and ``process_id``). Call it before anything else uses JAX."""
    jax.distributed.initialize(**kwargs)


def devices(spec: Devices) -> list[jax.Device]:
    """The devices to spread work over: None or 1, the first device only (the single-device
    path); an int n, the first n; or the given devices. Across hosts, the count is global and
    each process uses its own (addressable) share of them."""
    avail = jax.devices()
    if spec is None:
        return avail[:1]
    if isinstance(spec, bool):
        raise ValueError(f"devices must be a count or a list of devices, got {spec!r}")
    if isinstance(spec, int):
        if not 1 <= spec <= len(avail):
            raise ValueError(f"devices={spec}, but {len(avail)} device(s) are available")
        return avail[:spec]
    chosen = list(spec)
    if not chosen:
        raise ValueError("devices is an empty list")
    return chosen


def replicate(tree: Any, devs: Sequence[jax.Device]) -> dict[jax.Device, Any]:
    """One copy of ``tree`` (a pytree of arrays, e.g. a model) on each addressable device."""
    return {d: jax.device_put(tree, d) for d in devs if d.process_index == jax.process_index()}


def map_units(
    fn: Callable[..., Any],
    shared: Any,
    units: Sequence[tuple[np.ndarray, ...]],
    devs: Sequence[jax.Device],
    *,
    replicas: dict[jax.Device, Any] | None = None,
) -> list[Any]:
    """``fn(shared, *unit)`` for every unit, unit ``i`` on device ``devs[i % len(devs)]``;
    returns every unit's output, as NumPy pytrees in order, on every process.

    ``fn`` should be jitted: one compiled program per device, the same for every unit of equal
    shapes. Units run in waves of one per device (asynchronous dispatch overlaps them; waiting
    for each wave bounds the memory at one unit per device). The last wave is filled up with
    copies of the last unit, so that every device, and so every host, computes in every wave.
    """
    replicas = replicate(shared, devs) if replicas is None else replicas
    count, n = len(units), len(devs)
    units = [*units, *[units[-1]] * ((-count) % n)] if units else []
    out: list[Any] = [None] * len(units)
    for start in range(0, len(units), n):
        wave = []
        for i in range(start, start + n):
            d = devs[i % n]
            if d.process_index != jax.process_index():
                continue
            args = tuple(jax.device_put(a, d) for a in units[i])
            wave.append((i, fn(replicas[d], *args)))
        for i, res in wave:
            out[i] = jax.tree.map(np.asarray, res)
    return _gather(out)[:count]


def _gather(results: list[Any]) -> list[Any]:
    """Every process's units on every process (a no-op on one host)."""
    if jax.process_count() == 1 or not results:
        return results
    from jax.experimental import multihost_utils

    mine = [r for r in results if r is not None]
    if not mine:
        raise ValueError(f"process {jax.process_index()} owns none of the devices given")
    # Every process sends one stack of the same shape: its units, zeros elsewhere, plus a mask.
    flags = multihost_utils.process_allgather(np.array([r is not None for r in results]))
    zeros = jax.tree.map(np.zeros_like, mine[0])
    stacked = jax.tree.map(
        lambda *leaves: np.stack(leaves), *[r if r is not None else zeros for r in results]
    )
    everyone = multihost_utils.process_allgather(stacked)  # leaves (P, U, ...)
    owner = np.argmax(flags, axis=0)
    return [jax.tree.map(lambda a, i=i: a[owner[i], i], everyone) for i in range(len(results))]


def chunks(n: int, size: int) -> list[slice]:
    """Slices of ``size`` rows covering ``range(n)`` (the last one shorter)."""
    return [slice(s, min(s + size, n)) for s in range(0, n, size)]


__all__ = ["chunks", "devices", "initialize", "map_units", "replicate"]
