"""The physical basis's coefficients followed online: a Kalman filter on their drift.

A new wind, a payload or a worn rotor changes a few physical coefficients (a drag area per
axis, a thrust gain), not the shape of the function. :func:`track` gives a corrected model a
state that follows them label by label. For each load output ``j``,

    y_j(x_t) = m_j(x_t) + h_j(x_t)ᵀ w_j(t) + e_t,    e_t ~ N(0, r_t + v_j),

with ``m`` the offline corrected mean, ``h_j`` the columns of the correction's physical basis
(:mod:`gpg.flight.basis`: the prior's mean, whose coefficient is ``ρ``; ``M``'s loads, ``κ``;
airframe drag per axis, rotor drag, inflow, edgewise) and a constant (a bias: a force no column
explains), ``w_j`` the coefficients' drift from their offline values (in their physical units),
``r_t`` the label's own noise and ``v_j`` the discrepancy left that no column follows. The drift
is an Ornstein-Uhlenbeck process back to the offline posterior: between labels ``Δt`` apart,
with ``a = e^{−Δt/τ}`` for the basis's coefficients and ``e^{−Δt/τ_b}`` for the bias,

    w ← a ⊙ w,    Σ ← (a aᵀ) ⊙ (Σ − Σ_∞) + Σ_∞,    Σ_∞ = C₀ + diag(s² σ_B², s_b²),

with ``C₀`` the coefficients' offline covariance (the physical basis's ``A⁻¹``, with their
spread between the flights held out where the correction measured it; zero
for the regression form and the bias), ``σ_B`` their prior standard deviations
(:data:`gpg.flight.basis.PRIORS`), ``s`` the drift's spread in those units (one per column:
a term the flights do not move stays near its offline value) and ``s_b`` the bias's. A
flight starts from ``N(0, Σ_∞)``; each label is one rank-one update per output. Cost per
label ``O(P²)`` per output (``P = 9`` with ``M``), fixed memory, pure for ``lax.scan``.
The prediction adds ``hᵀ w̄`` to the offline mean; its band on the loads is the filter's
``hᵀ Σ h + v`` plus the discrepancy's latent variance: the offline coefficients' share is in
``Σ`` (it starts there), so the band narrows as the flight tells the coefficients and widens
where the columns grow (a faster wind); the discrepancy's share widens it away from the
flights' states, which the coefficients, spanning only the basis, do not learn. ``v`` takes
the place of the discrepancy's value noise ``ν²``. A flight's labels may be off by the same
amount from start to end: a sensor's bias (the accelerometer's times the mass where the force
comes from an IMU, the attitude's times the weight where it comes from the velocity). No label
tells it from the loads, so the filter (its bias column above all) learns it with them and
predicts the labels, off from the loads by it, sure of itself. :attr:`Drift.label_offset`
states its standard deviation ``σ_o`` per axis (a datasheet's: no flight can fit it), and the
band adds ``σ_o²``; the gain and the mean are unchanged.

:func:`fit_drift` fits ``τ``, ``s``, ``τ_b``, ``s_b`` and ``v`` by maximising the prequential
likelihood (each label predicted before the filter sees it) of training flights, each predicted
by a model that did not see it (the corrected model itself, or the physical basis fitted on
the others: the condition a new flight is in), so that no time constant is set by hand;
:func:`default_drift` is the start for a vehicle never flown. A filter that reads every sample
of a log is fitted on what it reads (``read``: the same flights at the log's rate, each still
predicted by the model fitted on the other flights' labels). A :class:`Drift` may also name
faster members (``fast``): a bank of filters whose biases relax faster, weighted by their
predictive densities with a fixed share (Herbster and Warmuth's switching), for a force that
changes faster than any training flight showed (a gust).
With :func:`gusts` the filter also follows a wind state ``g``: the air's deviation from the
logged ``v_air`` (world, m/s), an Ornstein-Uhlenbeck process of its own (``τ_g``, stationary
standard deviations per axis). Each label first conditions ``g`` by a Kalman step linearised at
``ḡ`` (``H`` the prediction's derivative in ``g``, by ``jax.jacfwd``; the innovation's
covariance ``H P_g Hᵀ`` plus the label's noise, ``v``, the coefficients' band ``hᵀΣh`` and the
discrepancy's latent variance), then the coefficients at ``v_air + ḡ``: two filters in turn
on one label, the cross-covariance between them dropped. A prediction reads the wind-free
model at ``v_air + ḡ`` and adds ``diag(J P_g Jᵀ)`` to the loads' variance
(:meth:`gpg.flight.Corrected.wind_state`).
:func:`prequential` runs any adapted model over a flight and returns what it predicted before
each update.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from gpg import _host
from gpg._dtype import float64
from gpg._precision import highest
from gpg.flight import correction as fc
from gpg.flight.basis import TERMS, PhysicalBasis
from gpg.flight.labels import Labels
from gpg.surrogate import Surrogate, predict_state

__all__ = [
    "DEFAULT_SPREAD",
    "DEFAULT_TAU",
    "Drift",
    "GUST_SD",
    "GUST_TAU",
    "Prequential",
    "Tracker",
    "default_drift",
    "fit_drift",
    "gusts",
    "prequential",
    "score_drift",
    "track",
]

N_LOADS = fc.N_LOADS
DEFAULT_TAU = 60.0
"""s: the default drift's time constant (:func:`default_drift`)."""
DEFAULT_SPREAD = 1.0
"""The default drift's spread, in the coefficients' prior standard deviations."""
DEFAULT_BIAS_TAU = 1.0
"""s: the default bias's time constant."""
DEFAULT_BIAS_SD = 1.0
"""The default bias's stationary standard deviation, in :data:`BIAS_SCALE` units."""
BIAS_SCALE = (1.0, 1.0, 1.0, 0.1, 0.1, 0.1)
"""N, N·m: the bias column's unit per load output (a force of 1 N, a torque of 0.1 N·m)."""
BANKS = ((), (1.0,))
"""The banks :func:`fit_drift` chooses among by their held-out prequential likelihood: one
filter, or one beside a member whose bias relaxes within a second (s)."""
SHARE = 0.01
"""The bank's switching rate: each label, this share of the weight is spread over all members
(fixed-share), so that a member out of favour can win again within tens of labels."""
# Bounds of the fitted drift: τ from a tenth of a second (faster than labels come) to a day,
# the spread from a thousandth to a hundred prior standard deviations.
TAU_RANGE = (0.1, 86400.0)
SPREAD_RANGE = (1e-3, 1e2)
GUST_SD = (1.5, 1.5, 0.0)
"""m/s: the gusts' stationary standard deviations along world x, y, z for :func:`gusts`: the
Dryden model's light turbulence 5 m above the ground horizontally (MIL-HDBK-1797, low
altitude, a wind of 15 kt at 20 ft: ``σ_u = σ_v = σ_w / (0.177 + 0.000823 h)^0.4 = 1.5`` m/s
with ``σ_w = 0.1 W₂₀ = 0.77`` m/s and ``h`` in feet), none vertically: air through the disks
is the thrust's inflow, which the tracked coefficients already follow, and a vertical wind
state takes the thrust's errors for wind (measured: the guide, "Adaptation at the unseen
winds"). Pass ``sd=(1.5, 1.5, 0.8)`` for the model's vertical gusts too."""
GUST_TAU = 3.0
"""s: the gusts' time constant for :func:`gusts`: the same model's horizontal length scale
there (``L_u = h / (0.177 + 0.000823 h)^1.2``, 37 m) over an airspeed of about 12 m/s."""


@dataclass(frozen=True)
class Drift:
    """The drift of the tracked coefficients (module docstring).

    Attributes:
        tau: s, ``τ``: how fast the coefficients move (and return to their offline values).
        spread: ``s``, the drift's stationary standard deviation in prior standard deviations:
            one number for every column, or one per column (:func:`fit_drift`'s default; in
            the order of ``columns``).
        bias_tau: s, ``τ_b``: the bias's time constant (what the last labels' error says of
            the next one's).
        bias_sd: ``s_b``, the bias's stationary standard deviation (:data:`BIAS_SCALE` units).
        noise: (6,) ``v_j``, the discrepancy each load output's measurements carry beyond the
            labels' own noise (the surrogate's normalised units).
        log_likelihood: the prequential log likelihood per label where fitted, else NaN.
        labels: the labels it was fitted on, or the rows read (``fit_drift``'s ``read``); 0:
            not fitted.
        source: ``"fitted"`` or ``"default"``.
        fast: s, the bias time constants of the bank's other members (module docstring);
            empty (the default): one filter.
        share: the bank's switching rate per label.
        wind_sd: m/s, (3,) the stationary standard deviations of a wind state ``g`` (world
            x, y, z) the filter follows beside the coefficients (module docstring); empty
            (the default): none. :func:`gusts` sets it.
        wind_tau: s, ``τ_g``: the wind state's time constant.
        columns: the columns ``spread`` gives one number each for (``"prior"``, ``"simple"``
            where ``M``'s loads are a column, then :data:`gpg.flight.basis.TERMS`); empty
            where ``spread`` is one number.
        label_offset: (N, N·m) ``σ_o``, the standard deviation per axis of an offset the
            flight's labels carry from start to end, force then torque: a sensor's bias
            (module docstring). It widens the band by ``σ_o²`` per axis, not the gain; (0, 0),
            the default: none.
    """

    tau: float
    spread: float | tuple[float, ...]
    noise: tuple[float, ...]
    bias_tau: float = DEFAULT_BIAS_TAU
    bias_sd: float = DEFAULT_BIAS_SD
    log_likelihood: float = float("nan")
    labels: int = 0
    source: str = "default"
    fast: tuple[float, ...] = ()
    share: float = SHARE
    wind_sd: tuple[float, ...] = ()
    wind_tau: float = GUST_TAU
    columns: tuple[str, ...] = ()
    label_offset: tuple[float, float] = (0.0, 0.0)

    @property
    def bias_taus(self) -> tuple[float, ...]:
        """The members' bias time constants: ``bias_tau``, then ``fast``."""
        return (float(self.bias_tau), *(float(f) for f in self.fast))


def _relax(mean, cov, a, stationary):
    """The OU step with a rate per column (``a``, (P,)): ``w ← a ⊙ w``,
    ``Σ ← (a aᵀ) ⊙ (Σ − Σ_∞) + Σ_∞`` (``Σ_∞``: (6, P, P), block-diagonal between columns of
    different rates, so that the step's noise is a covariance)."""
    return a * mean, jnp.outer(a, a) * (cov - stationary) + stationary


_relax_bank = jax.vmap(_relax, in_axes=(0, 0, 0, None))


def _measure(mean, cov, h, y, r):
    """One rank-one update per output (rows of ``h``); also each output's one-step-ahead log
    density of ``y``."""
    Sh = jnp.einsum("jpq,jq->jp", cov, h)
    s = jnp.sum(h * Sh, 1) + r
    e = y - jnp.sum(h * mean, 1)
    k = Sh / s[:, None]
    mean = mean + k * e[:, None]
    cov = cov - k[:, :, None] * Sh[:, None, :]
    cov = 0.5 * (cov + jnp.swapaxes(cov, 1, 2))  # keep it symmetric under rounding
    return mean, cov, -0.5 * (jnp.log(2 * jnp.pi * s) + e**2 / s)


_measure_bank = jax.vmap(_measure, in_axes=(0, 0, None, None, None))


def _reweigh(log_weight, ll, share):
    """The members' weights after a label (``ll``: each member's log density of it, (K,)):
    Bayes' rule, then the fixed share; and the mixture's log density of the label."""
    joint = log_weight + ll
    total = jax.scipy.special.logsumexp(joint)
    k = log_weight.shape[0]
    w = (1.0 - share) * jnp.exp(joint - total) + share / k
    return jnp.log(w), total


class Tracker(eqx.Module):
    """The tracked drift ``w`` of the physical basis's coefficients (module docstring): a bank
    of K filters that differ in the bias's ``τ_b``, weighted by how well each predicted the
    labels.

    Attributes:
        physics: the physical columns.
        prior_sd: (B,) ``σ_B`` (B = P − 1), the basis coefficients' prior standard deviations
            (physical units).
        offline_cov: (6, P, P) the coefficients' offline posterior covariance (zeros where the
            correction has none: the regression form, the bias).
        mean: (K, 6, P) each member's posterior mean of the drift per load output.
        cov: (K, 6, P, P) its posterior covariance.
        log_weight: (K,) the members' log weights.
        t: () s, the time of the last update.
        tau: () s, ``τ``.
        spread: (B,) ``s`` per basis column.
        bias_tau: (K,) s, each member's ``τ_b``.
        bias_sd: () ``s_b``.
        noise: (6,) ``v_j`` (normalised units).
        share: () the switching rate per label (fixed-share).
        wind_mean: (3,) m/s, the wind state's posterior mean ``ḡ`` (world), or None: no wind
            state (:func:`gusts`).
        wind_cov: (3, 3) its posterior covariance ``P_g``.
        wind_tau: () s, ``τ_g``.
        wind_sd: (3,) m/s, its stationary standard deviations.
        offset: (6,) ``σ_o²`` per load output (normalised units), the labels' flight-long
            offset's variance (:attr:`Drift.label_offset`), in the band only; None: none.
        with_simple: ``M``'s loads are a column (after the prior's mean).
    """

    physics: PhysicalBasis
    prior_sd: Float[Array, " B"]
    offline_cov: Float[Array, "6 P P"]
    mean: Float[Array, "K 6 P"]
    cov: Float[Array, "K 6 P P"]
    log_weight: Float[Array, " K"]
    t: Float[Array, ""]
    tau: Float[Array, ""]
    spread: Float[Array, " B"]
    bias_tau: Float[Array, " K"]
    bias_sd: Float[Array, ""]
    noise: Float[Array, " 6"]
    share: Float[Array, ""]
    wind_mean: Float[Array, " 3"] | None = None
    wind_cov: Float[Array, "3 3"] | None = None
    wind_tau: Float[Array, ""] | None = None
    wind_sd: Float[Array, " 3"] | None = None
    offset: Float[Array, " 6"] | None = None
    with_simple: bool = eqx.field(static=True, default=True)

    def bias_column(self) -> Float[Array, "6 1"]:
        """The bias column in normalised units.

        Returns:
            (6, 1) :data:`BIAS_SCALE` over the load outputs' scales.
        """
        y_std = self.physics.normalizer.y_std[:N_LOADS]
        return (jnp.asarray(BIAS_SCALE, y_std.dtype) / y_std)[:, None]

    @property
    def stationary(self) -> Float[Array, "6 P P"]:
        """``Σ_∞ = C₀ + S``: the offline posterior's covariance plus the drift's
        ``S = s² diag(σ_B²)``, per load output (the law the drift returns to)."""
        return self.offline_cov + _drift_cov(self.spread, self.prior_sd, self.bias_sd)

    @highest
    def relaxed(self, t: Float[ArrayLike, ""]) -> Tracker:
        """The drift's law at time ``t``: each member's OU step since :attr:`t` (a ``t``
        before it counts as no time: the state never runs backwards).

        Args:
            t: the time (s) to relax to.

        Returns:
            The tracker with its means, covariances and time advanced.
        """
        dt = jnp.maximum(jnp.asarray(t, self.t.dtype) - self.t, 0.0)
        a = _rates(dt, self.tau, self.bias_tau, self.prior_sd.shape[0])  # (K, P)
        mean, cov = _relax_bank(self.mean, self.cov, a, self.stationary)
        out = eqx.tree_at(lambda o: (o.mean, o.cov, o.t), self, (mean, cov, self.t + dt))
        if self.wind_mean is None:
            return out
        g = jnp.broadcast_to(jnp.exp(-dt / self.wind_tau), (3,))
        wind = _relax(self.wind_mean, self.wind_cov, g, jnp.diag(self.wind_sd**2))
        return eqx.tree_at(lambda o: (o.wind_mean, o.wind_cov), out, wind)

    @highest
    def wind_measured(self, residual: Callable) -> tuple[Tracker, Float[Array, " 3"]]:
        """The wind state conditioned on one label (module docstring), linearised at ``ḡ``.

        Args:
            residual: ``g ↦ (e, r, h)``: the label's residual against the offline mean with
                the air velocity shifted by ``g`` (normalised, GP frame), its own noise and the
                (6, P) columns there (for the coefficients' band).

        Returns:
            The tracker with ``ḡ`` and ``P_g`` updated, and the new ``ḡ``.

        Raises:
            ValueError: the tracker has no wind state.
        """
        if self.wind_mean is None:
            raise ValueError("wind_measured needs a tracker with a wind state (gpg.flight.gusts)")

        def f(g):
            e, r, h = residual(g)
            return e, (e, r, h)

        jac, (e, r, h) = jax.jacfwd(f, has_aux=True)(self.wind_mean)
        m, v = self.mean_var(h)
        H = -jac  # the prediction's change with the wind: the residual falls as it rises
        P = self.wind_cov
        S = H @ P @ H.T + jnp.diag(r + self.noise + v)
        PHt = P @ H.T
        gain = jnp.linalg.solve(S, PHt.T).T  # P Hᵀ S⁻¹ (S symmetric)
        mean = self.wind_mean + gain @ (e - m)
        cov = P - gain @ PHt.T
        cov = 0.5 * (cov + cov.T)
        return eqx.tree_at(lambda o: (o.wind_mean, o.wind_cov), self, (mean, cov)), mean

    @highest
    def measured(
        self, h: Float[Array, "6 P"], y: Float[Array, " 6"], r: Float[Array, " 6"]
    ) -> Tracker:
        """One Kalman update per member and output with the residual ``y`` against the offline
        mean; the members reweighed by their predictive densities of it.

        Args:
            h: (6, P) the columns at the label (:meth:`gpg.flight.Corrected.tracker_columns`).
            y: (6,) the label's residual against the offline mean (normalised, GP frame).
            r: (6,) its own noise variance; :attr:`noise` is added.

        Returns:
            The tracker conditioned on the label (not relaxed first: see :meth:`relaxed`).
        """
        mean, cov, ll = _measure_bank(self.mean, self.cov, h, y, r + self.noise)
        lw, _ = _reweigh(self.log_weight, jnp.sum(ll, 1), self.share)
        return eqx.tree_at(lambda o: (o.mean, o.cov, o.log_weight), self, (mean, cov, lw))

    @highest
    def mean_var(self, h: Float[Array, "6 P"]) -> tuple[Float[Array, " 6"], Float[Array, " 6"]]:
        """The drift's share of the prediction at columns ``h``: the members' mixture of
        ``hᵀ w̄`` and ``hᵀ Σ h`` (its mean, and its variance with the members' spread).

        Args:
            h: (6, P) the columns at the query.

        Returns:
            The (6,) mean and (6,) variance per load output (normalised units).
        """
        m = jnp.einsum("jp,kjp->kj", h, self.mean)
        v = jnp.einsum("jp,kjpq,jq->kj", h, self.cov, h)
        w = jnp.exp(self.log_weight)[:, None]
        mean = jnp.sum(w * m, 0)
        return mean, jnp.maximum(jnp.sum(w * (v + m**2), 0) - mean**2, 0.0)


def _drift_cov(spread, prior_sd, bias_sd):
    """``S``: the drift's stationary covariance, the basis's ``diag(s² σ_B²)`` then ``s_b²``
    (``s`` one number or one per column)."""
    return jnp.diag(jnp.concatenate([(spread * prior_sd) ** 2, jnp.reshape(bias_sd**2, (1,))]))


def _rates(dt, tau, bias_taus, n_basis: int):
    """Each member's per-column ``a = e^{−Δt/τ}`` (K, P): the basis's (one ``τ``), then the
    bias's (the member's own)."""
    k = bias_taus.shape[0]
    a = jnp.broadcast_to(jnp.exp(-dt / tau), (k, n_basis))
    return jnp.concatenate([a, jnp.exp(-dt / bias_taus)[:, None]], 1)


def _offline_cov(m, p: int, with_simple: bool) -> np.ndarray:
    """The offline covariance of the tracked columns' coefficients (6, P, P): the physical
    basis's where the correction integrated it (``A⁻¹``, with their spread between the parts
    held out where it measured one; its columns placed by name among the prior's mean,
    ``M``'s loads where ``with_simple``, the terms), zeros elsewhere."""
    out = np.zeros((N_LOADS, p, p))
    e = m.explicit
    if e is None:
        return out
    names = ["prior", *(["simple"] if with_simple else []), *TERMS]
    idx = np.array([names.index(c) for c in e.columns])
    chol = np.asarray(e.cov_chol)
    out[:, idx[:, None], idx[None, :]] = chol @ np.swapaxes(chol, 1, 2)
    return out


def default_drift(sur: Surrogate) -> Drift:
    """The drift for a vehicle never flown: ``τ`` = :data:`DEFAULT_TAU`, ``s`` =
    :data:`DEFAULT_SPREAD`, and ``v_j`` the discrepancy's own prior variance (its signal
    variance and value noise, times its output scale) where the model is corrected, else a
    tenth of the data's variance. Conservative: without flights held out to tell it, ``v``
    slows the filter to what the discrepancy could be anywhere (``ν²`` alone adapted faster
    and erred more), and the band holds the discrepancy's latent variance besides.

    Args:
        sur: the model to track.

    Returns:
        The default :class:`Drift`.
    """
    m = sur.model
    if isinstance(m, fc.Corrected) and len(m.delta) == N_LOADS:
        noise = tuple(float((d.hyper.variance + d.hyper.noise) * d.output_scale[0])
                      for d in m.delta)  # fmt: skip
    else:
        noise = (0.1,) * N_LOADS
    return Drift(tau=DEFAULT_TAU, spread=DEFAULT_SPREAD, noise=noise)


def _checked(drift: Drift) -> tuple[np.ndarray, np.ndarray]:
    """:func:`track`'s drift refused by name where it is not one; its noise and wind sd."""
    noise = np.asarray(drift.noise, float)
    spread = np.atleast_1d(np.asarray(drift.spread, float))
    if spread.ndim != 1 or (spread.size > 1 and len(drift.columns) != spread.size):
        raise ValueError(
            f"drift.spread must be one number, or one per column named in drift.columns, got "
            f"{drift.spread} for columns {drift.columns}"
        )
    if not (drift.tau > 0 and min(drift.bias_taus) > 0 and np.all(spread > 0)):
        raise ValueError(
            f"drift.tau, drift.bias_tau, drift.fast and drift.spread must be > 0, got "
            f"{drift.tau}, {drift.bias_taus}, {drift.spread}"
        )
    if not drift.bias_sd >= 0:
        raise ValueError(f"drift.bias_sd must be >= 0, got {drift.bias_sd}")
    if not 0 <= drift.share < 1:
        raise ValueError(f"drift.share must be in [0, 1), got {drift.share}")
    if noise.shape != (N_LOADS,) or not np.all(noise >= 0):
        raise ValueError(f"drift.noise must be {N_LOADS} numbers >= 0, got {drift.noise}")
    offset = np.asarray(drift.label_offset, float)
    if offset.shape != (2,) or not np.all(np.isfinite(offset) & (offset >= 0)):
        raise ValueError(
            f"drift.label_offset must be two numbers >= 0 (N for the force, N·m for the "
            f"torque), got {drift.label_offset}"
        )
    wind_sd = np.asarray(drift.wind_sd, float)
    if drift.wind_sd and (wind_sd.shape != (3,) or not np.all(wind_sd >= 0)
                          or not drift.wind_tau > 0):  # fmt: skip
        raise ValueError(
            f"drift.wind_sd must be empty or 3 numbers >= 0 (m/s) and drift.wind_tau > 0, got "
            f"{drift.wind_sd} and {drift.wind_tau}"
        )
    return noise, wind_sd


@float64
def track(sur: Surrogate, drift: Drift | None = None, *, t0: float = 0.0) -> Surrogate:
    """``sur`` (corrected or not) with its physical basis's coefficients followed online.

    Update it with :func:`gpg.flight.update` (or :func:`gpg.flight.online_step` from Python,
    ``lax.scan`` inside JAX), predict with it as with any surrogate.

    Args:
        sur: the model to track: a corrected one (either basis) or a prior (the prior's mean
            and ``M``'s loads then become columns with coefficients 1 and 0).
        drift: the drift's ``τ``, spread and noise (:func:`fit_drift`); default
            :func:`default_drift`.
        t0: s, the time of the first update.

    Returns:
        A :class:`~gpg.Surrogate` whose :class:`~gpg.flight.Corrected` model tracks.

    Raises:
        ValueError: a model adapted by :func:`gpg.flight.adapt`, or a drift whose time
            constants or spread are not positive, whose share is not in [0, 1), whose
            ``noise`` is not 6 non-negative numbers, whose ``wind_sd`` is neither empty
            nor 3 non-negative numbers (with ``wind_tau`` > 0), or whose ``label_offset`` is
            not two non-negative numbers.
    """
    drift = default_drift(sur) if drift is None else drift
    noise, wind_sd = _checked(drift)
    m = sur.model
    if not isinstance(m, fc.Corrected):
        m = fc.Corrected(prior=m, scale=jnp.ones(m.n_outputs), delta=())
        sur = dataclasses.replace(sur, model=m, model_name=f"{sur.model_name}+flight")
    if m.online is not None:
        raise ValueError(
            "track: the model carries the inducing-point term of gpg.flight.adapt; track the "
            "corrected model itself (gpg.flight.correct), not both"
        )
    if m.basis is None and sur.simple is not None:  # M's loads become a column, κ = 0
        simple = fc.SimpleBasis(sur.simple, sur.normalizer, sur.frame)
        m = eqx.tree_at(lambda c: (c.basis, c.kappa), m, (simple, jnp.zeros(N_LOADS)),
                        is_leaf=lambda a: a is None)  # fmt: skip
    physics = m.explicit.physics if m.explicit is not None else fc._physics(fc.base(sur))
    _, sd = fc._coefficient_prior(True, m.basis is not None)
    p = sd.size + 1
    spread = _column_spread(drift, _column_names(sd.size))
    c0 = _offline_cov(m, p, m.basis is not None)
    stat = c0 + np.asarray(_drift_cov(spread, jnp.asarray(sd), drift.bias_sd))
    k = len(drift.bias_taus)
    offset = None
    if any(drift.label_offset):
        # σ_o² in each load output's normalised units: the same in N² (N·m²) on every axis of
        # the GP's frame, so the world's band (a rotation of it) gets σ_o² on every axis too.
        o = np.repeat(np.asarray(drift.label_offset, float) ** 2, 3)
        offset = jnp.asarray(o / np.asarray(sur.normalizer.y_std)[:N_LOADS] ** 2)
    tracker = Tracker(
        physics=physics,
        prior_sd=jnp.asarray(sd),
        offline_cov=jnp.asarray(c0),
        mean=jnp.zeros((k, N_LOADS, p)),
        cov=jnp.broadcast_to(jnp.asarray(stat), (k, N_LOADS, p, p)),
        # every scalar with its dtype (not weak): a step's output must type as its input,
        # or the first call of a compiled step compiles a second program
        log_weight=jnp.full(k, -math.log(k), float),
        t=jnp.asarray(t0, float),
        tau=jnp.asarray(drift.tau, float),
        spread=jnp.asarray(spread),
        bias_tau=jnp.asarray(drift.bias_taus),
        bias_sd=jnp.asarray(drift.bias_sd, float),
        noise=jnp.asarray(noise),
        share=jnp.asarray(drift.share, float),
        offset=offset,
        with_simple=m.basis is not None,
    )
    if drift.wind_sd:
        tracker = eqx.tree_at(
            lambda o: (o.wind_mean, o.wind_cov, o.wind_tau, o.wind_sd),
            tracker,
            (jnp.zeros(3), jnp.diag(jnp.asarray(wind_sd**2)),
             jnp.asarray(drift.wind_tau, float), jnp.asarray(wind_sd)),
            is_leaf=lambda a: a is None,
        )  # fmt: skip
    m = eqx.tree_at(lambda c: c.tracker, m, tracker, is_leaf=lambda a: a is None)
    return dataclasses.replace(sur, model=m)


def _column_names(n: int) -> tuple[str, ...]:
    """The tracked basis columns' names for ``n`` of them: the prior's mean, ``M``'s loads
    where there are ``2 + len(TERMS)``, then :data:`TERMS`."""
    return ("prior", *(["simple"] if n == 2 + len(TERMS) else []), *TERMS)


def _column_spread(drift: Drift, names: tuple[str, ...]) -> np.ndarray:
    """``drift.spread`` as one number per column of ``names`` (B,); a spread per column must
    name the same columns."""
    spread = np.atleast_1d(np.asarray(drift.spread, float))
    if spread.size == 1:
        return np.full(len(names), float(spread[0]))
    if tuple(drift.columns) != tuple(names):
        raise ValueError(
            f"drift.spread is per column for {drift.columns}, but the model tracks {names}"
        )
    return spread


def gusts(drift: Drift, sd: Sequence[float] = GUST_SD, tau: float = GUST_TAU) -> Drift:
    """``drift`` with a wind state: the air's deviation from the logged ``v_air`` followed
    beside the coefficients (module docstring).

    The gusts' statistics are stated, not fitted: training flights in steady winds cannot tell
    them, and a wind the flights never had is what the state is for. The default is the
    Dryden model's light turbulence near the ground (:data:`GUST_SD`, :data:`GUST_TAU`).

    Args:
        drift: the coefficients' drift (:func:`fit_drift` or :func:`default_drift`).
        sd: m/s, the wind state's stationary standard deviations along world x, y, z.
        tau: s, its time constant ``τ_g``.

    Returns:
        The drift with ``wind_sd`` and ``wind_tau`` set (:func:`track` checks them).
    """
    return dataclasses.replace(drift, wind_sd=tuple(float(v) for v in sd), wind_tau=float(tau))


@float64
def fit_drift(
    sur: Surrogate,
    labels: Sequence[Labels],
    *,
    max_labels: int = 1500,
    max_steps: int = 200,
    fast: Sequence[float] | None = None,
    share: float = SHARE,
    per_column: bool = True,
    read: Sequence[Labels] | None = None,
) -> Drift:
    """The drift that best predicts new flights, label by label (module docstring).

    Each part of ``labels`` (a flight, or the flights of one wind) is predicted by a model
    that did not see it: ``sur`` itself where its correction did not take the part (by the
    labels' name), else the physical basis and discrepancy fitted on the other parts (with
    ``sur``'s discrepancy hyperparameters, the coefficients integrated out as in
    ``correct(basis="physical")``). The filter runs over it from the stationary law,
    restarting at each flight (where the time runs back), its gain from each label's own
    noise and ``v`` as in flight. ``τ``, ``s`` (one per basis column, ``per_column``), the
    first member's ``τ_b``, ``s_b`` and ``v`` maximise the sum of the one-step-ahead log
    densities of the bank's band, which adds the latent variance of that model's
    discrepancies at each label as the tracked band does (optimistix BFGS on their
    logarithms, from the best of a small grid, one ``s`` for all columns there); the ``fast``
    members keep their bias time constants (steady training flights cannot tell them: a gust
    can, and the bank's weights decide in flight).

    Args:
        sur: a corrected model (:func:`gpg.flight.correct`): its discrepancy hyperparameters.
        labels: two or more parts, in time order within each.
        max_labels: at most this many labels: beyond, each part's first labels, the same
            number of each (contiguous, so the drift sees the labels' own spacing; thinned
            evenly, every other label, it would fit a filter for labels twice as far apart).
        max_steps: BFGS steps.
        fast: s, the bank's other members' bias time constants; None (the default): each of
            :data:`BANKS`, the one whose fit predicts the held-out flights best.
        share: the bank's switching rate per label (:data:`SHARE`).
        per_column: one spread per basis column (the prior's mean, ``M``'s loads, each
            physical term: a term the flights move little is held near its offline value,
            one they move is free to); False: one for all.
        read: what the filter will read of each part, one per part in the same order:
            every sample of the same flights (labelled at the log's rate, as a filter on board
            reads them), so that ``v``, the spreads and the time constants are those of the
            filter on that stream. The held-out models are still fitted on ``labels``; the
            likelihood is of ``read``'s rows over the span of the labels kept (``max_labels``
            bounds the labels). None (the default): the labels themselves.

    Returns:
        The fitted :class:`Drift` (``source="fitted"``), without a labels' offset: the held-out
        labels share it and cannot tell it (state it with ``label_offset``).

    Raises:
        ValueError: fewer than two parts, ``sur`` not corrected by flights, or a ``fast``
            time constant not positive or a ``share`` outside [0, 1); ``read`` not one
            non-empty part per part of ``labels``.
    """
    parts = _parts(sur, labels, "fit_drift")
    stream = _checked_read(parts, read, "fit_drift")
    banks = BANKS if fast is None else (tuple(fast),)
    if not all(f > 0 for b in banks for f in b) or not 0 <= share < 1:
        raise ValueError(f"fast must be > 0 s and share in [0, 1), got {fast}, {share}")
    data, v0 = _held_out_sequences(sur, parts, max_labels, stream)
    n_spread = data[6].shape[0] if per_column else 1
    fits = [_fit_bank(data, v0, tuple(float(f) for f in b), float(share), max_steps, n_spread)
            for b in banks]  # fmt: skip
    return max(fits, key=lambda d: d.log_likelihood)


@float64
def score_drift(
    sur: Surrogate,
    labels: Sequence[Labels],
    drift: Drift | None = None,
    *,
    max_labels: int = 1500,
    read: Sequence[Labels] | None = None,
) -> float:
    """``drift``'s prequential log likelihood per label on flights held out: the number
    :func:`fit_drift` maximises (its ``log_likelihood``), for any drift, so that a drift set
    by hand, the default or one fitted elsewhere is compared on the same footing.

    Args:
        sur: a corrected model (:func:`gpg.flight.correct`), as for :func:`fit_drift`.
        labels: two or more parts (flights, or the flights of one wind), each predicted by a
            model that did not see it (:func:`fit_drift`).
        drift: the drift scored (its ``τ``, spread, bias, ``v`` and bank); default
            :func:`default_drift`.
        max_labels: at most this many labels, as :func:`fit_drift` takes them.
        read: what the filter reads of each part, as :func:`fit_drift` scores it.

    Returns:
        The mean log predictive density per label (nats, the six load outputs summed), of the
        labels' band (``drift.label_offset`` left out: the labels share it).

    Raises:
        ValueError: as :func:`fit_drift` for ``sur``, ``labels`` and ``read``; a drift :func:`track`
            refuses, one with a wind state (the fit's likelihood has none), or one whose time
            constants or spreads lie outside :data:`TAU_RANGE` and :data:`SPREAD_RANGE`.
    """
    drift = default_drift(sur) if drift is None else drift
    noise, _ = _checked(drift)
    if drift.wind_sd:
        raise ValueError("score_drift scores the coefficients' drift; drift has a wind state")
    inside = [TAU_RANGE[0] <= v <= TAU_RANGE[1] for v in (drift.tau, drift.bias_tau)]
    inside += [SPREAD_RANGE[0] <= v <= SPREAD_RANGE[1]
               for v in (*np.atleast_1d(drift.spread), drift.bias_sd)]  # fmt: skip
    if not all(inside):
        raise ValueError(
            f"score_drift: drift.tau and bias_tau must lie in {TAU_RANGE} s and spread and "
            f"bias_sd in {SPREAD_RANGE} (fit_drift's ranges), got {drift.tau}, "
            f"{drift.bias_tau}, {drift.spread}, {drift.bias_sd}"
        )
    parts = _parts(sur, labels, "score_drift")
    data, _ = _held_out_sequences(sur, parts, max_labels, _checked_read(parts, read, "score_drift"))
    spread = _column_spread(drift, _column_names(data[6].shape[0]))
    theta = _pack(drift.tau, drift.bias_tau, drift.bias_sd, np.maximum(noise, 1e-300), spread)
    args = (data, jnp.asarray(drift.fast, float).reshape(-1), float(drift.share))
    return -float(_neg_loglik(theta, args))


def _parts(sur: Surrogate, labels, who: str) -> list[Labels]:
    """``labels`` of :func:`fit_drift` or :func:`score_drift` (``who``, for the errors) as a
    list of two or more parts, ``sur`` corrected."""
    parts = [labels] if isinstance(labels, Labels) else list(labels)
    if len(parts) < 2:
        raise ValueError(
            f"{who} needs labels of two or more flights or winds (each predicted from the "
            f"others), got {len(parts)}; use gpg.flight.default_drift for one"
        )
    m = sur.model
    if not isinstance(m, fc.Corrected) or len(m.delta) != N_LOADS:
        raise ValueError(f"{who} needs a model corrected by gpg.flight.correct")
    return parts


def _fit_bank(data, v0, fast: tuple[float, ...], share: float, max_steps: int,
              n_spread: int) -> Drift:  # fmt: skip
    """:func:`fit_drift` for one bank, with ``n_spread`` spreads (1, or one per column)."""
    args = (data, jnp.asarray(fast, float).reshape(-1), share)
    theta0 = _grid_start(args, v0, n_spread)
    solver = optx.BFGS(rtol=1e-6, atol=1e-6)
    sol = optx.minimise(_neg_loglik, solver, theta0, args=args, max_steps=max_steps, throw=False)
    theta = sol.value
    if not bool(jnp.isfinite(_neg_loglik(theta, args))):
        theta = theta0
    tau, spread, bias_tau, bias_sd, noise = _unpack(theta)
    names = _column_names(data[6].shape[0])
    return Drift(
        tau=float(tau),
        spread=tuple(float(v) for v in spread) if n_spread > 1 else float(spread[0]),
        columns=names if n_spread > 1 else (),
        noise=tuple(float(v) for v in noise),
        bias_tau=float(bias_tau),
        bias_sd=float(bias_sd),
        log_likelihood=-float(_neg_loglik(theta, args)),
        labels=int(data[0].shape[0]),
        source="fitted",
        fast=fast,
        share=share,
    )


def _held_out_sequences(sur: Surrogate, parts: list[Labels], max_labels: int,
                        read: list[Labels] | None = None, inputs: bool = False):  # fmt: skip
    """Every label's residual against a model that did not see its part (``sur`` itself where
    its correction did not take the part, by name; else the basis fitted without it), with
    that model's coefficient covariance, the columns, the label's noise, time, whether a flight
    starts there and that model's discrepancies' latent variance there; and each output's mean
    held-out variance (the start of ``v``). With ``read`` (one per part, the same flights),
    the sequences are of ``read``'s rows over the span of the labels kept, each predicted by
    the model fitted on the other parts' labels. With ``inputs``, a third item: each row's
    normalised input and that model's band on the loads (its discrepancy's and coefficients'
    variance with ``ν²``, times the calibration factor ``δ`` carries; the model's own band
    where ``sur`` predicts), the rows an online term (:func:`gpg.flight.adapt`) reads."""
    prior = fc.base(sur)
    parts, read = _kept(parts, read, max_labels)
    X, Y, V, groups, t = fc._label_rows(prior, parts, max_labels, "physical")
    if read is not None:
        Xr, Yr, Vr, gr, t = fc._label_rows(prior, read, None, "physical")
    else:
        Xr, Yr, Vr, gr = X, Y, V, groups
    # The columns of the rows fitted on and of those read (the same rows without ``read``).
    H_all, with_simple = _columns(prior, np.concatenate([X, Xr]) if read is not None else X)
    H, Hr = (H_all[: len(X)], H_all[len(X) :]) if read is not None else (H_all, H_all)
    b, sd = fc._coefficient_prior(True, with_simple)
    sd_j = fc._chosen_prior(sur, True, with_simple)  # the prior each output was fitted with
    resid = np.full(Yr.shape, np.nan)
    bias = np.asarray(BIAS_SCALE) / np.asarray(prior.normalizer.y_std[:N_LOADS])
    v0 = np.zeros(N_LOADS)
    p = sd.size
    c0 = np.zeros((len(Xr), N_LOADS, p + 1, p + 1))  # the bias has no offline posterior
    # A part the model was not corrected on is predicted by the model itself: the drift is
    # then fitted for the model it will track, not for one refitted without the part.
    seen = set(sur.config.get("flight_correction", {}).get("flights", []))
    refit = [g for g, lab in enumerate(parts) if lab.name in seen]
    unseen = ~np.isin(gr, refit)
    # The latent variance of the discrepancy that predicts each label: in the tracked band
    # (Corrected.predictive_variance), so in the density the fit scores, though not in the
    # filter's gain (the update on board does not pay for δ's variance at every label).
    DL, band = np.zeros(Yr.shape), np.zeros(Yr.shape)
    for j, d in enumerate(sur.model.delta):
        outs = fc._held_out(X, H[:, j], Y[:, j], V[:, j], d.hyper, b, sd_j[j], groups, refit,
                            at=(Xr, Hr[:, j], gr))  # fmt: skip
        for te, mean, held_var, cov, latent, _ in outs:
            resid[te, j] = Yr[te, j] - mean
            c0[te, j, :p, :p] = cov
            DL[te, j] = float(d.output_scale[0]) * latent
            band[te, j] = float(d.output_scale[0]) * held_var
        # v starts at the held-out variance, or at the discrepancy's own where none was refit
        var = [v for _, _, v, *_ in outs] or [np.atleast_1d(d.hyper.variance + d.hyper.noise)]
        v0[j] = np.mean(np.concatenate(var))
    if unseen.any():
        own = fc.offline_model(sur.model)
        mean, DL[unseen], band[unseen] = _own_rows(own, Xr[unseen], inputs)
        resid[unseen] = Yr[unseen] - mean
        c0[unseen] = _offline_cov(own, p + 1, with_simple)
    keep = np.all(np.isfinite(resid), 1)
    start = np.ones(len(t), bool)
    start[1:] = (gr[1:] != gr[:-1]) | (np.diff(_flight_index(t)) > 0)  # a new part or flight
    start = start[keep]
    start[0] = True
    Ht = np.concatenate([Hr, np.broadcast_to(bias[None, :, None], (len(Hr), N_LOADS, 1))], 2)
    rows = (t[keep], start, Ht[keep], resid[keep], Vr[keep], c0[keep], sd, DL[keep])
    if inputs:
        return tuple(jnp.asarray(a) for a in rows), v0, (Xr[keep], band[keep])
    return tuple(jnp.asarray(a) for a in rows), v0


def _own_rows(own: fc.Corrected, X: np.ndarray, band: bool):
    """The offline model's own mean, its discrepancies' latent variance (not the prior's) and,
    with ``band``, its band on the loads (zeros without), at the normalised rows ``X``."""

    mean, latent, out = _own_moments(own, np.asarray(X), band)
    return np.asarray(mean), np.asarray(latent), np.asarray(out)


@eqx.filter_jit
def _own_moments(own: fc.Corrected, X, band: bool):
    """:func:`_own_rows` in one program (op by op, each operation compiled for each shape)."""

    def one(x):
        mean = own.offline_mean(x, own.prior.mean_one(x))[:N_LOADS]
        if not band:
            return mean, own._delta_latent_at(x), jnp.zeros(N_LOADS, x.dtype)
        return (mean, own._delta_latent_at(x),
                own.predictive_variance(own.mean_var_one(x)[1])[:N_LOADS])  # fmt: skip

    return jax.vmap(one)(X)


def _kept(parts: list[Labels], read: list[Labels] | None, max_labels: int):
    """The parts (and what is read of them) within ``max_labels``: beyond, each part's first
    labels, the same number of each, and what is read over their span."""
    if sum(len(p) for p in parts) <= max_labels:
        return parts, read
    k = max(2, max_labels // len(parts))
    if read is not None:
        read = [_within(r, p.take(slice(0, k))) for r, p in zip(read, parts, strict=True)]
    return [p.take(slice(0, k)) for p in parts], read


def _columns(prior: Surrogate, X: np.ndarray) -> tuple[np.ndarray, bool]:
    """The basis's columns (N, 6, P) at the normalised rows ``X`` (the prior's mean, ``M``'s
    loads where the prior has ``M``, the physical terms), and whether ``M``'s are there."""
    mu = np.asarray(prior.model.predict_mean(X))[:, :N_LOADS]
    ms = None
    if prior.simple is not None:
        simple = fc.SimpleBasis(prior.simple, prior.normalizer, prior.frame)
        ms = _host.each_row(simple, X)
    phys = _host.each_row(fc._physics(prior), X)
    H = np.stack([fc._basis_columns(mu, ms, phys, j) for j in range(N_LOADS)], 1)
    return H, ms is not None


def _flight_index(t: np.ndarray) -> np.ndarray:
    """Each row's flight within a part of flights one after another (the time runs back
    where the next starts)."""
    return np.concatenate([[0], np.cumsum(np.diff(t) <= 0)])


def _within(read: Labels, kept: Labels) -> Labels:
    """``read``'s rows up to the last of ``kept``'s labels (their flight and time): what a
    filter reading ``read`` saw over the span of the labels kept."""
    f_r, f_k = _flight_index(np.asarray(read.t)), _flight_index(np.asarray(kept.t))
    last_f, last_t = f_k[-1], float(kept.t[-1])
    mask = (f_r < last_f) | ((f_r == last_f) & (np.asarray(read.t) <= last_t))
    return read.take(np.flatnonzero(mask))


def _checked_read(parts: list[Labels], read, who: str) -> list[Labels] | None:
    """``read`` of :func:`fit_drift` or :func:`score_drift`: None, or one non-empty part per
    part of the labels."""
    if read is None:
        return None
    read = [read] if isinstance(read, Labels) else list(read)
    if len(read) != len(parts) or any(len(r) == 0 for r in read):
        raise ValueError(
            f"{who}: read must give one non-empty part per part of labels (the same flights, "
            f"in the same order), got {len(read)} for {len(parts)}"
        )
    return read


def _pack(tau, bias_tau, bias_sd, noise, spread) -> Float[Array, " T"]:
    """``θ = (log τ, log τ_b, log s_b, log v (6), log s (one, or one per column))``."""
    return jnp.log(jnp.asarray([tau, bias_tau, bias_sd, *np.ravel(noise), *np.ravel(spread)]))


def _unpack(theta):
    """:func:`_pack`'s ``θ`` to ``(τ, s, τ_b, s_b, v)``, the time constants and the spreads
    kept in their ranges (``s`` (1,) or one per column)."""
    (t_lo, t_hi), (s_lo, s_hi) = np.log(TAU_RANGE), np.log(SPREAD_RANGE)
    tau, bias_tau = (jnp.exp(jnp.clip(theta[i], t_lo, t_hi)) for i in (0, 1))
    bias_sd = jnp.exp(jnp.clip(theta[2], s_lo, s_hi))
    spread = jnp.exp(jnp.clip(theta[3 + N_LOADS :], s_lo, s_hi))
    return tau, spread, bias_tau, bias_sd, jnp.exp(theta[3 : 3 + N_LOADS])


@jax.jit
@highest
def _neg_loglik(theta, args):
    """Minus the prequential log likelihood per label of the bank with ``θ`` (:func:`_pack`)
    and the other members' ``fast`` time constants over the held-out sequences: the filter
    as it runs (its gain and its members' weights from the label's noise and ``v``), scored
    by the density of its band (the discrepancies' latent variance ``dl`` added, as the
    tracked model predicts)."""
    (t, start, H, y, r, c0, sd, dl), fast, share = args
    tau, spread, bias_tau, bias_sd, noise = _unpack(theta)
    bias_taus = jnp.concatenate([bias_tau[None], fast])
    k, p = bias_taus.shape[0], sd.shape[0] + 1
    drift = _drift_cov(spread, sd, bias_sd)
    mean0 = jnp.zeros((k, N_LOADS, p))
    lw0 = jnp.full(k, -jnp.log(k))

    def body(carry, row):
        mean, cov, lw, t_prev = carry
        ti, st, h, yi, ri, ci, di = row
        stat = ci + drift  # the law each row's group returns to
        a = _rates(jnp.maximum(ti - t_prev, 0.0), tau, bias_taus, p - 1)
        mean, cov = _relax_bank(mean, cov, a, stat)
        cov0 = jnp.broadcast_to(stat, cov.shape)
        mean, cov, lw = (jnp.where(st, x0, x) for x, x0 in ((mean, mean0), (cov, cov0), (lw, lw0)))
        s = jnp.einsum("jp,kjpq,jq->kj", h, cov, h) + ri + noise + di
        e = yi - jnp.einsum("jp,kjp->kj", h, mean)
        _, total = _reweigh(lw, jnp.sum(-0.5 * (jnp.log(2 * jnp.pi * s) + e**2 / s), 1), share)
        mean, cov, ll = _measure_bank(mean, cov, h, yi, ri + noise)
        lw, _ = _reweigh(lw, jnp.sum(ll, 1), share)
        return (mean, cov, lw, ti), total

    cov_init = jnp.broadcast_to(c0[0] + drift, (k, N_LOADS, p, p))
    _, ll = jax.lax.scan(body, (mean0, cov_init, lw0, t[0]), (t, start, H, y, r, c0, dl))
    return -jnp.mean(ll)


def _grid_start(args, v0, n_spread: int = 1) -> Float[Array, " T"]:
    """The best of a small grid of ``τ``, ``s`` (the same for the ``n_spread`` spreads),
    ``τ_b`` and ``s_b``, with ``v`` at the held-out variance."""
    best, best_val = None, np.inf
    v = np.maximum(v0, 1e-8)
    for tau, spread, bias_tau, bias_sd in itertools.product(
        (10.0, 60.0, 600.0), (0.1, 0.3, 1.0), (0.3, 3.0), (0.1, 1.0)
    ):
        theta = _pack(tau, bias_tau, bias_sd, v, np.full(n_spread, spread))
        val = float(_neg_loglik(theta, args))
        if val < best_val:
            best, best_val = theta, val
    return best


@dataclass(frozen=True)
class Prequential:
    """What an adapted model predicted at each label before it saw it (:func:`prequential`).

    Attributes:
        force: (N, 3) predicted force, world, N.
        torque: (N, 3) predicted torque, world, N·m.
        variance: (N, 6) their predictive variances (the model's band, not the labels' noise).
        final: the model after the last label.
    """

    force: np.ndarray
    torque: np.ndarray
    variance: np.ndarray
    final: Surrogate


def prequential(sur: Surrogate, labels: Labels) -> Prequential:
    """Each label predicted, then used: a whole flight through an adapted model in one
    compiled ``lax.scan`` (a model without an online state just predicts).

    Args:
        sur: a model prepared by :func:`track` or :func:`gpg.flight.adapt`, or any surrogate.
        labels: one flight's labels, in time order.

    Returns:
        The one-step-ahead predictions at the labels' states and the final model.

    Raises:
        ValueError: ``labels`` is not :class:`~gpg.flight.Labels` or is empty.
    """
    if not isinstance(labels, Labels) or len(labels) == 0:
        raise ValueError("prequential needs the labels of one flight (gpg.flight.Labels)")
    m = sur.model
    adaptive = isinstance(m, fc.Corrected) and (m.online is not None or m.tracker is not None)
    if not adaptive:
        p = sur.predict_batch(labels.rpm, labels.euler, labels.v_air)
        return Prequential(np.asarray(p.force), np.asarray(p.torque),
                           np.asarray(p.variance)[:, :6], sur)  # fmt: skip
    state = fc.online_state(sur)
    offline = dataclasses.replace(sur, model=fc.offline_model(m))
    cols = tuple(_host.asarray(c) for c in labels.columns())
    state, (f, tq, var) = _prequential_scan(offline, state, cols)
    return Prequential(np.asarray(f), np.asarray(tq), np.asarray(var)[:, :6],
                       fc.with_online(sur, state))  # fmt: skip


@jax.jit
@highest
def _prequential_scan(offline: Surrogate, state, cols):
    def body(st, row):
        p = predict_state(fc.with_online(offline, st), row[1], row[2], row[3], True)
        return fc.advance(offline, st, *row), (p.force, p.torque, p.variance)

    return jax.lax.scan(body, state, cols)
