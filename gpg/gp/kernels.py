"""RBF kernel, its derivative blocks, and Gram builders for value and gradient observations.

Paper, Section "Gaussian Processes with Gradient Information": for the base kernel
``k00(x, x') = σ exp(-½ Σ_d (x_d - x'_d)² / l_d²)`` the covariances between function values and
partial derivatives are

* ``kn0(x, x') = ∂k/∂x_n``        (derivative observation at ``x``, value at ``x'``),
* ``k0m(x, x') = ∂k/∂x'_m``       (value at ``x``, derivative observation at ``x'``),
* ``knm(x, x') = ∂²k/∂x_n ∂x'_m`` (two derivative observations),

Eq. (kernel_gradient). Here they are obtained by automatic differentiation of :func:`rbf`, so
isotropic (scalar ``l``) and ARD (one ``l_d`` per input) lengthscales are handled alike, and
the closed forms are a test, not the implementation.

Row layout of every Gram matrix (paper Eq. barK): all value rows first, then one block of ``N``
rows per gradient dimension, in the order given by ``dims``: ``[f(X); ∂_{d0} f(X); ∂_{d1} f(X);
...]``. A point's gradient rows are therefore ``i + N * (1 + g)`` for ``g = 0..G-1``.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg._precision import highest

__all__ = ["KernelBlocks", "direction_gram", "gradient_blocks", "gram", "rbf", "row_gram"]


class KernelBlocks(NamedTuple):
    """The four covariance blocks between ``(f(x), ∂f(x))`` and ``(f(x'), ∂f(x'))``."""

    k00: Float[Array, ""]
    k0m: Float[Array, " D"]
    kn0: Float[Array, " D"]
    knm: Float[Array, "D D"]


@highest
def rbf(
    x1: Float[ArrayLike, " D"],
    x2: Float[ArrayLike, " D"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
) -> Float[Array, ""]:
    """Squared-exponential kernel ``σ exp(-½ Σ_d (x1_d − x2_d)² / l_d²)``, paper Eq. (kernel 00).

    Args:
        x1: (D,) the first input.
        x2: (D,) the second input.
        variance: the paper's signal variance σ.
        lengthscale: its radius scale ``l``, a scalar (isotropic) or (D,) (ARD).

    Returns:
        The covariance ``k(x1, x2)``, a scalar.
    """
    r = (jnp.asarray(x1) - jnp.asarray(x2)) / lengthscale
    return variance * jnp.exp(-0.5 * jnp.dot(r, r))


@highest
def gradient_blocks(
    x1: Float[ArrayLike, " D"],
    x2: Float[ArrayLike, " D"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
) -> KernelBlocks:
    """``k00, k0m, kn0, knm`` of paper Eq. (kernel_gradient), by ``jax.grad``/``jax.hessian``.

    ``knm`` is the mixed block of ``jax.hessian`` of :func:`rbf` in ``(x1, x2)``:
    ``knm[n, m] = ∂²k/∂x1_n ∂x2_m``. The closed forms are what the tests compare it with.

    Args:
        x1: (D,) the input of the first observation (``x``).
        x2: (D,) the input of the second (``x'``).
        variance: the signal variance σ.
        lengthscale: ``l``, a scalar or (D,).

    Returns:
        The four blocks, ``k00`` () to ``knm`` (D, D), over all D inputs.
    """
    x1 = jnp.asarray(x1)
    x2 = jnp.asarray(x2)

    def k(a, b):
        return rbf(a, b, variance, lengthscale)

    k00, (kn0, k0m) = jax.value_and_grad(k, argnums=(0, 1))(x1, x2)
    knm = jax.hessian(k, argnums=(0, 1))(x1, x2)[0][1]
    return KernelBlocks(k00=k00, k0m=k0m, kn0=kn0, knm=knm)


def check_dims(dims: Sequence[int], n_inputs: int, name: str = "grad_dims") -> tuple[int, ...]:
    """Validate a tuple of gradient dimensions against ``n_inputs`` and return it."""
    dims = tuple(dims) if isinstance(dims, (list, tuple)) else dims
    if not isinstance(dims, tuple) or not all(
        isinstance(d, (int, np.integer)) and not isinstance(d, bool) for d in dims
    ):
        raise ValueError(f"{name} must be a sequence of integers, got {dims!r}")
    out = tuple(int(d) for d in dims)
    bad = [d for d in out if not 0 <= d < n_inputs]
    if bad:
        raise ValueError(f"{name} has dimensions {bad} out of range for {n_inputs} inputs")
    if len(set(out)) != len(out):
        raise ValueError(f"{name} repeats a dimension: {out}")
    return out


@highest
def pair_block(
    x1: Float[Array, " D"],
    x2: Float[Array, " D"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
    dims1: tuple[int, ...],
    dims2: tuple[int, ...],
) -> Float[Array, "G1p1 G2p1"]:
    """Covariance of ``(f, ∂_{dims1} f)(x1)`` with ``(f, ∂_{dims2} f)(x2)``: (1+G1, 1+G2).

    Only the derivatives a block needs are taken: a query row (``dims1 = ()``) needs the
    gradient in ``x2`` alone, not the Hessian, which halves its cost.
    """

    def k(a, b):
        return rbf(a, b, variance, lengthscale)

    i1, i2 = _selector(dims1), _selector(dims2)
    if not dims1 and not dims2:
        return k(x1, x2)[None, None]
    if not dims1:
        k00, k0m = jax.value_and_grad(k, argnums=1)(x1, x2)
        return jnp.concatenate([k00[None], k0m[i2]])[None, :]
    if not dims2:
        k00, kn0 = jax.value_and_grad(k, argnums=0)(x1, x2)
        return jnp.concatenate([k00[None], kn0[i1]])[:, None]
    b = gradient_blocks(x1, x2, variance, lengthscale)
    top = jnp.concatenate([b.k00[None], b.k0m[i2]])
    rest = jnp.concatenate([b.kn0[i1][:, None], b.knm[i1][:, i2]], axis=1)
    return jnp.concatenate([top[None, :], rest], axis=0)


def _selector(dims: tuple[int, ...]) -> slice | np.ndarray:
    """A slice for consecutive dims (XLA fuses it), an index array otherwise (a gather)."""
    if dims and dims == tuple(range(dims[0], dims[0] + len(dims))):
        return slice(dims[0], dims[0] + len(dims))
    return np.asarray(dims, dtype=np.int32)


@partial(jax.jit, static_argnames=("dims1", "dims2"))
@highest
def gram(
    X1: Float[Array, "N1 D"],
    X2: Float[Array, "N2 D"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
    dims1: tuple[int, ...] = (),
    dims2: tuple[int, ...] = (),
) -> Float[Array, "R1 R2"]:
    """Gram matrix ``K̄(X1, X2)`` with value rows and gradient rows for ``dims1``/``dims2``.

    Every pair's block comes from the derivatives of :func:`rbf` (compiled once per
    ``dims1``, ``dims2`` and shapes). With ``dims1 = dims2 = ()`` it is the plain kernel
    matrix ``k(X1, X2)``.

    Args:
        X1: (N1, D) the inputs of the rows.
        X2: (N2, D) the inputs of the columns.
        variance: the signal variance σ.
        lengthscale: ``l``, a scalar or (D,).
        dims1: the G1 input dims of the rows' gradient observations (static).
        dims2: the G2 input dims of the columns' (static).

    Returns:
        ``((1+G1)·N1, (1+G2)·N2)`` in the layout of the module docstring (no noise).
    """
    inner = jax.vmap(pair_block, in_axes=(None, 0, None, None, None, None), out_axes=2)
    outer = jax.vmap(inner, in_axes=(0, None, None, None, None, None), out_axes=1)
    # (1+G1, N1, 1+G2, N2): the reshape below is free and gives the dimension-major layout.
    blocks = outer(X1, X2, variance, lengthscale, dims1, dims2)
    return blocks.reshape((1 + len(dims1)) * X1.shape[0], (1 + len(dims2)) * X2.shape[0])


@highest
def correlation(
    X1: Float[Array, "N1 D"], X2: Float[Array, "N2 D"], lengthscale: Float[ArrayLike, "*L"]
) -> Float[Array, "N1 N2"]:
    """Kernel correlation ``k(x, x') / σ`` in [0, 1], used to pick near sets."""
    return jax.vmap(jax.vmap(rbf, (None, 0, None, None)), (0, None, None, None))(
        X1, X2, 1.0, lengthscale
    )


@highest
def query_rows(
    Xq: Float[Array, "Q D"],
    X: Float[Array, "N D"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
    dims: tuple[int, ...] = (),
) -> Float[Array, "Q R"]:
    """``K̄(Xq, X)`` for value queries: the same matrix as ``gram(Xq, X, ..., (), dims)``.

    Closed forms instead of autodiff: ``k = σ exp(-½ r²)`` with the squared scaled distance
    ``r² = |a|² + |b|² − 2 a·b`` (``a = x_q / l``, ``b = x / l``) from one matrix product, and
    ``k0m = k (x_q,m − x_m) / l_m²`` for the gradient rows. A prediction's cost is its kernel
    rows: per-pair autodiff evaluates them several times slower than one product.
    """
    d = X.shape[1]
    ls = jnp.broadcast_to(jnp.asarray(lengthscale, dtype=X.dtype), (d,))
    K = rbf_matrix(Xq / ls, X / ls, variance)
    if not dims:
        return K
    idx = np.asarray(dims)
    inv2 = 1.0 / ls[idx] ** 2
    # (Q, G, N): the scaled differences of the gradient dims; rows dimension-major as in gram.
    diff = (Xq[:, idx] * inv2)[:, :, None] - (X[:, idx] * inv2).T[None, :, :]
    rows = jnp.concatenate([K[:, None, :], K[:, None, :] * diff], axis=1)
    return rows.reshape(Xq.shape[0], (1 + len(dims)) * X.shape[0])


@jax.jit
@highest
def row_gram(
    X1: Float[Array, "R1 D"],
    a1: Int[Array, " R1"],
    X2: Float[Array, "R2 D"],
    a2: Int[Array, " R2"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
) -> Float[Array, "R1 R2"]:
    """Covariance of arbitrary rows, each a value or a derivative along one input.

    The blocks of Eq. (kernel_gradient) in closed form, with ``u = (x1 − x2) / l²``:
    ``k00 = k``, ``k0m = k u_m``, ``kn0 = −k u_n``, ``knm = k (δ_nm / l_n² − u_n u_m)``, i.e.
    ``k · s1 · s2 + k [n = m] / l_n²`` with ``s1 = −u_n`` (or 1 for a value row) and
    ``s2 = u_m`` (or 1). Rows of a case that lacks some gradients are then built as they are,
    with no row for what was not observed: the same matrix as :func:`gram` restricted to
    those rows, for ``R1·R2`` entries instead of ``(1+G)²`` times as many.

    Args:
        X1: (R1, D) each row's input.
        a1: (R1,) what each row observes: ``f(X1[i])`` where ``a1[i] < 0``, else
            ``∂f/∂x_{a1[i]}`` at ``X1[i]``.
        X2: (R2, D) each column's input.
        a2: (R2,) what each column observes, as ``a1``.
        variance: the signal variance σ.
        lengthscale: ``l``, a scalar or (D,).

    Returns:
        (R1, R2) the covariances (no noise).
    """
    d = X1.shape[1]
    ls = jnp.broadcast_to(jnp.asarray(lengthscale, dtype=X1.dtype), (d,))
    inv2 = 1.0 / ls**2
    K = rbf_matrix(X1 / ls, X2 / ls, variance)
    g1, g2 = a1 >= 0, a2 >= 0
    i1, i2 = jnp.where(g1, a1, 0), jnp.where(g2, a2, 0)
    # u_n(x1_i, x2_j) for the row's own dimension: (x1[i, n] − x2[j, n]) / l_n².
    own1 = X1[jnp.arange(X1.shape[0]), i1][:, None]
    own2 = X2[jnp.arange(X2.shape[0]), i2][None, :]
    s1 = jnp.where(g1[:, None], -(own1 - X2[:, i1].T) * inv2[i1][:, None], 1.0)
    s2 = jnp.where(g2[None, :], (X1[:, i2] - own2) * inv2[i2][None, :], 1.0)
    same = (g1[:, None] & g2[None, :]) & (i1[:, None] == i2[None, :])
    return K * (s1 * s2 + jnp.where(same, inv2[i1][:, None], 0.0))


@jax.jit
@highest
def direction_gram(
    X1: Float[Array, "R1 D"],
    E1: Float[Array, "R1 D"],
    v1: Bool[Array, " R1"],
    X2: Float[Array, "R2 D"],
    E2: Float[Array, "R2 D"],
    v2: Bool[Array, " R2"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
) -> Float[Array, "R1 R2"]:
    """Covariance of rows that observe ``f`` or its derivative along a direction.

    The paper's remark on derivatives in arbitrary directions. The blocks of
    Eq. (kernel_gradient) are linear in the directions, so with ``u = (x1 − x2) / l²``:
    ``cov(D_e f, f) = −(e·u) k``, ``cov(f, D_f f) = (f·u) k`` and
    ``cov(D_e f, D_f f) = (Σ_d e_d f_d / l_d² − (e·u)(f·u)) k``, i.e.
    ``k (a1 a2 + [both derivatives] e·f/l²)`` with ``a1 = −e·u`` (1 for a value) and
    ``a2 = f·u`` (1). One-hot directions give :func:`row_gram`.

    Args:
        X1: (R1, D) each row's input.
        E1: (R1, D) each derivative row's direction ``e`` (read only where ``v1`` is False).
        v1: (R1,) whether the row observes the value ``f(X1[i])``.
        X2: (R2, D) each column's input.
        E2: (R2, D) each derivative column's direction ``f``.
        v2: (R2,) whether the column observes the value.
        variance: the signal variance σ.
        lengthscale: ``l``, a scalar (isotropic) or (D,) (ARD).

    Returns:
        (R1, R2) the rows' covariances with the columns, without noise.
    """
    d = X1.shape[1]
    ls = jnp.broadcast_to(jnp.asarray(lengthscale, dtype=X1.dtype), (d,))
    inv2 = 1.0 / ls**2
    K = rbf_matrix(X1 / ls, X2 / ls, variance)
    W1, W2 = E1 * inv2, E2 * inv2
    # e·u for every pair from two products: e·(x1 − x2)/l² = (e/l²)·x1 − (e/l²)·x2.
    eu = jnp.sum(W1 * X1, 1)[:, None] - W1 @ X2.T
    fu = X1 @ W2.T - jnp.sum(W2 * X2, 1)[None, :]
    a1 = jnp.where(v1[:, None], 1.0, -eu)
    a2 = jnp.where(v2[None, :], 1.0, fu)
    both = (~v1)[:, None] & (~v2)[None, :]
    return K * (a1 * a2 + jnp.where(both, W1 @ E2.T, 0.0))


@highest
def rbf_matrix(A: Array, B: Array, variance: Float[ArrayLike, ""]) -> Array:
    """``σ exp(-½ |a − b|²)`` for the rows of ``A`` and ``B``, already divided by ``l``."""
    r2 = jnp.sum(A * A, 1)[:, None] + jnp.sum(B * B, 1)[None, :] - 2.0 * (A @ B.T)
    # Rounding can make r² a hair negative at coincident points; k must not exceed σ.
    return variance * jnp.exp(-0.5 * jnp.maximum(r2, 0.0))
