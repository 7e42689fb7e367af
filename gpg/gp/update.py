"""Conditioning an exact GP-G on more cases without a refit: the bordered Cholesky update.

:meth:`gpg.gp.exact.ExactGP.condition` is the public entry; the algebra is in its docstring.
The stored factor is ``L⁻¹`` in row bands (:class:`gpg.linalg.tri.BlockTriangular`); the new
rows' part is kept factored around it (:class:`gpg.linalg.tri.BorderedTriangular`), so an
update never copies what is stored and reads the old factor twice with thin products: once for
``S = (L⁻¹B)ᵀ`` (``R²r`` flops, the floor of any update that reads the stored factor) and once
for ``α`` (``R²M``). The factor's rows stay in
the order the cases came (old rows, then each update's), which is a permutation of the layout
of :mod:`gpg.gp.kernels` recorded in ``ExactGP.order``: the posterior does not depend on the
order of the rows, only the triangular factor does. Only observed rows are in the factor: the
rows of gradients a case lacks are never formed (:func:`gpg.gp.gram.rows_gram`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Float

from gpg import _host
from gpg.gp.assembly import assemble_rows_gram, rows_gram
from gpg.gp.directions import check_bases, from_bases
from gpg.gp.mean import GlobalMean, output_scale
from gpg.gp.targets import Checked, check_training_data
from gpg.linalg import dense, memory
from gpg.linalg.tri import BorderedTriangular

__all__ = ["grown_bases", "grown_rows", "layout_index"]


def check_new_cases(model, X, Y, dY, observed) -> Checked:
    """The new cases checked against ``model`` (inputs, outputs, gradient dims): a
    ``ValueError`` naming what does not match. Values-only cases of a gradient model are
    cases with no gradient observed."""
    dims = model.grad_dims
    if dY is not None and not dims:
        raise ValueError("dY given, but the model was fitted without gradient observations")
    data = check_training_data(X, Y, dY, dims if dY is not None else None, observed)
    n, d = data.X.shape
    if d != model.n_inputs:
        raise ValueError(f"X has {d} inputs but the model has {model.n_inputs}")
    if data.Y.shape[1] != model.n_outputs:
        raise ValueError(f"Y has {data.Y.shape[1]} outputs but the model has {model.n_outputs}")
    if dims and data.dY is None:
        zeros = np.zeros((n, data.Y.shape[1], len(dims)))
        data = Checked(data.X, data.Y, zeros, dims, np.zeros((n, len(dims)), dtype=bool))
    return data


def layout_index(n_old: int, n_new: int, n_grad: int) -> tuple[np.ndarray, np.ndarray]:
    """Where the rows of the old points and of the new points sit in the layout of all.

    In the row layout of :mod:`gpg.gp.kernels` of all ``n_old + n_new`` points, old points
    first: each block of rows (the values, then one per gradient dim) holds the old points'
    rows, then the new ones'.

    Args:
        n_old: the number of points already in.
        n_new: the number of new points.
        n_grad: the number of gradient dims G.

    Returns:
        The rows of the old points' layout (``n_old (1 + G)``,) and of the new points'
        (``n_new (1 + G)``,), each in the order of its own layout, as rows of the grown one.
    """
    n = n_old + n_new
    blocks = np.arange(1 + n_grad)[:, None] * n
    old = (blocks + np.arange(n_old)[None, :]).ravel()
    new = (blocks + n_old + np.arange(n_new)[None, :]).ravel()
    return old, new


def bordered(model, X, Y, dY, observed, bases=None):
    """:meth:`gpg.gp.exact.ExactGP.condition` (see there)."""
    data = check_new_cases(model, X, Y, dY, observed)
    bases = check_bases(bases, data.X.shape[0], data.grad_dims)
    old_b, new_b, all_b = grown_bases(model.bases, bases, model.X.shape[0], data.X.shape[0],
                                      len(data.grad_dims))  # fmt: skip
    h, dims, g = model.hyper, model.grad_dims, len(model.grad_dims)
    n_old, n_new = model.X.shape[0], data.X.shape[0]
    R, rows_new = model.alpha.shape[0], data.rows
    Rf = model.chol_inv.n  # the factor's rows: R, or fewer when some gradients are missing
    old_idx, new_idx = layout_index(n_old, n_new, g)
    # The factor's rows in the old layout, and the new cases' observed rows in theirs.
    order = np.arange(R) if model.order is None else np.asarray(model.order)
    fresh = np.arange(n_new * (1 + g)) if rows_new is None else np.flatnonzero(rows_new)
    r = fresh.size
    # Peak: two r×Rf arrays at a time (B and S, then S and M) and two r×r.
    memory.require(f"conditioning on {n_new} cases ({r} rows)", int(8 * r * (2 * Rf + 2 * r)))
    X_old = np.asarray(model.X)
    B = rows_gram(X_old, order, data.X, fresh, h, dims, bases1=old_b, bases2=new_b)  # (Rf, r)
    if model.observed is not None:  # files of format <= 8 keep unobserved rows, decoupled
        B[~np.asarray(model.observed)[order]] = 0.0
    S = model.chol_inv.host_matmul(B).T  # (r, Rf) = (L⁻¹ B)ᵀ, the update's one O(Rf²r) product
    L2 = _schur_factor(data.X, fresh, h, dims, S, new_b)
    alpha_old = np.asarray(model.alpha)[order]
    resid = data.targets()[fresh] - B.T @ alpha_old
    del B
    alpha2 = dense.cho_solve(L2, resid)
    # K̄⁻¹B α₂ = L⁻ᵀ (S ᵀα₂): the old factor applied to M columns, not to the r new rows.
    alpha1 = alpha_old - model.chol_inv.host_lmatmul(alpha2.T @ S).T
    log_det2 = float(np.sum(np.log(np.diag(L2))))
    L2inv = dense.triangular_inverse_inplace(L2)
    coupling = L2inv @ S
    del S
    size = R + n_new * (1 + g)
    new_order = np.concatenate([old_idx[order], new_idx[fresh]])
    alpha = np.zeros((size, alpha1.shape[1]))
    alpha[new_order] = np.concatenate([alpha1, alpha2])
    observed_all = grown_rows(model.observed, rows_new, old_idx, new_idx, size)
    dq = np.sum(resid * alpha2, axis=0)
    lml, scale = _likelihood_and_scale(model, observed_all, size, dq, log_det2)
    X_all = np.concatenate([X_old, data.X])
    coord = alpha if all_b is None else from_bases(alpha, all_b, X_all.shape[0])
    return eqx.tree_at(
        lambda t: (t.X, t.alpha, t.chol_inv, t.mean, t.output_scale, t.log_marginal_likelihood,
                   t.order, t.observed, t.bases),
        model,
        (
            jnp.asarray(X_all),
            jnp.asarray(alpha),
            BorderedTriangular(
                model.chol_inv, _host.asarray(coupling), _host.asarray(L2inv), Rf + r
            ),
            GlobalMean.from_alpha(X_all, coord, h.variance, h.lengthscale, dims),
            jnp.asarray(scale),
            jnp.asarray(lml),
            jnp.asarray(new_order, dtype=jnp.int32),  # int32: no warning in float32 programs
            None if observed_all is None else jnp.asarray(observed_all),
            None if all_b is None else jnp.asarray(all_b),
        ),
        is_leaf=lambda x: x is None,
    )  # fmt: skip


def _schur_factor(Xn, fresh, h, dims, S, bases=None) -> np.ndarray:
    """``L₂`` with ``L₂ L₂ᵀ = C − S Sᵀ`` over the new observed rows ``fresh``, or a
    ``ValueError`` when the new cases make ``K̄`` singular."""
    C = assemble_rows_gram(Xn, fresh, h, dims, bases=bases)
    C -= dense.gram_t(np.ascontiguousarray(S.T))  # S Sᵀ
    try:
        return dense.cholesky_inplace(C, what="the Schur complement of the new cases")
    except dense.NotPositiveDefiniteError as exc:
        raise ValueError(
            f"the {len(Xn)} new cases make K̄ singular ({exc}): a case that duplicates a "
            "training point (or another new case) adds nothing; drop it"
        ) from None


def _likelihood_and_scale(model, observed_all, size, dq, log_det2):
    """The grown model's log likelihood and output scales from the old ones and the new
    rows' terms: ``Δ(Ȳᵀ K̄⁻¹ Ȳ) = dq`` per output, ``Δ log det = 2 log_det2``."""
    R = model.alpha.shape[0]
    n_obs_old = R if model.observed is None else int(np.sum(model.observed))
    n_obs = size if observed_all is None else int(observed_all.sum())
    m = dq.shape[0]
    lml = float(model.log_marginal_likelihood) + float(
        -0.5 * np.sum(dq) - m * log_det2 - 0.5 * m * (n_obs - n_obs_old) * math.log(2 * math.pi)
    )
    scale = np.asarray(model.output_scale)
    if not np.all(scale == 1.0):  # ones: the model keeps one shared scale
        scale = output_scale(scale * n_obs_old + dq, n_obs)
    return lml, scale


def grown_bases(
    old: Float[ArrayLike, "N G G"] | None,
    new: Float[ArrayLike, "n G G"] | None,
    n_old: int,
    n_new: int,
    g: int,
) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """The directions of the old cases' gradient rows, of the new ones' and of all.

    A side without its own directions is along the inputs (the identity), once the other
    side has some.

    Args:
        old: (N, G, G) the directions of the cases already in, or None (the inputs).
        new: (n, G, G) those of the new cases, or None.
        n_old: N, the number of cases already in.
        n_new: n, the number of new cases.
        g: the number of gradient dims G.

    Returns:
        The old cases' (N, G, G), the new ones' (n, G, G) and all (N + n, G, G) directions;
        three None when both sides are along the inputs.
    """
    if old is None and new is None:
        return None, None, None
    old = np.broadcast_to(np.eye(g), (n_old, g, g)) if old is None else np.asarray(old)
    new = np.broadcast_to(np.eye(g), (n_new, g, g)) if new is None else np.asarray(new)
    return old, new, np.concatenate([old, new])


def grown_rows(
    old: Bool[ArrayLike, " R"] | None,
    new: Bool[ArrayLike, " r"] | None,
    old_idx: np.ndarray,
    new_idx: np.ndarray,
    size: int,
) -> np.ndarray | None:
    """The observed-row mask of the grown model in its layout.

    Args:
        old: (R,) the observed rows of the model already in its layout, or None (all).
        new: (r,) the new cases' observed rows in theirs, or None (all).
        old_idx: where the old layout's rows sit in the grown one (:func:`layout_index`).
        new_idx: where the new cases' rows sit.
        size: the number of rows of the grown layout.

    Returns:
        (size,) bool, or None when neither side has a mask (every row observed).
    """
    if old is None and new is None:
        return None
    out = np.ones(size, dtype=bool)
    if old is not None:
        out[old_idx] = np.asarray(old)
    if new is not None:
        out[new_idx] = new
    return out
