"""Hyperparameters by maximum marginal likelihood (optimistix BFGS on log-parameters).

The value-noise nugget ``ν²`` is fitted by default, bounded below by a reparametrisation
(``ν² = σ(floor + e^θ)``) so that an unconstrained solver can be used.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Bool, Float
from tqdm.auto import tqdm

from gpg import _host
from gpg._deprecated import deprecated
from gpg._dtype import float64
from gpg.gp import slq
from gpg.gp.cg import NotConverged
from gpg.gp.directions import check_bases
from gpg.gp.hyper import Hyper, gradient_noise
from gpg.gp.likelihood import log_marginal_likelihood
from gpg.gp.pic import inducing_inputs
from gpg.gp.targets import Checked, check_training_data

__all__ = [
    "FitError",
    "FitOptions",
    "FitWarning",
    "HyperFitResult",
    "Stochastic",
    "fit_hyperparameters",
]


@dataclass(frozen=True)
class Stochastic:
    """Options of the stochastic likelihood (:mod:`gpg.gp.slq`): ``probes`` fixed Gaussian
    probes drawn with ``seed``, CG to relative residual ``tol`` within ``max_iter`` steps
    (the probes' own solves to ``probe_tol``; None: ``tol``), at most ``lanczos`` of them in
    each quadrature, a Nyström preconditioner on ``points`` k-means inducing inputs, products
    ``tile`` points at a time; the fit ends once 3 accepted steps in a row each lowered the
    negative log likelihood per target by less than ``ftol`` (0: only optimistix's own test
    and the stalled line search end it)."""

    probes: int = 30
    tol: float = 1e-5
    max_iter: int = 500
    lanczos: int = 100
    points: int = 250
    seed: int = 0
    tile: int = 256
    progress: bool = True
    probe_tol: float | None = 1e-3
    ftol: float = 2e-5

    def __post_init__(self):
        for name in ("probes", "max_iter", "lanczos", "points", "tile"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"stochastic.{name} must be a positive integer, got {value!r}")
        for name in ("tol", "probe_tol"):
            value = getattr(self, name)
            if name == "probe_tol" and value is None:
                continue
            if isinstance(value, bool) or not (isinstance(value, float | int) and 0 < value < 1):
                raise ValueError(f"stochastic.{name} must be in (0, 1), got {value!r}")
        if isinstance(self.ftol, bool) or not (
            isinstance(self.ftol, float | int) and self.ftol >= 0
        ):
            raise ValueError(f"stochastic.ftol must be a number >= 0, got {self.ftol!r}")

    def arguments(self, X: Float[ArrayLike, "N D"], n_grad: int, rows: int) -> tuple:
        """The inducing inputs and the fixed probes for the points ``X``.

        Both are fixed for the whole fit, so that the objective is one deterministic function
        of the hyperparameters.

        Args:
            X: (N, D) the points the likelihood is evaluated on.
            n_grad: the number of gradient dims G.
            rows: R, the number of rows of ``Ȳ``.

        Returns:
            ``(Z, probes)``: ``min(points, N)`` k-means inducing inputs (a JAX array) and the
            :class:`gpg.gp.slq.Probes` drawn with ``seed``.
        """
        Z = inducing_inputs(np.asarray(X), min(self.points, X.shape[0]), seed=self.seed)
        Z = jnp.asarray(Z)
        return Z, slq.Probes.draw(rows, Z.shape[0] * (1 + n_grad), self.probes, self.seed)


@dataclass(frozen=True)
class FitOptions:
    """How :func:`fit_hyperparameters` fits, in one object (every field is also a keyword of
    that function, which overrides it).

    Attributes:
        ard: one lengthscale per input (else one for all).
        fit_grad_noise: also fit the scale ``s`` of the gradient noise ``λ_i² = s·Var(∂_i Ỹ)``.
        fit_noise: fit the value-noise nugget ``ν²`` (else it stays as in ``init``).
        noise_floor: the fitted ``ν²/σ`` stays above this.
        noise_init: ``ν²/σ`` where the fit starts.
        subset_size: points per likelihood evaluation (a random subset beyond; None: all).
        seed: the subset's draw.
        max_steps: BFGS steps.
        rtol: BFGS's relative tolerance.
        atol: BFGS's absolute tolerance.
        on_failure: ``"warn"`` (a :class:`FitWarning`, the last iterate returned),
            ``"raise"`` (:class:`FitError`) or ``"ignore"``.
        likelihood: ``"dense"`` (``K̄`` factorised at every step) or ``"stochastic"``
            (:mod:`gpg.gp.slq`, options in ``stochastic``).
        stochastic: the stochastic likelihood's options (None: :class:`Stochastic`'s defaults).
    """

    ard: bool = True
    fit_grad_noise: bool = False
    fit_noise: bool = True
    noise_floor: float = 1e-6
    noise_init: float = 1e-2
    subset_size: int | None = 400
    seed: int = 0
    max_steps: int = 200
    rtol: float = 1e-6
    atol: float = 1e-6
    on_failure: str = "warn"
    likelihood: str = "dense"
    stochastic: Stochastic | None = None

    def __post_init__(self):
        if self.likelihood not in ("dense", "stochastic"):
            raise ValueError(f"likelihood must be 'dense' or 'stochastic', got {self.likelihood!r}")
        if self.on_failure not in ("warn", "raise", "ignore"):
            raise ValueError(
                f"on_failure must be 'warn', 'raise' or 'ignore', got {self.on_failure!r}"
            )
        if self.fit_noise and not (0 < self.noise_floor < self.noise_init):
            raise ValueError(
                "noise_floor and noise_init (ν²/σ) must satisfy 0 < noise_floor < noise_init, "
                f"got {self.noise_floor} and {self.noise_init}"
            )


def _stochastic(X, Ybar, hyper, grad_dims, args, opts: Stochastic) -> slq.StochasticLML:
    Z, probes = args
    return slq.stochastic_log_marginal_likelihood(
        X, Ybar, hyper, grad_dims, Z, probes,
        tol=opts.tol, max_iter=opts.max_iter, lanczos=opts.lanczos, tile=opts.tile,
        probe_tol=opts.probe_tol,
    )  # fmt: skip


def _stochastic_lml(X, Ybar, hyper, grad_dims, args, opts: Stochastic):
    """The stochastic log likelihood, −∞ (a rejected step) where a CG solve fell short."""
    out = _stochastic(X, Ybar, hyper, grad_dims, args, opts)
    return jnp.where(out.converged, out.value, -jnp.inf)


def _check_solves(X, Ybar, hyper, data, args, opts: Stochastic) -> float:
    """The log likelihood at the starting point, whose CG solves must reach their tolerance,
    else ``NotConverged`` saying what to change (later steps that fall short are rejected
    by the line search)."""
    out = eqx.filter_jit(_stochastic)(X, Ybar, hyper, data.grad_dims, args, opts)
    if not bool(out.converged):
        raise NotConverged(
            f"the likelihood's CG solves did not reach the relative residual {opts.tol:g}"
            + ("" if opts.probe_tol is None else f" (probes {opts.probe_tol:g})")
            + " in "
            f"{opts.max_iter} iterations at the starting hyperparameters; raise "
            "stochastic.max_iter (hyper.cg_max_iter), loosen stochastic.tol (hyper.cg_tol), or "
            "use more preconditioner points"
        )
    return float(out.value)


class _WithAux(eqx.Module):
    """``loss`` as optimistix's ``fn`` (value, aux), a static field: the jitted steps below are
    keyed by the loss itself, so the fits of one loss share their compiled programs."""

    loss: Any = eqx.field(static=True)

    def __call__(self, y, args):
        return self.loss(y, args), None


@eqx.filter_jit
def _solver_step(solver, fn, y, state, args):
    return solver.step(fn, y, args, {}, state, frozenset())


@eqx.filter_jit
def _solver_terminate(solver, fn, y, state, args):
    return solver.terminate(fn, y, args, {}, state, frozenset())


def _minimise_with_progress(
    loss, solver, params, args, max_steps: int, progress: bool, stall: int = 5,
    stall_step: float = 1e-3, ftol: float = 0.0, patience: int = 3,
):  # fmt: skip
    """``optx.minimise`` one jitted step at a time (optimistix's own stepping interface), so
    a fit whose steps take seconds shows its progress: the solution, status and step count.

    It also ends, successfully, once ``stall`` steps in a row were rejected and the line
    search is trying a step below ``stall_step`` in every (log-)parameter: the stochastic
    objective is exact only to its CG tolerance (its step counts change with the
    hyperparameters), so near the optimum the line search finds nothing lower and
    optimistix's Cauchy test, which needs an accepted step, never passes: at data=default
    the fit converged, then spent the rest of ``max_steps`` on rejected steps
    (docs/scaling.md). Rejections alone are no sign: far from the optimum a quasi-Newton
    step may need several halvings.

    With ``ftol > 0`` it ends, successfully, once ``patience`` accepted steps in a row each
    lowered the objective by less than ``ftol`` (scipy's ``ftol``, absolute: the loss is a
    negative log likelihood per target); rejected steps neither count nor reset that run.
    The full-data refit spends its second half crawling along a nearly flat valley that
    moves the likelihood by a few nats per step and the test errors hardly at all
    (docs/scaling.md measures both)."""
    fn = _WithAux(loss)
    f_struct = jax.ShapeDtypeStruct((), jnp.result_type(float))
    state = solver.init(fn, params, args, {}, f_struct, None, frozenset())
    step = lambda y, s, a: _solver_step(solver, fn, y, s, a)  # noqa: E731
    terminate = lambda y, s, a: _solver_terminate(solver, fn, y, s, a)  # noqa: E731
    y, aux, n, rejected, stalled, flat = params, None, 0, 0, False, 0
    done, status = terminate(y, state, args)
    best = np.inf
    bar = tqdm(total=max_steps, desc="likelihood fit", unit="step", disable=not progress)
    with bar:
        while not bool(done) and n < max_steps and not stalled:
            y, state, aux = step(y, state, args)
            done, status = terminate(y, state, args)
            n += 1
            f = float(state.f_info.f)
            rejected = rejected + 1 if f >= best else 0
            if f < best:
                flat = flat + 1 if best - f < ftol else 0
            best = min(best, f)
            pairs = zip(jax.tree.leaves(state.y_eval), jax.tree.leaves(y), strict=True)
            trial = max(float(jnp.max(jnp.abs(a - b))) for a, b in pairs)
            stalled = (rejected >= stall and trial <= stall_step) or flat >= patience
            bar.update()
            bar.set_postfix_str(f"nll {f:.6g}")
    if stalled:
        status = optx.RESULTS.successful
    elif not bool(done):
        status = optx.RESULTS.max_steps_reached
    y, _, _ = solver.postprocess(fn, y, aux, args, {}, state, frozenset(), status)
    return y, status, n


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
    noise_fitted: bool = False

    @property
    def noise_ratio(self) -> float:
        """The value-noise nugget relative to the signal variance, ``ν²/σ``."""
        return float(self.hyper.noise / self.hyper.variance)


def _unpack(params, base: Hyper, grad_var, noise_floor: float):
    variance = jnp.exp(params["log_variance"])
    grad_noise = base.grad_noise
    if "log_s" in params:
        grad_noise = jnp.exp(params["log_s"]) * grad_var
    noise = base.noise
    if "log_noise_ratio" in params:
        # ν² = σ (floor + e^θ): the bound holds exactly for every θ, so an unconstrained
        # optimiser can be used (no projection, no clipping of the gradient).
        noise = variance * (noise_floor + jnp.exp(params["log_noise_ratio"]))
    return Hyper(
        variance=variance,
        lengthscale=jnp.exp(params["log_lengthscale"]),
        noise=noise,
        grad_noise=grad_noise,
    )


def _finite(nll):
    """A non-PD trial point gives NaN: reported as a bad step, so the line search backs off."""
    return jnp.where(jnp.isfinite(nll), nll, jnp.asarray(1e10))


@dataclass(frozen=True, eq=False)
class _Host:
    """A host array (or None) as a static argument of the jitted fit, equal by content: fits
    on equal row layouts share a compiled program."""

    a: Any

    def _key(self):
        a = self.a
        return None if a is None else (a.shape, a.dtype.str, np.ascontiguousarray(a).tobytes())

    def __hash__(self):
        return hash(self._key())

    def __eq__(self, other):
        return isinstance(other, _Host) and self._key() == other._key()


def _dense_loss(p, args):
    """The dense negative log marginal likelihood per target at log-parameters ``p``."""
    Xs, Ybar, noise, init, grad_var, floor, grad_dims, scale, rows, bases = args
    h = _unpack(p, init, grad_var, floor)
    lml = log_marginal_likelihood(Xs, Ybar, h, grad_dims, rows.a, bases.a, row_noise=noise)
    return _finite(-lml / scale)


# The loss before and after the fit (its warning's and its result's), one compiled program
# for both: run op by op, each of its operations compiled on its own at every new shape.
_dense_loss_jit = eqx.filter_jit(_dense_loss)


def _stochastic_loss(p, args):
    """The stochastic negative log marginal likelihood per target at log-parameters ``p``."""
    fixed, Xs, Ybar, init, grad_var, floor, grad_dims, scale, sto = args
    h = _unpack(p, init, grad_var, floor)
    return _finite(-_stochastic_lml(Xs, Ybar, h, grad_dims, fixed, sto) / scale)


_RENAMED = {"fit_jitter": "fit_noise", "jitter_floor": "noise_floor", "jitter_init": "noise_init"}


def _checked_init(data, init: Hyper | None, ard: bool, fit_grad_noise: bool, subset_size):
    """The starting hyperparameters, checked against the data (``ValueError`` naming what)."""
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
    if fit_grad_noise and g == 0:
        raise ValueError("fit_grad_noise=True needs gradient observations (dY)")
    return init.validate(d, g)


def _subset(n: int, size: int | None, seed: int) -> np.ndarray:
    """The points the likelihood is evaluated on: all, or ``size`` drawn with ``seed``."""
    if size is not None and n > size:
        return np.sort(np.random.default_rng(seed).choice(n, size=size, replace=False))
    return np.arange(n)


def _initial_params(data, init: Hyper, fit_grad_noise, fit_noise, noise_init, noise_floor):
    """The optimiser's log-parameters at ``init``, and the gradients' variances that ``s``
    scales (None unless ``fit_grad_noise``)."""
    grad_var = None
    params = {
        "log_variance": jnp.log(init.variance),
        "log_lengthscale": jnp.log(init.lengthscale),
    }
    if fit_grad_noise:
        grad_var = gradient_noise(data.gradients(), s=1.0)
        lam = jnp.broadcast_to(init.grad_noise, (len(data.grad_dims),))
        params["log_s"] = jnp.mean(jnp.log(lam / grad_var))
    if fit_noise:
        params["log_noise_ratio"] = jnp.log(jnp.asarray(noise_init - noise_floor))
    return params, grad_var


def _outcome(status, hyper: Hyper, nll: float) -> tuple[bool, str]:
    """Whether the optimiser converged to a finite likelihood, and what to say if not."""
    ok = bool(status == optx.RESULTS.successful)
    message = "converged" if ok else f"optimistix stopped: {_result_message(status)}"
    finite = all(np.all(np.isfinite(np.asarray(v))) for v in jax.tree.leaves(hyper))
    if ok and (not finite or nll >= 1e10):
        ok, message = False, "the likelihood is not finite at the optimum"
    return ok, message


def _options(options: FitOptions | None, keywords: dict[str, Any]) -> FitOptions:
    """``options`` with ``keywords`` (its fields, or the renamed ones of earlier releases)."""
    fields = {f.name for f in dataclasses.fields(FitOptions)}
    out = {}
    for name, value in keywords.items():
        if name in _RENAMED:
            deprecated(f"fit_hyperparameters({name}=...)", f"{_RENAMED[name]}=...")
            name = _RENAMED[name]
        elif name not in fields:
            raise TypeError(f"fit_hyperparameters() got an unexpected keyword argument {name!r}")
        out[name] = value
    return dataclasses.replace(FitOptions() if options is None else options, **out)


# Long by design: its signature, one documented keyword per option of the fit, is a third of it.
@float64
def fit_hyperparameters(
    X: Float[ArrayLike, "N D"],
    Y: Float[ArrayLike, "N M"],
    dY: Float[ArrayLike, "N M G"] | None = None,
    *,
    grad_dims: Sequence[int] | None = None,
    init: Hyper | None = None,
    options: FitOptions | None = None,
    observed: Bool[ArrayLike, "N G"] | None = None,
    bases: Float[ArrayLike, "N G G"] | None = None,
    row_noise: Float[ArrayLike, " N"] | None = None,
    **keywords: Any,
) -> HyperFitResult:
    """Maximise the log marginal likelihood over log-parameters with optimistix BFGS.

    Fitted: signal variance σ, lengthscale(s) ``l`` (one per input if ``ard``), the value-noise
    nugget ``ν²`` if ``fit_noise`` (bounded below by ``noise_floor·σ``, started from
    ``noise_init·σ``; otherwise it stays as in ``init``), and, if ``fit_grad_noise``, the scale
    ``s`` of the gradient noise ``λ_i² = s·Var(∂_i Ỹ)``. A fixed tiny ``ν²`` leaves the model
    overconfident on data that no smooth function fits exactly (finite-difference gradients,
    a simulator's own discretisation): the nugget is what absorbs that misfit. When N exceeds
    ``subset_size`` the likelihood is evaluated on a random subset of that many points (drawn
    with ``seed``), since each step factorises K̄. ``"stochastic"`` likelihood never forms it
    (CG solves and stochastic Lanczos quadrature), so ``subset_size=None`` fits on all points
    at any N, with a progress bar per step.

    Args:
        X: inputs (N, D).
        Y: values (N, M).
        dY: gradients (N, M, G) or None.
        grad_dims: the G input dimensions of ``dY`` (default: all when ``dY`` is given).
        init: where the fit starts (default ``Hyper()``); the fields not fitted stay.
        options: how to fit (:class:`FitOptions`; default its defaults).
        observed: (N, G) the gradients each case has (:func:`gpg.gp.gram.observed_rows`;
            dense likelihood only).
        bases: (N, G, G) the directions of the gradient rows
            (:func:`gpg.gp.gram.row_directions`; dense only).
        row_noise: (N,) each case's own value-noise variance on top of ``ν²``
            (:meth:`gpg.gp.exact.ExactGP.fit`; dense only).
        **keywords: fields of :class:`FitOptions`, overriding ``options`` (the keywords
            ``fit_jitter``, ``jitter_floor`` and ``jitter_init`` of earlier releases are read
            as the ``noise`` ones with a ``DeprecationWarning``).

    Returns:
        The fitted hyperparameters and how the fit went (:class:`HyperFitResult`).

    Raises:
        ValueError: bad data or options (the message names them).
        TypeError: a keyword that is not an option.
        FitError: a failed fit with ``on_failure="raise"``.
    """
    opts = _options(options, keywords)
    ard, fit_grad_noise, fit_noise = opts.ard, opts.fit_grad_noise, opts.fit_noise
    noise_floor, noise_init, likelihood = opts.noise_floor, opts.noise_init, opts.likelihood
    data = check_training_data(X, Y, dY, grad_dims, observed)
    if data.observed is not None and likelihood != "dense":
        raise ValueError("observed (cases without some gradients) needs likelihood='dense'")
    bases = check_bases(bases, data.X.shape[0], data.grad_dims)
    if bases is not None and likelihood != "dense":
        raise ValueError("bases (directional gradient rows) needs likelihood='dense'")
    if row_noise is not None:
        if likelihood != "dense":
            raise ValueError("row_noise (per-case value noise) needs likelihood='dense'")
        row_noise = np.asarray(row_noise, dtype=np.float64)
        n = data.X.shape[0]
        if row_noise.shape != (n,):
            raise ValueError(f"row_noise must have shape ({n},), got {row_noise.shape}")
        if not np.all(np.isfinite(row_noise)) or np.any(row_noise < 0):
            raise ValueError("row_noise must be finite and >= 0")
    init = _checked_init(data, init, ard, fit_grad_noise, opts.subset_size)
    subset = _subset(data.X.shape[0], opts.subset_size, opts.seed)
    sub_noise = None if row_noise is None else jnp.asarray(row_noise[subset])
    Xs = jnp.asarray(data.X[subset])
    pick = (None if a is None else a[subset] for a in (data.dY, data.observed))
    sub = Checked(data.X[subset], data.Y[subset], next(pick), data.grad_dims, next(pick))
    rows = sub.rows
    sub_bases = None if bases is None else bases[subset]
    Ybar = _host.asarray(sub.targets())
    scale = float(Ybar.size if rows is None else rows.sum() * Ybar.shape[1])
    params, grad_var = _initial_params(
        data, init, fit_grad_noise, fit_noise, noise_init, noise_floor
    )

    solver = optx.BFGS(rtol=opts.rtol, atol=opts.atol)
    max_steps = opts.max_steps
    if likelihood == "dense":
        # The data go in as arguments of one module-level loss (not a closure over them), so
        # that fits of equal shapes and settings (a correction's six outputs, a test's many
        # fits) reuse one traced and compiled optimiser instead of tracing it per call.
        dense = (Xs, Ybar, sub_noise, init, grad_var, noise_floor, data.grad_dims, scale,
                 _Host(rows), _Host(sub_bases))  # fmt: skip
        nll0 = float(_dense_loss_jit(params, dense))
        sol = optx.minimise(_dense_loss, solver, params, args=dense, max_steps=max_steps,
                            throw=False)  # fmt: skip
        value, status, steps = sol.value, sol.result, int(sol.stats["num_steps"])
        nll1 = float(_dense_loss_jit(value, dense))
    else:
        sto = Stochastic() if opts.stochastic is None else opts.stochastic
        args = sto.arguments(Xs, len(data.grad_dims), Ybar.shape[0])
        h0 = _unpack(params, init, grad_var, noise_floor)
        nll0 = -_check_solves(Xs, Ybar, h0, data, args, sto) / scale
        # as the dense fit's: the data are arguments of one module-level loss
        args = (args, Xs, Ybar, init, grad_var, noise_floor, data.grad_dims, scale, sto)
        value, status, steps = _minimise_with_progress(
            _stochastic_loss, solver, params, args, max_steps, sto.progress, ftol=sto.ftol
        )
        nll1 = float(eqx.filter_jit(_stochastic_loss)(value, args))
    hyper = _unpack(value, init, grad_var, noise_floor)
    ok, message = _outcome(status, hyper, nll1)
    result = HyperFitResult(
        hyper=hyper,
        converged=ok,
        num_steps=steps,
        nll_initial=nll0 * scale,
        nll_final=nll1 * scale,
        message=message,
        subset=subset,
        grad_noise_scale=float(jnp.exp(value["log_s"])) if fit_grad_noise else None,
        noise_fitted=fit_noise,
    )
    if not ok:
        _failed(result, opts.on_failure)
    return result


def _failed(result: HyperFitResult, on_failure: str) -> None:
    text = (
        f"hyperparameter fit did not converge after {result.num_steps} steps "
        f"({result.message}); negative log likelihood {result.nll_initial:.6g} -> "
        f"{result.nll_final:.6g}"
    )
    if on_failure == "raise":
        raise FitError(text)
    if on_failure == "warn":
        warnings.warn(text, FitWarning, stacklevel=4)


def _result_message(result) -> str:
    """The optimistix result's own explanation, e.g. "The maximum number of steps was reached"."""
    text = str(result)
    start, stop = text.find("<"), text.rfind(">")
    return text[start + 1 : stop] if 0 <= start < stop else text
