"""Dense factorisations on the accelerator, and the rule that places them.

The host path (:mod:`gpg.linalg.dense`) factorises ``K̄`` in place with LAPACK: on the CPU it is
the faster of the two and the only one that fits ``data=paper``'s ``K̄`` (40000² doubles) in
one copy.
With an accelerator, the same solve runs there in float64 (``K̄`` assembled on the device,
``jax.lax.linalg`` Cholesky and triangular solves), many times faster than on the host's cores
(docs/measurements.md, "One GPU").

**The rule** (:func:`place`): ``solver.device`` ``host`` or ``device`` is obeyed (``device``
on a CPU-only machine runs the device program on the CPU: how the tests check it); ``auto``
picks the device when JAX's default backend is not the CPU and the solve's peak, with
:data:`HEADROOM`, fits in the device memory free at that moment
(``memory_stats()``: ``bytes_limit − bytes_in_use``), else the host. Each choice is logged
(logger ``gpg``) with the sizes it was made from.
"""

from __future__ import annotations

import logging
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from gpg._precision import highest
from gpg.linalg.dense import NotPositiveDefiniteError

__all__ = [
    "HEADROOM",
    "PLACEMENTS",
    "accelerator",
    "cholesky",
    "factor_solve",
    "free_bytes",
    "place",
    "solve_bytes",
]

PLACEMENTS = ("auto", "host", "device")
# The device path's peak is counted exactly (its buffers); the headroom covers XLA's own
# workspace (the Cholesky's panels, the allocator's fragmentation) and what else the process
# holds on the device meanwhile.
HEADROOM = 1.25

log = logging.getLogger("gpg")


def accelerator() -> jax.Device | None:
    """The accelerator the ``auto`` rule may place a solve on.

    Returns:
        JAX's first default device when it is not a CPU, else None.
    """
    dev = jax.devices()[0]
    return None if dev.platform == "cpu" else dev


def free_bytes(device: jax.Device) -> int | None:
    """Bytes the device can still allocate now, from its ``memory_stats()``.

    Args:
        device: the JAX device asked (:func:`accelerator`).

    Returns:
        ``bytes_limit − bytes_in_use``, or None where the device reports no limit (a CPU, or a
        backend without ``memory_stats``).
    """
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    if not stats or "bytes_limit" not in stats:
        return None
    return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))


def place(mode: str, peak_bytes: int, what: str) -> str:
    """Where a dense solve runs: the host (LAPACK) or JAX's default device.

    The rule is the module docstring's: ``host`` and ``device`` are obeyed, ``auto`` takes the
    accelerator when there is one and ``HEADROOM × peak_bytes`` fits its free memory. The
    choice is logged (logger ``gpg``) with the sizes it was made from.

    Args:
        mode: ``solver.device``, one of :data:`PLACEMENTS`.
        peak_bytes: the device program's peak (:func:`solve_bytes`).
        what: the solve's name in the log (``"the global α over 8000 rows"``).

    Returns:
        ``"host"`` or ``"device"``.

    Raises:
        ValueError: if ``mode`` is not one of :data:`PLACEMENTS`.
    """
    if mode not in PLACEMENTS:
        raise ValueError(f"solver.device must be one of {PLACEMENTS}, got {mode!r}")
    if mode != "auto":
        log.info("%s: on the %s (solver.device=%s)", what, mode, mode)
        return mode
    dev = accelerator()
    if dev is None:
        log.info("%s: on the host (no accelerator: JAX's default backend is the CPU)", what)
        return "host"
    free = free_bytes(dev)
    need = int(HEADROOM * peak_bytes)
    if free is not None and need > free:
        log.info(
            "%s: on the host (%.2f GB with headroom do not fit the %.2f GB free on %s)",
            what, need / 1e9, free / 1e9, dev,
        )  # fmt: skip
        return "host"
    log.info(
        "%s: on %s (%.2f GB with headroom, %s GB free)",
        what, dev, need / 1e9, "?" if free is None else f"{free / 1e9:.2f}",
    )  # fmt: skip
    return "device"


def solve_bytes(rows: int, inverse: bool) -> int:
    """Peak device bytes of :func:`factor_solve`, counted from its buffers.

    ``K̄``'s buffer is reused by the factor; with ``inverse`` the identity and ``L⁻¹`` are held
    beside ``L``.

    Args:
        rows: rows of ``K̄``.
        inverse: whether ``L⁻¹`` is formed as well.

    Returns:
        ``8 rows²`` bytes, three times that with ``inverse``.
    """
    return 8 * rows * rows * (3 if inverse else 1)


@partial(jax.jit, donate_argnums=0)
def _cholesky(K: Float[Array, "r r"]) -> Float[Array, "r r"]:
    return jnp.linalg.cholesky(K)


def cholesky(K: Float[Array, "r r"], *, what: str = "K̄") -> Float[Array, "r r"]:
    """The lower Cholesky factor of ``K``, computed on ``K``'s device.

    ``K``'s buffer is donated: do not read ``K`` afterwards.

    Args:
        K: (r, r) symmetric positive definite JAX array, float64.
        what: the matrix's name in the error message.

    Returns:
        The (r, r) lower factor ``L`` with ``L Lᵀ = K``, on the same device.

    Raises:
        NotPositiveDefiniteError: if the factorisation failed (JAX's device Cholesky returns
            NaN where it fails, on CPU and GPU the whole factor, so no pivot is named).
    """
    L = _cholesky(K)
    if not bool(jnp.all(jnp.isfinite(jnp.diagonal(L)))):
        raise NotPositiveDefiniteError(
            f"{what} ({L.shape[0]} rows) is not numerically positive definite: its Cholesky "
            "factorisation on the device failed. Increase the jitter / gradient noise, or "
            "check for duplicated inputs."
        )
    return L


@jax.jit
@highest
def _solve(L, Ybar):
    alpha = jax.scipy.linalg.cho_solve((L, True), Ybar)
    return alpha, jnp.sum(jnp.log(jnp.diagonal(L)))


@partial(jax.jit, donate_argnums=0)
def _inverse(L):
    eye = jnp.eye(L.shape[0], dtype=L.dtype)
    return jax.lax.linalg.triangular_solve(L, eye, left_side=True, lower=True)


def factor_solve(
    K: Float[Array, "r r"], Ybar: Float[Array, "r M"], *, inverse: bool, what: str = "K̄"
) -> tuple[np.ndarray, float, Float[Array, "r r"] | None]:
    """Factorise ``K = L Lᵀ`` and solve for ``α = K⁻¹ Ȳ``, all on ``K``'s device in float64.

    ``K``'s buffer is reused (donated) by the factor: do not read ``K`` afterwards.

    Args:
        K: (r, r) the Gram matrix ``K̄`` (noise included), a JAX array on its device.
        Ybar: (r, M) the stacked targets ``Ȳ``.
        inverse: whether to form ``L⁻¹`` as well (for the variance).
        what: the matrix's name in the error message.

    Returns:
        ``α`` (r, M) on the host, ``log det L`` as a float, and ``L⁻¹`` (r, r) left on the
        device with ``inverse``, else None.

    Raises:
        NotPositiveDefiniteError: if ``K`` is not numerically positive definite (from
            :func:`cholesky`).
    """
    L = cholesky(K, what=what)
    alpha, logdet = _solve(L, jnp.asarray(Ybar, L.dtype, device=_device_of(L)))
    alpha, logdet = np.asarray(alpha), float(logdet)
    Linv = _inverse(L) if inverse else None
    del L
    return alpha, logdet, Linv


def _device_of(a: jax.Array) -> jax.Device:
    return next(iter(a.devices()))
