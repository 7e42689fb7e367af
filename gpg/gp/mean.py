"""The exact GP-G posterior mean ``μ(x_q) = k̄_qᵀ α`` over every training point, folded.

With ``α = K̄⁻¹ Ȳ`` split into its value block ``α⁰`` (N, M) and one block ``αᵍ`` per gradient
dimension ``g``, and ``k0m = k (x_q,g − x_g) / l_g²`` for the value-gradient covariance
(paper Eq. kernel_gradient),

    μ(x_q) = Σ_p k(x_q, x_p) [α⁰_p − Σ_g x_p,g/l_g² αᵍ_p] + Σ_g x_q,g/l_g² Σ_p k(x_q, x_p) αᵍ_p.

The brackets do not depend on the query, so a prediction is one row of plain kernel values
``k(x_q, X)`` (N entries, from one matrix product) times a fixed (N, (1+G)·M) coefficient
matrix, plus a combination of ``1+G`` results: O(N·(1+G)·M) per query with no per-pair
gradient kernel, and a batch of queries is two dense matrix products. This is what makes the
exact mean cheap enough for real time; the expensive part of GP-G is its variance.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg import _host
from gpg._precision import highest
from gpg.gp import kernels

__all__ = ["GlobalMean", "output_scale"]


class GlobalMean(eqx.Module):
    """``x ↦ k̄(x, X)ᵀ α`` for one query, in the folded form of the module docstring.

    Attributes:
        Xs: training inputs divided by the lengthscales, ``X / l`` (N, D).
        coef: ``[α⁰ − Σ_g (x_g/l_g²) αᵍ, α^{g_0}, …, α^{g_{G-1}}]`` side by side (N, (1+G)·M).
        inv_ls: ``1/l`` per input (D,).
        variance: signal variance σ.
        grad_dims: the G gradient dimensions (static).
    """

    Xs: Float[Array, "N D"]
    coef: Float[Array, "N C"]
    inv_ls: Float[Array, " D"]
    variance: Float[Array, ""]
    grad_dims: tuple[int, ...] = eqx.field(static=True)

    @classmethod
    def from_alpha(
        cls,
        X: Float[ArrayLike, "N D"],
        alpha: Float[ArrayLike, "R M"],
        variance: Float[ArrayLike, ""],
        lengthscale: Float[ArrayLike, "*L"],
        grad_dims: tuple[int, ...],
    ) -> GlobalMean:
        """Fold ``α`` into the coefficients of the module docstring's form.

        The lengthscales enter the coefficients (``x_g / l_g²``), so the folded mean is for
        these hyperparameters only.

        Args:
            X: (N, D) the training inputs.
            alpha: (R, M) ``α = K̄⁻¹ Ȳ``, ``R = N(1+G)`` in the row layout of
                :mod:`gpg.gp.kernels` (over coordinate rows:
                :func:`gpg.gp.gram.from_bases` for directional ones).
            variance: the signal variance σ.
            lengthscale: ``l``, a scalar or (D,).
            grad_dims: the G input dims of the gradient rows.

        Returns:
            The folded mean.

        Raises:
            ValueError: if ``alpha`` is not (N(1+G), M).
        """
        X = np.asarray(X, dtype=float)
        alpha = np.asarray(alpha, dtype=float)
        n, d = X.shape
        g = len(grad_dims)
        if alpha.ndim != 2 or alpha.shape[0] != n * (1 + g):
            raise ValueError(f"alpha must have shape ({n * (1 + g)}, M), got {alpha.shape}")
        ls = np.broadcast_to(np.asarray(lengthscale, dtype=float), (d,))
        m = alpha.shape[1]
        blocks = alpha.reshape(1 + g, n, m)
        inv_ls2 = 1.0 / ls[list(grad_dims)] ** 2
        a0 = blocks[0] - np.einsum("ng,gnm->nm", X[:, list(grad_dims)] * inv_ls2, blocks[1:])
        coef = np.concatenate([a0, *blocks[1:]], axis=1)
        return cls(
            Xs=jnp.asarray(X / ls),
            coef=_host.asarray(coef),
            inv_ls=jnp.asarray(1.0 / ls),
            variance=jnp.asarray(variance, dtype=float),
            grad_dims=tuple(grad_dims),
        )

    @property
    def n_outputs(self) -> int:
        return self.coef.shape[1] // (1 + len(self.grad_dims))

    @highest
    def __call__(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """Mean (M,) at one query ``x`` (D,): ``k(x, X)`` times the folded coefficients."""
        k = kernels.rbf_matrix((x * self.inv_ls)[None], self.Xs, self.variance)[0]
        out = (k @ self.coef).reshape(1 + len(self.grad_dims), self.n_outputs)
        if not self.grad_dims:
            return out[0]
        idx = np.asarray(self.grad_dims)
        xg = x[idx] * self.inv_ls[idx] ** 2
        return out[0] + xg @ out[1:]


def output_scale(yty: Float[ArrayLike, " M"], n_rows: int) -> np.ndarray:
    """Per-output signal scale ``c_m = Ȳ_mᵀ K̄⁻¹ Ȳ_m / R`` (M,).

    All outputs share one kernel; scaling it by ``c_m`` for output ``m`` leaves the mean
    unchanged and maximises the likelihood of that output in closed form, so the predictive
    variance of output ``m`` is ``c_m (var + ν²)``. From ``α`` already computed: no extra
    factorisation. With one shared scale the forces were over-covered and the moments
    under-covered; the per-output scales' effect on NLPD and coverage is in docs/results.md
    ("Fitted noise").

    Args:
        yty: (M,) ``Ȳ_mᵀ α_m`` per output.
        n_rows: R, the number of observed rows of ``Ȳ``.

    Returns:
        ``c`` (M,), at least the smallest positive float.

    Raises:
        ValueError: if ``n_rows`` is not positive.
    """
    yty = np.asarray(yty, dtype=float)
    if n_rows <= 0:
        raise ValueError(f"n_rows must be positive, got {n_rows}")
    return np.maximum(yty / n_rows, np.finfo(float).tiny)
