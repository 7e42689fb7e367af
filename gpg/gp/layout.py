"""The row layout of ``K̄`` and ``Ȳ`` (paper Eq. barK): which point each row belongs to, what it
observes, which rows were observed, and how a row kernel reads a set of rows.

The layout is that of :mod:`gpg.gp.kernels`: the ``N`` value rows first, then one block of
``N`` rows per gradient dimension, so that row ``i + N (1 + g)`` is case ``i``'s gradient row
``g``. A case whose gradient rows are derivatives along other directions than the inputs keeps
the same layout; :mod:`gpg.gp.directions` says along what.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg.gp import kernels
from gpg.gp.directions import row_directions

__all__ = ["observed_rows"]


def row_kinds(
    index: Int[np.ndarray, " r"], n: int, grad_dims: tuple[int, ...]
) -> tuple[Int[np.ndarray, " r"], Int[np.ndarray, " r"]]:
    """For rows ``index`` of the layout of ``n`` points: each row's point and what it observes
    (``-1`` the value, ``d`` the derivative along input ``d``), as :func:`kernels.row_gram`
    reads them."""
    index = np.asarray(index, dtype=np.int64)
    deriv = np.asarray((-1, *grad_dims), dtype=np.int32)[index // n]
    return index % n, deriv


def layout_rows(
    index: Int[ArrayLike, " r"],
    n: int,
    grad_dims: tuple[int, ...],
    bases: Float[ArrayLike, "N G G"] | None,
    directional: bool,
    d: int,
) -> tuple[np.ndarray, tuple[np.ndarray, ...], Callable[..., Any]]:
    """Rows ``index`` of the layout of ``n`` points as a row kernel reads them: their points,
    what each observes, and the kernel. Along the inputs, :func:`row_kinds` for
    :func:`kernels.row_gram` (cheaper than the general form on coordinate rows); with
    ``directional`` (either side has ``bases``), :func:`row_directions` for
    :func:`kernels.direction_gram`."""
    if not directional:
        p, a = row_kinds(index, n, grad_dims)
        return p, (a,), kernels.row_gram
    p, E, v = row_directions(index, n, grad_dims, None if bases is None else np.asarray(bases), d)
    return p, (E, v), kernels.direction_gram


def observed_rows(observed: Bool[np.ndarray, "N G"] | None, n: int) -> np.ndarray | None:
    """Per stacked row (R,), whether it was observed.

    A case whose simulator run skipped some finite-difference perturbations has no rows for
    those gradient dims. The layout keeps its fixed shape (targets 0 there); the exact GP forms
    and factorises only the observed rows (:func:`gpg.gp.assembly.rows_gram`,
    ``ExactGP.order``), and the partitioned models' local factors decouple the missing ones
    (:func:`gpg.gp.assembly.mask_gram_inplace`: identity rows and columns). Either way the
    posterior is exactly the one conditioned on the observed rows alone, with no change to the
    query code.

    Args:
        observed: (N, G) whether case ``i`` has its gradient along grad dim ``g``, or None
            (every gradient observed).
        n: the number of cases ``N``.

    Returns:
        (N (1 + G),) bool: value rows always, gradient row ``(i, g)`` where ``observed[i, g]``;
        None when every gradient was observed (the common case, no mask).
    """
    if observed is None:
        return None
    observed = np.asarray(observed, dtype=bool)
    if observed.all():
        return None
    return np.concatenate([np.ones(n, dtype=bool), observed.T.ravel()])


def value_row_noise(row_noise: Float[ArrayLike, " N"], n: int, g: int) -> Float[Array, " R"]:
    """Per-case value noise (N,) spread over the layout's ``n(1+g)`` rows: on the value rows,
    0 on the gradient rows (:mod:`gpg.gp.kernels`: the N value rows come first)."""
    return jnp.concatenate([jnp.asarray(row_noise), jnp.zeros(n * g)])
