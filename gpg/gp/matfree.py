"""Products with ``K̄`` (plus its noise diagonal) without forming it.

For the RBF kernel every block of the gradient kernel is the plain kernel ``k(x_i, x_j)`` times
a low-degree polynomial of the input differences (:mod:`gpg.gp.kernels`): with
``r_n = (x_n − x'_n)/l_n²``,

* value–value ``k``, value–gradient ``k0m = k r_m``, gradient–value ``kn0 = −k r_n``,
* gradient–gradient ``knm = k (δ_nm / l_n² − r_n r_m)``.

Expanding the polynomials, ``K̄ V`` for a right-hand side ``V = [v_0; v_1 … v_G]`` (value rows,
then each gradient dimension's rows) needs only products of the plain ``K`` (N × N) with the
``(G+1)(G+2)`` columns ``v_0, x_n v_0, v_m, x_n v_m, s, x_n s`` where ``s = Σ_m x_m v_m / l_m²``
(72 for G = 7). ``K`` is computed tile by tile of rows and never stored: memory ``O(N · 72 M)``
for the columns plus one tile of ``K``, time ``O(N² · 72 M)`` in matrix products.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from gpg import parallel
from gpg._precision import highest
from gpg.gp.hyper import Hyper

__all__ = [
    "gram_matvec",
    "gram_matvec_devices",
]


@highest
def _columns(Xg, il2, v0, Vg):
    """The right-hand sides of ``K`` for ``V`` (module docstring), (N, C, M) with ``C =
    (G+1)(G+2)``, and ``s``."""
    n, g = Xg.shape
    k = v0.shape[1]
    s = jnp.einsum("nm,m,nmk->nk", Xg, il2, Vg)
    parts = [
        v0[:, None],  # v_0
        Xg[:, :, None] * v0[:, None],  # x_n v_0
        Vg,  # v_m
        (Xg[:, :, None, None] * Vg[:, None]).reshape(n, g * g, k),  # x_n v_m
        s[:, None],  # s
        Xg[:, :, None] * s[:, None],  # x_n s
    ]
    return jnp.concatenate(parts, axis=1)


@highest
def _tile_product(xt, X, Wflat, variance, lengthscale, il2, dims, m):
    """``K̄`` rows of the points ``xt`` (t, D) times ``V`` from the products ``K(xt, X) W``."""
    g = len(dims)
    a, b = xt / lengthscale, X / lengthscale
    r2 = jnp.sum(a * a, 1)[:, None] + jnp.sum(b * b, 1)[None] - 2.0 * a @ b.T
    K = variance * jnp.exp(-0.5 * jnp.maximum(r2, 0.0))
    P = (K @ Wflat).reshape(xt.shape[0], -1, m)
    KA, KC0 = P[:, 0], P[:, 1 : 1 + g]
    KB = P[:, 1 + g : 1 + 2 * g]
    KCv = P[:, 1 + 2 * g : 1 + 2 * g + g * g].reshape(xt.shape[0], g, g, m)
    KS, KCs = P[:, 1 + 2 * g + g * g], P[:, 2 + 2 * g + g * g :]
    xi = xt[:, jnp.asarray(dims)] if g else jnp.zeros((xt.shape[0], 0), xt.dtype)
    T = jnp.einsum("tm,m,tmk->tk", xi, il2, KB)
    value = KA + T - KS
    cross = jnp.einsum("tm,m,tnmk->tnk", xi, il2, KCv)
    grad = (
        -(xi[:, :, None] * KA[:, None] - KC0)
        + KB
        - xi[:, :, None] * T[:, None]
        + xi[:, :, None] * KS[:, None]
        + cross
        - KCs
    ) * il2[None, :, None]
    return value, grad


@partial(jax.jit, static_argnames=("grad_dims",))
@highest
def _prepare(X, hyper: Hyper, grad_dims: tuple[int, ...], V):
    """The columns ``W`` (N, C·M) that ``K`` multiplies, and the lengthscales as used."""
    n, d = X.shape
    g, m = len(grad_dims), V.shape[1]
    ls = jnp.broadcast_to(jnp.asarray(hyper.lengthscale, X.dtype), (d,))
    idx = jnp.asarray(grad_dims, dtype=int)
    il2 = 1.0 / ls[idx] ** 2 if g else jnp.zeros((0,), X.dtype)
    Xg = X[:, idx] if g else jnp.zeros((n, 0), X.dtype)
    Vg = V[n:].reshape(g, n, m).transpose(1, 0, 2)
    return _columns(Xg, il2, V[:n], Vg).reshape(n, -1), ls, il2


@highest
def _assemble(value, grad, V, hyper: Hyper, n: int, g: int):
    """Stacked rows (value rows, then each gradient dimension's) plus the noise diagonal."""
    m = V.shape[1]
    value = value.reshape(-1, m)
    grad = grad.reshape(value.shape[0], g, m)[:n].transpose(1, 0, 2).reshape(g * n, m)
    value = value[:n]
    return jnp.concatenate([value, grad]) + hyper.noise_diagonal(n, g)[:, None] * V


def _tiles(X, tile: int):
    """``X`` padded to whole tiles of ``tile`` points (T, tile, D)."""
    n, d = X.shape
    pad = (-n) % tile
    return jnp.concatenate([X, jnp.zeros((pad, d), X.dtype)]).reshape(-1, tile, d)


@partial(jax.jit, static_argnames=("grad_dims", "tile"))
@highest
def gram_matvec(
    X: Float[Array, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    V: Float[Array, "R M"],
    *,
    tile: int = 256,
) -> Float[Array, "R M"]:
    """``(K̄ + diag(ν², λ²)) V`` without forming ``K̄``.

    Equal to the dense product of :func:`gpg.gp.gram.noisy_gram` to rounding. Rows of the
    plain ``K`` are made ``tile`` points at a time (``lax.map``), so memory is one tile of
    ``K`` plus the ``(G+1)(G+2)·M`` columns it multiplies; in reverse mode each tile is
    rematerialised rather than kept.

    Args:
        X: (N, D) training inputs.
        hyper: the hyperparameters (σ, l, ν², λ_i²); l may be isotropic or per input.
        grad_dims: the input dimensions that carry gradient rows (G of them).
        V: (R, M) right-hand sides, ``R = N(1+G)`` rows in the layout of
            :mod:`gpg.gp.kernels` (value rows, then each gradient dimension's).
        tile: training points per tile of ``K``.

    Returns:
        The (R, M) product, in the layout of ``V``.
    """
    n, g, m = X.shape[0], len(grad_dims), V.shape[1]
    W, ls, il2 = _prepare(X, hyper, grad_dims, V)
    # Rematerialised in reverse mode: a gradient through the product (the likelihood on all
    # points, :mod:`gpg.gp.slq`) keeps one tile of K at a time, not all N² entries.
    tile_product = jax.checkpoint(
        lambda xt: _tile_product(xt, X, W, hyper.variance, ls, il2, grad_dims, m)
    )
    value, grad = jax.lax.map(tile_product, _tiles(X, tile))
    return _assemble(value, grad, V, hyper, n, g)


def gram_matvec_devices(
    X: Float[Array, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    V: Float[Array, "R M"],
    *,
    devices: parallel.Devices,
    tile: int = 256,
) -> Float[Array, "R M"]:
    """:func:`gram_matvec` with the row tiles spread over JAX devices.

    Every tile runs the same compiled program, so the result is bit-identical for any number
    of devices; each device holds ``X``, the columns and one tile of ``K``.

    Args:
        X: (N, D) training inputs.
        hyper: the hyperparameters (σ, l, ν², λ_i²).
        grad_dims: the input dimensions that carry gradient rows (G of them).
        V: (R, M) right-hand sides, ``R = N(1+G)`` rows in the layout of :mod:`gpg.gp.kernels`.
        devices: a device count or a list of devices (:func:`gpg.parallel.devices`; across
            hosts after :func:`gpg.parallel.initialize`).
        tile: training points per tile of ``K``, the unit of work handed to a device.

    Returns:
        The (R, M) product ``(K̄ + diag(ν², λ²)) V``.
    """
    devs = parallel.devices(devices)
    n, g, m = X.shape[0], len(grad_dims), V.shape[1]
    W, ls, il2 = _prepare(X, hyper, grad_dims, V)
    fn = partial(_unit_product_jit, grad_dims=tuple(grad_dims), m=m)
    units = [(np.asarray(t),) for t in _tiles(X, tile)]
    parts = parallel.map_units(fn, (X, W, hyper.variance, ls, il2), units, devs)
    value = jnp.concatenate([jnp.asarray(v) for v, _ in parts])
    grad = jnp.concatenate([jnp.asarray(gr) for _, gr in parts])
    return _assemble(value, grad, V, hyper, n, g)


def _unit_product(shared, xt, *, grad_dims, m):
    X, W, variance, ls, il2 = shared
    return _tile_product(xt, X, W, variance, ls, il2, grad_dims, m)


# jitted once at module level (static "grad_dims", "m"): calls of one shape share the program
_unit_product_jit = jax.jit(_unit_product, static_argnames=("grad_dims", "m"))
