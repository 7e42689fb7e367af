"""The local precompute: an exact GP on each bin's near set alone, the far set dropped.

Used by the no-Schur baselines (``gps_1x``, ``gps_8x``, ``gpgs``) and by the hybrid's variance.
Bin ``b`` with near points ``n`` gets mean coefficients ``c = K̄_nn⁻¹ Ȳ_n`` and the lower
factor ``F = L⁻¹`` of ``K̄_nn = L Lᵀ``, so that ``var = σ − ‖F k_qn‖²``
(:class:`gpg.gp.binned.BinFactors`). It never forms ``K̄``.

Two executions of the one formula: on the host, one LAPACK factorisation per bin at its own
size (:func:`gpg.linalg.dense.cholesky_inplace`); with ``devices``, the bins padded to one
width (:func:`gpg.gp.binned.pad_units`) and spread over JAX devices by
:func:`gpg.parallel.map_units`, the same compiled program for every bin. Both start from the
same ``K̄_nn`` plus noise (:func:`gpg.gp.gram.assemble_gram` on the host,
:func:`gpg.gp.gram.noisy_gram` traced) and agree to rounding (tests/test_parallel.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float

from gpg import parallel
from gpg.gp.binned import BinFactors, bin_yty, near_rows, pad_units
from gpg.gp.gram import assemble_gram, mask_gram_inplace, noisy_gram
from gpg.gp.hyper import Hyper
from gpg.gp.partition import NearSets
from gpg.linalg import dense

__all__ = [
    "precompute",
]


def precompute(
    X: Float[np.ndarray, "N D"],
    Ybar: Float[np.ndarray, "R M"],
    hyper: Hyper,
    grad_dims: Sequence[int],
    near: NearSets,
    *,
    devices: parallel.Devices = None,
    rows: np.ndarray | None = None,
    bins: Sequence[int] | None = None,
    bases: np.ndarray | None = None,
) -> list[BinFactors]:
    """Per-bin coefficients and factors of the local GPs over ``near.near``.

    Bin ``b`` gets ``c = K̄_nn⁻¹ Ȳ_n`` and the lower factor ``F = L⁻¹`` of ``K̄_nn = L Lᵀ``
    (module docstring); the far set is dropped, not corrected for.

    Args:
        X: (N, D) normalised training inputs.
        Ybar: (N(1+G), M) stacked targets ``Ȳ`` in the layout of :mod:`gpg.gp.kernels`.
        hyper: the hyperparameters (σ, l, ν², λ_i²).
        grad_dims: the input dimensions that carry gradient rows.
        near: the near sets (:func:`gpg.gp.partition.near_sets`).
        devices: a device count or a list of devices (:func:`gpg.parallel.devices`) to spread
            the bins over, the same compiled program for every bin; None keeps the host path.
        rows: (R,) the observed rows (:func:`gpg.gp.gram.observed_rows`; host path only), None
            for all.
        bins: restrict the work to these bins (the others are not returned).
        bases: (N, G, G) the directions of the gradient rows (host path only,
            :func:`gpg.gp.gram.row_directions`).

    Returns:
        One :class:`gpg.gp.binned.BinFactors` per bin (of ``bins``, in that order), with the
        bin's share of the output scale.

    Raises:
        ValueError: if ``rows`` or ``bases`` is given with ``devices``.
        gpg.linalg.dense.NotPositiveDefiniteError: if a bin's ``K̄_nn`` is not positive
            definite.
    """
    dims = tuple(grad_dims)
    chosen = near.near if bins is None else [near.near[b] for b in bins]
    if devices is not None:
        if rows is not None or bases is not None:
            raise ValueError(
                "cases without some gradients, or with directional ones, are built on the "
                "host: devices=None"
            )
        return _sharded(X, Ybar, hyper, dims, chosen, parallel.devices(devices))
    n, g = X.shape[0], len(dims)
    return [_host(X, Ybar, hyper, dims, nb, near_rows(nb, n, g), rows, bases) for nb in chosen]


def _host(X, Ybar, hyper, dims, nb: np.ndarray, r: np.ndarray, rows=None, bases=None):
    seen = None if rows is None else rows[r]
    sub = None if bases is None else bases[nb]
    gram = mask_gram_inplace(assemble_gram(X[nb], hyper, dims, bases=sub), seen)
    L = dense.cholesky_inplace(gram, what="K̄_nn")
    coef = dense.cho_solve(L, Ybar[r])
    inv = dense.triangular_inverse_inplace(L)
    if seen is not None:
        inv[:, ~seen] = 0.0
    n_rows = r.size if seen is None else int(seen.sum())
    return BinFactors(coef, inv, True, yty=bin_yty(Ybar[r], coef), n_rows=n_rows)


def _sharded(X, Ybar, hyper, dims, near: Sequence[np.ndarray], devs) -> list[BinFactors]:
    """Peak memory: one padded ``K̄_nn`` and its inverse factor per device."""
    n, g = X.shape[0], len(dims)
    units, pos = pad_units(X, Ybar, near, g)
    results = parallel.map_units(partial(_block_jit, dims=tuple(dims)), hyper, units, devs)
    out = []
    for b, ((coef, inv), r) in enumerate(zip(results, pos, strict=True)):
        if not (np.isfinite(coef).all() and np.isfinite(inv).all()):
            raise dense.NotPositiveDefiniteError(f"K̄_nn of bin {b} is not positive definite")
        c = coef[r]
        yty = bin_yty(Ybar[near_rows(near[b], n, g)], c)
        inv_r = np.ascontiguousarray(inv[np.ix_(r, r)])
        out.append(BinFactors(c, inv_r, True, yty=yty, n_rows=r.size))
    return out


def _block(h: Hyper, Xb: Array, Yb: Array, *, dims: tuple[int, ...]):
    """One (padded) bin: coefficients ``K̄_nn⁻¹ Ȳ_n`` and the lower factor ``L⁻¹``."""
    L = jnp.linalg.cholesky(noisy_gram(Xb, h, dims))
    coef = jsl.cho_solve((L, True), Yb)
    return coef, jsl.solve_triangular(L, jnp.eye(L.shape[0], dtype=L.dtype), lower=True)


# jitted once at module level (static "dims"): calls of one shape share the program
_block_jit = jax.jit(_block, static_argnames="dims")
