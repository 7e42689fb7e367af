"""The log marginal likelihood on all the data without forming ``K̄`` (GPyTorch's BBMM, for
the gradient kernel).

``log p(Ȳ | X) = −½ Σ_m Ȳ_mᵀ K̄⁻¹ Ȳ_m − ½ M log|K̄| − ½ M R log 2π`` needs two things that
are usually read off a Cholesky factor:

* the data term, from ``α = K̄⁻¹ Ȳ`` by preconditioned CG over matrix-free products
  (:func:`gpg.gp.matfree.gram_matvec`, the Nyström preconditioner ``P̂`` of :mod:`gpg.gp.cg`);
* ``log|K̄| = log|P̂| + tr log(P̂^{-½} K̄ P̂^{-½})``: ``log|P̂|`` exactly (determinant lemma),
  the trace by stochastic Lanczos quadrature with probes ``z_p ~ N(0, P̂)``: the CG run on
  ``K̄ u_p = z_p`` is Lanczos on the preconditioned matrix, its step sizes give the
  tridiagonal ``T_p`` and ``tr log ≈ (1/P) Σ_p (z_pᵀ P̂⁻¹ z_p) e₁ᵀ log(T_p) e₁``.

The gradient is not differentiated through the iterations: with ``α`` and ``u_p = K̄⁻¹ z_p``
held fixed, ``∂(−log p) = −½ Σ_m α_mᵀ ∂K̄ α_m + ½ M tr(K̄⁻¹ ∂K̄)`` and Hutchinson's estimate
``tr(K̄⁻¹ ∂K̄) ≈ (1/P) Σ_p u_pᵀ ∂K̄ P̂⁻¹ z_p`` (unbiased since ``E[z zᵀ] = P̂``) are both
bilinear forms in ``K̄``, differentiated by reverse mode through one matrix-free product.

The probes are drawn once (``eps``) and pushed through each ``P̂``, so the objective is a
deterministic function of the hyperparameters, as a quasi-Newton line search needs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from gpg.gp import cg
from gpg.gp.hyper import Hyper
from gpg.gp.matfree import gram_matvec

__all__ = [
    "PCGResult",
    "Probes",
    "StochasticLML",
    "pcg_lanczos",
    "stochastic_log_marginal_likelihood",
]


class Probes(NamedTuple):
    """Standard normal draws behind the probes ``z = V ε_V + D^{½} ε_D`` (``P̂ = V Vᵀ + D``):
    ``eps_v`` (U(1+G), P), ``eps_d`` (R, P)."""

    eps_v: Float[Array, "Q P"]
    eps_d: Float[Array, "R P"]

    @classmethod
    def draw(cls, rows: int, inducing_rows: int, n_probes: int, seed: int) -> Probes:
        """Fixed probes for a ``K̄`` and its Nyström preconditioner, from a seed.

        The draws stay fixed over a fit, so the objective is a deterministic function of the
        hyperparameters; each ``P̂`` turns them into its own probes.

        Args:
            rows: R, the rows of ``K̄``.
            inducing_rows: U(1+G), the inducing rows of the preconditioner.
            n_probes: P, the number of probes, a positive integer.
            seed: seed of the draws.

        Returns:
            The standard normal draws ``eps_v`` (U(1+G), P) and ``eps_d`` (R, P).

        Raises:
            ValueError: if ``n_probes`` is not a positive integer.
        """
        if isinstance(n_probes, bool) or not isinstance(n_probes, int) or n_probes < 1:
            raise ValueError(f"the number of probes must be a positive integer, got {n_probes!r}")
        rng = np.random.default_rng(seed)
        return cls(
            jnp.asarray(rng.standard_normal((inducing_rows, n_probes))),
            jnp.asarray(rng.standard_normal((rows, n_probes))),
        )


class PCGResult(NamedTuple):
    """:func:`pcg_lanczos`'s solution ``x`` and per column: ``steps`` taken, the step sizes
    ``alpha`` and ratios ``beta`` of each step (rows past ``steps`` are 0), ``rz0 = bᵀ P̂⁻¹ b``
    and the final relative ``residual``."""

    x: Float[Array, "R K"]
    steps: Int[Array, " K"]
    alpha: Float[Array, "J K"]
    beta: Float[Array, "J K"]
    rz0: Float[Array, " K"]
    residual: Float[Array, " K"]


def pcg_lanczos(
    matvec: Callable[[Array], Array],
    B: Float[Array, "R K"],
    precond: Callable[[Array], Array],
    *,
    tol: float,
    max_iter: int,
) -> PCGResult:
    """Preconditioned CG on every column of ``B``, keeping what Lanczos quadrature needs.

    Traceable (``lax.while_loop``), unlike :func:`gpg.gp.cg.solve`: the step sizes ``α_j``
    and ratios ``β_j`` of each column's run are the entries of its Lanczos tridiagonal ``T``
    on the preconditioned matrix. A column stops (its coefficients frozen) once its relative
    residual is at most ``tol``; all stop after ``max_iter`` steps, converged or not.

    Args:
        matvec: the product with the symmetric positive definite ``K̄`` (R, K) -> (R, K).
        B: (R, K) right-hand sides: the targets and the probes.
        precond: ``P̂⁻¹`` applied to an (R, K) block (:class:`gpg.gp.cg.Nystrom`).
        tol: relative residual at which a column stops.
        max_iter: the most steps any column takes (the length of the coefficient history).

    Returns:
        The solution, the steps each column took, the coefficients of each step, ``bᵀ P̂⁻¹ b``
        and the final relative residuals (:class:`PCGResult`).
    """
    bnorm = jnp.linalg.norm(B, axis=0)
    bnorm = jnp.where(bnorm > 0, bnorm, 1.0)
    z = precond(B)
    rz0 = jnp.sum(B * z, 0)
    k = B.shape[1]
    hist = jnp.zeros((max_iter, k), B.dtype)
    init = (0, jnp.zeros_like(B), B, z, rz0, rz0 > 0, jnp.zeros(k, int), hist, hist)

    def cond(s):
        return (s[0] < max_iter) & jnp.any(s[5])

    def body(s):
        i, x, r, p, rz, active, steps, ha, hb = s
        q = matvec(p)
        pq = jnp.sum(p * q, 0)
        a = jnp.where(active & (pq > 0), rz / jnp.where(pq > 0, pq, 1.0), 0.0)
        x, r = x + a * p, r - a * q
        z = precond(r)
        rz_new = jnp.sum(r * z, 0)
        b = jnp.where(active, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
        p = jnp.where(active, z + b * p, p)
        steps = steps + active
        rz = jnp.where(active, rz_new, rz)
        active = active & (jnp.linalg.norm(r, axis=0) / bnorm > tol)
        return i + 1, x, r, p, rz, active, steps, ha.at[i].set(a), hb.at[i].set(b)

    _, x, r, _, _, _, steps, ha, hb = jax.lax.while_loop(cond, body, init)
    return PCGResult(x, steps, ha, hb, rz0, jnp.linalg.norm(r, axis=0) / bnorm)


def lanczos_log_quadrature(
    alpha: Float[Array, "J K"], beta: Float[Array, "J K"], steps: Int[Array, " K"], lanczos: int
) -> Float[Array, " K"]:
    """``e₁ᵀ log(T) e₁`` for each column's Lanczos tridiagonal ``T`` (from CG's step sizes
    ``alpha`` and ratios ``beta``; its first ``min(steps, lanczos)`` steps)."""
    a, b = alpha[:lanczos].T, beta[:lanczos].T  # (K, J)
    j = jnp.arange(a.shape[1])
    valid = j[None] < jnp.minimum(steps, lanczos)[:, None]
    inv_a = jnp.where(valid, 1.0 / jnp.where(valid, a, 1.0), 0.0)
    prev = jnp.concatenate([jnp.zeros_like(a[:, :1]), (b * inv_a)[:, :-1]], axis=1)
    # Steps past a column's own are a decoupled identity block: log 1 = 0 adds nothing.
    diag = jnp.where(valid, inv_a + prev, 1.0)
    off_valid = valid[:, 1:]
    off = jnp.where(off_valid, jnp.sqrt(jnp.maximum(b[:, :-1], 0.0)) * inv_a[:, :-1], 0.0)
    T = jax.vmap(jnp.diag)(diag) + jax.vmap(lambda o: jnp.diag(o, 1) + jnp.diag(o, -1))(off)
    lam, U = jnp.linalg.eigh(T)
    return jnp.sum(U[:, 0, :] ** 2 * jnp.log(jnp.maximum(lam, jnp.finfo(lam.dtype).tiny)), axis=1)


class StochasticLML(NamedTuple):
    """:func:`stochastic_log_marginal_likelihood`'s value (with the gradient described in the
    module docstring), its log-determinant estimate, CG steps and whether every solve reached
    its tolerance."""

    value: Float[Array, ""]
    log_det: Float[Array, ""]
    steps: Int[Array, ""]
    converged: Array


def stochastic_log_marginal_likelihood(
    X: Float[Array, "N D"],
    Ybar: Float[Array, "R M"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    Z: Float[Array, "U D"],
    probes: Probes,
    *,
    tol: float = 1e-5,
    max_iter: int = 500,
    lanczos: int = 100,
    tile: int = 256,
    probe_tol: float | None = None,
) -> StochasticLML:
    """``log p(Ȳ | X)`` without forming ``K̄``: CG, stochastic Lanczos quadrature, Hutchinson.

    The sum over the M columns of ``Ȳ``, as :func:`gpg.gp.gram.log_marginal_likelihood`: CG
    for the data term, stochastic Lanczos quadrature for ``log|K̄|`` with the fixed
    ``probes``, a Nyström preconditioner on the inducing inputs; reverse- and forward-mode
    differentiable in ``hyper`` through Hutchinson's estimate of the trace term (module
    docstring). Pure JAX. The probes' sampling error dwarfs a looser solve's, and their
    Lanczos quadrature converges long before the solve does, so ``probe_tol`` ≫ ``tol`` saves
    most of the products (docs/scaling.md measures it).

    Args:
        X: (N, D) training inputs.
        Ybar: (R, M) stacked targets ``Ȳ``, ``R = N(1+G)``, in the layout of
            :mod:`gpg.gp.kernels`.
        hyper: the hyperparameters (σ, l, ν², λ_i²) the likelihood and its gradient are
            taken at.
        grad_dims: the input dimensions that carry gradient rows.
        Z: (U, D) inducing inputs of the preconditioner ``P̂``.
        probes: the fixed draws behind the probes (:meth:`Probes.draw`).
        tol: relative residual of the data solves ``K̄ α = Ȳ``.
        max_iter: the most CG steps per solve.
        lanczos: the most Lanczos steps in each probe's quadrature.
        tile: training points per tile of the matrix-free products.
        probe_tol: relative residual of the probe solves (default ``tol``); when it differs
            they run as a second CG of their own.

    Returns:
        The log likelihood (its gradient through the surrogate), the ``log|K̄|`` estimate,
        the most CG steps taken and whether every solve reached its tolerance
        (:class:`StochasticLML`).
    """
    h = jax.lax.stop_gradient(hyper)
    r, m = Ybar.shape
    n_probes = probes.eps_d.shape[1]
    P = cg.Nystrom.create(X, h, grad_dims, Z, chunk=None)
    Zp = P.V @ probes.eps_v + jnp.sqrt(1.0 / P.d_inv)[:, None] * probes.eps_d
    ptol = tol if probe_tol is None else probe_tol

    def solve(B, tol):
        matvec = lambda v: gram_matvec(X, h, grad_dims, v, tile=tile)  # noqa: E731
        return pcg_lanczos(matvec, B, P, tol=tol, max_iter=max_iter)

    if ptol == tol:
        res = solve(jnp.concatenate([Ybar, Zp], axis=1), tol)
        fit, probe = res, jax.tree.map(lambda a: a[..., m:], res)
    else:
        # Two loops: one shared loop runs every column as long as its slowest one.
        fit, probe = solve(Ybar, tol), solve(Zp, ptol)
    quad = lanczos_log_quadrature(probe.alpha, probe.beta, probe.steps, lanczos)
    log_det = P.log_det() + jnp.mean(probe.rz0 * quad)
    alpha, u = fit.x[:, :m], probe.x
    data = jnp.sum(Ybar * alpha)
    value = -0.5 * data - 0.5 * m * log_det - 0.5 * m * r * jnp.log(2 * jnp.pi)
    # The bilinear surrogate carries the gradient of −log p (module docstring); the value is
    # the estimate above.
    left = jax.lax.stop_gradient(jnp.concatenate([alpha, u], axis=1))
    right = jax.lax.stop_gradient(jnp.concatenate([alpha, P(Zp)], axis=1))
    weight = jnp.concatenate([jnp.full(m, -0.5), jnp.full(n_probes, 0.5 * m / n_probes)])
    surrogate = -jnp.sum(left * weight * gram_matvec(X, hyper, grad_dims, right, tile=tile))
    value = jax.lax.stop_gradient(value - surrogate) + surrogate
    converged = jnp.all(fit.residual <= tol) & jnp.all(probe.residual <= ptol)
    steps = jnp.maximum(jnp.max(fit.steps), jnp.max(probe.steps))
    return StochasticLML(value, log_det, steps, converged)
