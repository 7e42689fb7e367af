"""PIC: partially independent conditional GP-G with gradient inducing points (``gpg_pic``).

Snelson and Ghahramani's PIC approximation (2007), with value *and* gradient rows. The training
rows are split into blocks ``b`` (the bins); ``U`` inducing inputs ``Z`` each carry value rows
and the gradient rows of the chosen dims (``U' = U(1+G)`` rows ``u``). The prior covariance is
replaced by ``K̃ = Q + blkdiag_b(K̄_bb − Q_bb)`` with ``Q = K̄_fu K̄_uu⁻¹ K̄_uf``: exact within a
block, low rank through ``u`` between blocks, and a query in bin ``b`` belongs to block ``b``.
So each bin keeps an exact GP-G block, and the far field enters through the inducing points
instead of being dropped (``gpgs``) or amplified (the Schur forms).

Training never forms ``K̄`` (time O(N'·U'²) plus the blocks, memory O(block² + block·U')):
with ``K̄_uu = L_u L_uᵀ``, ``V_b = L_u⁻¹ K̄_ub``, ``Λ_b = K̄_bb + Σ_b − V_bᵀ V_b`` (``Σ_b`` the
noise ``ν²``/``λ²``), the Woodbury identity gives everything from the ``U' × U'`` matrix
``B = I + Σ_b V_b Λ_b⁻¹ V_bᵀ`` and ``r̂ = Σ_b V_b Λ_b⁻¹ Ȳ_b``, accumulated bin by bin (pass 1).
Pass 2, again bin by bin: with ``β = B⁻¹ r̂`` and ``w_b = Λ_b⁻¹ (Ȳ_b − V_bᵀ β)``,

* mean ``μ(x_q) = k_uᵀ c_b + k_bᵀ w_b`` with ``c_b = L_u⁻ᵀ (β − V_b w_b)``;
* variance ``σ − q_b`` with, for ``k̂ = L_u⁻¹ k_u``, ``d = k_b − V_bᵀ k̂``,
  ``ê = V_b Λ_b⁻¹ d``:  ``q_b = ‖k̂‖² + dᵀ Λ_b⁻¹ d − (k̂ − ê)ᵀ B⁻¹ (k̂ − ê)``,

a quadratic form in ``[k_u; k_b]`` stored as a factor ``F_b`` (``q_b = ‖F_b [k_u; k_b]‖²``)
that is block upper triangular: a dense leading ``U' × U'`` block, then triangular.
With one block (or every point inducing), PIC is the exact GP-G.

Both passes are per block: with ``devices`` (:func:`iter_precompute_devices`) the blocks are
spread over JAX devices (:mod:`gpg.parallel`), the pass-1 sums are taken on the host in block
order, and the result is the same, bit for bit, for any number of devices.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from functools import partial

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import scipy.linalg as sla
from jaxtyping import ArrayLike, Float

from gpg import parallel
from gpg.gp import kernels
from gpg.gp.binned import BinFactors, near_rows, pad_units
from gpg.gp.gram import assemble_gram, noisy_gram
from gpg.gp.hyper import Hyper
from gpg.linalg import dense

__all__ = [
    "inducing_inputs",
    "iter_precompute",
    "iter_precompute_devices",
    "precompute",
]


def inducing_inputs(X: Float[ArrayLike, "N D"], n: int, *, seed: int = 0) -> np.ndarray:
    """``n`` inducing inputs by k-means (k-means++ start) on the training inputs ``X``.

    An empty cluster would keep a stale centre that duplicates another: each duplicate is
    replaced by an unused training input, so the inducing inputs are distinct.

    Args:
        X: (N, D) training inputs.
        n: the number of inducing inputs, in ``[1, N]``; all N points when ``n == N``.
        seed: seed of the k-means start and of the replacements.

    Returns:
        The (n, D) inducing inputs.

    Raises:
        ValueError: if ``n`` is not a positive integer or exceeds N.
    """
    from scipy.cluster.vq import kmeans2

    X = np.asarray(X, dtype=float)
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"the number of inducing points must be a positive integer, got {n!r}")
    if n > X.shape[0]:
        raise ValueError(
            f"{n} inducing points are more inducing points than the {X.shape[0]} training points"
        )
    if n == X.shape[0]:
        return X.copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an empty cluster is handled below
        centres, labels = kmeans2(X, int(n), seed=seed, minit="++", iter=20)
    # An empty cluster keeps a stale centre; replace any duplicate by an unused training input.
    _, first = np.unique(np.round(centres, 12), axis=0, return_index=True)
    if first.size < n:
        used = set(first.tolist())
        spare = (i for i in np.random.default_rng(seed).permutation(X.shape[0]))
        for j in range(n):
            if j not in used:
                centres[j] = X[next(spare)]
    return centres


def _gram(A, B, hyper: Hyper, dims) -> np.ndarray:
    """A writeable NumPy copy of ``K̄(A, B)``."""
    return np.array(
        kernels.gram(jnp.asarray(A), jnp.asarray(B), hyper.variance, hyper.lengthscale, dims, dims)
    )


def _tri(L, B, trans: bool = False):
    return dense.solve_lower(L, B, trans=trans)


class _Block:
    """One block's ``V_b = L_u⁻¹ K̄_ub`` and the Cholesky factor of ``Λ_b``."""

    def __init__(self, X, rows_b, idx, Z, L_u, hyper, dims):
        Xb = X[idx]
        self.rows = rows_b
        self.V = _tri(L_u, _gram(Z, Xb, hyper, dims))
        lam = assemble_gram(jnp.asarray(Xb), hyper, dims)
        lam -= dense.gram_t(self.V)
        self.L = dense.cholesky_inplace(lam, what="the PIC block Λ_b")
        # W_b = L_b⁻¹ V_bᵀ: V_b Λ_b⁻¹ V_bᵀ = W_bᵀ W_b
        self.W = _tri(self.L, np.ascontiguousarray(self.V.T))


def _inducing_factor(n, blocks, Z, hyper: Hyper, dims, jitter: float) -> np.ndarray:
    """``L_u`` with ``K̄_uu (1 + jitter on the diagonal) = L_u L_uᵀ``, after checking that
    ``blocks`` partition ``range(n)``."""
    idx_all = np.sort(np.concatenate(blocks))
    if idx_all.size != n or np.any(idx_all != np.arange(n)):
        raise ValueError("blocks must partition the training points (each in exactly one)")
    Kuu = _gram(Z, Z, hyper, dims)
    Kuu.flat[:: Kuu.shape[0] + 1] *= 1.0 + jitter
    return dense.cholesky_inplace(np.ascontiguousarray(Kuu), what="K̄_uu (inducing points)")


def precompute(
    X: np.ndarray,
    Ybar: np.ndarray,
    hyper: Hyper,
    grad_dims: Sequence[int],
    blocks: Sequence[np.ndarray],
    Z: np.ndarray,
    *,
    jitter: float = 1e-6,
) -> list[BinFactors]:
    """:func:`iter_precompute` as a list (every block's dense factor held at once).

    Args:
        X: the (N, D) training inputs, normalised.
        Ybar: the targets ``Ȳ``, (N(1+G), M), value rows then gradient rows.
        hyper: σ, l, ν² and λ_i².
        grad_dims: which inputs have gradient rows.
        blocks: per bin, its training indices (each point in exactly one block).
        Z: the (U, D) inducing inputs.
        jitter: the relative jitter on ``K̄_uu``'s diagonal.

    Returns:
        One :class:`gpg.gp.binned.BinFactors` per block, in block order.

    Raises:
        ValueError: if ``blocks`` do not partition the training points.
    """
    return list(iter_precompute(X, Ybar, hyper, grad_dims, blocks, Z, jitter=jitter))


def iter_precompute(
    X: np.ndarray,
    Ybar: np.ndarray,
    hyper: Hyper,
    grad_dims: Sequence[int],
    blocks: Sequence[np.ndarray],
    Z: np.ndarray,
    *,
    jitter: float = 1e-6,
) -> Iterator[BinFactors]:
    """Per-block mean coefficients and variance factors of PIC (see the module docstring).

    Yielded block by block so that a consumer can store each one compactly before the next is
    computed: the dense factors of all blocks together would dominate the peak memory. Two
    passes over the blocks (the inducing system first), on the host.

    Args:
        X: (N, D) normalised training inputs.
        Ybar: (N(1+G), M) stacked targets ``Ȳ`` in the layout of :mod:`gpg.gp.kernels`.
        hyper: the hyperparameters (σ, l, ν², λ_i²).
        grad_dims: the input dimensions that carry gradient rows.
        blocks: the training indices of each bin, a partition of ``range(N)``.
        Z: (U, D) inducing inputs (:func:`inducing_inputs`).
        jitter: added to ``K̄_uu``'s diagonal, relative to it (inducing values are
            noise-free).

    Yields:
        Per block, a :class:`gpg.gp.binned.BinFactors` over the rows ``[u; b]``: the inducing
        rows (dimension-major over ``Z``), then the block's rows (dimension-major over its
        points); its ``factor`` is block upper triangular (dense over the first ``U'`` rows).

    Raises:
        ValueError: if ``blocks`` do not partition the training points (when the first block
            is drawn).
    """
    dims = tuple(grad_dims)
    n, g = X.shape[0], len(dims)
    L_u = _inducing_factor(n, blocks, Z, hyper, dims, jitter)
    up = L_u.shape[0]
    m = Ybar.shape[1]

    # Pass 1: B = I + Σ W_bᵀ W_b and r̂ = Σ W_bᵀ L_b⁻¹ Ȳ_b, one block at a time.
    Bm = np.eye(up)
    rhat = np.zeros((up, m))
    for idx in blocks:
        rows = near_rows(idx, n, g)
        blk = _Block(X, rows, idx, Z, L_u, hyper, dims)
        Bm += dense.gram_t(blk.W)
        rhat += blk.W.T @ _tri(blk.L, Ybar[rows])
        del blk
    L_B = dense.cholesky_inplace(Bm, what="the PIC inducing system B")
    beta = dense.cho_solve(L_B, rhat)

    # Pass 2: each block's coefficients and factor, recomputing its (cheap) block quantities.
    for idx in blocks:
        rows = near_rows(idx, n, g)
        blk = _Block(X, rows, idx, Z, L_u, hyper, dims)
        w = dense.cho_solve(blk.L, Ybar[rows] - blk.V.T @ beta)
        c_u = _tri(L_u, beta - blk.V @ w, trans=True)
        nb = rows.size
        # Whitened coordinates z = [k̂; k_b]: q = zᵀ H̃ z with
        # H̃ = blkdiag(I, 0) + G_dᵀ G_d − G_eᵀ G_e, G_d = L_b⁻¹ [−V_bᵀ, I],
        # G_e = L_B⁻¹ [I + V_b Λ_b⁻¹ V_bᵀ, −V_b Λ_b⁻¹].
        Linv_b = dense.triangular_inverse_inplace(blk.L)  # L_b⁻¹ (nb, nb), L_b is done
        G_d = np.concatenate([-blk.W, Linv_b], axis=1)
        H = dense.gram_t(G_d)
        del G_d
        Vlam = blk.W.T @ Linv_b  # V_b Λ_b⁻¹ = W_bᵀ L_b⁻¹  (U', nb)
        G_e = _tri(L_B, np.concatenate([np.eye(up) + blk.W.T @ blk.W, -Vlam], axis=1))
        del blk, Linv_b, Vlam
        H -= dense.gram_t(G_e)
        del G_e
        H[np.arange(up), np.arange(up)] += 1.0
        R = _upper_factor(H)
        del H
        # Back to raw coordinates [k_u; k_b]: F = R̃ blkdiag(L_u⁻¹, I), block upper triangular.
        R[:, :up] = _tri(L_u, R[:, :up].T, trans=True).T  # R[:, :up] L_u⁻¹
        coef = np.concatenate([c_u, w], axis=0)
        yty = np.sum(Ybar[rows] * w, axis=0)  # Σ_b Ȳ_bᵀ w_b = Ȳᵀ (K̃ + Σ)⁻¹ Ȳ
        yield BinFactors(coef, R, False, dense_rows=up, yty=yty, n_rows=nb)


def iter_precompute_devices(
    X: np.ndarray,
    Ybar: np.ndarray,
    hyper: Hyper,
    grad_dims: Sequence[int],
    blocks: Sequence[np.ndarray],
    Z: np.ndarray,
    *,
    jitter: float = 1e-6,
    devices: parallel.Devices = None,
) -> Iterator[BinFactors]:
    """:func:`iter_precompute` in JAX with the blocks spread over devices, one per device at
    a time.

    Blocks are padded to the largest with far-away points, whose rows decouple from every
    other row (zero kernel), so each padded quantity restricted to the real rows is the real
    one. The pass-1 sums are taken on the host in block order: equal to
    :func:`iter_precompute` up to rounding, bit-identical for any number of devices. Memory: a
    few padded blocks per device, as the host path.

    Args:
        X: (N, D) normalised training inputs, padded per block on the host.
        Ybar: (N(1+G), M) stacked targets ``Ȳ``, padded with the inputs.
        hyper: the hyperparameters (σ, l, ν², λ_i²), shared by every device.
        grad_dims: the input dimensions that carry gradient rows.
        blocks: the training indices of each bin, a partition of ``range(N)``: the units of
            work.
        Z: (U, D) inducing inputs, shared by every device.
        jitter: added to ``K̄_uu``'s diagonal, relative to it (``K̄_uu`` is factored on the
            host).
        devices: a device count or a list of devices (:func:`gpg.parallel.devices`); None, the
            first device.

    Yields:
        Per block, its :class:`gpg.gp.binned.BinFactors`, as :func:`iter_precompute` does.

    Raises:
        ValueError: on the first draw, if ``blocks`` is not a partition of ``range(N)``.
    """
    dims = tuple(grad_dims)
    n, g = X.shape[0], len(dims)
    devs = parallel.devices(devices)
    L_u = _inducing_factor(n, blocks, Z, hyper, dims, jitter)
    up = L_u.shape[0]
    units, pos = pad_units(X, Ybar, blocks, g)
    shared = (hyper, jnp.asarray(Z), jnp.asarray(L_u))
    parts = parallel.map_units(partial(_pass1_jit, dims=dims), shared, units, devs)
    Bm = np.eye(up)
    rhat = np.zeros((up, Ybar.shape[1]))
    for wtw, wty in parts:  # in block order: the same sums for any number of devices
        Bm += wtw
        rhat += wty
    L_B = dense.cholesky_inplace(Bm, what="the PIC inducing system B")
    beta = dense.cho_solve(L_B, rhat)
    shared2 = (*shared, jnp.asarray(L_B), jnp.asarray(beta))
    two = partial(_pass2_jit, dims=dims)
    # Pass 2 in waves of one block per device: each block's dense form is stored compactly
    # by the consumer before the next wave is drawn.
    for start in range(0, len(units), len(devs)):
        wave = parallel.map_units(two, shared2, units[start : start + len(devs)], devs)
        for k, (coef, H) in enumerate(wave):
            b = start + k
            r = np.concatenate([np.arange(up), up + pos[b]])
            R = _upper_factor(H[np.ix_(r, r)])
            R[:, :up] = _tri(L_u, R[:, :up].T, trans=True).T  # back to raw [k_u; k_b]
            rows = near_rows(blocks[b], n, g)
            w = coef[up:][pos[b]]
            yield BinFactors(
                np.concatenate([coef[:up], w]),
                R,
                False,
                dense_rows=up,
                yty=np.sum(Ybar[rows] * w, axis=0),
                n_rows=rows.size,
            )


def _block_terms(h: Hyper, Z, L_u, Xb, dims):
    """``V_b = L_u⁻¹ K̄_ub``, the lower factor of ``Λ_b`` and ``W_b = L_b⁻¹ V_bᵀ``."""
    V = jsl.solve_triangular(
        L_u, kernels.gram(Z, Xb, h.variance, h.lengthscale, dims, dims), lower=True
    )
    lam = noisy_gram(Xb, h, dims) - V.T @ V
    L = jnp.linalg.cholesky(lam)
    return V, L, jsl.solve_triangular(L, V.T, lower=True)


def _pass1_block(shared, Xb, Yb, *, dims):
    h, Z, L_u = shared
    _, L, W = _block_terms(h, Z, L_u, Xb, dims)
    return W.T @ W, W.T @ jsl.solve_triangular(L, Yb, lower=True)


def _pass2_block(shared, Xb, Yb, *, dims):
    """Coefficients ``[c_u; w_b]`` and the whitened quadratic form ``H̃`` (module docstring)."""
    h, Z, L_u, L_B, beta = shared
    V, L, W = _block_terms(h, Z, L_u, Xb, dims)
    w = jsl.cho_solve((L, True), Yb - V.T @ beta)
    c_u = jsl.solve_triangular(L_u, beta - V @ w, lower=True, trans=1)
    up, nb = V.shape
    Linv = jsl.solve_triangular(L, jnp.eye(nb, dtype=L.dtype), lower=True)
    G_d = jnp.concatenate([-W, Linv], axis=1)
    G_e = jsl.solve_triangular(
        L_B,
        jnp.concatenate([jnp.eye(up, dtype=L.dtype) + W.T @ W, -(W.T @ Linv)], axis=1),
        lower=True,
    )
    H = G_d.T @ G_d - G_e.T @ G_e
    H = H.at[jnp.arange(up), jnp.arange(up)].add(1.0)
    return jnp.concatenate([c_u, w], axis=0), H


def _upper_factor(H: np.ndarray) -> np.ndarray:
    """Upper ``R`` with ``RᵀR = H`` for the symmetric positive semi-definite ``H``.

    ``H`` is PSD in exact arithmetic (a quadratic form of a posterior), but it is a difference
    of two Gram matrices and rounding can leave it a hair indefinite: a jitter relative to its
    largest diagonal entry (1e-13, raised tenfold up to 1e-9) is added when the Cholesky
    factorisation fails; it moves the variance by that fraction of ``‖z‖²``, far below ν².
    """
    H = 0.5 * (H + H.T)
    scale = float(np.max(np.diag(H)))
    for rel in (0.0, 1e-13, 1e-12, 1e-11, 1e-10, 1e-9):
        A = np.array(H, order="C")  # a copy: a failed attempt overwrites part of it
        if rel:
            A.flat[:: A.shape[0] + 1] += rel * scale
        try:
            return np.ascontiguousarray(dense.cholesky_inplace(A, what="PIC variance form").T)
        except dense.NotPositiveDefiniteError:
            continue
    w, V = np.linalg.eigh(H)
    half = np.sqrt(np.clip(w, 0.0, None))[:, None] * V.T
    return np.ascontiguousarray(sla.qr(half, mode="r", check_finite=False)[0])


# Module-level jitted passes (their dims static): every fit and rebuild of one shape reuses
# the programs, where a jit of a fresh partial per call traced them again.
_pass1_jit = jax.jit(_pass1_block, static_argnames="dims")
_pass2_jit = jax.jit(_pass2_block, static_argnames="dims")
