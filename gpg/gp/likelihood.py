"""The log marginal likelihood of the stacked targets ``Ȳ`` under ``K̄`` plus its noise: the
differentiable dense form the hyperparameters are fitted by (:mod:`gpg.gp.fit`), on a subset
small enough to factorise at every step.
"""

from __future__ import annotations

import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from gpg._precision import highest
from gpg.gp.assembly import noisy_gram
from gpg.gp.hyper import Hyper
from gpg.gp.layout import layout_rows, value_row_noise

__all__ = ["log_marginal_likelihood"]


@highest
def log_marginal_likelihood(
    X: Float[Array, "N D"],
    Ybar: Float[Array, "R M"],
    hyper: Hyper,
    grad_dims: tuple[int, ...] = (),
    rows: Bool[ArrayLike, " R"] | None = None,
    bases: Float[ArrayLike, "N G G"] | None = None,
    row_noise: Float[ArrayLike, " N"] | None = None,
) -> Float[Array, ""]:
    """``Σ_m log N(Ȳ_m | 0, K̄)``: pure JAX, differentiable in ``hyper`` (small N only).

    Only the observed rows are formed and count: a values-only case adds one row to the
    factorisation, not ``1 + G``. ``K̄`` is factorised densely, so the cost is cubic in the
    number of rows.

    Args:
        X: (N, D) the training inputs.
        Ybar: (R, M) the stacked targets of :func:`gpg.gp.targets.stack_targets`, R = N (1 + G),
            0 on the unobserved rows.
        hyper: the hyperparameters (σ, l, ν², λ²), the variable of the fit.
        grad_dims: the G input dims of the gradient rows.
        rows: (R,) the observed rows (:func:`gpg.gp.layout.observed_rows`), a host array; None
            for all.
        bases: (N, G, G) the directions of the gradient rows
            (:func:`gpg.gp.directions.row_directions`), or None (along the inputs).
        row_noise: (N,) each case's own value-noise variance, added to ``ν²`` on its value row
            (heteroscedastic labels), or None.

    Returns:
        The log likelihood, a scalar summed over the M outputs.
    """
    n, g = X.shape[0], len(grad_dims)
    extra = None if row_noise is None else value_row_noise(row_noise, n, g)
    if rows is None and bases is None:
        K = noisy_gram(X, hyper, grad_dims)
        if extra is not None:
            K = K + jnp.diag(extra)
    else:
        index = np.arange(n * (1 + g)) if rows is None else np.flatnonzero(np.asarray(rows))
        p, what, kernel = layout_rows(index, n, grad_dims, bases, bases is not None, X.shape[1])
        Xr = jnp.asarray(X)[p]
        what = tuple(jnp.asarray(a) for a in what)
        K = kernel(Xr, *what, Xr, *what, hyper.variance, hyper.lengthscale)
        K = K + jnp.diag(hyper.noise_diagonal(n, g)[index])
        if extra is not None:
            K = K + jnp.diag(extra[index])
        Ybar = Ybar[index]
    c, lower = jsl.cho_factor(K, lower=True)
    alpha = jsl.cho_solve((c, lower), Ybar)
    m = Ybar.shape[1]
    r = Ybar.shape[0]
    return (
        -0.5 * jnp.sum(Ybar * alpha)
        - m * jnp.sum(jnp.log(jnp.diag(c)))
        - 0.5 * m * r * jnp.log(2 * jnp.pi)
    )
