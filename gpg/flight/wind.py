"""The wind of a flight estimated from its labels, where no anemometer logged it.

The measured force depends on the air velocity ``v − w``; a model of the force (the identified
vehicle's physics, :class:`gpg.flight.Identification`, or a fitted surrogate) turns each label
into a constraint on the wind ``w``. The wind is a slowly varying state: piecewise linear in
time between knots ``knot_s`` apart, with a random-walk prior between knots (``drift`` m/s per
√s) and a wide prior on its start. Gauss-Newton on the whitened residuals (each label's noise
plus the model's error variance, itself re-estimated from the residuals) gives the posterior
mean and covariance of the knots; a label's wind is their interpolation, with its standard
deviation.

The manoeuvres make drag and wind separable: a vehicle that flies at one velocity sees one air
velocity, and only the sum of its drag and the wind's is measured, whereas a vehicle that
changes its velocity sweeps the drag's curve, whose shape fixes the wind. With the drag known
(identified), a flight at one velocity still gives a wind wherever the force responds to the
air velocity, but then a constant error of the model reads as wind. Both cases warn and name the
axis (:class:`WindWarning`): an axis without manoeuvres (the ground velocity's spread under
``min_manoeuvre``), and an axis the flight does not inform (its posterior standard deviation
above ``max_sd``). The vertical wind is held at zero by default
(``axes="xy"``): vertical drag and the rotors' inflow are confounded with it.

:func:`with_wind` puts an estimate into labels: their air velocity becomes ``v − ŵ``, and the
wind's uncertainty enters the force labels' noise, ``(∂F/∂v)² σ_w²`` per component.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from gpg._dtype import float64
from gpg.flight.labels import Labels

__all__ = [
    "WindEstimate",
    "WindWarning",
    "estimate_wind",
    "force_model",
    "wind_variance",
    "with_wind",
]


class WindWarning(UserWarning):
    """A flight that cannot tell the wind along an axis from the drag (named)."""


@dataclass(frozen=True)
class WindEstimate:
    """The wind along a flight (:func:`estimate_wind`), at its labels' times.

    Attributes:
        t: (N,) the labels' times, s.
        wind: (N, 3) the estimated wind, world NED, m/s.
        sd: (N, 3) its posterior standard deviation, m/s.
        knot_t: (K,) the knots' times, s.
        knots: (K, 3) the wind at the knots.
        force_var: (N, 3) the force labels' variance from the wind's uncertainty, N².
        model_var: (3,) the force model's error variance per component, N².
        informed: (3,) whether the flight determines each axis (``max_sd``).
        iterations: Gauss-Newton steps taken.
        name: the flight's name.
    """

    t: np.ndarray
    wind: np.ndarray
    sd: np.ndarray
    knot_t: np.ndarray
    knots: np.ndarray
    force_var: np.ndarray
    model_var: np.ndarray
    informed: np.ndarray
    iterations: int
    name: str = "flight"

    @property
    def mean(self) -> np.ndarray:
        """(3,) the flight's mean wind, m/s."""
        return self.wind.mean(0)


def force_model(model: Any) -> Callable:
    """The world-frame force of a model as ``f(rpm, euler, v_air) -> (3,)``, traceable.

    Args:
        model: an :class:`~gpg.flight.Identification` (its vehicle's physics, the motor
            curve's gain and power applied), a :class:`~gpg.Surrogate` (its mean), or such a
            function itself.

    Returns:
        The force function of one state.

    Raises:
        ValueError: any other model.
    """
    from gpg.flight.identify import Identification
    from gpg.surrogate import Surrogate

    if isinstance(model, Identification):
        motor = jnp.asarray([model.motor_gain, model.motor_exponent, model.rpm_ref])
        return _PhysicsForce(model.vehicle, motor, model.physics)
    if isinstance(model, Surrogate):
        return _SurrogateForce(model)
    if callable(model) and not isinstance(model, str | bytes):
        return model
    raise ValueError(
        f"estimate_wind needs a gpg.flight.Identification, a gpg.Surrogate or a force "
        f"function f(rpm, euler, v_air), got "
        f"{type(model).__name__}"
    )


class _PhysicsForce(eqx.Module):
    """The identified vehicle's physics as a force function (a pytree: compiled once)."""

    vehicle: Any
    motor: Any  # (gain, exponent, rpm_ref) of the identified curve
    cfg: Any

    def __call__(self, rpm, euler, v_air):
        from gpg.flight.identify import motor_speeds, physics_loads

        g, p, r = self.motor[0], self.motor[1], self.motor[2]
        speeds = motor_speeds(rpm, jnp.log(g), jnp.log(p), r)
        out = physics_loads(self.vehicle, self.cfg, speeds[None], euler[None], v_air[None])
        return out[0, :3]


class _SurrogateForce(eqx.Module):
    """A surrogate's mean force as a force function (a pytree: compiled once)."""

    sur: Any

    def __call__(self, rpm, euler, v_air):
        return self.sur.predict(rpm, euler, v_air).force


@eqx.filter_jit
def _linearised(f, rpm, euler, v_air):
    def one(r, e, v):
        return f(r, e, v), jax.jacfwd(lambda vv: f(r, e, vv))(v)

    return jax.vmap(one)(rpm, euler, v_air)


@float64
def estimate_wind(
    labels: Labels,
    model: Any,
    *,
    knot_s: float = 5.0,
    drift: float = 0.3,
    axes: str = "xy",
    max_sd: float = 1.0,
    start_sd: float = 15.0,
    max_iter: int = 15,
    min_manoeuvre: float = 0.5,
) -> WindEstimate:
    """The wind along one flight, from its labels and a force model (module docstring).

    Args:
        labels: one flight's labels, made without a wind (their ``v_air`` is the ground
            velocity).
        model: the force model (:func:`force_model`): the identified vehicle, a surrogate, or
            a traceable function ``f(rpm, euler, v_air) -> (3,)`` (world frame).
        knot_s: s between the wind's knots.
        drift: m/s per √s, the random walk's scale between knots (a steady wind: small).
        axes: the axes estimated, ``"xy"`` (the vertical wind held at 0) or ``"xyz"``.
        max_sd: m/s; an axis whose posterior standard deviation (median over the flight) is
            above it is not informed by the flight: warned.
        start_sd: m/s, the prior's standard deviation of the first knot.
        max_iter: Gauss-Newton steps at most per pass (two passes: the model's error variance
            is refitted between them).
        min_manoeuvre: m/s; an estimated axis along which the ground velocity's standard
            deviation is under it has no manoeuvres: warned (a model's bias reads as wind).

    Returns:
        The :class:`WindEstimate`.

    Raises:
        ValueError: labels of several flights (times that go back), fewer than 10 labels, a
            bad option.
    """
    t = _checked(labels, axes, knot_s, drift, max_sd, start_sd)
    f = force_model(model)
    nax = len(axes)
    knot_t, Phi, D = _knots(t, knot_s, drift, start_sd)
    K = knot_t.size
    Dk = np.kron(D, np.eye(nax))
    rpm, euler, v_g = (jnp.asarray(a, float) for a in (labels.rpm, labels.euler, labels.v_air))
    y = np.asarray(labels.force, float)
    var = np.asarray(labels.force_var, float)

    linearised = _at_knots(f, rpm, euler, v_g, Phi)

    def system(W, model_var):
        """The residuals, the Gauss-Newton matrix and gradient, and the cost at ``W``."""
        F, Jv = linearised(W)
        r = y - F
        wgt = 1.0 / (var + model_var)  # (N, 3)
        Jw = -Jv[:, :, :nax]  # dF/dw = −J_v, over the estimated axes
        G = np.einsum("nca,nc,ncb->nab", Jw, wgt, Jw)
        A = np.einsum("nk,nab,nl->kalb", Phi, G, Phi).reshape(K * nax, K * nax) + Dk
        x = W[:, :nax].reshape(-1)
        g = np.einsum("nk,nca,nc->ka", Phi, Jw, wgt * r).reshape(-1) - Dk @ x
        cost = 0.5 * (np.sum(wgt * r * r) + x @ Dk @ x)
        return r, A, g, cost

    def error_var(r):
        return np.maximum(np.mean(r**2 - var, 0), 1e-4 * np.mean(y**2, 0) + 1e-9)

    W = np.zeros((K, 3))
    # The model's error variance: first from the calm guess (conservative), then refitted.
    model_var = error_var(system(W, np.ones(3))[0])
    it = 0
    for _ in range(2):
        W, r, n = _damped_gauss_newton(system, W, model_var, nax, max_iter)
        it += n
        model_var = error_var(r)
    A = system(W, model_var)[1]
    cov4 = np.linalg.inv(A).reshape(K, nax, K, nax)  # the knots' posterior covariance
    sd = np.zeros((t.size, 3))
    sd[:, :nax] = np.sqrt(np.maximum(np.einsum("nk,kala,nl->na", Phi, cov4, Phi), 0.0))
    w_t = Phi @ W
    _, Jv = linearised(W)
    informed = np.zeros(3, bool)
    informed[:nax] = np.median(sd[:, :nax], 0) <= max_sd
    _warn(labels, sd, informed, nax, max_sd, min_manoeuvre)
    return WindEstimate(t=t, wind=w_t, sd=sd, knot_t=knot_t, knots=W,
                        force_var=np.einsum("nca,na->nc", Jv**2, sd**2), model_var=model_var,
                        informed=informed, iterations=it, name=labels.name)  # fmt: skip


def _checked(labels, axes, knot_s, drift, max_sd, start_sd) -> np.ndarray:
    """The labels' times, after the options and the labels are checked."""
    if not isinstance(labels, Labels):
        raise ValueError("estimate_wind needs one flight's gpg.flight.Labels")
    if axes not in ("xy", "xyz"):
        raise ValueError(f"axes must be 'xy' or 'xyz', got {axes!r}")
    if not (knot_s > 0 and drift > 0 and max_sd > 0 and start_sd > 0):
        raise ValueError("knot_s, drift, max_sd and start_sd must be > 0")
    t = np.asarray(labels.t, float)
    if len(labels) < 10:
        raise ValueError(f"estimate_wind needs at least 10 labels, got {len(labels)}")
    if np.any(np.diff(t) <= 0):
        raise ValueError(
            "estimate_wind takes one flight at a time: the labels' times do not increase "
            "(labels of several flights concatenated?)"
        )
    return t


def _at_knots(f, rpm, euler, v_g, Phi):
    """``linearised(W)``: the force and its Jacobian in the air velocity with the wind of the
    knots ``W``, the last kept (each pass starts, and the estimate ends, where the previous
    evaluation was)."""
    last: list = [None, None]

    def linearised(W):
        if last[0] is None or not np.array_equal(last[0], W):
            out = _linearised(f, rpm, euler, v_g - jnp.asarray(Phi @ W))
            last[:] = [W.copy(), tuple(np.asarray(a) for a in out)]
        return last[1]

    return linearised


def _knots(t: np.ndarray, knot_s: float, drift: float, start_sd: float):
    """The knots' times, each label's linear interpolation weights on them (N, K), and the
    prior's precision over them: a wide start and the random walk between knots."""
    knot_t = np.arange(t[0], t[-1] + knot_s, knot_s)
    K = knot_t.size
    Phi = np.zeros((t.size, K))
    if K > 1:
        j = np.clip(np.searchsorted(knot_t, t, side="right") - 1, 0, K - 2)
        a = (t - knot_t[j]) / (knot_t[j + 1] - knot_t[j])
        Phi[np.arange(t.size), j] = 1 - a
        Phi[np.arange(t.size), j + 1] = a
    else:
        Phi[:, 0] = 1.0
    D = np.zeros((K, K))
    D[0, 0] = 1.0 / start_sd**2
    for k in range(K - 1):
        q = 1.0 / (drift**2 * (knot_t[k + 1] - knot_t[k]))
        D[k : k + 2, k : k + 2] += q * np.array([[1.0, -1.0], [-1.0, 1.0]])
    return knot_t, Phi, D


def _damped_gauss_newton(system, W, model_var, nax: int, max_iter: int):
    """Levenberg-Marquardt steps on the knots from ``W``: a step that lowers the cost is
    taken and the damping shrunk, else the damping grows; stops when no knot moves by a
    millimetre per second. Returns the knots, the residuals there and the steps taken."""
    r, A, g, cost = system(W, model_var)
    mu, n = 1e-3, 0
    for _ in range(max_iter):
        n += 1
        step = np.linalg.solve(A + mu * np.diag(np.diag(A)), g).reshape(W.shape[0], nax)
        trial = W.copy()
        trial[:, :nax] += step
        r2, A2, g2, cost2 = system(trial, model_var)
        if np.isfinite(cost2) and cost2 <= cost:
            W, r, A, g, cost, mu = trial, r2, A2, g2, cost2, max(mu / 10, 1e-9)
            if np.max(np.abs(step)) < 1e-3:
                break
        else:
            mu *= 10
            if mu > 1e8:
                break
    return W, r, n


def _warn(labels: Labels, sd, informed, nax: int, max_sd: float, min_manoeuvre: float) -> None:
    """What the flight cannot tell, named: axes without manoeuvres, axes not informed."""
    axis = ("x", "y", "z")
    # Without manoeuvres along an axis a constant error of the force model reads as wind:
    # the estimate is then the model's, not the flight's.
    still = [axis[a] for a in range(nax) if np.std(np.asarray(labels.v_air)[:, a]) < min_manoeuvre]
    if still:
        warnings.warn(
            f"{labels.name}: no manoeuvres along {', '.join(still)} (ground velocity sd under "
            f"{min_manoeuvre:g} m/s): a bias of the force model there reads as wind",
            WindWarning,
            stacklevel=3,
        )
    weak = [axis[a] for a in range(nax) if not informed[a]]
    if weak:
        warnings.warn(
            f"{labels.name}: the flight does not determine the wind along {', '.join(weak)} "
            f"(posterior sd {np.round(np.median(sd[:, :nax], 0), 2).tolist()} m/s above "
            f"{max_sd:g}): too few manoeuvres or too little airspeed to tell drag from wind",
            WindWarning,
            stacklevel=3,
        )


def with_wind(labels: Labels, estimate: WindEstimate) -> Labels:
    """Labels with an estimated wind: air velocity ``v − ŵ``, the wind's uncertainty added to
    the force labels' noise.

    Args:
        labels: the labels the estimate was made from (no wind in their log).
        estimate: :func:`estimate_wind` of them.

    Returns:
        The labels with the wind applied.

    Raises:
        ValueError: an estimate of other labels (their times differ).
    """
    if len(labels) != estimate.t.size or not np.array_equal(labels.t, estimate.t):
        raise ValueError(
            f"the wind estimate of {estimate.name!r} is not of these labels ({labels.name!r}): "
            "their times differ"
        )
    return dataclasses.replace(
        labels,
        v_air=labels.v_air - estimate.wind,
        force_var=labels.force_var + estimate.force_var,
    )


def wind_variance(
    model: Any,
    rpm: np.ndarray,
    euler: np.ndarray,
    v_air: np.ndarray,
    wind_sd: np.ndarray,
) -> np.ndarray:
    """The force's variance from an uncertain wind, to first order: ``Σ_a (∂F_c/∂v_a)² σ_a²``.

    For predictions at a wind known only roughly (a gusting wind given as its mean, an
    estimate with its standard deviation): add it to the predictive variance of the force.

    Args:
        model: the force model (:func:`force_model`).
        rpm: (N, 4) rotor speeds, rpm.
        euler: (N, 3) attitudes, rad.
        v_air: (N, 3) the air velocities used, world, m/s.
        wind_sd: (N, 3) or (3,) the wind's standard deviation per axis, m/s.

    Returns:
        (N, 3) the force's added variance per component, N².
    """
    f = force_model(model)
    args = (jnp.asarray(a, float) for a in (rpm, euler, v_air))
    _, Jv = (np.asarray(a) for a in _linearised(f, *args))
    sd = np.broadcast_to(np.asarray(wind_sd, float), (Jv.shape[0], 3))
    return np.einsum("nca,na->nc", Jv**2, sd**2)
