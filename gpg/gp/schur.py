"""Offline per-bin precompute: Schur complements through one global factorisation, the paper's
direct per-bin route, and the purely local (no Schur) variant.

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
* ``local`` (the no-Schur baselines ``gpgs``, ``gps_*``): an exact GP on the near set alone,
  ``K̄_nn⁻¹``; the far set is discarded. It never forms ``K̄``, and with ``devices`` its bins
  are spread over JAX devices (:func:`local_sharded`).

Each route returns, per bin, mean coefficients ``c`` and a triangular factor
``F`` such that ``mean = k_qnᵀ c`` and ``var = σ − ‖F k_qn‖²``; the factor is stored, never the
dense inverse.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import scipy.linalg as sla

from gpg import parallel
from gpg.gp import kernels
from gpg.gp.gram import assemble_gram
from gpg.gp.hyper import Hyper
from gpg.gp.partition import NearSets, Partition, far_correlation
from gpg.linalg import dense, memory

ROUTES = ("global", "direct", "local")
MEAN_FORMS = ("exact", "paper")
# Median largest query-to-far correlation above which the k_qf ≈ 0 assumption is called
# violated. Where the Schur correction was measured to help (README, +experiment=schur_regime)
# the median was 0.12; where it failed, 0.77.
KQF_WARN = 0.1
FAR = 1e3  # padding position: its kernel with any query in [-1, 1]^D underflows to 0


class SchurAssumptionWarning(UserWarning):
    """The far set is not far: the Schur forms' ``k_qf ≈ 0`` does not hold on the data."""


def diagnose(
    X: np.ndarray,
    partition: Partition,
    near: NearSets,
    lengthscale,
    *,
    name: str = "gpgs_schur",
    threshold: float = KQF_WARN,
) -> dict[str, Any]:
    """Measure the Schur assumption ``k_qf ≈ 0`` on the training inputs and warn when it fails.

    Returns the near-set ε per bin and the distribution (median, p90, max) of each training
    input's largest correlation with its bin's far set (:func:`gpg.gp.partition.far_correlation`);
    ``kqf_violated`` is True, with one :class:`SchurAssumptionWarning`, when the median
    exceeds ``threshold``.
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


@dataclass(frozen=True)
class BinFactors:
    """One bin, over its near rows (:func:`near_rows`, bin-local dimension-major order): mean
    coefficients ``coef`` (r, M) and variance factor ``factor`` (r, r), triangular (``lower`` or
    upper). An upper factor may be dense in its first ``dense_rows`` rows (PIC's inducing
    block, :mod:`gpg.gp.pic`); below them it is triangular."""

    coef: np.ndarray
    factor: np.ndarray
    lower: bool
    dense_rows: int = 0
    # ``Ȳ_bᵀ K_b⁻¹ Ȳ_b`` (M,) over the bin's own rows and their number: pooled over bins they
    # give the per-output signal scale (:func:`gpg.gp.mean.output_scale`).
    yty: np.ndarray | None = None
    n_rows: int = 0


def near_rows(near: np.ndarray, n_points: int, n_grad: int) -> np.ndarray:
    """Rows of ``K̄`` for near points ``near``: value rows, then each gradient dimension's rows."""
    return np.concatenate([near + k * n_points for k in range(1 + n_grad)])


def check_options(mean: str, route: str) -> None:
    """``ValueError`` for an unknown mean form or precompute route."""
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
    devices=None,
) -> list[BinFactors]:
    """Per-bin coefficients and variance factors by ``route`` (see module docstring).

    ``X`` are the (normalised) training inputs (N, D) and ``Ybar`` the stacked targets
    (N(1+G), M) in the layout of :mod:`gpg.gp.kernels`. ``mean`` is ignored by ``local``.
    ``devices`` (``local`` only; a mesh, a device count or list, see :mod:`gpg.parallel`)
    spreads the bins over JAX devices; None keeps the single-process LAPACK path.
    """
    check_options(mean, route)
    dims = tuple(grad_dims)
    n, g = X.shape[0], len(dims)
    rows = [near_rows(nb, n, g) for nb in near.near]
    if route == "local":
        if devices is not None:
            return local_sharded(X, Ybar, hyper, dims, near.near, parallel.devices(devices))
        return [_local(X, Ybar, hyper, dims, nb, r) for nb, r in zip(near.near, rows, strict=True)]
    if devices is not None:
        raise ValueError(f"devices applies to the local route only, not {route!r}")
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
        out.append(BinFactors(coef, R, False, yty=_yty(Ybar[r], coef), n_rows=r.size))
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
    return BinFactors(coef, inv, True, yty=_yty(Ybar[r], coef), n_rows=r.size)


def _local(X, Ybar, hyper, dims, nb: np.ndarray, r: np.ndarray) -> BinFactors:
    L = dense.cholesky_inplace(assemble_gram(jnp.asarray(X[nb]), hyper, dims), what="K̄_nn")
    coef = dense.cho_solve(L, Ybar[r])
    inv = dense.triangular_inverse_inplace(L)
    return BinFactors(coef, inv, True, yty=_yty(Ybar[r], coef), n_rows=r.size)


def local_sharded(
    X: np.ndarray,
    Ybar: np.ndarray,
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    near: Sequence[np.ndarray],
    devs: Sequence[jax.Device],
) -> list[BinFactors]:
    """The ``local`` route in JAX, the bins spread over the devices ``devs``
    (:func:`gpg.parallel.map_units`).

    Every bin's near set is padded to the largest one with far-away points (their kernel with
    the real points underflows to zero, so the padded ``K̄_nn`` is block diagonal and its
    Cholesky factor restricted to the real rows is the real one). Each device factorises one
    bin at a time with the same program, so the result is the same, bit for bit, for any number
    of devices. Peak memory: one padded ``K̄_nn`` and its inverse factor per device.
    """
    n, d = X.shape
    g = len(grad_dims)
    width = max(nb.size for nb in near)
    units, pos = [], []
    for nb in near:
        Xp = np.full((width, d), FAR)
        Xp[: nb.size] = X[nb]
        pos.append(near_rows(np.arange(nb.size), width, g))
        Yp = np.zeros((width * (1 + g), Ybar.shape[1]))
        Yp[pos[-1]] = Ybar[near_rows(nb, n, g)]
        units.append((Xp, Yp))
    fn = jax.jit(partial(_local_block, dims=grad_dims))
    results = parallel.map_units(fn, hyper, units, devs)
    out = []
    for b, ((coef, inv), r) in enumerate(zip(results, pos, strict=True)):
        if not (np.isfinite(coef).all() and np.isfinite(inv).all()):
            raise dense.NotPositiveDefiniteError(f"K̄_nn of bin {b} is not positive definite")
        c = coef[r]
        out.append(
            BinFactors(
                c,
                np.ascontiguousarray(inv[np.ix_(r, r)]),
                True,
                yty=_yty(Ybar[near_rows(near[b], n, g)], c),
                n_rows=r.size,
            )
        )
    return out


def _local_block(h: Hyper, Xb, Yb, *, dims: tuple[int, ...]):
    """One (padded) bin: coefficients ``K̄_nn⁻¹ Ȳ_n`` and the lower factor ``L⁻¹``."""
    K = kernels.gram(Xb, Xb, h.variance, h.lengthscale, dims, dims)
    K = K + jnp.diag(h.noise_diagonal(Xb.shape[0], len(dims)))
    L = jnp.linalg.cholesky(K)
    coef = jsl.cho_solve((L, True), Yb)
    return coef, jsl.solve_triangular(L, jnp.eye(K.shape[0], dtype=K.dtype), lower=True)


def _yty(Ybar: np.ndarray, coef: np.ndarray) -> np.ndarray:
    return np.sum(Ybar * coef, axis=0)
