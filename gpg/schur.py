"""Offline per-bin precompute: Schur complements through one global factorisation, the paper's
direct per-bin route, and the purely local (no Schur) variant.

For bin ``i`` with near rows ``n`` (a near point brings its value row and its gradient rows) and
far rows ``f``, the paper (Eqs. GPGSmean/GPGSvariance) predicts with the Schur complement
``S = K̄_nn − K̄_nf K̄_ff⁻¹ K̄_fn``:

* variance ``σ − k_qnᵀ S⁻¹ k_qn`` (exact when ``k_qf = 0``);
* mean, two forms (DESIGN pitfall 1): ``paper`` ``k_qnᵀ S⁻¹ Ȳ_n`` (Eq. GPGSmean), and
  ``exact`` ``k_qnᵀ α_n`` with the global ``α = K̄⁻¹ Ȳ``, which is what ``k_qf = 0`` really
  gives: ``α_n = S⁻¹(Ȳ_n − K̄_nf K̄_ff⁻¹ Ȳ_f)``, so the paper's form drops the far targets.

Routes to ``S⁻¹``:

* ``global`` (default): block inversion gives ``S⁻¹ = [K̄⁻¹]_nn``. With ``K̄ = L Lᵀ`` and
  ``W = L⁻¹`` (computed once, in place), ``[K̄⁻¹]_nn = W_nᵀ W_n`` for the columns ``W_n`` of the
  near rows; a QR factorisation ``W_n = Q R`` then gives a triangular factor with
  ``S⁻¹ = Rᵀ R`` without forming the Gram matrix (no squared condition number). One
  factorisation of ``K̄`` serves every bin.
* ``direct``: the paper's route, a Cholesky factorisation of ``K̄_ff`` per bin (ten large
  factorisations for ten bins); kept to check the global route.
* ``local`` (the no-Schur baselines ``gpgs``, ``gps_*``): an exact GP on the near set alone,
  ``K̄_nn⁻¹``; the far set is discarded.

Each route returns, per bin, mean coefficients ``c`` and a triangular factor
``F`` such that ``mean = k_qnᵀ c`` and ``var = σ − ‖F k_qn‖²``; the factor is stored, never the
dense inverse.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla

from gpg import linalg, memory
from gpg.gp import Hyper, assemble_gram
from gpg.partition import NearSets

ROUTES = ("global", "direct", "local")
MEAN_FORMS = ("exact", "paper")


@dataclass(frozen=True)
class BinFactors:
    """One bin, over its near rows (:func:`near_rows`, bin-local dimension-major order): mean
    coefficients ``coef`` (r, M) and variance factor ``factor`` (r, r), triangular (``lower`` or
    upper)."""

    coef: np.ndarray
    factor: np.ndarray
    lower: bool


def near_rows(near: np.ndarray, n_points: int, n_grad: int) -> np.ndarray:
    """Rows of ``K̄`` for near points ``near``: value rows, then each gradient dimension's rows."""
    return np.concatenate([near + k * n_points for k in range(1 + n_grad)])


def _check(mean: str, route: str) -> None:
    if mean not in MEAN_FORMS:
        raise ValueError(f"unknown mean form {mean!r}; valid: {list(MEAN_FORMS)}")
    if route not in ROUTES:
        raise ValueError(f"unknown precompute route {route!r}; valid: {list(ROUTES)}")


def precompute(
    X: np.ndarray,
    Ybar: np.ndarray,
    hyper: Hyper,
    grad_dims: Sequence[int],
    near: NearSets,
    *,
    route: str = "global",
    mean: str = "exact",
) -> list[BinFactors]:
    """Per-bin coefficients and variance factors by ``route`` (see module docstring).

    ``X`` are the (normalised) training inputs (N, D) and ``Ybar`` the stacked targets
    (N(1+G), M) in the layout of :mod:`gpg.kernels`. ``mean`` is ignored by ``local``.
    """
    _check(mean, route)
    dims = tuple(grad_dims)
    n, g = X.shape[0], len(dims)
    rows = [near_rows(nb, n, g) for nb in near.near]
    if route == "local":
        return [_local(X, Ybar, hyper, dims, nb, r) for nb, r in zip(near.near, rows, strict=True)]
    R = n * (1 + g)
    widest = max(r.size for r in rows)
    extra = 2 * R * widest * 8 if route == "global" else 2 * R * R * 8
    memory.require(f"the {route} Schur precompute over {R} rows", R * R * 8 + extra)
    K = assemble_gram(jnp.asarray(X), hyper, dims)
    if route == "direct":
        return [_direct(K, Ybar, r, mean) for r in rows]
    L = linalg.cholesky_inplace(K)
    alpha = linalg.cho_solve(L, Ybar)
    W = linalg.triangular_inverse_inplace(L)  # K̄⁻¹ = Wᵀ W; the factor's buffer is reused
    out = []
    for r in rows:
        # Rows above the first near row of a lower-triangular W are zero: skip them.
        Wn = W[r.min() :, r]
        R = _gram_factor(Wn)
        coef = alpha[r] if mean == "exact" else R.T @ (R @ Ybar[r])
        out.append(BinFactors(coef=coef, factor=R, lower=False))
    return out


def _gram_factor(Wn: np.ndarray) -> np.ndarray:
    """Upper-triangular ``R`` with ``RᵀR = W_nᵀ W_n``.

    The Cholesky factor of the Gram matrix (a tenth of the cost of a QR of ``W_n``); where
    rounding has made the Gram matrix indefinite, the QR factor instead, which never fails.
    """
    try:
        return np.ascontiguousarray(linalg.cholesky_inplace(linalg.gram_t(Wn), what="[K̄⁻¹]_nn").T)
    except linalg.NotPositiveDefiniteError:
        return np.ascontiguousarray(sla.qr(Wn, mode="r", check_finite=False)[0][: Wn.shape[1]])


def _direct(K: np.ndarray, Ybar: np.ndarray, r: np.ndarray, mean: str) -> BinFactors:
    far = np.setdiff1d(np.arange(K.shape[0]), r)
    K_nn = K[np.ix_(r, r)]
    if far.size:
        L_ff = linalg.cholesky_inplace(K[np.ix_(far, far)], what="K̄_ff")
        V = sla.solve_triangular(L_ff, K[np.ix_(far, r)], lower=True, check_finite=False)
        S = K_nn - linalg.gram_t(V)
        target = Ybar[r]
        if mean == "exact":  # Ȳ_n − K̄_nf K̄_ff⁻¹ Ȳ_f; the paper's form keeps Ȳ_n
            u = sla.solve_triangular(L_ff, Ybar[far], lower=True, check_finite=False)
            target = target - V.T @ u
    else:
        S, target = K_nn, Ybar[r]
    L_S = linalg.cholesky_inplace(np.ascontiguousarray(S), what="Schur complement S")
    coef = linalg.cho_solve(L_S, target)
    return BinFactors(coef=coef, factor=linalg.triangular_inverse_inplace(L_S), lower=True)


def _local(X, Ybar, hyper, dims, nb: np.ndarray, r: np.ndarray) -> BinFactors:
    L = linalg.cholesky_inplace(assemble_gram(jnp.asarray(X[nb]), hyper, dims), what="K̄_nn")
    coef = linalg.cho_solve(L, Ybar[r])
    return BinFactors(coef=coef, factor=linalg.triangular_inverse_inplace(L), lower=True)
