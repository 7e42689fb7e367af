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

__all__ = ["Devices", "chunks", "devices", "initialize", "map_units", "replicate"]

Devices = int | Sequence[jax.Device] | None


def initialize(**kwargs: Any) -> None:
    """Join a multi-host run: :func:`jax.distributed.initialize` with the cluster's environment.

    SLURM, Open MPI and Kubernetes are detected from the environment; elsewhere the cluster is
    described by the keywords. Call it before anything else uses JAX.

    Args:
        **kwargs: passed to :func:`jax.distributed.initialize`, e.g. ``coordinator_address``,
            ``num_processes`` and ``process_id`` where the cluster is not detected.
    """
    jax.distributed.initialize(**kwargs)


def devices(spec: Devices) -> list[jax.Device]:
    """The devices to spread work over.

    Across hosts the count is global, and each process uses its own (addressable) share of
    the devices.

    Args:
        spec: None or 1, the first device only (the single-device path); an int n, the first n
            of ``jax.devices()``; or a sequence of devices, taken as given.

    Returns:
        The chosen devices, in order.

    Raises:
        ValueError: if ``spec`` is a bool, a count outside 1 to the number of devices, or an
            empty sequence.
    """
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
    """One copy of ``tree`` on each addressable device.

    Args:
        tree: a pytree of arrays, e.g. a model.
        devs: the devices; those of other processes get no copy here.

    Returns:
        The copies, keyed by the devices of this process among ``devs``.
    """
    return {d: jax.device_put(tree, d) for d in devs if d.process_index == jax.process_index()}


def map_units(
    fn: Callable[..., Any],
    shared: Any,
    units: Sequence[tuple[np.ndarray, ...]],
    devs: Sequence[jax.Device],
    *,
    replicas: dict[jax.Device, Any] | None = None,
) -> list[Any]:
    """``fn(shared, *unit)`` for every unit, unit ``i`` on device ``devs[i % len(devs)]``.

    Units run in waves of one per device (asynchronous dispatch overlaps them; waiting for
    each wave bounds the memory at one unit per device). The last wave is filled up with
    copies of the last unit, so that every device, and so every host, computes in every wave.

    Args:
        fn: the work of one unit, ``fn(shared, *unit)``. It should be jitted: one compiled
            program per device, the same for every unit of equal shapes.
        shared: what every unit reads (e.g. a model), copied once to each device.
        units: the units, each a tuple of arrays passed after ``shared``.
        devs: the devices, e.g. from :func:`devices`.
        replicas: copies of ``shared`` already made by :func:`replicate` (then ``shared`` is
            not copied again).

    Returns:
        Every unit's output as a NumPy pytree, in the order of ``units``, on every process.

    Raises:
        ValueError: on several hosts, if this process owns none of ``devs``.
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
    """Slices of ``size`` rows covering ``range(n)``.

    Args:
        n: the number of rows.
        size: the rows per slice.

    Returns:
        The slices in order, the last one shorter when ``size`` does not divide ``n``.
    """
    return [slice(s, min(s + size, n)) for s in range(0, n, size)]
