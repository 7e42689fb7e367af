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
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg import _host
from gpg._dtype import float64, in_model_dtype
from gpg._precision import highest
from gpg.gp import kernels, predictor
from gpg.gp.assembly import assemble_gram, assemble_rows_gram, device_gram
from gpg.gp.directions import check_bases, from_bases, to_bases
from gpg.gp.hyper import Hyper
from gpg.gp.layout import value_row_noise
from gpg.gp.mean import GlobalMean, output_scale
from gpg.gp.predictor import Predictor, plain
from gpg.gp.targets import check_training_data
from gpg.linalg import dense, memory
from gpg.linalg import device as linalg_device
from gpg.linalg.tri import BlockTriangular, BorderedTriangular

__all__ = ["ExactGP"]


class ExactGP(Predictor):
    """Exact GP with optional gradient observations (GP-G). Build with :meth:`ExactGP.fit`.

    Attributes:
        X: training inputs ``X_d`` (N, D).
        alpha: ``K̄⁻¹ Ȳ`` (R, M) in the layout of :mod:`gpg.gp.kernels`, ``R = N(1+G)``, 0 on
            the rows of gradients a case does not have.
        chol_inv: ``L⁻¹`` for the lower Cholesky factor ``L`` of ``K̄`` over the observed rows
            (``R_f`` of them, ``R_f = R`` when every case has every gradient), stored in row
            bands (:class:`gpg.linalg.tri.BlockTriangular`), so that the variance is
            ``σ − ‖L⁻¹ k̄_q‖²``. A matrix-vector product with the stored inverse reads the
            triangle once, row-major; a triangular solve in JAX first copies ``L`` to
            column-major order and is much slower per query (docs/measurements.md). A model
            grown by :meth:`condition` keeps the new rows' part factored around it
            (:class:`gpg.linalg.tri.BorderedTriangular`).
        hyper: the hyperparameters used.
        mean: ``α`` folded for a fast mean (:class:`gpg.gp.mean.GlobalMean`).
        output_scale: per-output ML signal scale ``Ȳ_mᵀ α_m / R``
            (:func:`gpg.gp.mean.output_scale`).
        grad_dims: input dimensions with gradient observations (static).
        log_marginal_likelihood: ``log p(Ȳ | X)`` summed over the M outputs.
        order: None when the factor's rows are the layout's, else the row of the layout of
            :mod:`gpg.gp.kernels` that each row of ``chol_inv`` stands for (R_f,): a model
            with cases that lack some gradients factorises only the rows it observed (a
            values-only case is one row, not ``1 + G``), and the factor of a model grown by
            :meth:`condition` keeps its blocks in the order the data came.
        observed: None when every row was observed, else which rows were (R,) in the layout
            (:func:`gpg.gp.gram.observed_rows`: cases without some gradients). Files of format
            7 and 8 kept the unobserved rows in the factor, decoupled; they still load.
        bases: None when the gradient rows are coordinate derivatives, else (N, G, G): row
            ``g`` of case ``i`` observed the derivative along ``Σ_h bases[i, g, h] e_{d_h}``
            (``d = grad_dims``; the paper's remark on derivatives in arbitrary directions,
            :func:`gpg.gp.gram.row_directions`). ``alpha`` and the factor are then over the
            directional rows; ``mean`` reads their coordinate form
            (:func:`gpg.gp.gram.from_bases`).
    """

    X: Float[Array, "N D"]
    alpha: Float[Array, "R M"]
    chol_inv: BlockTriangular | BorderedTriangular
    hyper: Hyper
    mean: GlobalMean
    output_scale: Float[Array, " M"]
    log_marginal_likelihood: Float[Array, ""]
    grad_dims: tuple[int, ...] = eqx.field(static=True)
    order: Int[Array, " R"] | None = None
    observed: Bool[Array, " R"] | None = None
    bases: Float[Array, "N G G"] | None = None

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
        observed: Bool[ArrayLike, "N G"] | None = None,
        bases: Float[ArrayLike, "N G G"] | None = None,
        device: str = "auto",
        row_noise: Float[ArrayLike, " N"] | None = None,
    ) -> ExactGP:
        """Condition the GP on values ``Y`` and, optionally, gradients ``dY``.

        Args:
            X: inputs (N, D).
            Y: values (N, M) or (N,) for one output.
            dY: gradients (N, M, G): ``dY[i, m, g] = ∂y_m/∂x_{grad_dims[g]}`` at ``X[i]``.
            grad_dims: the G input dimensions of ``dY`` (default: all D when ``dY`` is given).
            hyper: kernel and noise hyperparameters (default ``Hyper()``).
            observed: (N, G) which gradients each case has (default: all); the others'
                ``dY`` entries are never read (:func:`gpg.gp.gram.observed_rows`).
            bases: (N, G, G) when ``dY[i, :, g]`` is the derivative along the direction
                ``Σ_h bases[i, g, h] e_{grad_dims[h]}`` rather than along ``grad_dims[g]``
                (converted data, :func:`gpg.data.convert.to_body`); default coordinates.
            device: where ``K̄`` is formed and factorised: ``host`` (LAPACK in place),
                ``device`` (JAX's default device, float64) or ``auto``
                (:func:`gpg.linalg.device.place`: the accelerator when there is one and
                ``K̄`` fits in its free memory).
            row_noise: (N,) each case's own value-noise variance (normalised units), added to
                ``ν²`` on its value row: labels of known, unequal noise (measured flights).
                Not stored: cases added by :meth:`condition` carry ``ν²`` alone.

        Returns:
            The fitted GP, its log marginal likelihood and per-output scales included.

        Raises:
            ValueError: mismatched shapes, NaN/inf in an input, bad ``grad_dims`` or
                non-positive hyperparameters (the message names the input), or a ``K̄`` that
                is not numerically positive definite.
        """
        data = check_training_data(X, Y, dY, grad_dims, observed)
        bases = check_bases(bases, data.X.shape[0], data.grad_dims)
        hyper = (Hyper() if hyper is None else hyper).validate(data.X.shape[1], len(data.grad_dims))
        Xj = _host.asarray(data.X)
        Ybar, rows = data.targets(), data.rows
        # Cases without some gradients: only the rows they observed enter K̄ and its factor,
        # whose rows ``order`` names in the layout (a values-only case is one row, not 1 + G).
        index = None if rows is None else np.flatnonzero(rows)
        r = Ybar.shape[0] if index is None else index.size
        extra = _row_noise(row_noise, data.X.shape[0], len(data.grad_dims), index)
        Ybar, alpha, logdet, bands = _factorise(data, hyper, index, bases, Ybar, r, device, extra)
        m = Ybar.shape[1]
        lml = -0.5 * float(np.sum(Ybar * alpha)) - m * logdet - 0.5 * m * r * math.log(2 * math.pi)
        scale = output_scale(np.sum(Ybar * alpha, axis=0), r)
        if index is not None:  # α in the layout, 0 on the rows not observed
            alpha = _scatter(alpha, index, rows.size)
        # The mean reads coordinate rows: k̄_dirᵀ α = k̄ᵀ (Pᵀ α).
        coord = alpha if bases is None else from_bases(alpha, bases, data.X.shape[0])
        return cls(
            X=Xj,
            alpha=_host.asarray(alpha),
            chol_inv=bands,
            hyper=hyper,
            mean=GlobalMean.from_alpha(
                data.X, coord, hyper.variance, hyper.lengthscale, data.grad_dims
            ),
            output_scale=jnp.asarray(scale),
            log_marginal_likelihood=jnp.asarray(lml),
            grad_dims=data.grad_dims,
            order=None if index is None else jnp.asarray(index, dtype=jnp.int32),
            observed=None if rows is None else jnp.asarray(rows),
            bases=None if bases is None else jnp.asarray(bases),
        )

    @float64
    def condition(
        self,
        X: Float[ArrayLike, "n D"],
        Y: Float[ArrayLike, "n M"],
        dY: Float[ArrayLike, "n M G"] | None = None,
        *,
        observed: Bool[ArrayLike, "n G"] | None = None,
        bases: Float[ArrayLike, "n G G"] | None = None,
    ) -> ExactGP:
        """This GP conditioned on ``n`` more cases, hyperparameters kept: the same model as
        :meth:`fit` on all the points (to rounding), by a bordered Cholesky update.

        With ``K̄ = L Lᵀ`` over the ``R`` rows already in, ``B = K̄(X_old, X)`` and
        ``C = K̄(X, X)`` plus noise over the ``r`` new rows, the grown factor is
        ``[[L, 0], [S, L₂]]`` with ``S = (L⁻¹ B)ᵀ`` and ``L₂ L₂ᵀ = C − S Sᵀ`` (the Schur
        complement). Its inverse gains the rows ``[−L₂⁻¹ S L⁻¹, L₂⁻¹]``, stored as
        ``M = L₂⁻¹ S`` and ``L₂⁻¹`` (:class:`gpg.linalg.tri.BorderedTriangular`); the rows
        already stored are not touched. ``α₂ = (C − S Sᵀ)⁻¹ (Ȳ₂ − Bᵀ α)`` and
        ``α₁ = α − L⁻ᵀ Sᵀ α₂``. Cost ``r R²`` flops (one product of the stored ``L⁻¹`` with
        ``r`` columns) against ``2R³/3`` for a refit; memory ``O(r R)``.

        ``output_scale`` is re-formed as a refit would (from ``Ȳᵀ α``); a model whose scales
        were set to ones keeps ones.

        Args:
            X: (n, D) the new cases' inputs.
            Y: (n, M) their values, or (n,) for one output.
            dY: (n, M, G) their gradients over the model's gradient dims; None: the new cases
                are values only.
            observed: (n, G) which gradients each new case has, as in :meth:`fit`.
            bases: (n, G, G) the directions of the new cases' gradient rows, as in
                :meth:`fit`; default coordinates.

        Returns:
            The grown GP; this one is unchanged.

        Raises:
            ValueError: inputs, outputs or gradient dims that do not match the model, NaN,
                or new cases that make ``K̄`` singular (a duplicate of a training point with
                too little noise): the model is unchanged.
        """
        from gpg.gp.update import bordered

        return bordered(self, X, Y, dY, observed, bases)

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
        """This GP with ``output_scale`` replaced (the factor and ``α`` shared, not copied).

        Args:
            scale: (M,) the per-output variance scale.

        Returns:
            The GP with the new scale.
        """
        return eqx.tree_at(lambda m: m.output_scale, self, jnp.asarray(scale))

    def describe(self) -> dict[str, Any]:
        """The hyperparameters as plain values, for a checkpoint's metadata.

        Returns:
            ``{"hyperparameters": {...}}``: σ (``variance``), ``lengthscale``, ``ν²``
            (``noise``) and ``λ²`` (``grad_noise``) as nested lists.
        """
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
        """Posterior mean at one query, Eq. (GPGmean).

        In the folded form of :mod:`gpg.gp.mean`: plain kernel values times fixed coefficients.

        Args:
            x: (D,) the normalised query.

        Returns:
            ``μ(x)`` (M,).
        """
        return self.mean(x)

    @highest
    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        """Posterior mean and latent variance at one query: Eqs. (GPGmean, GPGvariance).

        The variance is ``σ − ‖L⁻¹ k̄_q‖²``, with ``k̄_q`` turned to the directional rows when
        the model has ``bases``. The batched, jitted :meth:`predict` / :meth:`predict_mean` are
        inherited from :class:`gpg.gp.predictor.Predictor`.

        Args:
            x: (D,) a normalised query.

        Returns:
            The mean (M,) and the latent variance (), not clipped.
        """
        k = _cross(self, x[None])[0]
        if self.bases is not None:
            k = to_bases(k, self.bases, self.X.shape[0])
        v = self.chol_inv.matvec(k if self.order is None else k[self.order])
        # Rounding can push the difference a hair below zero on training points: predict clips.
        return self.mean(x), self.hyper.variance - v @ v

    def mean_view(self) -> ExactGP:
        """This GP without ``L⁻¹``: the folded mean reads ``mean`` only.

        Returns:
            The GP with an empty factor (its variance is not to be used).
        """
        return eqx.tree_at(lambda m: m.chol_inv, self, BlockTriangular((), self.chol_inv.n, True))

    def predict_gradient(self, Xq: Float[ArrayLike, "Q D"]) -> Float[Array, "Q M D"]:
        """Mean of ``∂f(x_q)``, the predicted gradient (the paper's first remark).

        By forward-mode differentiation of :meth:`mean_one`, for all D inputs whether or not
        the model was given their gradients.

        Args:
            Xq: (Q, D) the normalised queries, finite.

        Returns:
            ``out[q, m, d] = ∂μ_m/∂x_d`` at ``Xq[q]``, (Q, M, D).
        """
        return in_model_dtype(self, lambda: _predict_gradient(self, jnp.asarray(Xq)), Xq)


def _row_noise(row_noise, n: int, g: int, index) -> np.ndarray | None:
    """``row_noise`` (N,) checked and laid over the factor's rows (None without it)."""
    if row_noise is None:
        return None
    rn = np.asarray(row_noise, dtype=np.float64)
    if rn.shape != (n,):
        raise ValueError(f"row_noise must have shape ({n},), got {rn.shape}")
    if not np.all(np.isfinite(rn)) or np.any(rn < 0):
        raise ValueError("row_noise must be finite and >= 0")
    extra = np.asarray(value_row_noise(rn, n, g))
    return extra if index is None else extra[index]


def _factorise(data, hyper: Hyper, index, bases, Ybar: np.ndarray, r: int, device: str, extra=None):
    """``K̄`` over the factor's rows formed and factorised where ``device`` places it
    (:func:`gpg.linalg.device.place`): the targets of those rows, ``α``, ``log det L`` and
    ``L⁻¹`` in bands. ``extra`` (r,): more noise on the factor's diagonal (``row_noise``)."""
    what = f"K̄ of an exact GP ({r} rows)"
    if linalg_device.place(device, linalg_device.solve_bytes(r, True), what) == "device":
        Ybar = Ybar if index is None else Ybar[index]
        K = device_gram(data.X, hyper, data.grad_dims, index=index, bases=bases)
        if extra is not None:
            K = K + jnp.diag(jnp.asarray(extra))
        alpha, logdet, Linv = linalg_device.factor_solve(K, Ybar, inverse=True, what=what)
        del K
        return Ybar, alpha, logdet, BlockTriangular.from_device(Linv, n_blocks=8)
    # One dense r x r buffer, factorised and inverted in place, then moved into JAX band by
    # band while its rows are released: the peak stays near one copy (8 r² bytes).
    memory.require(f"an exact GP with {r} rows", int(r * r * 8 * 1.2))
    buf = memory.square_buffer(r)
    gram, sel = _gram(data, hyper, index, bases, buf.array)
    if extra is not None:
        diag = np.arange(r)
        gram[diag, diag] += extra
    Ybar = Ybar if sel is None else Ybar[sel]
    chol = dense.cholesky_inplace(gram)
    alpha = dense.cho_solve(chol, Ybar)
    logdet = float(np.sum(np.log(np.diag(chol))))
    dense.triangular_inverse_inplace(chol)  # overwrites the factor: one buffer
    return Ybar, alpha, logdet, BlockTriangular.from_buffer(buf, lower=True, n_blocks=8)


def _gram(data, hyper: Hyper, index, bases, out: np.ndarray):
    """``K̄`` plus noise over the factor's rows, written into ``out``, and those rows of the
    layout (None: all of them, in order): the observed ones (``index``), all of them along
    their directions (``bases``), or the plain layout."""
    if index is None and bases is None:
        return assemble_gram(jnp.asarray(data.X), hyper, data.grad_dims, out=out), None
    sel = np.arange(out.shape[0]) if index is None else index
    return assemble_rows_gram(data.X, sel, hyper, data.grad_dims, out=out, bases=bases), sel


def _scatter(a: np.ndarray, index: np.ndarray, size: int) -> np.ndarray:
    """Rows ``a`` placed at ``index`` of ``size`` rows, zeros elsewhere."""
    out = np.zeros((size,) + a.shape[1:], dtype=a.dtype)
    out[index] = a
    return out


def _cross(gp: ExactGP, Xq: Array) -> Float[Array, "Q R"]:
    return kernels.query_rows(Xq, gp.X, gp.hyper.variance, gp.hyper.lengthscale, gp.grad_dims)


@eqx.filter_jit
@highest
def _predict_gradient(gp: ExactGP, Xq: Array):
    predictor.check_query(Xq, gp.n_inputs)
    Xq = eqx.error_if(Xq, ~jnp.all(jnp.isfinite(Xq)), "Xq holds NaN or inf")
    return jax.vmap(jax.jacfwd(gp.mean_one))(Xq)
