"""Exact Gaussian process conditioned on function values and gradients.

Paper, Sections "Gaussian Processes" and "Gaussian Processes with Gradient Information". With
``N`` training inputs ``X`` (the paper's ``X_d = X_g``), ``M`` outputs ``Y`` sharing one kernel,
and gradients ``dY`` for the ``G`` input dimensions ``grad_dims`` (Remark "no gradient": the
other dimensions simply have no rows), the covariance ``K̄ = K̄(X_a, X_a)`` of Eq. (barK) carries
noise ``ν²`` on value rows and ``λ_i²`` on the rows of gradient dimension ``i``
(Eq. gradient_covariance_noise). One Cholesky factorisation of ``K̄`` serves all ``M`` outputs:

* mean ``μ = K̄_qa K̄⁻¹ Ȳ`` (Eq. GPGmean),
* variance ``K_qq − K̄_qa K̄⁻¹ K̄_aq`` of the latent ``f`` (Eq. GPGvariance), shared by outputs,
* predicted gradient ``∂μ(x_q)``, the mean of ``∂f(x_q)`` (the paper's first remark).

The targets ``Ȳ`` of shape ``(N(1+G), M)`` follow the row layout of :mod:`gpg.gp.kernels`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg._dtype import float64
from gpg.gp import kernels, predictor
from gpg.gp.gram import assemble_gram, check_training_data, stack_targets
from gpg.gp.hyper import Hyper
from gpg.gp.mean import GlobalMean, output_scale
from gpg.gp.predictor import Predictor, plain
from gpg.linalg import dense, memory
from gpg.linalg.tri import BlockTriangular


class ExactGP(Predictor):
    """Exact GP with optional gradient observations (GP-G). Build with :meth:`ExactGP.fit`.

    Attributes:
        X: training inputs ``X_d`` (N, D).
        alpha: ``K̄⁻¹ Ȳ`` (R, M), ``R = N(1+G)``.
        chol_inv: ``L⁻¹`` for the lower Cholesky factor ``L`` of ``K̄`` (R, R), stored in row
            bands (:class:`gpg.linalg.tri.BlockTriangular`), so that the variance is
            ``σ − ‖L⁻¹ k̄_q‖²``. A matrix-vector product with the stored inverse reads the
            triangle once, row-major; a triangular solve in JAX first copies ``L`` to
            column-major order and is over ten times slower per query at 8000 rows.
        hyper: the hyperparameters used.
        mean: ``α`` folded for a fast mean (:class:`gpg.gp.mean.GlobalMean`).
        output_scale: per-output ML signal scale ``Ȳ_mᵀ α_m / R``
            (:func:`gpg.gp.mean.output_scale`).
        grad_dims: input dimensions with gradient observations (static).
        log_marginal_likelihood: ``log p(Ȳ | X)`` summed over the M outputs.
    """

    X: Float[Array, "N D"]
    alpha: Float[Array, "R M"]
    chol_inv: BlockTriangular
    hyper: Hyper
    mean: GlobalMean
    output_scale: Float[Array, " M"]
    log_marginal_likelihood: Float[Array, ""]
    grad_dims: tuple[int, ...] = eqx.field(static=True)

    @classmethod
    @float64
    def fit(
        cls,
        X: Float[ArrayLike, "N D"],
        Y: Float[ArrayLike, "N M"],
        dY: Float[ArrayLike, "N M G"] | None = None,
        *,
        grad_dims: Sequence[int] | None = None,
        hyper: Hyper | None = None,
    ) -> ExactGP:
        """Condition the GP on values ``Y`` and, optionally, gradients ``dY``.

        Args:
            X: inputs (N, D).
            Y: values (N, M) or (N,) for one output.
            dY: gradients (N, M, G): ``dY[i, m, g] = ∂y_m/∂x_{grad_dims[g]}`` at ``X[i]``.
            grad_dims: the G input dimensions of ``dY`` (default: all D when ``dY`` is given).
            hyper: kernel and noise hyperparameters (default ``Hyper()``).

        Raises:
            ValueError: mismatched shapes, NaN/inf in an input, bad ``grad_dims`` or
                non-positive hyperparameters (the message names the input), or a ``K̄`` that
                is not numerically positive definite.
        """
        data = check_training_data(X, Y, dY, grad_dims)
        hyper = (Hyper() if hyper is None else hyper).validate(data.X.shape[1], len(data.grad_dims))
        Xj = jnp.asarray(data.X)
        Ybar = stack_targets(data.Y, data.dY)
        r = Ybar.shape[0]
        # One dense R x R buffer, factorised and inverted in place, then moved into JAX band by
        # band while its rows are released: the peak stays near one copy (12.8 GB at 40000 rows).
        memory.require(f"an exact GP with {r} rows", int(r * r * 8 * 1.2))
        buf = memory.square_buffer(r)
        chol = dense.cholesky_inplace(assemble_gram(Xj, hyper, data.grad_dims, out=buf.array))
        alpha = dense.cho_solve(chol, Ybar)
        m = Ybar.shape[1]
        lml = (
            -0.5 * float(np.sum(Ybar * alpha))
            - m * float(np.sum(np.log(np.diag(chol))))
            - 0.5 * m * r * math.log(2 * math.pi)
        )
        dense.triangular_inverse_inplace(chol)  # overwrites the factor: one buffer
        bands = BlockTriangular.from_buffer(buf, lower=True, n_blocks=8)
        del chol, buf
        return cls(
            X=Xj,
            alpha=jnp.asarray(alpha),
            chol_inv=bands,
            hyper=hyper,
            mean=GlobalMean.from_alpha(
                data.X, alpha, hyper.variance, hyper.lengthscale, data.grad_dims
            ),
            output_scale=jnp.asarray(output_scale(np.sum(Ybar * alpha, axis=0), r)),
            log_marginal_likelihood=jnp.asarray(lml),
            grad_dims=data.grad_dims,
        )

    @property
    def n_outputs(self) -> int:
        return self.alpha.shape[1]

    @property
    def noise(self) -> Float[Array, ""]:
        return self.hyper.noise

    @property
    def n_inputs(self) -> int:
        return self.X.shape[1]

    @property
    def partition(self) -> None:
        """No bins: every query conditions on every training row."""
        return None

    def with_output_scale(self, scale: Float[ArrayLike, " M"]) -> ExactGP:
        return eqx.tree_at(lambda m: m.output_scale, self, jnp.asarray(scale))

    def describe(self) -> dict[str, Any]:
        h = self.hyper
        return {
            "hyperparameters": {
                "variance": plain(h.variance),
                "lengthscale": plain(h.lengthscale),
                "noise": plain(h.noise),
                "grad_noise": plain(h.grad_noise),
            }
        }

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """Posterior mean (M,) at one query, Eq. (GPGmean), in the folded form of
        :mod:`gpg.gp.mean` (plain kernel values times fixed coefficients)."""
        return self.mean(x)

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        """Posterior mean (M,) and latent variance () at one query: Eqs. (GPGmean, GPGvariance).

        The batched, jitted :meth:`predict` / :meth:`predict_mean` are inherited from
        :class:`gpg.gp.predictor.Predictor`.
        """
        k = _cross(self, x[None])[0]
        v = self.chol_inv.matvec(k)
        # Rounding can push the difference a hair below zero on training points: predict clips.
        return self.mean(x), self.hyper.variance - v @ v

    def mean_view(self) -> ExactGP:
        """Without ``L⁻¹`` (the folded mean reads ``mean`` only)."""
        return eqx.tree_at(lambda m: m.chol_inv, self, BlockTriangular((), self.chol_inv.n, True))

    def predict_gradient(self, Xq: Float[ArrayLike, "Q D"]) -> Float[Array, "Q M D"]:
        """Mean of ``∂f(x_q)``: ``out[q, m, d] = ∂μ_m/∂x_d`` at ``Xq[q]`` (all D inputs)."""
        return _predict_gradient(self, jnp.asarray(Xq))


def _cross(gp: ExactGP, Xq: Array) -> Float[Array, "Q R"]:
    return kernels.query_rows(Xq, gp.X, gp.hyper.variance, gp.hyper.lengthscale, gp.grad_dims)


@eqx.filter_jit
def _predict_gradient(gp: ExactGP, Xq: Array):
    predictor.check_query(Xq, gp.n_inputs)
    Xq = eqx.error_if(Xq, ~jnp.all(jnp.isfinite(Xq)), "Xq holds NaN or inf")
    return jax.vmap(jax.jacfwd(gp.mean_one))(Xq)
