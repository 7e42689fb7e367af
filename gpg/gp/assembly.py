"""``K̄`` of Eq. (barK) plus its noise diagonal, assembled on the host, on a device, or traced.

Three forms of one matrix, all in the row layout of :mod:`gpg.gp.layout`:

* :func:`noisy_gram`, traced JAX, the one form every traced factorisation starts from (the
  likelihood, the local bins on devices, PIC's blocks);
* :func:`assemble_gram` and :func:`assemble_rows_gram`, written block by block into one C-ordered
  NumPy buffer (the only full-size allocation) for the host's in-place Cholesky;
* :func:`device_gram`, built a block of rows at a time into one preallocated buffer on JAX's
  default device, for :mod:`gpg.linalg.device`.

:func:`rows_gram` forms any rows against any columns (the observed rows only, the covariances
of new cases with old ones); :func:`mask_gram_inplace` decouples unobserved rows of a full
``K̄`` instead.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg import _host
from gpg._precision import highest
from gpg.gp import kernels
from gpg.gp.hyper import Hyper
from gpg.gp.layout import layout_rows

__all__ = [
    "assemble_gram",
    "assemble_rows_gram",
    "device_gram",
    "mask_gram_inplace",
    "noisy_gram",
    "rows_gram",
]


def assemble_gram(
    X: Float[ArrayLike, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    out: np.ndarray | None = None,
    chunk_rows: int = 256,
    bases: np.ndarray | None = None,
) -> np.ndarray:
    """``K̄(X, X)`` plus its noise diagonal, written into a C-ordered NumPy buffer.

    Built in blocks of about ``chunk_rows`` rows so that the only full-size allocation is the
    result, ready for :func:`gpg.linalg.dense.cholesky_inplace`. Small blocks stay in cache:
    the default was the fastest block on the development machine (docs/measurements.md).

    Args:
        X: (N, D) the training inputs.
        hyper: the hyperparameters (σ, l, ν², λ²).
        grad_dims: the G input dims of the gradient rows.
        out: an (R, R) float64 buffer to write into, R = N (1 + G); a new one if None.
        chunk_rows: about how many rows each block makes.
        bases: (N, G, G) directions of the gradient rows (:func:`gpg.gp.directions.row_directions`);
            the matrix is then made by :func:`assemble_rows_gram`.

    Returns:
        The (R, R) matrix: ``out`` when given.

    Raises:
        ValueError: if ``out`` is not (R, R).
    """
    n = np.asarray(X).shape[0]
    g = len(grad_dims)
    r = n * (1 + g)
    if bases is not None:
        return assemble_rows_gram(np.asarray(X), np.arange(r), hyper, grad_dims, out=out,
                                  bases=bases)  # fmt: skip
    X = _host.asarray(X)
    if out is None:
        out = np.empty((r, r))
    elif out.shape != (r, r):
        raise ValueError(f"out must have shape ({r}, {r}), got {out.shape}")
    step = max(1, chunk_rows // (1 + g))
    for start in range(0, n, step):
        stop = min(start + step, n)
        rows = np.asarray(
            kernels.gram(X[start:stop], X, hyper.variance, hyper.lengthscale, grad_dims, grad_dims)
        )
        width = stop - start
        for blk in range(1 + g):
            out[blk * n + start : blk * n + stop] = rows[blk * width : (blk + 1) * width]
    out.flat[:: r + 1] += _noise_diagonal(hyper, n, g)
    return out


def rows_gram(
    X1: Float[np.ndarray, "N1 D"],
    index1: Int[np.ndarray, " r1"],
    X2: Float[np.ndarray, "N2 D"],
    index2: Int[np.ndarray, " r2"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    out: np.ndarray | None = None,
    chunk: int = 2048,
    bases1: np.ndarray | None = None,
    bases2: np.ndarray | None = None,
) -> np.ndarray:
    """``K̄(X1, X2)`` (no noise) restricted to some rows and columns, on the host.

    The rest is never formed: how a model whose cases lack some gradients keeps only the rows
    it observed (a values-only case costs one row, not ``1 + G``). Built ``chunk`` rows at a
    time, the last chunk padded, so that a model that grows reuses one compiled program per
    width.

    Args:
        X1: (N1, D) the points of the rows.
        index1: (r1,) the rows, in the layout of ``X1`` (:mod:`gpg.gp.layout`).
        X2: (N2, D) the points of the columns.
        index2: (r2,) the columns, in the layout of ``X2``.
        hyper: the hyperparameters (σ and l are read).
        grad_dims: the G input dims of the gradient rows.
        out: an (r1, r2) buffer to write into; a new one if None.
        chunk: how many rows each compiled block makes.
        bases1: (N1, G, G) directions of the gradient rows of ``X1``'s cases
            (:func:`gpg.gp.directions.row_directions`), or None (along the inputs).
        bases2: (N2, G, G) the same for ``X2``'s cases.

    Returns:
        The (r1, r2) matrix: ``out`` when given.
    """
    X1, X2 = np.asarray(X1), np.asarray(X2)
    directional = bases1 is not None or bases2 is not None
    p1, left, kernel = layout_rows(index1, X1.shape[0], grad_dims, bases1, directional, X1.shape[1])
    p2, right, _ = layout_rows(index2, X2.shape[0], grad_dims, bases2, directional, X2.shape[1])
    r1 = p1.shape[0]
    if out is None:
        out = np.empty((r1, p2.shape[0]))
    step = min(chunk, max(r1, 1))
    right = (_host.asarray(X2[p2]), *(_host.asarray(a) for a in right))
    for start in range(0, r1, step):
        stop = min(start + step, r1)
        sel = np.arange(start, start + step).clip(max=r1 - 1)  # padded with the last row
        block = kernel(
            _host.asarray(X1[p1[sel]]), *(_host.asarray(a[sel]) for a in left), *right,
            hyper.variance, hyper.lengthscale,
        )  # fmt: skip
        out[start:stop] = np.asarray(block)[: stop - start]
    return out


def assemble_rows_gram(
    X: Float[np.ndarray, "N D"],
    index: Int[np.ndarray, " r"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    out: np.ndarray | None = None,
    bases: np.ndarray | None = None,
) -> np.ndarray:
    """``K̄`` plus its noise diagonal over some layout rows only: :func:`assemble_gram` for them.

    The rows are typically the observed rows of cases that lack some gradients
    (:func:`gpg.gp.layout.observed_rows`). Each row keeps the noise of its place in the layout:
    ``ν²`` on a value row, ``λ_g²`` on gradient row ``g``, along a direction or not.

    Args:
        X: (N, D) the training inputs.
        index: (r,) the rows to form, in the layout of ``X``.
        hyper: the hyperparameters (σ, l, ν², λ²).
        grad_dims: the G input dims of the gradient rows.
        out: an (r, r) buffer to write into; a new one if None.
        bases: (N, G, G) the directions of the cases' gradient rows
            (:func:`gpg.gp.directions.row_directions`), or None (along the inputs).

    Returns:
        The (r, r) matrix: ``out`` when given.
    """
    out = rows_gram(
        X, index, X, index, hyper, grad_dims, out=out, chunk=256, bases1=bases, bases2=bases
    )
    n, g = np.asarray(X).shape[0], len(grad_dims)
    out.flat[:: out.shape[0] + 1] += _noise_diagonal(hyper, n, g)[np.asarray(index)]
    return out


@highest
def noisy_gram(
    X: Float[Array, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    rows: Bool[ArrayLike, " R"] | None = None,
) -> Float[Array, "R R"]:
    """``K̄(X, X)`` plus its noise diagonal (``ν²`` on value rows, ``λ²`` on gradient rows) in JAX.

    The one form every traced factorisation starts from (the likelihood, the local bins on
    devices, PIC's blocks); :func:`assemble_gram` is its host twin for large ``K̄``. The
    unobserved rows are decoupled as :func:`mask_gram_inplace` does on the host.

    Args:
        X: (N, D) the training inputs.
        hyper: the hyperparameters (σ, l, ν², λ²).
        grad_dims: the G input dims of the gradient rows.
        rows: (R,) the observed rows (:func:`gpg.gp.layout.observed_rows`), or None (all).

    Returns:
        The (R, R) matrix, R = N (1 + G), with identity rows and columns where not observed.
    """
    K = kernels.gram(X, X, hyper.variance, hyper.lengthscale, grad_dims, grad_dims)
    K = K + jnp.diag(hyper.noise_diagonal(X.shape[0], len(grad_dims)))
    if rows is None:
        return K
    m = jnp.asarray(rows, dtype=K.dtype)
    return K * m[:, None] * m[None, :] + jnp.diag(1.0 - m)


def mask_gram_inplace(K: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """Decouple the unobserved rows of a host ``K̄``: identity rows and columns there.

    With the targets 0 there (:func:`gpg.gp.targets.mask_targets`), the posterior is the one
    conditioned on the observed rows alone (:func:`gpg.gp.layout.observed_rows`).

    Args:
        K: (R, R) the matrix, overwritten.
        rows: (R,) bool, the observed rows, or None (all of them: ``K`` is left as it is).

    Returns:
        ``K`` itself.
    """
    if rows is None:
        return K
    miss = np.flatnonzero(~rows)
    K[miss, :] = 0.0
    K[:, miss] = 0.0
    K[miss, miss] = 1.0
    return K


def device_gram(
    X: Float[ArrayLike, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    index: Int[np.ndarray, " r"] | None = None,
    bases: np.ndarray | None = None,
    chunk_bytes: int = 1 << 28,
) -> Float[Array, "r r"]:
    """``K̄`` plus its noise diagonal over some layout rows, built on JAX's default device.

    The device twin of :func:`assemble_gram` and :func:`assemble_rows_gram`, in float64, for
    :mod:`gpg.linalg.device`. Rows are made a block at a time into one preallocated buffer (the
    kernels' elementwise temporaries of a block stay under ``chunk_bytes``), so the peak is the
    matrix itself.

    Args:
        X: (N, D) the training inputs.
        hyper: the hyperparameters (σ, l, ν², λ²).
        grad_dims: the G input dims of the gradient rows.
        index: (r,) the rows to form, in the layout of ``X``; None for all N (1 + G).
        bases: (N, G, G) the directions of the cases' gradient rows
            (:func:`gpg.gp.directions.row_directions`), or None (along the inputs).
        chunk_bytes: the bound on a block's temporaries, in bytes.

    Returns:
        The (r, r) matrix on the default device.
    """
    X = np.asarray(X, dtype=np.float64)
    n, g = X.shape[0], len(grad_dims)
    index = np.arange(n * (1 + g)) if index is None else np.asarray(index)
    p, what, kernel = layout_rows(index, n, grad_dims, bases, bases is not None, X.shape[1])
    r = index.size
    # The row kernels hold a few (block x r) temporaries, (block x r x D) for directions.
    per_row = 8 * r * (4 + (X.shape[1] if bases is not None else 0))
    block = int(max(1, min(r, chunk_bytes // per_row)))
    noise = _noise_diagonal(hyper, n, g)[index]
    return _device_gram(
        _host.asarray(X[p]), tuple(_host.asarray(a) for a in what), _host.asarray(noise),
        hyper.variance, hyper.lengthscale, kernel=kernel, block=block,
    )  # fmt: skip


@partial(jax.jit, static_argnames=("kernel", "block"))
@highest
def _device_gram(
    Xr: Float[Array, "r D"],
    what: tuple[Array, ...],
    noise: Float[Array, " r"],
    variance: Float[ArrayLike, ""],
    lengthscale: Float[ArrayLike, "*L"],
    *,
    kernel: Callable[..., Any],
    block: int,
) -> Float[Array, "r r"]:
    r = Xr.shape[0]
    n_blocks = -(-r // block)

    def fill(i, K):
        # The last block starts early enough to end at r: its first rows are made twice.
        start = jnp.minimum(i * block, r - block)
        rows = (jax.lax.dynamic_slice_in_dim(a, start, block) for a in (Xr, *what))
        part = kernel(*rows, Xr, *what, variance, lengthscale)
        return jax.lax.dynamic_update_slice_in_dim(K, part, start, axis=0)

    K = jax.lax.fori_loop(0, n_blocks, fill, jnp.zeros((r, r), Xr.dtype))
    diag = jnp.arange(r)
    return K.at[diag, diag].add(noise)  # in place: no second r x r array


def _noise_diagonal(hyper: Hyper, n: int, g: int) -> np.ndarray:
    """:meth:`Hyper.noise_diagonal` on the host, for the Grams assembled there: the same values
    (copies, no arithmetic), without the four small programs the eager one compiled for every
    ``n``."""
    noise = np.asarray(hyper.noise)
    if g == 0:
        return np.full(n, noise)
    per_block = np.concatenate([noise[None], np.broadcast_to(np.asarray(hyper.grad_noise), (g,))])
    return np.repeat(per_block, n)
