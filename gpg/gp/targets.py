"""The stacked targets ``Ȳ`` and the training data they are stacked from, checked.

``Ȳ`` has the row layout of :mod:`gpg.gp.kernels` (:mod:`gpg.gp.layout`): the ``N`` values,
then one block of ``N`` rows per gradient dimension. :func:`check_training_data` turns what a
caller passes (``X``, ``Y``, ``dY``, the gradient dims, which gradients were observed) into
float arrays of known shapes once, naming the argument that is wrong, so that the numerics
behind it need no checks of their own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from gpg import _checks
from gpg.gp import kernels
from gpg.gp.layout import observed_rows

__all__ = ["mask_targets", "stack_targets"]


def stack_targets(Y: Float[Array, "N M"], dY: Float[Array, "N M G"] | None) -> Float[Array, "R M"]:
    """Stack values and gradients into ``Ȳ`` with the layout of :mod:`gpg.gp.kernels`.

    The values first, then the gradients one dimension after the other, as ``K̄``'s rows.
    NumPy in, NumPy out (no compilation for the offline fit); JAX arrays stay JAX arrays.

    Args:
        Y: (N, M) the values of the M outputs at the N training inputs.
        dY: (N, M, G) their gradients along the G gradient dims, or None (values only).

    Returns:
        ``Ȳ`` (N (1 + G), M); ``Y`` itself when there are no gradients.
    """
    xp = np if isinstance(Y, np.ndarray) and (dY is None or isinstance(dY, np.ndarray)) else jnp
    if dY is None or dY.shape[2] == 0:
        return Y
    grads = xp.moveaxis(dY, 2, 0).reshape(-1, Y.shape[1])
    return xp.concatenate([Y, grads], axis=0)


def mask_targets(Ybar: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """``Ȳ`` with the unobserved rows 0.

    The stored values of those rows, NaN or not, are never read: a model conditions on the
    observed rows alone (:func:`gpg.gp.layout.observed_rows`).

    Args:
        Ybar: (R, M) the stacked targets.
        rows: (R,) bool, the observed rows, or None (all of them).

    Returns:
        A float copy of ``Ybar`` with the unobserved rows 0; ``Ybar`` itself when ``rows`` is
        None.
    """
    if rows is None:
        return Ybar
    out = np.array(Ybar, dtype=float, copy=True)
    out[~rows] = 0.0
    return out


@dataclass(frozen=True)
class Checked:
    """Training data after :func:`check_training_data`: float arrays, ``Y`` (N, M), ``dY``
    (N, M, G) or None, and the gradient dims as a tuple."""

    X: np.ndarray
    Y: np.ndarray
    dY: np.ndarray | None
    grad_dims: tuple[int, ...]
    observed: np.ndarray | None = None  # (N, G) bool, None when every gradient was observed

    @property
    def rows(self) -> np.ndarray | None:
        """The observed stacked rows (:func:`gpg.gp.layout.observed_rows`)."""
        return observed_rows(self.observed, self.X.shape[0])

    def gradients(self) -> np.ndarray | None:
        """``dY`` with NaN where a gradient was not observed (what :mod:`gpg.data` passes).

        Returns:
            (N, M, G) the gradients, NaN where not observed; None without gradients.
        """
        if self.dY is None or self.observed is None:
            return self.dY
        return np.where(self.observed[:, None], self.dY, np.nan)

    def targets(self) -> np.ndarray:
        """``Ȳ`` (R, M), 0 on the unobserved rows.

        Returns:
            The stacked targets (:func:`stack_targets`).
        """
        dY = self.dY if self.observed is None else np.where(self.observed[:, None], self.dY, 0.0)
        return stack_targets(self.Y, dY)


def check_training_data(
    X: Float[ArrayLike, "N D"],
    Y: Float[ArrayLike, "N M"] | Float[ArrayLike, " N"],
    dY: Float[ArrayLike, "N M G"] | Float[ArrayLike, "N G"] | None,
    grad_dims: Sequence[int] | None,
    observed: Bool[ArrayLike, "N G"] | None = None,
) -> Checked:
    """Training data as float arrays of known shapes, every error naming its argument.

    A single output may come as ``Y`` (N,) and ``dY`` (N, G). Without ``grad_dims`` the
    gradients are along every input. Only the observed entries of ``dY`` must be finite: the
    others are never read.

    Args:
        X: (N, D) the training inputs, N ≥ 1.
        Y: (N, M) or (N,) the values at ``X``.
        dY: (N, M, G) or, with one output, (N, G) the gradients; None for values only.
        grad_dims: the G input dims the gradients are along; None for all D (``dY`` then has
            G = D).
        observed: (N, G) bool, which gradients each case has; None when all were observed.

    Returns:
        The :class:`Checked` data (``observed`` None when every gradient was observed).

    Raises:
        ValueError: if ``X`` is empty, a shape does not match ``X`` or the other arrays,
            ``grad_dims`` or ``observed`` is given without ``dY``, ``grad_dims`` disagrees
            with ``dY``, or an array (the observed part of ``dY``) is not finite.
    """
    X = _checks.as_float_array("X", X, ndim=2)
    Y = _checks.as_float_array("Y", Y, ndim=(1, 2))
    if Y.ndim == 1:
        Y = Y[:, None]
    n, d = X.shape
    if n == 0:
        raise ValueError("X must hold at least one point")
    if Y.shape[0] != n:
        raise ValueError(f"Y has {Y.shape[0]} rows but X has {n}")
    _checks.require_finite("X", X)
    _checks.require_finite("Y", Y)
    if dY is None:
        if grad_dims not in (None, (), []):
            raise ValueError(f"grad_dims={tuple(grad_dims)} given but dY is None")
        if observed is not None:
            raise ValueError("observed given but dY is None: it marks which gradients exist")
        return Checked(X, Y, None, ())
    dY = _checks.as_float_array("dY", dY, ndim=(2, 3))
    if dY.ndim == 2:
        if Y.shape[1] != 1:
            raise ValueError(f"dY must have shape (N, M, G) for M={Y.shape[1]} outputs")
        dY = dY[:, None, :]
    if dY.shape[:2] != Y.shape:
        raise ValueError(f"dY must have shape (N, M, G) = ({n}, {Y.shape[1]}, G), got {dY.shape}")
    if grad_dims is None:
        if dY.shape[2] != d:
            raise ValueError(
                f"dY has {dY.shape[2]} gradient dims but X has {d} inputs: pass grad_dims"
            )
        grad_dims = tuple(range(d))
    grad_dims = kernels.check_dims(grad_dims, d)
    if len(grad_dims) != dY.shape[2]:
        raise ValueError(f"grad_dims names {len(grad_dims)} dims but dY has {dY.shape[2]}")
    if observed is None:
        _checks.require_finite("dY", dY)
        return Checked(X, Y, dY, grad_dims)
    observed = np.asarray(observed)
    if observed.dtype != bool or observed.shape != (n, len(grad_dims)):
        raise ValueError(
            f"observed must be a boolean array of shape (N, G) = ({n}, {len(grad_dims)}), "
            f"got {observed.dtype} {observed.shape}"
        )
    _checks.require_finite("dY", np.where(observed[:, None, :], dY, 0.0))
    return Checked(X, Y, dY, grad_dims, None if observed.all() else observed)
