"""``α = K̄⁻¹ Ȳ`` by preconditioned conjugate gradients, never forming ``K̄``.

The products are :func:`gpg.gp.matfree.gram_matvec`; the preconditioner is a Nyström
approximation from inducing inputs that carry value and gradient rows (gpg's PIC inducing
points, :func:`gpg.gp.pic.inducing_inputs`), with the diagonal left over:

``P = Q + D``, ``Q = K̄_xu K̄_uu⁻¹ K̄_ux``, ``D = diag(K̄ − Q) + diag(ν², λ²)``,

applied by the Woodbury identity through one Cholesky factor of size ``U(1+G)``. Each output
(column of ``Ȳ``) is its own CG run, all advanced together; a run stops counting once its
relative residual ``‖Ȳ_m − K̄ α_m‖ / ‖Ȳ_m‖`` is below ``tol``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from gpg._precision import highest
from gpg.gp import kernels
from gpg.gp.hyper import Hyper

__all__ = [
    "CGInfo",
    "NotConverged",
    "Nystrom",
    "solve",
]


class NotConverged(ValueError):
    """A CG solve did not reach its tolerance within its iteration budget."""


@dataclass(frozen=True)
class CGInfo:
    """How a solve went: ``iterations`` run, each output's final relative ``residual``,
    whether all reached ``tol``, and the seconds the iterations took."""

    iterations: int
    residual: np.ndarray
    tol: float
    converged: bool
    solve_s: float


class Nystrom(eqx.Module):
    """The preconditioner ``P = V Vᵀ + D`` (module docstring) as ``P⁻¹ r``.

    ``V = K̄_xu L_u⁻ᵀ`` (R, P) with ``K̄_uu = L_u L_uᵀ``, ``d_inv = 1/D`` (R,), ``chol`` the
    lower factor of ``I + Vᵀ D⁻¹ V`` (P, P)."""

    V: Float[Array, "R P"]
    d_inv: Float[Array, " R"]
    chol: Float[Array, "P P"]

    @classmethod
    @highest
    def create(
        cls,
        X: Float[Array, "N D"],
        hyper: Hyper,
        grad_dims: tuple[int, ...],
        Z: Float[Array, "U D"],
        *,
        jitter: float = 1e-6,
        chunk: int | None = 512,
    ) -> Nystrom:
        """The preconditioner for ``K̄`` of ``X`` from inducing inputs ``Z``.

        The inducing inputs carry gradient rows for ``grad_dims`` too, as the training rows
        do; ``K̄_xu`` is never needed whole on the host path.

        Args:
            X: (N, D) training inputs.
            hyper: the hyperparameters (σ, l, ν², λ_i²).
            grad_dims: the input dimensions that carry gradient rows.
            Z: (U, D) inducing inputs (:func:`gpg.gp.pic.inducing_inputs`).
            jitter: added to ``K̄_uu``'s diagonal, relative to it.
            chunk: ``K̄_xu`` made this many points at a time into a host buffer; None: in pure
                JAX (traceable, ``K̄_xu`` held whole: the likelihood on all points rebuilds
                it at every hyperparameter step, :mod:`gpg.gp.slq`).

        Returns:
            The preconditioner, applied as ``P⁻¹ r`` by calling it.
        """
        X, Z = jnp.asarray(X), jnp.asarray(Z)
        n, g = X.shape[0], len(grad_dims)
        Lu = _inducing_factor(Z, hyper, grad_dims, jitter)
        if chunk is None:
            V = _nystrom_rows(X, Z, Lu, hyper, grad_dims=grad_dims)
            d_inv = 1.0 / _residual_diagonal(jnp.sum(V * V, 1), hyper, grad_dims, n, X)
            inner = jnp.eye(V.shape[1], dtype=V.dtype) + V.T @ (V * d_inv[:, None])
            return cls(V=V, d_inv=d_inv, chol=jnp.linalg.cholesky(inner))
        # V = K̄_xu L_u⁻ᵀ a chunk of points at a time, into one host buffer in the
        # dimension-major row layout: K̄_xu itself is never held whole.
        V = np.empty((n * (1 + g), Lu.shape[0]))
        block = partial(_nystrom_rows_jit, grad_dims=tuple(grad_dims))
        for s in range(0, n, chunk):
            rows = np.asarray(block(X[s : s + chunk], Z, Lu, hyper))
            w = min(chunk, n - s)
            for k in range(1 + g):
                V[k * n + s : k * n + s + w] = rows[k * w : (k + 1) * w]
        q = np.einsum("ij,ij->i", V, V)
        d_inv = 1.0 / np.asarray(_residual_diagonal(q, hyper, grad_dims, n, X))
        inner = np.eye(V.shape[1])
        for s in range(0, V.shape[0], chunk * (1 + g)):
            Vc = V[s : s + chunk * (1 + g)]
            inner += Vc.T @ (Vc * d_inv[s : s + chunk * (1 + g), None])
        return cls(V=jnp.asarray(V), d_inv=jnp.asarray(d_inv), chol=jnp.linalg.cholesky(inner))

    def log_det(self) -> Float[Array, ""]:
        """``log|P̂| = log|D| + log|I + Vᵀ D⁻¹ V|`` (the matrix determinant lemma).

        Returns:
            The scalar log-determinant of the preconditioner, exact (no sampling).
        """
        return -jnp.sum(jnp.log(self.d_inv)) + 2.0 * jnp.sum(jnp.log(jnp.diag(self.chol)))

    @highest
    def __call__(self, r: Float[Array, "R M"]) -> Float[Array, "R M"]:
        y = self.d_inv[:, None] * r
        t = jsl.cho_solve((self.chol, True), self.V.T @ y)
        return y - self.d_inv[:, None] * (self.V @ t)


def _inducing_factor(Z, hyper: Hyper, grad_dims: tuple[int, ...], jitter: float) -> Array:
    """``L_u`` with ``L_u L_uᵀ = K̄_uu`` plus ``jitter`` times its diagonal."""
    Kuu = kernels.gram(Z, Z, hyper.variance, hyper.lengthscale, grad_dims, grad_dims)
    return jnp.linalg.cholesky(Kuu + jitter * jnp.diag(jnp.diag(Kuu)))


def _residual_diagonal(q, hyper: Hyper, grad_dims: tuple[int, ...], n: int, X) -> Array:
    """``D = diag(K̄ − Q) + diag(ν², λ²)`` from ``diag Q = q``: each row's prior variance (σ
    on values, σ/l_d² on gradient d) less what the inducing rows explain, floored at 0."""
    ls = jnp.broadcast_to(jnp.asarray(hyper.lengthscale, X.dtype), (X.shape[1],))
    per_block = jnp.stack([hyper.variance] + [hyper.variance / ls[d] ** 2 for d in grad_dims])
    prior = jnp.repeat(per_block, n)
    return jnp.maximum(prior - q, 0.0) + hyper.noise_diagonal(n, len(grad_dims))


@highest
def _nystrom_rows(Xc, Z, Lu, hyper, *, grad_dims):
    """Rows of ``V = K̄_xu L_u⁻ᵀ`` for the points ``Xc`` (their own dimension-major order)."""
    K = kernels.gram(Xc, Z, hyper.variance, hyper.lengthscale, grad_dims, grad_dims)
    return jsl.solve_triangular(Lu, K.T, lower=True).T


# jitted once at module level (static "grad_dims"): calls of one shape share the program
_nystrom_rows_jit = jax.jit(_nystrom_rows, static_argnames="grad_dims")


@eqx.filter_jit
@highest
def _first(precond, B):
    z = precond(B)
    return jnp.zeros_like(B), B, z, z, jnp.sum(B * z, 0)


@eqx.filter_jit
@highest
def _step(matvec, precond, x, r, p, rz):
    q = matvec(p)
    pq = jnp.sum(p * q, 0)
    # A column already solved has r = 0 exactly: its step lengths stay 0, not 0/0.
    alpha = jnp.where(pq > 0, rz / jnp.where(pq > 0, pq, 1.0), 0.0)
    x = x + alpha * p
    r = r - alpha * q
    z = precond(r)
    rz_new = jnp.sum(r * z, 0)
    beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
    return x, r, z + beta * p, rz_new, jnp.linalg.norm(r, axis=0)


def solve(
    matvec: Callable[[Array], Array],
    B: Float[Array, "R M"],
    precond: Callable[[Array], Array],
    *,
    tol: float = 1e-6,
    max_iter: int = 1000,
    progress: bool = True,
    what: str = "K̄ α = Ȳ",
) -> tuple[Array, CGInfo]:
    """``X`` with ``matvec(X) = B`` by preconditioned CG on every column of ``B`` at once.

    The operator must be symmetric positive definite. Iteration stops when every column's
    relative residual ``‖B_m − matvec(X)_m‖ / ‖B_m‖`` is at most ``tol``; a column already
    solved keeps step length 0. A progress bar shows the worst residual.

    Args:
        matvec: the operator's product with an (R, M) block (:func:`gpg.gp.matfree.gram_matvec`).
        B: (R, M) right-hand sides, one CG run per column.
        precond: an approximation of the inverse applied to an (R, M) block (:class:`Nystrom`).
        tol: relative residual every column must reach, in (0, 1).
        max_iter: the iteration budget.
        progress: show the progress bar.
        what: the system's name in the progress bar and the error.

    Returns:
        The (R, M) solution and a :class:`CGInfo` on how the solve went.

    Raises:
        ValueError: if ``tol`` is not in (0, 1) or ``max_iter`` is not a positive integer.
        NotConverged: naming ``what`` and the residual reached, if ``max_iter`` iterations do
            not bring every column to ``tol``.
    """
    if not (isinstance(tol, float | int) and 0 < tol < 1):
        raise ValueError(f"tol must be in (0, 1), got {tol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    t0 = time.perf_counter()
    bnorm = np.asarray(jnp.linalg.norm(B, axis=0))
    bnorm = np.where(bnorm > 0, bnorm, 1.0)
    x, r, z, p, rz = _first(precond, B)
    res = np.asarray(jnp.linalg.norm(r, axis=0)) / bnorm
    it = 0
    bar = tqdm(total=max_iter, desc=f"CG {what}", unit="it", disable=not progress, leave=False)
    while res.max() > tol and it < max_iter:
        x, r, p, rz, rn = _step(matvec, precond, x, r, p, rz)
        res = np.asarray(rn) / bnorm
        it += 1
        bar.update()
        bar.set_postfix_str(f"residual {res.max():.1e}")
    bar.close()
    info = CGInfo(it, res, float(tol), bool(res.max() <= tol), time.perf_counter() - t0)
    if not info.converged:
        raise NotConverged(
            f"CG for {what} did not reach the relative residual {tol:g} in {max_iter} "
            f"iterations (worst output {res.max():.3g}); raise solver.max_iter, loosen "
            "solver.tol, or use more preconditioner points (solver.points)"
        )
    return x, info
