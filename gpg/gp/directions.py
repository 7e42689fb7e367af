"""Directional derivative rows: cases whose gradient rows observe derivatives along directions
other than the inputs (the paper's remark on derivatives in arbitrary directions).

Case ``i``'s gradient row ``g`` observes the derivative along ``Σ_h B_i[g, h] e_{grad_dims[h]}``
with ``B_i = bases[i]`` (G, G); without ``bases`` the directions are the one-hot input axes.
The layout of the rows is unchanged (:mod:`gpg.gp.layout`): only what each gradient row
observes is. :func:`to_bases` and :func:`from_bases` move kernel rows and coefficients between
the coordinate rows and the directional ones.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg import _checks
from gpg._precision import highest

__all__ = ["from_bases", "row_directions", "to_bases"]


def check_bases(
    bases: Float[ArrayLike, "N G G"] | None, n: int, grad_dims: tuple[int, ...]
) -> np.ndarray | None:
    """``bases`` as a float (N, G, G) array, or None; ``ValueError`` naming it otherwise."""
    if bases is None:
        return None
    g = len(grad_dims)
    if not g:
        raise ValueError("bases given but the data has no gradient rows")
    bases = _checks.as_float_array("bases", bases, ndim=3)
    if bases.shape != (n, g, g):
        raise ValueError(f"bases must have shape (N, G, G) = ({n}, {g}, {g}), got {bases.shape}")
    _checks.require_finite("bases", bases)
    return bases


def row_directions(
    index: Int[np.ndarray, " r"],
    n: int,
    grad_dims: tuple[int, ...],
    bases: Float[np.ndarray, "N G G"] | None,
    d: int,
) -> tuple[Int[np.ndarray, " r"], Float[np.ndarray, "r D"], Bool[np.ndarray, " r"]]:
    """Each of the rows ``index`` as :func:`gpg.gp.kernels.direction_gram` reads it.

    Gradient row ``g`` of case ``i`` observes the derivative along
    ``Σ_h bases[i, g, h] e_{grad_dims[h]}`` (one-hot ``e_{grad_dims[g]}`` without ``bases``).

    Args:
        index: (r,) rows of the layout of ``n`` points (:mod:`gpg.gp.layout`).
        n: the number of points ``N``.
        grad_dims: the G input dims of the gradient rows.
        bases: (N, G, G) the directions of each case's gradient rows, or None (the inputs).
        d: the number of inputs ``D``.

    Returns:
        Each row's point (r,), its direction in the ``d`` inputs (r, D), zero on a value row,
        and whether it is a value row (r,).
    """
    index = np.asarray(index, dtype=np.int64)
    p, blk = index % n, index // n
    value = blk == 0
    g = np.where(value, 0, blk - 1)
    E = np.zeros((index.size, d))
    dims = np.asarray(grad_dims, dtype=np.int64)
    if bases is None:
        E[np.flatnonzero(~value), dims[g[~value]]] = 1.0
    elif dims.size:
        E[:, dims] = np.asarray(bases)[p, g, :]
        E[value] = 0.0
    return p, E, value


@highest
def to_bases(k: Float[Array, "*Q R"], bases: Float[Array, "N G G"], n: int) -> Float[Array, "*Q R"]:
    """Kernel rows over the coordinate layout turned into the rows the cases observe (JAX).

    A column block per gradient dim of ``∂k`` becomes, per case, ``B_i ∂k``: the covariance
    with the derivatives along the case's directions, since the kernel's derivative blocks are
    linear in the direction. The value columns are kept as they are.

    Args:
        k: (..., N (1 + G)) kernel rows in the coordinate layout (values, then one block per
            gradient dim).
        bases: (N, G, G) each case's directions ``B_i``.
        n: the number of cases ``N``.

    Returns:
        (..., N (1 + G)) the same rows over the directional gradient rows.
    """
    g = bases.shape[1]
    lead = k.shape[:-1]
    grads = k[..., n:].reshape(*lead, g, n)
    turned = jnp.einsum("igh,...hi->...gi", bases.astype(k.dtype), grads)
    return jnp.concatenate([k[..., :n], turned.reshape(*lead, g * n)], axis=-1)


def from_bases(alpha: Float[np.ndarray, "R M"], bases: np.ndarray, n: int) -> np.ndarray:
    """Coefficients over directional rows as coefficients over the coordinate layout.

    ``Σ_g B_i[g, h] α_{g,i}``: what the folded mean and the exports read, so that
    ``k̄_coordᵀ α_coord = k̄_dirᵀ α``. The transpose of :func:`to_bases`, on the host.

    Args:
        alpha: (N (1 + G), M) coefficients over the directional rows (0 on rows not observed).
        bases: (N, G, G) each case's directions ``B_i``.
        n: the number of cases ``N``.

    Returns:
        (N (1 + G), M) the coefficients over the coordinate rows; the value rows unchanged.
    """
    g = bases.shape[1]
    grads = np.einsum("igh,gim->him", bases, alpha[n:].reshape(g, n, -1))
    return np.concatenate([alpha[:n], grads.reshape(g * n, -1)])
