"""Hyperparameters by maximum marginal likelihood (optimistix BFGS on log-parameters).

The value-noise nugget ``ν²`` is fitted by default, bounded below by a reparametrisation
(``ν² = σ(floor + e^θ)``) so that an unconstrained solver can be used.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Float

from gpg._dtype import float64
from gpg.gp.gram import check_training_data, log_marginal_likelihood, stack_targets
from gpg.gp.hyper import Hyper, gradient_noise


class FitWarning(UserWarning):
    """A hyperparameter fit did not converge; the returned values are the last iterate."""


class FitError(RuntimeError):
    """A hyperparameter fit failed and the caller asked for an exception."""


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


@float64
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
    data = check_training_data(X, Y, dY, grad_dims)
    n, d = data.X.shape
    g = len(data.grad_dims)
    if n < 2 or (subset_size is not None and subset_size < 2):
        raise ValueError(
            f"a marginal-likelihood fit needs at least 2 points (got {min(n, subset_size or n)}): "
            "one point says nothing about lengthscales; fix the hyperparameters instead"
        )
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
            warnings.warn(text, FitWarning, stacklevel=3)
    return result


def _result_message(result) -> str:
    """The optimistix result's own explanation, e.g. "The maximum number of steps was reached"."""
    text = str(result)
    start, stop = text.find("<"), text.rfind(">")
    return text[start + 1 : stop] if 0 <= start < stop else text
