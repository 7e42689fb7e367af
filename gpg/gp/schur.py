"""The paper's Schur correction: per-bin Schur complements through one global factorisation or
the paper's direct per-bin route, and the build-time check of its ``k_qf ≈ 0`` assumption.

For bin ``i`` with near rows ``n`` (a near point brings its value row and its gradient rows) and
far rows ``f``, the paper (Eqs. GPGSmean/GPGSvariance) predicts with the Schur complement
``S = K̄_nn − K̄_nf K̄_ff⁻¹ K̄_fn``:

* variance ``σ − k_qnᵀ S⁻¹ k_qn`` (exact when ``k_qf = 0``);
* mean, two forms (docs/design.md, pitfall 1): ``paper`` ``k_qnᵀ S⁻¹ Ȳ_n`` (Eq. GPGSmean), and
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

Dropping the far set instead (no Schur correction) is :mod:`gpg.gp.local`.

Each route returns, per bin, mean coefficients ``c`` and a triangular factor
``F`` such that ``mean = k_qnᵀ c`` and ``var = σ − ‖F k_qn‖²``; the factor is stored, never the
dense inverse.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla
from jaxtyping import ArrayLike, Float

from gpg.gp.binned import BinFactors, bin_yty, near_rows
from gpg.gp.gram import assemble_gram
from gpg.gp.hyper import Hyper
from gpg.gp.partition import NearSets, Partition, far_correlation
from gpg.linalg import dense, memory

__all__ = [
    "SchurAssumptionWarning",
    "check_options",
    "diagnose",
    "precompute",
]

ROUTES = ("global", "direct")
MEAN_FORMS = ("exact", "paper")
# Median largest query-to-far correlation above which the k_qf ≈ 0 assumption is called
# violated: the measured medians where the correction helped and where it failed are in
# docs/results (schur_regime); this threshold lies between them.
KQF_WARN = 0.1


class SchurAssumptionWarning(UserWarning):
    """The far set is not far: the Schur forms' ``k_qf ≈ 0`` does not hold on the data."""


def diagnose(
    X: np.ndarray,
    partition: Partition,
    near: NearSets,
    lengthscale: Float[ArrayLike, "*L"],
    *,
    name: str = "gpgs_schur",
    threshold: float = KQF_WARN,
) -> dict[str, Any]:
    """Measure the Schur assumption ``k_qf ≈ 0`` on the training inputs and warn when it fails.

    Each training input, as a query in its own bin, gets its largest correlation with the
    bin's far set (:func:`gpg.gp.partition.far_correlation`). What the correction drops is
    amplified by ``S⁻¹``, so a violated assumption makes the Schur model much worse than
    dropping the far set (``gpgs``).

    Args:
        X: (N, D) normalised training inputs.
        partition: the bins (not read: the near sets carry each bin's anchors).
        near: the near sets (:func:`gpg.gp.partition.near_sets`).
        lengthscale: the kernel lengthscale l.
        name: the model named in the warning.
        threshold: the median correlation above which the assumption counts as violated.

    Returns:
        ``near_epsilon`` (per bin), ``far_correlation_median``, ``far_correlation_p90``,
        ``far_correlation_max``, ``kqf_threshold`` and ``kqf_violated``, True (with one
        :class:`SchurAssumptionWarning`) when the median exceeds ``threshold``.
    """
    corr = far_correlation(X, near, lengthscale)
    med = float(np.median(corr))
    out = {
        "near_epsilon": near.epsilon.tolist(),
        "far_correlation_median": med,
        "far_correlation_p90": float(np.percentile(corr, 90)),
        "far_correlation_max": float(corr.max()),
        "kqf_threshold": threshold,
        "kqf_violated": med > threshold,
    }
    if out["kqf_violated"]:
        warnings.warn(
            f"{name}: the Schur correction assumes the far set is uncorrelated with the "
            f"queries (k_qf ≈ 0), but on the training inputs the median query's most "
            f"correlated far point has correlation {med:.2f} (90 % below "
            f"{out['far_correlation_p90']:.2f}; threshold {threshold}). What the correction "
            "drops is then not small, and it is amplified by S⁻¹: expect this model to be "
            "much worse than dropping the far set (gpgs). Shorter lengthscales or larger "
            "near sets make the far set far.",
            SchurAssumptionWarning,
            stacklevel=3,
        )
    return out


def check_options(mean: str, route: str) -> None:
    """Check a mean form and a precompute route of the Schur correction.

    Dropping the far set is not a route of the Schur correction but another model
    (:mod:`gpg.gp.local`, ``gpgs``): asking for route ``local`` says so.

    Args:
        mean: the mean form, ``exact`` or ``paper`` (module docstring).
        route: the route to ``S⁻¹``, ``global`` or ``direct``.

    Raises:
        ValueError: for an unknown mean form or route, listing the valid ones.
    """
    if mean not in MEAN_FORMS:
        raise ValueError(f"unknown mean form {mean!r}; valid: {list(MEAN_FORMS)}")
    if route not in ROUTES:
        hint = " (no Schur correction is gpg.gp.local, the model gpgs)" if route == "local" else ""
        raise ValueError(f"unknown precompute route {route!r}; valid: {list(ROUTES)}{hint}")


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

    The memory the route needs (``K̄`` and its working arrays) is checked before ``K̄`` is
    formed (:func:`gpg.linalg.memory.require`).

    Args:
        X: (N, D) the normalised training inputs.
        Ybar: (N(1+G), M) the stacked targets ``Ȳ`` (layout of :mod:`gpg.gp.kernels`).
        hyper: σ, l, ν², λ_i², as fitted.
        grad_dims: the inputs with gradient rows.
        near: the near sets; their complements are the far sets.
        route: ``global`` (one factorisation of ``K̄`` for every bin) or ``direct`` (the
            paper's, one factorisation of ``K̄_ff`` per bin).
        mean: ``exact`` (``k_qnᵀ α_n``) or ``paper`` (``k_qnᵀ S⁻¹ Ȳ_n``, Eq. GPGSmean).

    Returns:
        One :class:`gpg.gp.binned.BinFactors` per bin: upper factors from the global route,
        lower ones from the direct route.

    Raises:
        ValueError: for an unknown ``mean`` or ``route`` (:func:`check_options`).
        gpg.linalg.memory.InsufficientMemory: if ``K̄`` and the route's working arrays do
            not fit the memory available.
        gpg.linalg.dense.NotPositiveDefiniteError: if ``K̄`` (global route) or a bin's
            ``K̄_ff`` or ``S`` (direct route) is not positive definite.
    """
    check_options(mean, route)
    dims = tuple(grad_dims)
    n, g = X.shape[0], len(dims)
    rows = [near_rows(nb, n, g) for nb in near.near]
    R = n * (1 + g)
    widest = max(r.size for r in rows)
    extra = 2 * R * widest * 8 if route == "global" else 2 * R * R * 8
    memory.require(f"the {route} Schur precompute over {R} rows", R * R * 8 + extra)
    K = assemble_gram(jnp.asarray(X), hyper, dims)
    if route == "direct":
        return [_direct(K, Ybar, r, mean) for r in rows]
    L = dense.cholesky_inplace(K)
    alpha = dense.cho_solve(L, Ybar)
    W = dense.triangular_inverse_inplace(L)  # K̄⁻¹ = Wᵀ W; the factor's buffer is reused
    out = []
    for r in rows:
        # Rows above the first near row of a lower-triangular W are zero: skip them.
        Wn = W[r.min() :, r]
        R = _gram_factor(Wn)
        coef = alpha[r] if mean == "exact" else R.T @ (R @ Ybar[r])
        out.append(BinFactors(coef, R, False, yty=bin_yty(Ybar[r], coef), n_rows=r.size))
    return out


def _gram_factor(Wn: np.ndarray) -> np.ndarray:
    """Upper-triangular ``R`` with ``RᵀR = W_nᵀ W_n``.

    The Cholesky factor of the Gram matrix (a tenth of the cost of a QR of ``W_n``); where
    rounding has made the Gram matrix indefinite, the QR factor instead, which never fails.
    """
    try:
        return np.ascontiguousarray(dense.cholesky_inplace(dense.gram_t(Wn), what="[K̄⁻¹]_nn").T)
    except dense.NotPositiveDefiniteError:
        return np.ascontiguousarray(sla.qr(Wn, mode="r", check_finite=False)[0][: Wn.shape[1]])


def _direct(K: np.ndarray, Ybar: np.ndarray, r: np.ndarray, mean: str) -> BinFactors:
    far = np.setdiff1d(np.arange(K.shape[0]), r)
    K_nn = K[np.ix_(r, r)]
    if far.size:
        L_ff = dense.cholesky_inplace(K[np.ix_(far, far)], what="K̄_ff")
        V = sla.solve_triangular(L_ff, K[np.ix_(far, r)], lower=True, check_finite=False)
        S = K_nn - dense.gram_t(V)
        target = Ybar[r]
        if mean == "exact":  # Ȳ_n − K̄_nf K̄_ff⁻¹ Ȳ_f; the paper's form keeps Ȳ_n
            u = sla.solve_triangular(L_ff, Ybar[far], lower=True, check_finite=False)
            target = target - V.T @ u
    else:
        S, target = K_nn, Ybar[r]
    L_S = dense.cholesky_inplace(np.ascontiguousarray(S), what="Schur complement S")
    coef = dense.cho_solve(L_S, target)
    inv = dense.triangular_inverse_inplace(L_S)
    return BinFactors(coef, inv, True, yty=bin_yty(Ybar[r], coef), n_rows=r.size)
