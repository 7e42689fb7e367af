"""Exact Gaussian process conditioned on function values and gradients.

Paper, Sections "Gaussian Processes" and "Gaussian Processes with Gradient Information". With
``N`` training inputs ``X`` (the paper's ``X_d = X_g``), ``M`` outputs ``Y`` sharing one kernel,
and gradients ``dY`` for the ``G`` input dimensions ``grad_dims`` (Remark "no gradient": the
other dimensions simply have no rows), the covariance ``K̄ = K̄(X_a, X_a)`` of Eq. (barK) carries
jitter ``ν²`` on value rows and ``λ_i²`` on the rows of gradient dimension ``i``
(Eq. gradient_covariance_noise). One Cholesky factorisation of ``K̄`` serves all ``M`` outputs:

* mean ``μ = K̄_qa K̄⁻¹ Ȳ`` (Eq. GPGmean),
* variance ``K_qq − K̄_qa K̄⁻¹ K̄_aq`` of the latent ``f`` (Eq. GPGvariance), shared by outputs,
* predicted gradient ``∂μ(x_q)``, the mean of ``∂f(x_q)`` (the paper's first remark).

The targets ``Ȳ`` of shape ``(N(1+G), M)`` follow the row layout of :mod:`gpg.kernels`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from gpg import _checks, kernels, linalg, memory, predictor
from gpg.mean import GlobalMean, output_scale
from gpg.predictor import Predictor
from gpg.tri import BlockTriangular


class FitWarning(UserWarning):
    """A hyperparameter fit did not converge; the returned values are the last iterate."""


class FitError(RuntimeError):
    """A hyperparameter fit failed and the caller asked for an exception."""


class Hyper(eqx.Module):
    """Kernel and noise hyperparameters (paper symbols in brackets).

    Attributes:
        variance: signal variance σ of the RBF kernel.
        lengthscale: radius scale ``l``: a scalar (isotropic) or one per input (ARD).
        jitter: ``ν²`` added to the diagonal of value rows.
        grad_noise: ``λ_i²`` added to the diagonal of the rows of gradient dimension ``i``;
            a scalar (same for all) or one per gradient dimension.
    """

    variance: Float[Array, ""]
    lengthscale: Float[Array, "*L"]
    jitter: Float[Array, ""]
    grad_noise: Float[Array, "*G"]

    def __init__(self, variance=1.0, lengthscale=1.0, jitter=1e-8, grad_noise=1e-6):
        self.variance = jnp.asarray(variance, dtype=float)
        self.lengthscale = jnp.asarray(lengthscale, dtype=float)
        self.jitter = jnp.asarray(jitter, dtype=float)
        self.grad_noise = jnp.asarray(grad_noise, dtype=float)

    def validate(self, n_inputs: int, n_grad: int) -> Hyper:
        """Check shapes and positivity against ``n_inputs`` inputs and ``n_grad`` gradient dims.

        Raises ``ValueError`` naming the offending field. Needs concrete values (not under jit).
        """
        for name in ("variance", "jitter"):
            if getattr(self, name).ndim != 0:
                raise ValueError(f"hyper.{name} must be a scalar, got {getattr(self, name).shape}")
        if self.lengthscale.shape not in ((), (n_inputs,)):
            raise ValueError(
                f"hyper.lengthscale must be a scalar or have shape ({n_inputs},), "
                f"got {self.lengthscale.shape}"
            )
        # Without gradient rows λ² is unused, so a vector meant for another model is accepted.
        if n_grad and self.grad_noise.shape not in ((), (n_grad,)):
            raise ValueError(
                f"hyper.grad_noise must be a scalar or have shape ({n_grad},), "
                f"got {self.grad_noise.shape}"
            )
        for name in ("variance", "lengthscale", "jitter", "grad_noise"):
            _checks.require_positive(f"hyper.{name}", np.asarray(getattr(self, name)))
        return self

    def noise_diagonal(self, n_points: int, n_grad: int) -> Float[Array, " R"]:
        """Diagonal ``(ν², …, ν², λ_1², …, λ_G², …)`` of length ``n_points·(1+n_grad)``."""
        if n_grad == 0:
            return jnp.full(n_points, self.jitter)
        lam = jnp.broadcast_to(self.grad_noise, (n_grad,))
        per_block = jnp.concatenate([self.jitter[None], lam])
        return jnp.repeat(per_block, n_points)


def gradient_noise(dY: Float[ArrayLike, "N M G"], s: float = 0.3) -> Float[Array, " G"]:
    """The paper's rule ``λ_i² = s · Var(∂_i Ỹ)``, the variance taken over points and outputs.

    ``dY`` are the (normalised) gradients, ``s`` the paper's scale (0.3 in the paper).
    """
    dY = _checks.as_float_array("dY", dY, ndim=3)
    if not s > 0:
        raise ValueError(f"s must be > 0, got {s}")
    var = np.var(dY.reshape(-1, dY.shape[2]), axis=0)
    # A dimension whose gradients are all equal would get zero noise; keep K̄ positive definite.
    return jnp.asarray(s * np.maximum(var, np.finfo(float).tiny))


def stack_targets(Y: Float[Array, "N M"], dY: Float[Array, "N M G"] | None) -> Float[Array, "R M"]:
    """Stack values and gradients into ``Ȳ`` with the layout of :mod:`gpg.kernels`.

    NumPy in, NumPy out (no compilation for the offline fit); JAX arrays stay JAX arrays.
    """
    xp = np if isinstance(Y, np.ndarray) and (dY is None or isinstance(dY, np.ndarray)) else jnp
    if dY is None or dY.shape[2] == 0:
        return Y
    grads = xp.moveaxis(dY, 2, 0).reshape(-1, Y.shape[1])
    return xp.concatenate([Y, grads], axis=0)


@dataclass(frozen=True)
class _Checked:
    X: np.ndarray
    Y: np.ndarray
    dY: np.ndarray | None
    grad_dims: tuple[int, ...]


def _check_training_data(X, Y, dY, grad_dims) -> _Checked:
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
        return _Checked(X, Y, None, ())
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
    _checks.require_finite("dY", dY)
    return _Checked(X, Y, dY, grad_dims)


def assemble_gram(
    X: Float[ArrayLike, "N D"],
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    out: np.ndarray | None = None,
    chunk_rows: int = 256,
) -> np.ndarray:
    """``K̄(X, X)`` plus its noise diagonal, written into a C-ordered NumPy buffer.

    Built in blocks of about ``chunk_rows`` rows so that the only full-size allocation is the
    result (``out`` if given), ready for :func:`gpg.linalg.cholesky_inplace`. Small blocks
    stay in cache: 256 rows assembled the 8000-row K̄ fastest on the development machine.
    """
    X = jnp.asarray(X)
    n = X.shape[0]
    g = len(grad_dims)
    r = n * (1 + g)
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
    out.flat[:: r + 1] += np.asarray(hyper.noise_diagonal(n, g))
    return out


class ExactGP(Predictor):
    """Exact GP with optional gradient observations (GP-G). Build with :meth:`ExactGP.fit`.

    Attributes:
        X: training inputs ``X_d`` (N, D).
        alpha: ``K̄⁻¹ Ȳ`` (R, M), ``R = N(1+G)``.
        chol_inv: ``L⁻¹`` for the lower Cholesky factor ``L`` of ``K̄`` (R, R), stored in row
            bands (:class:`gpg.tri.BlockTriangular`), so that the variance is
            ``σ − ‖L⁻¹ k̄_q‖²``. A matrix-vector product with the stored inverse reads the
            triangle once, row-major; a triangular solve in JAX first copies ``L`` to
            column-major order and is over ten times slower per query at 8000 rows.
        hyper: the hyperparameters used.
        mean: ``α`` folded for a fast mean (:class:`gpg.mean.GlobalMean`).
        output_scale: per-output ML signal scale ``Ȳ_mᵀ α_m / R`` (:func:`gpg.mean.output_scale`).
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
        data = _check_training_data(X, Y, dY, grad_dims)
        hyper = (Hyper() if hyper is None else hyper).validate(data.X.shape[1], len(data.grad_dims))
        Xj = jnp.asarray(data.X)
        Ybar = stack_targets(data.Y, data.dY)
        r = Ybar.shape[0]
        # One dense R x R buffer, factorised and inverted in place, then moved into JAX band by
        # band while its rows are released: the peak stays near one copy (12.8 GB at 40000 rows).
        memory.require(f"an exact GP with {r} rows", int(r * r * 8 * 1.2))
        buf = memory.square_buffer(r)
        chol = linalg.cholesky_inplace(assemble_gram(Xj, hyper, data.grad_dims, out=buf.array))
        alpha = linalg.cho_solve(chol, Ybar)
        m = Ybar.shape[1]
        lml = (
            -0.5 * float(np.sum(Ybar * alpha))
            - m * float(np.sum(np.log(np.diag(chol))))
            - 0.5 * m * r * math.log(2 * math.pi)
        )
        linalg.triangular_inverse_inplace(chol)  # overwrites the factor: one buffer
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
        return self.hyper.jitter

    @property
    def n_inputs(self) -> int:
        return self.X.shape[1]

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """Posterior mean (M,) at one query, Eq. (GPGmean), in the folded form of
        :mod:`gpg.mean` (plain kernel values times fixed coefficients)."""
        return self.mean(x)

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        """Posterior mean (M,) and latent variance () at one query: Eqs. (GPGmean, GPGvariance).

        The batched, jitted :meth:`predict` / :meth:`predict_mean` are inherited from
        :class:`gpg.predictor.Predictor`.
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


# ----------------------------------------------------------------------------------------------
# Marginal likelihood and hyperparameter fit
# ----------------------------------------------------------------------------------------------


def log_marginal_likelihood(
    X: Float[Array, "N D"],
    Ybar: Float[Array, "R M"],
    hyper: Hyper,
    grad_dims: tuple[int, ...] = (),
) -> Float[Array, ""]:
    """``Σ_m log N(Ȳ_m | 0, K̄)``: pure JAX, differentiable in ``hyper`` (small N only).

    ``Ybar`` is the stacked target of :func:`stack_targets`.
    """
    n = X.shape[0]
    g = len(grad_dims)
    K = kernels.gram(X, X, hyper.variance, hyper.lengthscale, grad_dims, grad_dims)
    K = K + jnp.diag(hyper.noise_diagonal(n, g))
    c, lower = jsl.cho_factor(K, lower=True)
    alpha = jsl.cho_solve((c, lower), Ybar)
    r, m = Ybar.shape
    return (
        -0.5 * jnp.sum(Ybar * alpha)
        - m * jnp.sum(jnp.log(jnp.diag(c)))
        - 0.5 * m * r * jnp.log(2 * jnp.pi)
    )


@dataclass(frozen=True)
class HyperFitResult:
    """Outcome of :func:`fit_hyperparameters`.

    ``converged`` is False when the optimiser stopped without meeting its tolerance or ended on
    a non-finite likelihood; ``message`` then says why, and ``hyper`` holds the last iterate.
    """

    hyper: Hyper
    converged: bool
    num_steps: int
    nll_initial: float
    nll_final: float
    message: str
    subset: np.ndarray
    grad_noise_scale: float | None
    jitter_fitted: bool = False

    @property
    def noise_ratio(self) -> float:
        """The value-noise nugget relative to the signal variance, ``ν²/σ``."""
        return float(self.hyper.jitter / self.hyper.variance)


def _unpack(params, base: Hyper, grad_var, jitter_floor: float):
    variance = jnp.exp(params["log_variance"])
    grad_noise = base.grad_noise
    if "log_s" in params:
        grad_noise = jnp.exp(params["log_s"]) * grad_var
    jitter = base.jitter
    if "log_noise_ratio" in params:
        # ν² = σ (floor + e^θ): the bound holds exactly for every θ, so an unconstrained
        # optimiser can be used (no projection, no clipping of the gradient).
        jitter = variance * (jitter_floor + jnp.exp(params["log_noise_ratio"]))
    return Hyper(
        variance=variance,
        lengthscale=jnp.exp(params["log_lengthscale"]),
        jitter=jitter,
        grad_noise=grad_noise,
    )


def fit_hyperparameters(
    X: Float[ArrayLike, "N D"],
    Y: Float[ArrayLike, "N M"],
    dY: Float[ArrayLike, "N M G"] | None = None,
    *,
    grad_dims: Sequence[int] | None = None,
    init: Hyper | None = None,
    ard: bool = True,
    fit_grad_noise: bool = False,
    fit_jitter: bool = True,
    jitter_floor: float = 1e-6,
    jitter_init: float = 1e-2,
    subset_size: int | None = 400,
    seed: int = 0,
    max_steps: int = 200,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    on_failure: str = "warn",
) -> HyperFitResult:
    """Maximise the log marginal likelihood over log-parameters with optimistix BFGS.

    Fitted: signal variance σ, lengthscale(s) ``l`` (one per input if ``ard``), the value-noise
    nugget ``ν²`` if ``fit_jitter`` (bounded below by ``jitter_floor·σ``, started from
    ``jitter_init·σ``; otherwise it stays as in ``init``), and, if ``fit_grad_noise``, the scale
    ``s`` of the gradient noise ``λ_i² = s·Var(∂_i Ỹ)``. A fixed tiny ``ν²`` leaves the model
    overconfident on data that no smooth function fits exactly (finite-difference gradients,
    a simulator's own discretisation): the nugget is what absorbs that misfit. When N exceeds
    ``subset_size`` the likelihood is evaluated on a random subset of that many points (drawn
    with ``seed``), since each step factorises K̄.

    ``on_failure``: ``"warn"`` (a :class:`FitWarning`, result returned with
    ``converged=False``), ``"raise"`` (:class:`FitError`) or ``"ignore"``.
    """
    if on_failure not in ("warn", "raise", "ignore"):
        raise ValueError(f"on_failure must be 'warn', 'raise' or 'ignore', got {on_failure!r}")
    data = _check_training_data(X, Y, dY, grad_dims)
    n, d = data.X.shape
    g = len(data.grad_dims)
    init = Hyper() if init is None else init
    if ard and init.lengthscale.ndim == 0:
        init = eqx.tree_at(lambda h: h.lengthscale, init, jnp.full(d, init.lengthscale))
    if not ard and init.lengthscale.ndim != 0:
        raise ValueError("init.lengthscale must be a scalar when ard=False")
    init = init.validate(d, g)
    if fit_grad_noise and g == 0:
        raise ValueError("fit_grad_noise=True needs gradient observations (dY)")
    if fit_jitter and not (0 < jitter_floor < jitter_init):
        raise ValueError(
            "jitter_floor and jitter_init (ν²/σ) must satisfy 0 < jitter_floor < jitter_init, "
            f"got {jitter_floor} and {jitter_init}"
        )

    rng = np.random.default_rng(seed)
    if subset_size is not None and n > subset_size:
        subset = np.sort(rng.choice(n, size=subset_size, replace=False))
    else:
        subset = np.arange(n)
    Xs = jnp.asarray(data.X[subset])
    Ys = jnp.asarray(data.Y[subset])
    dYs = None if data.dY is None else jnp.asarray(data.dY[subset])
    Ybar = stack_targets(Ys, dYs)
    scale = float(Ybar.size)

    grad_var = None
    params = {
        "log_variance": jnp.log(init.variance),
        "log_lengthscale": jnp.log(init.lengthscale),
    }
    if fit_grad_noise:
        grad_var = gradient_noise(data.dY, s=1.0)
        lam = jnp.broadcast_to(init.grad_noise, (g,))
        params["log_s"] = jnp.mean(jnp.log(lam / grad_var))
    if fit_jitter:
        params["log_noise_ratio"] = jnp.log(jnp.asarray(jitter_init - jitter_floor))

    def loss(p, _):
        h = _unpack(p, init, grad_var, jitter_floor)
        nll = -log_marginal_likelihood(Xs, Ybar, h, data.grad_dims) / scale
        # A non-PD trial point gives NaN: report it as a bad step so the line search backs off.
        return jnp.where(jnp.isfinite(nll), nll, jnp.asarray(1e10))

    nll0 = float(loss(params, None))
    sol = optx.minimise(
        loss,
        optx.BFGS(rtol=rtol, atol=atol),
        params,
        max_steps=max_steps,
        throw=False,
    )
    hyper = _unpack(sol.value, init, grad_var, jitter_floor)
    nll1 = float(loss(sol.value, None))
    ok = bool(sol.result == optx.RESULTS.successful)
    message = "converged" if ok else f"optimistix stopped: {_result_message(sol.result)}"
    finite = all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(hyper))
    if ok and (not finite or nll1 >= 1e10):
        ok, message = False, "the likelihood is not finite at the optimum"
    result = HyperFitResult(
        hyper=hyper,
        converged=ok,
        num_steps=int(sol.stats["num_steps"]),
        nll_initial=nll0 * scale,
        nll_final=nll1 * scale,
        message=message,
        subset=subset,
        grad_noise_scale=float(jnp.exp(sol.value["log_s"])) if fit_grad_noise else None,
        jitter_fitted=fit_jitter,
    )
    if not ok:
        text = (
            f"hyperparameter fit did not converge after {result.num_steps} steps ({message}); "
            f"negative log likelihood {result.nll_initial:.6g} -> {result.nll_final:.6g}"
        )
        if on_failure == "raise":
            raise FitError(text)
        if on_failure == "warn":
            warnings.warn(text, FitWarning, stacklevel=2)
    return result


def _result_message(result) -> str:
    """The optimistix result's own explanation, e.g. "The maximum number of steps was reached"."""
    text = str(result)
    start, stop = text.find("<"), text.rfind(">")
    return text[start + 1 : stop] if 0 <= start < stop else text
