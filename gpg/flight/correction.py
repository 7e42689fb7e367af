"""The simulator-trained surrogate corrected by measured flights, and adapted while flying.

A fitted surrogate is the prior mean; flights correct it (two-fidelity co-kriging, Kennedy and
O'Hagan 2000, in the surrogate's normalised units):

    y_real(x) = ρ ⊙ μ_sim(x) + δ(x) (+ ε, the labels' own noise),

with ``μ_sim`` the surrogate's GP mean, ``ρ`` a fitted scale per output (or ones) and ``δ`` a
GP on the discrepancy, one per force and torque component, fitted on values only (flights
measure no gradients: :class:`gpg.gp.exact.ExactGP` with values-only cases, or beyond
``exact_labels`` labels :class:`gpg.gp.inducing.InducingGP` on every label) with its own
hyperparameters and each label's noise on its diagonal (``row_noise``). The prediction's
variance adds the parts: ``ρ² var_sim + var_δ``. The levels (dB) are not measured in flight and
stay the prior's.

While flying, :func:`adapt` adds an online term ``η`` to the corrected model and updates it
label by label: ``η(x) = ψ(x)ᵀ w`` on ``m`` inducing inputs ``Z``, with ``ψ = L⁻¹ k_Z(x)``
(``K_ZZ = L Lᵀ``, the whitened basis of a subset-of-regressors GP) and weights ``w`` whose
Gaussian posterior is a Kalman filter: between labels they relax to their prior ``N(0, I)`` as
an Ornstein-Uhlenbeck process with time constant ``τ`` (``μ ← aμ``, ``Σ ← a²Σ + (1 − a²)I``,
``a = e^{−Δt/τ}``: exponential forgetting that stays a proper prior), and each label is one
rank-one measurement update. Cost per label ``O(m²)`` per output and fixed memory, jittable,
inside ``lax.scan``; the adapted surrogate is a :class:`~gpg.Surrogate` at every step.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from functools import lru_cache
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg import _host
from gpg._dtype import float64
from gpg._precision import highest
from gpg.data.preprocess import Normalizer
from gpg.flight.basis import PRIORS, TERMS, Explicit, PhysicalBasis, posterior, posterior_gram
from gpg.flight.labels import Labels
from gpg.gp import kernels
from gpg.gp.exact import ExactGP
from gpg.gp.fit import FitOptions, fit_hyperparameters
from gpg.gp.hyper import Hyper
from gpg.gp.inducing import (
    InducingGP,
    StackedInducing,
    fit_collapsed,
    inducing_inputs,
    project,
)
from gpg.gp.predictor import Predictor, plain
from gpg.quadrotor.frames import R_WB, matvec
from gpg.quadrotor.simple_model import SimpleModel
from gpg.surrogate import Surrogate, gp_inputs

__all__ = [
    "Corrected",
    "Online",
    "adapt",
    "base",
    "correct",
    "online_step",
    "online_state",
    "update",
    "update_jit",
    "with_online",
]

N_LOADS = 6  # force and torque: what a flight measures
# The discrepancy GPs' lengthscales on normalised inputs (span 2) are kept in this range.
LENGTHSCALE_MIN, LENGTHSCALE_MAX = 1e-2, 1e2
# Factors on the physical terms' prior standard deviations (PRIORS) that correct(...,
# basis_prior="held_out") chooses among per load output: from the terms nearly held at zero
# (the prior's physics as it is) to three times the stated prior.
BASIS_PRIOR_GRID = (0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
# The least factor correct's held-out calibration puts on the prior's share of the band
# (where the discrepancy's band and the labels' noise alone cover a held-out flight's
# errors): the prior's variance is still what says how far a state is from its data.
PRIOR_SHARE_FLOOR = 1e-3
# The standard normal's upper 2.5-percent point: a 95-percent band's half-width in standard
# deviations.
Z95 = 1.959963984540054


class Online(eqx.Module):
    """The online term ``η`` of an adapted model (module docstring), one per load output.

    Attributes:
        Z: (m, D) inducing inputs (normalised).
        whiten: (6, m, m) ``L⁻¹`` of each output's ``K_ZZ`` (its own hyperparameters).
        variance: (6,) signal variance of ``η`` per output (normalised units).
        lengthscale: (6, D).
        noise: (6,) value noise added to each label's own in an update.
        mean: (6, m) posterior mean of the whitened weights.
        cov: (6, m, m) their posterior covariance.
        t: () time of the last update (s).
        tau: (), (6,) or (6, m) s, the forgetting time constant: one for every weight, one
            per output (the outputs' weights are independent, so each may forget at its own
            rate) or one per weight (an OU process per weight: a term of several time
            scales).
        shared: whether ``η``'s prior is a share of the offline model's band rather than an
            addition to it (:func:`adapt`'s ``band``): the loads' band is then
            ``max(b − ψᵀψ, 0) + ψᵀΣψ`` (``b`` the offline band), which starts as ``b``.
    """

    Z: Float[Array, "m D"]
    whiten: Float[Array, "6 m m"]
    variance: Float[Array, " 6"]
    lengthscale: Float[Array, "6 D"]
    noise: Float[Array, " 6"]
    mean: Float[Array, "6 m"]
    cov: Float[Array, "6 m m"]
    t: Float[Array, ""]
    tau: Float[Array, ""] | Float[Array, " 6"] | Float[Array, "6 m"]
    shared: bool = eqx.field(static=True, default=False)

    @highest
    def features(self, x: Float[Array, " D"]) -> Float[Array, "6 m"]:
        """The whitened features ``ψ(x) = L⁻¹ k_Z(x)`` of one input, per output.

        Each output has its own kernel (``variance``, ``lengthscale``) and so its own ``L⁻¹``.

        Args:
            x: (D,) a normalised input.

        Returns:
            (6, m) ``ψ(x)`` of each load output.
        """

        def one(L_inv, var, ls):
            return L_inv @ _cross(x[None], self.Z, var, ls)[0]

        return jax.vmap(one)(self.whiten, self.variance, self.lengthscale)

    @highest
    def mean_var(self, x: Float[Array, " D"]) -> tuple[Float[Array, " 6"], Float[Array, " 6"]]:
        """``η``'s mean and variance per output at ``x``.

        The mean is ``ψ(x)ᵀ μ`` and the variance ``ψ(x)ᵀ Σ ψ(x)``, with ``μ, Σ`` the
        weights' current posterior (not relaxed to any later time: see :meth:`relaxed`).

        Args:
            x: (D,) a normalised input.

        Returns:
            The (6,) mean and the (6,) variance of ``η(x)`` (normalised units).
        """
        return self.moments(self.features(x))[:2]

    @highest
    def moments(
        self, psi: Float[Array, "6 m"]
    ) -> tuple[Float[Array, " 6"], Float[Array, " 6"], Float[Array, " 6"]]:
        """``η``'s mean ``ψᵀμ``, variance ``ψᵀΣψ`` and prior variance ``ψᵀψ`` per output from
        the features :meth:`features` gave (one feature evaluation for all three).

        Args:
            psi: (6, m) ``ψ(x)`` of each load output.

        Returns:
            The (6,) mean, variance and prior variance (normalised units).
        """
        mean = jnp.einsum("om,om->o", psi, self.mean)
        var = jnp.einsum("om,omn,on->o", psi, self.cov, psi)
        return mean, var, jnp.einsum("om,om->o", psi, psi)

    @property
    def n_parts(self) -> int:
        """The entries :meth:`latent` adds to the corrected model's latent variance."""
        return N_LOADS * (2 if self.shared else 1)

    def describe(self) -> dict[str, Any]:
        """Plain values for a checkpoint's metadata.

        Returns:
            The inducing inputs ``m``, ``τ`` and the band.
        """
        return {"inducing": int(self.Z.shape[0]), "tau": plain(self.tau),
                "band": "shared" if self.shared else "added"}  # fmt: skip

    @highest
    def latent(self, x: Float[Array, " D"]) -> tuple[Float[Array, " 6"], Float[Array, " P"]]:
        """``η``'s mean at ``x`` and its parts of the corrected model's latent variance
        (:meth:`Corrected.mean_var_one`), which :meth:`band` turns into the loads' band.

        Args:
            x: (D,) a normalised input.

        Returns:
            The (6,) mean and the (:attr:`n_parts`,) parts: ``ψᵀΣψ``, then with :attr:`shared`
            ``ψᵀψ``.
        """
        mean, var, prior = self.moments(self.features(x))
        return mean, jnp.concatenate([var, prior]) if self.shared else var

    def band(
        self, offline: Float[Array, "*Q 6"], parts: Float[Array, "*Q P"]
    ) -> Float[Array, "*Q 6"]:
        """The loads' band with ``η`` from the offline model's ``b`` and :meth:`latent`'s
        parts: ``b + ψᵀΣψ``, or with :attr:`shared` ``max(b − ψᵀψ, 0) + ψᵀΣψ`` (what the flight
        has told ``η`` leaves the offline band).

        Args:
            offline: (..., 6) ``b``, the offline model's predictive variance of the loads.
            parts: (..., :attr:`n_parts`) the parts.

        Returns:
            (..., 6) the loads' predictive variance (normalised units).
        """
        post = jnp.maximum(parts[..., :N_LOADS], 0.0)
        if not self.shared:
            return offline + post
        return jnp.maximum(offline - jnp.maximum(parts[..., N_LOADS:], 0.0), 0.0) + post

    @highest
    def prior_var(self, x: Float[Array, " D"]) -> Float[Array, " 6"]:
        """``η``'s prior variance per output at ``x``, ``ψ(x)ᵀψ(x)`` (at most its kernel's
        variance: the part of ``η`` the inducing inputs span there).

        Args:
            x: (D,) a normalised input.

        Returns:
            (6,) the prior variance (normalised units).
        """
        return self.moments(self.features(x))[2]

    @highest
    def relaxed(self, t: Float[ArrayLike, ""]) -> Online:
        """The weights' law at time ``t``: relaxed toward the prior since :attr:`t`.

        The Ornstein-Uhlenbeck step of the module docstring, ``a = e^{−Δt/τ}`` per weight
        (:meth:`rates`); a ``t`` before the last update counts as ``Δt = 0`` (the state never
        runs backwards).

        Args:
            t: the time (s) to relax to.

        Returns:
            The online term with ``μ ← Aμ``, ``Σ ← AΣA + I − A²`` (``A = diag(a)``; with one
            ``τ`` per output, ``a²Σ + (1 − a²)I``) and its time advanced.
        """
        dt = jnp.maximum(jnp.asarray(t, self.t.dtype) - self.t, 0.0)
        a = self.rates(dt)
        eye = jnp.eye(self.Z.shape[0], dtype=self.cov.dtype)
        cov = a[:, :, None] * self.cov * a[:, None, :] + (1.0 - a**2)[:, :, None] * eye
        return eqx.tree_at(lambda o: (o.mean, o.cov, o.t), self, (a * self.mean, cov, self.t + dt))

    def tau_per_weight(self) -> Float[Array, "6 m"]:
        """:attr:`tau` broadcast to the whitened weights, one time constant (s) each.

        Returns:
            (6, m) each output's weights' forgetting time constants.
        """
        tau = jnp.asarray(self.tau)
        tau = tau.reshape(tau.shape + (1,) * (2 - tau.ndim))  # (), (6,) or (6, m) to 2-D
        return jnp.broadcast_to(tau, self.mean.shape)

    def rates(self, dt: Float[ArrayLike, ""]) -> Float[Array, "6 m"]:
        """Each weight's ``a = e^{−Δt/τ}`` over ``dt`` (s) (:meth:`tau_per_weight`).

        Args:
            dt: s, the time since the last update (not negative).

        Returns:
            (6, m) the factor on each output's whitened weights.
        """
        return jnp.exp(-jnp.asarray(dt) / self.tau_per_weight())

    @highest
    def measured(
        self, x: Float[Array, " D"], y: Float[Array, " 6"], r: Float[Array, " 6"]
    ) -> Online:
        """One Kalman update per output with the label residual ``y`` of noise variance ``r``.

        A rank-one measurement update of each output's weights; the noise is the label's own
        ``r`` plus the term's value noise :attr:`noise`. It does not relax the weights first:
        call :meth:`relaxed` before, as :func:`update` does.

        Args:
            x: (D,) the label's normalised input.
            y: (6,) its residual against the offline model, normalised, in the GP's frame.
            r: (6,) the residual's noise variance (normalised units).

        Returns:
            The online term conditioned on the label.
        """
        psi = self.features(x)

        def one(mu, S, p, yy, rr, nu):
            Sp = S @ p
            s = p @ Sp + rr + nu
            k = Sp / s
            return mu + k * (yy - p @ mu), S - jnp.outer(k, Sp)

        mean, cov = jax.vmap(one)(self.mean, self.cov, psi, y, r, self.noise)
        cov = 0.5 * (cov + jnp.swapaxes(cov, 1, 2))  # keep it symmetric under rounding
        return eqx.tree_at(lambda o: (o.mean, o.cov), self, (mean, cov))


class SimpleBasis(eqx.Module):
    """``M``'s own loads in the GP's frame and normalised units at a normalised input: the
    regressor whose coefficient ``κ`` corrects ``M`` itself (a thrust or drag-torque
    coefficient that is off on the real vehicle, which the prior's GP, a residual over ``M``,
    cannot scale). In the airflow frame the body's attitude to the air is the input's angles
    (``R_HB = R_WB(ψ_H, θ_H, φ_H)``); in the body frame it is the identity.

    Attributes:
        simple: ``M``.
        normalizer: the surrogate's (inputs back to physical units, the outputs' scales).
        frame: ``"airflow"`` or ``"body"``.
    """

    simple: SimpleModel
    normalizer: Normalizer
    frame: str = eqx.field(static=True, default="airflow")

    @highest
    def __call__(self, xn: Float[Array, " D"]) -> Float[Array, " 6"]:
        x = self.normalizer.x_inv(xn)
        F, tau = self.simple.wrench_body(x[:4])
        if self.frame != "body":
            R = R_WB(x[4:7])
            F, tau = matvec(R, F), matvec(R, tau)
        return jnp.concatenate([F, tau]) / self.normalizer.y_std[:N_LOADS]


class Corrected(Predictor):
    """A prior predictor corrected by flights: ``ρ ⊙ μ_prior + κ ⊙ m + δ (+ η)`` (module
    docstring; ``m`` is :class:`SimpleBasis`).

    Its latent "variance" is a vector: the prior's latent variance, then each ``δ``'s, then
    ``η``'s per output, then the integrated coefficients' per output (where the physical basis
    is used, :mod:`gpg.flight.basis`), then the tracked coefficients' per output (where they
    are followed online, :mod:`gpg.flight.tracking`); :meth:`predictive_variance` turns it into
    the per-output predictive variance ``ρ² var_prior + var_δ + var_η + var_β + var_w``: the
    prior's latent variance (its value noise is the simulator data's), each ``δ``'s with its
    own value noise (the flights'), ``η``'s, ``Rᵀ Σ_β R`` of the coefficients (their
    covariance, ``A⁻¹`` and their spread between the flights held out); where they are
    tracked, ``hᵀ Σ_w h`` of their drift, its noise ``v`` and each ``δ``'s latent variance in
    place of the prior's, the coefficients' and ``δ``'s ``ν²``.

    Attributes:
        prior: the simulator-trained predictor.
        scale: (M,) ``ρ``, ones for the outputs not corrected.
        delta: the discrepancy GPs, one per load output (values only, one output each):
            exact (:class:`~gpg.gp.exact.ExactGP`) up to ``exact_labels`` labels, through
            inducing inputs (:class:`~gpg.gp.inducing.InducingGP`) on every label beyond.
        online: the online term (:class:`Online`, or a :class:`gpg.flight.Bank` of them), or
            None.
        kappa: (6,) ``κ``, the coefficients of ``M``'s own loads, or None.
        basis: ``m`` (:class:`SimpleBasis`) where ``kappa`` is given.
        explicit: the physical basis with its coefficients integrated out
            (:class:`gpg.flight.basis.Explicit`), or None (``ρ`` and ``κ`` point estimates).
        tracker: the basis's coefficients' drift followed online
            (:class:`gpg.flight.tracking.Tracker`), or None.
    """

    prior: Predictor
    scale: Float[Array, " M"]
    delta: tuple[ExactGP | InducingGP, ...]
    online: Online | None = None
    kappa: Float[Array, " 6"] | None = None
    basis: SimpleBasis | None = None
    explicit: Explicit | None = None
    # gpg.flight.tracking.Tracker (that module builds on this one: no import back)
    tracker: eqx.Module | None = None

    def _columns(self, x: Float[Array, " D"]) -> tuple[Array | None, Array | None]:
        """``M``'s loads ``m(x)`` (6,) and the physical columns (6, T) at one query, each None
        where the model lacks it: evaluated once a query, for the mean, the coefficients'
        variance and the tracked columns alike (each is a frame rotation and a few hundred
        operations more in every program that predicts)."""
        simple = None if self.basis is None else self.basis(x)
        physics = None if self.explicit is None else self.explicit.physics(x)
        return simple, physics

    def _mean_terms(
        self, x: Float[Array, " D"], cols: tuple[Array | None, Array | None] | None = None
    ) -> Float[Array, " M"]:
        """``κ ⊙ m(x)`` and the physical columns' ``hᵀβ̄``, padded to the outputs (zeros
        without a basis); ``cols`` :meth:`_columns` at ``x`` where the caller has them."""
        simple, physics = self._columns(x) if cols is None else cols
        out = jnp.zeros(N_LOADS, x.dtype)
        if simple is not None:
            out = out + self.kappa * simple
        if physics is not None:
            out = out + self.explicit.mean_of(physics)
        return self._pad(out)

    def _explicit_variance(
        self,
        x: Float[Array, " D"],
        prior_mean: Float[Array, " M"],
        k: Float[Array, "6 N"] | None = None,
        cols: tuple[Array | None, Array | None] | None = None,
    ) -> Float[Array, " 6"]:
        """The coefficients' share of the variance per load output (:mod:`gpg.flight.basis`);
        ``k`` each ``δ``'s kernel row at ``x`` and ``cols`` :meth:`_columns` at ``x`` where
        the caller has them."""
        e = self.explicit
        simple, physics = self._columns(x) if cols is None else cols
        h = []
        if e.with_prior:
            h.append(prior_mean[:N_LOADS, None])
        if e.with_simple:
            h.append(simple[:, None])
        h = jnp.concatenate([*h, physics], 1)
        if k is None:
            k = jnp.stack([_cross(x[None], d.X, d.hyper.variance, d.hyper.lengthscale)[0]
                           for d in self.delta])  # fmt: skip
        return e.variance(h, k)

    @highest
    def offline_moments(
        self, x: Float[Array, " D"]
    ) -> tuple[Float[Array, " M"], Float[Array, " 6"]]:
        """The offline model's mean and loads' band at one query: what
        :meth:`mean_var_one` and :meth:`predictive_variance` give a model without online parts,
        read in one pass where ``δ`` is a :class:`~gpg.gp.inducing.StackedInducing` view
        (:meth:`stacked`; each kernel row once, for ``δ``'s mean, its variance and the
        coefficients'). For a :class:`gpg.flight.Bank`'s scores at each label.

        Args:
            x: (D,) a normalised input.

        Returns:
            The (M,) mean and the (6,) loads' predictive variance (normalised units).

        Raises:
            ValueError: ``δ`` stacked without its variance (a :meth:`mean_view`'s stack).
        """
        d0 = self.delta[0] if self.delta else None
        if (
            not isinstance(d0, StackedInducing)
            or self.online is not None
            or self.tracker is not None
        ):
            mean, var = self.mean_var_one(x)
            return mean, self.predictive_variance(var)[:N_LOADS]
        if not d0.tri:
            raise ValueError("offline_moments: the stacked discrepancies carry no variance "
                             "(a mean_view's stack); stack variance_views() instead")  # fmt: skip
        prior_mean, prior_var = self.prior.mean_var_one(x)
        k, dmean, latent = d0.evaluate(x)
        cols = self._columns(x)
        mean = self.scale * prior_mean + self._mean_terms(x, cols) + self._pad(dmean)
        band = (jnp.maximum(prior_var, 0.0) * self.prior.output_scale * self.scale**2)[:N_LOADS]
        band = band + (jnp.maximum(latent, 0.0) + d0.noise) * d0.output_scale
        if self.explicit is not None:
            band = band + jnp.maximum(self._explicit_variance(x, prior_mean, k, cols), 0.0)
        return mean, band

    @property
    def output_scale(self) -> Float[Array, " M"]:
        return self.prior.output_scale

    @property
    def partition(self):
        return None

    @property
    def noise(self) -> Float[Array, ""]:
        return self.prior.noise

    @property
    def n_inputs(self) -> int:
        return self.prior.n_inputs

    @property
    def n_outputs(self) -> int:
        return self.prior.n_outputs

    def with_output_scale(self, scale: Float[ArrayLike, " M"]) -> Corrected:
        """This model with the prior's per-output variance scale replaced.

        Only the prior's scale changes: ``ρ``, ``κ``, the ``δ`` GPs and ``η`` keep theirs.

        Args:
            scale: (M,) the prior's new output scale.

        Returns:
            The corrected model over the rescaled prior.
        """
        return eqx.tree_at(lambda c: c.prior, self, self.prior.with_output_scale(scale))

    def describe(self) -> dict[str, Any]:
        """Plain values for a checkpoint's metadata: the prior's, plus the correction's.

        Returns:
            The prior's :meth:`~gpg.gp.predictor.Predictor.describe` with a
            ``flight_correction`` entry: ``scale`` (``ρ``), ``kappa``, each discrepancy's
            hyperparameters, the number of labels and the online term's size and ``τ``.
        """
        out = self.prior.describe()
        out["flight_correction"] = {
            "scale": plain(self.scale),
            "kappa": None if self.kappa is None else plain(self.kappa),
            "discrepancy": [d.describe()["hyperparameters"] for d in self.delta],
            "n_labels": _cases(self.delta[0]) if self.delta else 0,
            "inducing": int(self.delta[0].X.shape[0])
            if self.delta and isinstance(self.delta[0], InducingGP)
            else None,
            "online": None if self.online is None else self.online.describe(),
            "explicit": None
            if self.explicit is None
            else {"columns": list(self.explicit.columns), "beta": plain(self.explicit.beta)},
            "tracker": None
            if self.tracker is None
            else {
                "tau": plain(self.tracker.tau),
                "spread": plain(self.tracker.spread),
                "wind_sd": None if self.tracker.wind_sd is None else plain(self.tracker.wind_sd),
                "offset": None if self.tracker.offset is None else plain(self.tracker.offset),
            },
        }
        return out

    def wind_state(self) -> tuple[Float[Array, " 3"], Float[Array, "3 3"]] | None:
        """The tracked wind state's mean ``ḡ`` and covariance ``P_g`` (m/s, world), or None.

        A prediction (:func:`gpg.surrogate.predict_state`) reads the model at ``v_air + ḡ``
        and adds ``J P_g Jᵀ`` to the loads' variance (``J`` the loads' derivative in the air
        velocity).

        Returns:
            ``(ḡ, P_g)`` where the model tracks a wind state (:func:`gpg.flight.gusts`),
            else None.
        """
        t = self.tracker
        if t is None or getattr(t, "wind_mean", None) is None:
            return None
        return t.wind_mean, t.wind_cov

    def without_wind(self) -> Corrected:
        """This model with its tracked wind state removed (the coefficients' drift kept).

        Returns:
            The model that :meth:`wind_state`'s prediction shifts.
        """
        if self.wind_state() is None:
            return self
        none = (None, None, None, None)
        t = eqx.tree_at(lambda o: (o.wind_mean, o.wind_cov, o.wind_tau, o.wind_sd), self.tracker,
                        none, is_leaf=lambda a: a is None)  # fmt: skip
        return eqx.tree_at(lambda c: c.tracker, self, t)

    def _pad(self, v: Float[Array, " L"]) -> Float[Array, " M"]:
        return jnp.concatenate([v, jnp.zeros(self.n_outputs - v.shape[0], v.dtype)])

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """The corrected mean at one query: ``ρ ⊙ μ_prior + κ ⊙ m + δ (+ η)``.

        Args:
            x: (D,) a normalised input.

        Returns:
            (M,) the mean (normalised units); ``δ``, ``κ`` and ``η`` add to the load outputs
            only, the levels keep ``ρ = 1``.
        """
        prior_mean = self.prior.mean_one(x)
        cols = self._columns(x)
        out = self._offline_mean(x, prior_mean, cols)
        if self.online is not None:
            out = out + self._pad(self.online.latent(x)[0])
        if self.tracker is not None:
            h = self._tracker_columns(x, prior_mean, cols)
            out = out + self._pad(self.tracker.mean_var(h)[0])
        return out

    def offline_mean(
        self, x: Float[Array, " D"], prior_mean: Float[Array, " M"]
    ) -> Float[Array, " M"]:
        """The mean without its online parts (``η``, the tracked drift): ``ρ ⊙ μ_prior + κ ⊙ m
        + hᵀβ̄ + δ``, the reference an online update's residual is taken against.

        Args:
            x: (D,) a normalised input.
            prior_mean: (M,) the prior's mean at ``x`` (computed once by the caller).

        Returns:
            (M,) the offline mean (normalised units).
        """
        return self._offline_mean(x, prior_mean, self._columns(x))

    def _offline_mean(self, x, prior_mean, cols) -> Float[Array, " M"]:
        """:meth:`offline_mean` with :meth:`_columns` at ``x`` given."""
        out = self.scale * prior_mean + self._mean_terms(x, cols)
        if self.delta:
            d0 = self.delta[0]
            if isinstance(d0, StackedInducing):  # online_step's view
                return out + self._pad(d0.means(x))
            out = out + self._pad(jnp.concatenate([d.mean_one(x) for d in self.delta]))
        return out

    def tracker_columns(
        self, x: Float[Array, " D"], prior_mean: Float[Array, " M"]
    ) -> Float[Array, "6 P"]:
        """The tracked coefficients' columns ``h(x)`` per load output: the prior's mean, ``M``'s
        loads (where the model has ``M``), the physical terms, then a constant (the bias).

        Args:
            x: (D,) a normalised input.
            prior_mean: (M,) the prior's mean at ``x``.

        Returns:
            (6, P) the columns (normalised units per unit coefficient).

        Raises:
            ValueError: the model tracks no coefficients.
        """
        if self.tracker is None:
            raise ValueError("tracker_columns needs a model prepared by gpg.flight.track")
        return self._tracker_columns(x, prior_mean, self._columns(x))

    def _tracker_columns(self, x, prior_mean, cols) -> Float[Array, "6 P"]:
        """:meth:`tracker_columns` with :meth:`_columns` at ``x`` given. The tracker's physical
        columns are the model's own where it has them (``track`` takes them from there)."""
        simple, physics = cols
        h = [prior_mean[:N_LOADS, None]]
        if self.tracker.with_simple:
            h.append(simple[:, None])
        h += [self.tracker.physics(x) if physics is None else physics, self.tracker.bias_column()]
        return jnp.concatenate(h, 1)

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, " V"]]:
        """The corrected mean and the latent variance's parts at one query.

        Args:
            x: (D,) a normalised input.

        Returns:
            The (M,) mean (as :meth:`mean_one`) and the (V,) latent variance: the prior's, then
            each ``δ``'s, then ``η``'s, the coefficients' and the tracked drift's per output,
            where the model has them (:meth:`predictive_variance` combines them).
        """
        prior_mean, var = self.prior.mean_var_one(x)
        cols = self._columns(x)
        mean = self.scale * prior_mean + self._mean_terms(x, cols)
        parts = [jnp.reshape(var, (1,))]
        for d in self.delta:
            m, v = d.mean_var_one(x)
            mean = mean.at[len(parts) - 1].add(m[0])
            parts.append(jnp.reshape(v, (1,)))
        if self.online is not None:
            m, v = self.online.latent(x)
            mean = mean + self._pad(m)
            parts.append(v)
        if self.explicit is not None and self.tracker is None:
            parts.append(self._explicit_variance(x, prior_mean, cols=cols))
        if self.tracker is not None:
            m, v = self.tracker.mean_var(self._tracker_columns(x, prior_mean, cols))
            mean = mean + self._pad(m)
            parts.append(v)
        return mean, jnp.concatenate(parts)

    def predictive_variance(self, var: Float[ArrayLike, "*Q V"]) -> Float[Array, "*Q M"]:
        """Each output's predictive variance from the latent parts of :meth:`mean_var_one`.

        ``ρ² var_prior`` scaled by the prior's output scale, plus each ``δ``'s predictive
        variance (its own value noise, the flights', included), ``η``'s and the coefficients',
        on the load outputs. A tracked model's loads have the filter's band instead: the
        tracked drift's ``hᵀ Σ h`` plus its extra noise ``v`` (:mod:`gpg.flight.tracking`),
        each ``δ``'s latent variance without its ``ν²`` and the labels' offset ``σ_o²``
        (:attr:`gpg.flight.Drift.label_offset`).

        Args:
            var: (..., V) the latent variance parts.

        Returns:
            (..., M) the predictive variance per output (normalised units).
        """
        var = jnp.asarray(var)
        # The prior's latent part only: its value noise ν² is the simulator data's, while the
        # flights' noise and whatever the prior misses are δ's (its own ν² is in its part).
        out = jnp.maximum(var[..., 0], 0.0)[..., None] * self.prior.output_scale * self.scale**2
        nd = len(self.delta)
        if nd:
            dv = jnp.stack(
                [d.predictive_variance(var[..., 1 + j])[..., 0] for j, d in enumerate(self.delta)],
                axis=-1,
            )
            out = out + jnp.concatenate(
                [dv, jnp.zeros((*dv.shape[:-1], self.n_outputs - nd), dv.dtype)], axis=-1
            )
        at = 1 + nd
        # A tracker carries the coefficients' offline covariance in its own: their share is
        # the tracker's, not counted twice.
        explicit = self.explicit if self.tracker is None else None
        online = None
        if self.online is not None:  # its band is taken from the offline one, summed below
            online = var[..., at : at + self.online.n_parts]
            at += self.online.n_parts
        for part in (explicit, self.tracker):
            if part is None:
                continue
            ov = jnp.maximum(var[..., at : at + N_LOADS], 0.0)
            at += N_LOADS
            out = out + jnp.concatenate(
                [ov, jnp.zeros((*ov.shape[:-1], self.n_outputs - ov.shape[-1]), ov.dtype)],
                axis=-1,
            )
        if online is not None:
            loads = self.online.band(out[..., :N_LOADS], online)
            out = jnp.concatenate([loads, out[..., N_LOADS:]], axis=-1)
        if self.tracker is not None:
            # The tracked model's band on the loads: the filter's hᵀΣh and the extra noise v
            # its drift was fitted with, plus each δ's own latent variance. The tracked
            # coefficients follow what the basis spans, so they take the place of the prior's
            # latent part, the coefficients' offline share and δ's value noise ν² (which v
            # stands for); δ's mean is still added, and what it does not know away from the
            # flights (a state the basis does not span) still is not known.
            tracked = jnp.maximum(var[..., at - N_LOADS : at], 0.0) + self.tracker.noise
            if nd:
                tracked = tracked + self._delta_latent(var)
            if self.tracker.offset is not None:  # the labels' own offset: no label tells it
                tracked = tracked + self.tracker.offset
            out = jnp.concatenate([tracked, out[..., N_LOADS:]], axis=-1)
        return out

    def variance_parts(self, var: Float[ArrayLike, "*Q V"]) -> dict[str, Float[Array, "*Q M"]]:
        """:meth:`predictive_variance` of an offline correction split into its terms.

        Args:
            var: (..., V) the latent variance parts of :meth:`mean_var_one`.

        Returns:
            (..., M) each, normalised units, summing to :meth:`predictive_variance`:
            ``"prior"`` (``ρ² var_prior``, its output scale), ``"discrepancy"`` (each ``δ``'s
            latent variance, the held-out factor in it), ``"discrepancy_noise"`` (its
            ``ν²``) and ``"basis"`` (the coefficients' ``Rᵀ Σ_β R``), the last three where
            the model has them (zeros beyond the loads).

        Raises:
            ValueError: an adapted model (:func:`adapt`, :func:`gpg.flight.track`), whose
                band is not a sum of these terms.
        """
        if self.online is not None or self.tracker is not None:
            raise ValueError(
                "variance_parts: an adapted model's band is not a sum of terms (its filter's "
                "band takes the offline one's place); split the offline model's"
            )
        var = jnp.asarray(var)
        prior = jnp.maximum(var[..., 0], 0.0)[..., None] * self.prior.output_scale * self.scale**2
        out = {"prior": prior}

        def padded(v):
            return jnp.concatenate([v, jnp.zeros((*v.shape[:-1], self.n_outputs - v.shape[-1]),
                                                 v.dtype)], axis=-1)  # fmt: skip

        nd = len(self.delta)
        if nd:
            # each δ's own split (latent, ν²): the terms its predictive_variance sums
            dp = [d.variance_parts(var[..., 1 + j]) for j, d in enumerate(self.delta)]
            for key, name in (("latent", "discrepancy"), ("noise", "discrepancy_noise")):
                out[name] = padded(jnp.stack([p[key][..., 0] for p in dp], axis=-1))
        if self.explicit is not None:
            out["basis"] = padded(jnp.maximum(var[..., 1 + nd : 1 + nd + N_LOADS], 0.0))
        return out

    def _delta_latent(self, var: Float[ArrayLike, "*Q V"]) -> Float[Array, "*Q 6"]:
        """Each ``δ``'s latent variance times its output scale (no ``ν²``), per load output,
        from the latent parts ``var`` of :meth:`mean_var_one`."""
        var = jnp.asarray(var)
        parts = [jnp.maximum(var[..., 1 + j], 0.0) * d.output_scale[0]
                 for j, d in enumerate(self.delta)]  # fmt: skip
        return jnp.stack(parts, axis=-1)

    def _delta_latent_at(self, x: Float[Array, " D"]) -> Float[Array, " 6"]:
        """:meth:`_delta_latent` at one normalised query, the discrepancies alone (not the
        prior's variance); zeros without them."""
        if not self.delta:
            return jnp.zeros(N_LOADS)
        if isinstance(self.delta[0], StackedInducing):
            d = self.delta[0]
            return jnp.maximum(d.latents(x), 0.0) * d.output_scale
        parts = [jnp.maximum(jnp.reshape(d.mean_var_one(x)[1], ()), 0.0) * d.output_scale[0]
                 for d in self.delta]  # fmt: skip
        return jnp.stack(parts)

    def mean_view(self, keep_delta: bool = False) -> Corrected:
        """This model with the prior and each ``δ`` reduced to what their means read.

        For mean-only loops (:func:`online_step`); its variance is not to be used.

        Args:
            keep_delta: keep each ``δ``'s variance (:meth:`_delta_latent_at` reads it: the
                wind state's update does), as :meth:`variance_views` gives it.

        Returns:
            The corrected model over the mean views.
        """
        delta = self.variance_views().delta if keep_delta else (
            tuple(d.mean_view() for d in self.delta))  # fmt: skip
        return eqx.tree_at(lambda c: (c.prior, c.delta), self, (self.prior.mean_view(), delta))

    def stacked(self) -> Corrected:
        """This model with its discrepancies stacked into one
        :class:`~gpg.gp.inducing.StackedInducing` where they are one-output inducing-point
        GPs of one size (else itself): their six kernel rows, means and variances at a query
        in one program. For :func:`online_step`'s view only: :meth:`offline_mean` and the
        wind state's variance read it, nothing else does. On the host, once.

        Returns:
            The corrected model over the stack (or the model itself).
        """
        # a mean_view's δ have no variance factors (StackedInducing.of refuses exact δ)
        variance = all(isinstance(d, InducingGP) and d.whiten.shape[0] > 0 for d in self.delta)
        stack = StackedInducing.of(self.delta, variance)
        if stack is None:
            return self
        return eqx.tree_at(lambda c: c.delta, self, (stack,))

    def variance_views(self) -> Corrected:
        """This model with each inducing-point ``δ``'s latent variance folded into one
        triangle (:meth:`gpg.gp.inducing.InducingGP.variance_view`): the same predictions to
        rounding, half the products a query in ``δ``'s variance. For the loops that read it
        at every label from Python (:func:`online_step` with a wind state); on the host, once.
        The fold (an eigendecomposition per ``δ``) costs more than a flight's
        :func:`gpg.flight.prequential` scan saves by it, so that scan does not take it.

        Returns:
            The corrected model with folded discrepancies (an exact ``δ`` has one triangle
            already and is kept).
        """
        delta = tuple(d.variance_view() if isinstance(d, InducingGP) else d for d in self.delta)
        return eqx.tree_at(lambda c: c.delta, self, delta)


def base(sur: Surrogate) -> Surrogate:
    """The simulator-trained surrogate under a corrected one (itself if not corrected).

    For what takes only the prior: the export layouts, or a correction anew.

    Args:
        sur: a surrogate, corrected (:func:`correct`, :func:`adapt`) or not.

    Returns:
        The surrogate of the prior, its model name without the ``+flight`` suffix.
    """
    m = sur.model
    if not isinstance(m, Corrected):
        return sur
    prior = m.prior
    scale = sur.config.get("flight_correction", {}).get("prior_output_scale")
    if scale is not None:  # the held-out calibration's q undone
        prior = prior.with_output_scale(jnp.asarray(scale, prior.output_scale.dtype))
    return dataclasses.replace(sur, model=prior, model_name=_base_name(sur.model_name))


def _narrowed(model, share):
    """The prior's ``model`` with its output scale times the held-out calibration's ``q``
    (:func:`_held_out_scale`) on the load outputs: every part of the corrected model and its
    exports reads the prior's share through that scale. ``share`` None: the model itself."""
    if share is None or all(q == 1.0 for q in share):
        return model
    os = model.output_scale
    q = np.ones(os.shape[0])
    q[:N_LOADS] = share
    return model.with_output_scale(os * jnp.asarray(q, os.dtype))


def _base_name(name: str) -> str:
    return name.split("+flight")[0]


@highest
def gp_rows(
    sur: Surrogate,
    rpm: Float[Array, " 4"],
    euler: Float[Array, " 3"],
    v_air: Float[Array, " 3"],
    force: Float[Array, " 3"],
    torque: Float[Array, " 3"],
    force_var: Float[Array, " 3"],
    torque_var: Float[Array, " 3"],
) -> tuple[Float[Array, " D"], Float[Array, " 6"], Float[Array, " 6"]]:
    """A world-frame label as the GP sees it.

    The residual is taken against ``M`` where the surrogate has one and rotated into the GP's
    frame (``R_WHᵀ (F_W − F_M)``, likewise the torque); the variances are rotated with ``R²``
    (independent components) and divided by the output scales².

    Args:
        sur: the surrogate whose frame and normaliser apply.
        rpm: (4,) rotor speeds, rpm.
        euler: (3,) (yaw, pitch, roll), rad.
        v_air: (3,) air velocity, world, m/s.
        force: (3,) the measured aerodynamic force, world, N.
        torque: (3,) the measured aerodynamic torque, world, N·m.
        force_var: (3,) the force's noise variances, world.
        torque_var: (3,) the torque's noise variances, world.

    Returns:
        The (D,) normalised input ``x``, the (6,) normalised load residual and its (6,) noise
        variance.
    """
    x, R = gp_inputs(sur, rpm, euler, v_air)  # the half-turn image's where sur reads it
    f, tau = force, torque
    if sur.simple is not None:
        y_m = sur.simple(jnp.concatenate([rpm, euler]))
        f, tau = f - y_m[:3], tau - y_m[3:6]
    y = jnp.concatenate([matvec(R.T, f), matvec(R.T, tau)])
    var = jnp.concatenate([(R**2).T @ force_var, (R**2).T @ torque_var])
    std = sur.normalizer.y_std[:N_LOADS]
    yn = (y - sur.normalizer.y_mean[:N_LOADS]) / std
    return sur.normalizer.x(x), yn, var / std**2


_rows_batch = jax.jit(jax.vmap(gp_rows, in_axes=(None, 0, 0, 0, 0, 0, 0, 0)))


def training_rows(sur: Surrogate, labels: Labels) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`gp_rows` of every label, against the prior under ``sur`` (:func:`base`).

    Args:
        sur: the surrogate (a corrected one's prior is used).
        labels: the labels (world frame).

    Returns:
        ``X`` (N, D), ``Y`` (N, 6) and the noise variances (N, 6), as NumPy arrays.
    """
    x, y, v = _rows_batch(
        base(sur),
        *(
            jnp.asarray(a)
            for a in (
                labels.rpm,
                labels.euler,
                labels.v_air,
                labels.force,
                labels.torque,
                labels.force_var,
                labels.torque_var,
            )
        ),
    )
    return np.asarray(x), np.asarray(y), np.asarray(v)


# Long by design: the arguments checked, the labels' rows, then the two bases' fits side by side.
@float64
def correct(
    prior: Surrogate,
    labels: Labels | Sequence[Labels],
    *,
    basis: str = "regression",
    scale: bool = True,
    use_prior: bool = True,
    simple_term: bool = True,
    max_labels: int | None = None,
    exact_labels: int = 1500,
    inducing: int = 512,
    subset_size: int = 400,
    max_steps: int = 200,
    seed: int = 0,
    calibrate: bool = True,
    basis_prior: float | str = "auto",
    hyperparameters: str = "subset",
    coefficient_spread: bool = True,
) -> Surrogate:
    """The surrogate ``prior`` corrected by flight ``labels`` (module docstring).

    Args:
        prior: a fitted surrogate (its GP mean is ``μ_sim``; a corrected one is corrected
            anew from its prior).
        labels: :func:`gpg.flight.label` of one or more flights.
        basis: ``"regression"``: ``ρ`` and ``κ`` as weighted least-squares point estimates,
            then ``δ`` on what is left (for a prior of the same vehicle, flown where the
            flights went); ``"physical"``: the prior's mean, ``M``'s loads and the physical
            terms of :mod:`gpg.flight.basis` (drag, rotor drag, inflow) as explicit basis
            functions whose coefficients are integrated out under a Gaussian prior, so that
            their uncertainty widens the band where no flight went (for an identified
            vehicle's prior, and winds or speeds the flights did not reach).
        scale: fit ``ρ`` per load output; False keeps ``ρ = 1``: for an identified
            vehicle's prior with ``basis="physical"``, whose physics is taken as it is (a
            fitted ``ρ`` trades with the drag columns where the flights went and
            extrapolates wrong beyond).
        use_prior: False sets ``ρ = 0`` for the loads: a values-only GP on the flights
            alone (residuals against ``M``), the baseline that has no simulator knowledge.
        simple_term: also fit ``κ``, the coefficient of ``M``'s own loads
            (:class:`SimpleBasis`; jointly with ``ρ``): a thrust or drag-torque coefficient
            that differs on the real vehicle is one number, where ``δ`` would have to learn
            it state by state. Needs a prior with ``M``.
        max_labels: at most this many labels enter ``δ`` (evenly thinned in time beyond);
            None: every label.
        exact_labels: up to this many labels, each ``δ`` is the exact GP (``N³``); beyond,
            an inducing-point GP on every label (:class:`~gpg.gp.inducing.InducingGP`,
            ``O(N m²)`` time, ``O(m²)`` memory besides the labels), and a calibration
            (``calibrate``) on this many labels evenly spread.
        inducing: ``m``, the inducing inputs beyond ``exact_labels`` (k-means centres of the
            labels' inputs, :func:`~gpg.gp.inducing.inducing_inputs`).
        subset_size: labels per likelihood evaluation of the hyperparameter fit, drawn at
            random (which labels, and how many, move the fit: the guide measures 400
            against 1000).
        max_steps: BFGS steps of each discrepancy's hyperparameter fit
            (:func:`gpg.gp.fit.fit_hyperparameters`).
        seed: the subsets' seed.
        calibrate: with ``basis="physical"`` and labels of two flights or more, scale each
            component's discrepancy and coefficient variance by the ``c`` under which every
            flight, held out and predicted from the others, is covered as the band the model
            predicts says: the mean of ``e² / (c v + q p + n)`` is 1 over their labels in
            the prior's domain (``v`` the latent variance, ``p`` the prior's share ``ρ²
            var_prior``, ``n`` the labels' noise; ``c`` only widens): a band honest for a
            flight in conditions the others did not have, not only within them. Where every
            flight held out is covered more widely than that, the prior's share is narrowed
            instead: ``q`` at most 1 (at least :data:`PRIOR_SHARE_FLOOR`) on the prior's
            output scale, the largest factor on ``p`` that any one held-out flight needs
            (the prior's near-set variance is a bound, which flights of the vehicle can show
            several times too wide); recorded with the scale before it
            (``flight_correction.prior_share``, ``prior_output_scale``), which :func:`base`
            restores. Outside the prior's domain ``p`` is its kernel's whole variance, which
            says nothing of the discrepancy's width; with no held-out label inside it, every
            label counts. False: the discrepancies' own band and the prior's (``basis_prior``
            chooses as with True: its candidates are scored under the discrepancy's own
            held-out factor either way).
        basis_prior: with ``basis="physical"``, the prior of the physical terms'
            coefficients: a factor on :data:`~gpg.flight.basis.PRIORS`'s standard deviations;
            ``"auto"``: ``"held_out"`` where the prior's physics is taken as it is
            (``scale=False``), else 1 (with ``ρ`` fitted, or no prior, the terms are the only
            physics past the flights, and holding them near zero measured worse); or
            ``"held_out"``: per load output, the factor of :data:`BASIS_PRIOR_GRID` under
            which the flight predicted worst when each is held out and predicted from the
            others is predicted best (its mean log predictive density under the
            discrepancy's and the coefficients' band alone, widened by the factor that makes
            that band cover the held-out flights); with labels of one flight, 1. A term that
            fits the flights' conditions but predicts a held-out one badly (a quadratic in the
            airspeed fitted on three winds) is held near zero, and the prior's physics carries
            the model past the flights.
        hyperparameters: ``"subset"``: each discrepancy's on ``subset_size`` labels drawn at
            random; ``"all"``: that fit refined on every label by the collapsed bound
            (:func:`gpg.gp.inducing.fit_collapsed`) through ``inducing`` k-means inputs
            (``O(N m²)`` a step).
        coefficient_spread: with ``basis="physical"`` and labels of two flights or more
            held out (``calibrate`` or ``basis_prior="held_out"``), the physical
            coefficients' covariance ``A⁻¹`` plus their spread between the flights: the
            delete-a-flight jackknife of their posterior means, each flight held out in
            turn (pass one part per condition, a wind say). ``A⁻¹`` takes the labels as
            independent given the discrepancy, and shrinks with their number; where the
            basis is not the truth's form, the coefficients that fit the flights move with
            the conditions flown, and the band past every flight (a faster wind, where the
            terms carry the model) is as wide as they move. Within the flights the
            discrepancy's kernel takes much of it back (``R = h − Gᵀk``), not all. False:
            ``A⁻¹`` alone.

    Returns:
        A :class:`~gpg.Surrogate` whose model is :class:`Corrected`: ``predict`` gives the
        corrected force and torque and the combined variance; the environment, the MPC and
        checkpoints take it.

    Raises:
        ValueError: no labels, fewer than 8, labels with NaN (naming the array), an
            unknown ``basis`` or ``hyperparameters``, a ``basis_prior`` that is not a
            positive number, ``"auto"`` or ``"held_out"``, or sizes under 1.
    """
    for name, v in (("exact_labels", exact_labels), ("inducing", inducing)):
        if not int(v) >= 1:
            raise ValueError(f"{name} must be >= 1, got {v}")
    if hyperparameters not in ("subset", "all"):
        raise ValueError(f"hyperparameters must be 'subset' or 'all', got {hyperparameters!r}")
    if basis_prior == "auto":
        basis_prior = "held_out" if (use_prior and not scale) else 1.0
    if basis_prior != "held_out" and not (
        isinstance(basis_prior, int | float) and not isinstance(basis_prior, bool)
        and np.isfinite(basis_prior) and basis_prior > 0
    ):  # fmt: skip
        raise ValueError(
            f"basis_prior must be 'auto', 'held_out' or a number > 0, got {basis_prior!r}"
        )
    parts = [labels] if isinstance(labels, Labels) else list(labels)
    prior = base(prior)
    X, Y, V, groups, _ = _label_rows(prior, parts, max_labels, basis)
    # Beyond exact_labels: inducing inputs shared by the six discrepancies; the held-out
    # calibration (dense per flight) on exact_labels rows spread evenly.
    Z = None if X.shape[0] <= exact_labels else inducing_inputs(X, int(inducing), seed=seed)
    cal = _thin(X.shape[0], int(exact_labels))
    Zh = None
    if hyperparameters == "all":
        Zh = Z if Z is not None else inducing_inputs(X, int(inducing), seed=seed)
    mu = np.asarray(prior.model.predict_mean(X))[:, :N_LOADS]
    simple = None
    if simple_term and prior.simple is not None:
        simple = SimpleBasis(prior.simple, prior.normalizer, prior.frame)
    m = None if simple is None else _host.each_row(simple, X)
    rho = np.ones(prior.model.n_outputs)  # the levels keep ρ = 1
    explicit = None
    fit = (subset_size, max_steps, seed)
    if basis == "regression":
        rho6, kappa = _regression(Y, V, mu, m, fit_rho=use_prior and scale, use_prior=use_prior)
        R = Y - rho6 * mu - (0.0 if m is None else kappa * m)
        deltas = tuple(_fit_delta(X, R[:, j], V[:, j], *fit[:2], seed + j, Z, Zh)
                       for j in range(N_LOADS))  # fmt: skip
        choice = None
    else:
        fixed_rho = None if (use_prior and scale) else (1.0 if use_prior else 0.0)
        band = None  # the prior's share of the held-out band, and its domain, where read
        if use_prior and np.unique(groups).size >= 2 and (calibrate or basis_prior == "held_out"):
            band = _prior_band(prior, parts, max_labels, X, cal)
        rho6, kappa, deltas, explicit, choice = _fit_explicit(
            X, Y, V, mu, m, _physics(prior), fixed_rho, *fit,
            groups=groups, Z=Z, cal=cal, Zh=Zh, basis_prior=basis_prior, calibrate=calibrate,
            prior_band=band, spread=bool(coefficient_spread),
        )  # fmt: skip
    rho[:N_LOADS] = rho6
    share = (choice or {}).get("prior_share") if calibrate else None
    model = Corrected(
        prior=_narrowed(prior.model, share),
        scale=jnp.asarray(rho),
        delta=deltas,
        kappa=None if simple is None else jnp.asarray(kappa),
        basis=simple,
        explicit=explicit,
    )
    cfg = dict(prior.config)
    cfg["flight_correction"] = {
        "basis": basis,
        "scale": bool(scale),
        "use_prior": bool(use_prior),
        "simple_term": simple is not None,
        "n_labels": int(X.shape[0]),
        "inducing": None if Z is None else int(Z.shape[0]),
        "flights": [p.name for p in parts],
        "hyperparameters": hyperparameters,
        # the physical coefficients' spread between the flights held out in their band
        "coefficient_spread": bool(coefficient_spread),
        # the factor q on the prior's share of the band per load output (held-out
        # calibration), and the prior's output scale before it, which base() restores
        "prior_share": share,
        "prior_output_scale": None if share is None else plain(prior.model.output_scale),
        # basis_prior's candidates, the factor chosen per load output and, where flights
        # were held out, each candidate's score: the worst-predicted flight's mean negative
        # log predictive density (nats per label)
        "basis_prior": choice,
    }
    return dataclasses.replace(
        prior,
        model=model,
        model_name=f"{prior.model_name}+flight",
        config_json=json.dumps(cfg, sort_keys=True),
    )


def _prior_band(prior: Surrogate, parts: list[Labels], max_labels, X, cal):
    """At the calibration rows ``X[cal]`` (``X`` :func:`_label_rows`'s), the prior's
    latent variance times its output scale per load output (normalised units: its share of
    the corrected band for ``ρ = 1``), and whether each row's state is in the prior's domain
    (``in_domain`` of its prediction)."""
    lab = Labels.concatenate(parts)
    rows = np.arange(len(lab))  # the calibration rows' labels, thinned as _label_rows thins
    if max_labels is not None:
        rows = rows[_thin(rows.size, int(max_labels))]
    rows = rows[cal]
    states = (np.asarray(a)[rows] for a in (lab.rpm, lab.euler, lab.v_air))
    inside = np.asarray(prior.predict_batch(*states, mean_only=True).in_domain)
    _, var = prior.model.predict(jnp.asarray(X[cal]))
    share = np.maximum(np.asarray(var, float), 0.0)[:, None] * np.asarray(
        prior.model.output_scale, float)[:N_LOADS]  # fmt: skip
    return share, inside


def _physics(prior: Surrogate) -> PhysicalBasis:
    """The physical columns in the prior's frame and units; without ``M`` the rotors' hubs are
    not known, and the rotor terms' torque columns are zero."""
    hubs = jnp.zeros((4, 3)) if prior.simple is None else prior.simple.positions
    return PhysicalBasis(prior.normalizer, hubs, prior.frame)


def _held_out_scale(
    X, H, y, noise, hyper: Hyper, b, sd, groups, widen: bool = True, prior=None
) -> tuple[float, float, list[float], float, np.ndarray | None]:
    """The factor ``c`` on the latent variance and the factor ``q`` on the prior's share that
    make each flight, predicted from the others (:func:`_held_out`), covered as the band the
    model predicts says; the largest over the flights of a held-out flight's mean negative
    log predictive density (nats per label: what the basis's prior is chosen by); each
    held-out flight's share of labels inside the predicted band ``Z95²(c v + q p + n)``
    (``widen`` False: without ``c`` and ``q``; one pooled ``c`` can cover one flight loosely
    and another tightly: the spread says how far the band's width carries from one condition
    to the next); and the coefficients' spread between the flights held out
    (:func:`_spread`; None where none could be).

    ``prior``: ``(p, inside)``, the prior's share of the band at each label (``ρ²
    var_prior``: the prior is not refitted without a flight) and whether the label is in the
    prior's domain; None: no prior's share (``q`` = 1). Over the held-out labels in the
    domain (``e`` the error, ``v`` the latent variance, ``n`` the label's noise):

    - ``q`` (:func:`_share`) narrows the prior's share where every flight's band is wider
      than its errors: the largest over the flights of the factor ``f`` on ``p`` at which
      that flight's mean ``e² / (v + f p + n)`` is 1, at most 1: the band the model then
      predicts for the worst-predicted flight held out is as wide as its errors. The prior's
      variance (GP-G's near-set bound) can be several times what the prior misses where the
      flights went; the flights measure it. The worst-covered flight sets it (a pooled mean
      is the easy flights'), and ``v``, the discrepancy's own, is kept as it is.
    - ``c`` is then the root of the pooled mean ``e² / (c v + q p + n)`` = 1, at least 1:
      solved with ``q p + n`` beside ``c v``, since the mean of ``e² / (v + n)`` taken as
      ``c`` leaves a band too narrow by about ``n / v`` where the labels' noise outweighs
      the latent variance, and a ``c`` solved without ``p`` widens the discrepancy for
      errors the prior's variance already covers. One of the two is 1: a flight under-
      covered at ``q`` = 1 keeps ``q`` = 1, and with ``q`` < 1 every flight's mean, so
      the pooled one, is at most 1 at ``c`` = 1.

    The score is the band of the discrepancy and the coefficients alone, under their own
    such factor (``p`` = 0): it judges the basis's mean beyond the flights, which ``p``,
    the same for every candidate, would only dilute."""
    parts = _held_out(X, H, y, noise, hyper, b, sd, groups)
    if not parts:
        return 1.0, 0.0, [], 1.0, None
    p, inside = (np.zeros(len(y)), np.ones(len(y), bool)) if prior is None else prior
    te_all = np.concatenate([np.nonzero(te)[0] for te, *_ in parts])
    e2 = np.concatenate([(y[te] - mean) ** 2 for te, mean, *_ in parts])
    v = np.concatenate([var for _, _, var, *_ in parts])
    n = noise[te_all]
    k = inside[te_all] if inside[te_all].any() else np.ones(te_all.size, bool)
    flight = np.concatenate([np.full(int(te.sum()), i) for i, (te, *_) in enumerate(parts)])
    q = 1.0 if prior is None else _share(e2[k], v[k], n[k], p[te_all][k], flight[k])
    c = _factor(e2[k], v[k], n[k] + q * p[te_all][k])
    own = c if prior is None else _factor(e2, v, n)
    # The worst-predicted flight's score: a prior that predicts the flights within the others'
    # conditions well and the one beyond them badly is the one not to extrapolate with.
    worst, coverage = -np.inf, []
    for te, mean, var, *_ in parts:
        s2 = own * var + noise[te]
        e2g = (y[te] - mean) ** 2
        worst = max(worst, float(np.mean(0.5 * np.log(2.0 * np.pi * s2) + 0.5 * e2g / s2)))
        band = (c * var + q * p[te] if widen else var + p[te]) + noise[te]
        coverage.append(float(np.mean(e2g <= Z95**2 * band)))
    return c, worst, coverage, q, _spread([beta for *_, beta in parts])


def _spread(betas: list[np.ndarray]) -> np.ndarray | None:
    """The delete-a-group jackknife covariance of the coefficients (P, P), from their
    posterior means with each group held out in turn: ``(G − 1)/G Σ_g (β̄₋g − β̃)(β̄₋g −
    β̃)ᵀ``, ``β̃`` their mean (None with fewer than two groups). The posterior ``A⁻¹`` takes
    the labels as independent given the discrepancy; the labels of one wind share its
    unmodelled aerodynamics, and where the basis is not the truth's form the coefficients
    that fit the flights move with the conditions they were flown in. The jackknife measures
    that from the flights, without the assumption: the coefficients' width where the basis
    carries the model past every flight."""
    if len(betas) < 2:
        return None
    B = np.stack(betas)
    d = B - B.mean(0)
    return (len(B) - 1) / len(B) * d.T @ d


def _share(e2, v, n, p, flight) -> float:
    """``q`` of :func:`_held_out_scale`: the largest over the ``flight`` groups of the ``f``
    at which that group's mean ``e² / (v + f p + n)`` is 1, at most 1 and at least
    :data:`PRIOR_SHARE_FLOOR` (where the discrepancy's band and the labels' noise alone
    cover a flight's errors)."""
    from scipy.optimize import brentq

    q = PRIOR_SHARE_FLOOR
    for g in np.unique(flight):
        i = flight == g
        rest = v[i] + n[i]

        def excess(f: float, i=i, rest=rest) -> float:
            return float(np.mean(e2[i] / (f * p[i] + rest))) - 1.0

        if excess(1.0) >= 0.0:
            return 1.0
        if excess(q) > 0.0:  # a root above the largest so far; excess falls in f
            q = float(brentq(excess, q, 1.0, rtol=1e-12))
    return q


def _factor(e2: np.ndarray, v: np.ndarray, n: np.ndarray) -> float:
    """The ``c >= 1`` at which the mean of ``e² / (c v + n)`` is 1 (1 where it is under 1 at
    ``c = 1``)."""
    from scipy.optimize import brentq

    def excess(c: float) -> float:
        return float(np.mean(e2 / (c * v + n))) - 1.0

    if excess(1.0) <= 0.0:
        return 1.0
    # v >= ν > 0: at c = mean(e²) / min(v) every term is at most e² / mean(e²), so the root
    # is bracketed, and excess falls monotonically in c.
    return float(brentq(excess, 1.0, float(np.mean(e2) / np.min(v)), rtol=1e-12))


def _prior_grid(basis_prior, held: bool) -> tuple[float, ...]:
    """The factors on :data:`PRIORS`'s physical terms to try: :data:`BASIS_PRIOR_GRID` where
    ``basis_prior`` is ``"held_out"`` and flights can be held out, else the one factor."""
    if basis_prior == "held_out":
        return BASIS_PRIOR_GRID if held else (1.0,)
    return (float(basis_prior),)


def _held_out(X, H, y, noise, hyper: Hyper, b, sd, groups, predict=None, at=None):
    """Each group of labels predicted from the others by one load output's physical basis
    (coefficients integrated out, prior ``N(b, diag(sd²))``) and discrepancy GP (``hyper``,
    the labels' ``noise`` on the diagonal), the same hyperparameters throughout: the
    coefficients' posterior and the discrepancy conditioned anew without the group. Dense
    LAPACK on the host: one factorisation per group, and no program compiled per shape.
    ``predict`` names the groups to predict (default: every one); ``at`` = ``(X', H',
    groups')``, other rows of the same groups to predict there (what a filter reads of the
    group: every sample of its flights) instead of the group's own labels: the model that
    predicts a group is conditioned on the other groups' labels alone either way.

    Returns:
        A list of ``(mask, mean, variance, cov, latent, beta)``: the group's rows (of ``at``'s
        where given), their held-out
        mean and latent variance (the discrepancy's, its ``ν²`` and the coefficients'; not the
        labels' noise), the coefficients' posterior covariance without the group (P, P), the
        discrepancy's own latent variance alone (its posterior's, without ``ν²`` or the
        coefficients'), and the coefficients' posterior mean without the group (P,). A group
        whose complement has fewer than 8 labels is left out.
    """
    from scipy.linalg import cho_factor, cho_solve, solve_triangular

    s2, nu = float(hyper.variance), float(hyper.noise)
    Z = X / np.broadcast_to(np.asarray(hyper.lengthscale, float), X.shape[1:])

    def kern(A, B):
        d2 = np.sum(A * A, 1)[:, None] + np.sum(B * B, 1)[None, :] - 2 * A @ B.T
        return s2 * np.exp(-0.5 * np.maximum(d2, 0.0))

    Xa, Ha, ga = (X, H, groups) if at is None else at
    Za = Xa / np.broadcast_to(np.asarray(hyper.lengthscale, float), Xa.shape[1:])
    out = []
    for g in np.unique(groups) if predict is None else predict:
        tr, te = groups != g, ga == g
        if tr.sum() < 8:
            continue
        K = kern(Z[tr], Z[tr]) + np.diag(noise[tr] + nu)
        L = cho_factor(K, lower=True)
        KiH, Kiy = cho_solve(L, H[tr]), cho_solve(L, y[tr])
        beta, chol = posterior(H[tr], KiH, Kiy, b, sd)
        kq = kern(Za[te], Z[tr])
        mean = Ha[te] @ beta + kq @ (Kiy - KiH @ beta)
        v = solve_triangular(np.tril(L[0]), kq.T, lower=True)
        r = Ha[te] - kq @ KiH
        latent = np.maximum(s2 - np.sum(v * v, 0), 0)
        var = latent + nu + np.sum((r @ chol) ** 2, 1)
        out.append((te, mean, var, chol @ chol.T, latent, beta))
    return out


def _label_rows(prior: Surrogate, parts: list[Labels], max_labels: int, basis: str):
    """The labels of every flight as the GP's rows (:func:`training_rows`), checked, evenly
    thinned in time to ``max_labels``; each row's flight (its index in ``parts``) and time."""
    if basis not in ("physical", "regression"):
        raise ValueError(f"basis must be 'physical' or 'regression', got {basis!r}")
    if not parts:
        raise ValueError("correct needs labels of at least one flight")
    lab = Labels.concatenate(parts)
    if len(lab) < 8:
        raise ValueError(f"correct needs at least 8 labels, got {len(lab)}")
    X, Y, V = training_rows(prior, lab)
    t = np.asarray(lab.t, float)
    groups = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    for name, a in (("X", X), ("Y", Y), ("noise", V)):
        if not np.isfinite(a).all():
            raise ValueError(f"labels give non-finite GP {name} rows: check the labels' arrays")
    if max_labels is not None:
        keep = _thin(X.shape[0], int(max_labels))
        X, Y, V, groups, t = X[keep], Y[keep], V[keep], groups[keep], t[keep]
    return X, Y, V, groups, t


def _thin(n: int, most: int) -> np.ndarray:
    """At most ``most`` of ``n`` rows, evenly spread in order (all of them where ``n`` is not
    over ``most``)."""
    if n <= most:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, most).round().astype(int))


def _cases(d: ExactGP | InducingGP) -> int:
    """The labels a discrepancy was fitted on."""
    return d.n_cases if isinstance(d, InducingGP) else int(d.X.shape[0])


# Long by design: one loop over the load outputs whose exact and inducing-point branches share
# the prior, the calibration and the assembly of the result.
def _fit_explicit(X, Y, V, mu, m, physics: PhysicalBasis, fixed_rho, subset_size, max_steps,
                  seed, *, groups=None, Z=None, cal=None, Zh=None,
                  basis_prior="held_out", calibrate=True, prior_band=None,
                  spread=True):  # fmt: skip
    """The physical basis with integrated coefficients (:mod:`gpg.flight.basis`), per load
    output: ``β`` first by weighted least squares under its prior with the labels' noise, the
    discrepancy's hyperparameters on what is left, then ``β``'s posterior given that GP and
    the discrepancy conditioned on ``y − Hβ̄``. A fixed ``ρ`` (1, or 0 without the prior)
    moves the prior's mean into the targets instead of a column. With inducing inputs ``Z``
    the discrepancy is an inducing-point GP on every row, and the calibration reads the rows
    ``cal``; ``Zh``: the hyperparameters refined on every row through it. With ``groups``
    (two or more), the physical terms' prior is the one of ``basis_prior``'s candidates
    under which the worst-predicted group held out is predicted best, and (``calibrate``)
    the band widened by the held-out factor, solved with the prior's share of the band
    (``prior_band``: :func:`_prior_band` at the rows ``cal``) beside it; with ``spread`` the
    coefficients' covariance also holds their spread between the groups held out
    (:func:`_spread`); returned last: the candidates, the factor chosen per output, the
    candidates' held-out scores and the spread's standard deviations."""
    phys = _host.each_row(physics, X)  # (N, 6, T)
    n_out = N_LOADS
    rho = np.zeros(n_out) if fixed_rho is None else np.full(n_out, float(fixed_rho))
    kappa = np.zeros(n_out)
    betas, Gs, chols, deltas = [], [], [], []
    b, sd0 = _coefficient_prior(fixed_rho is None, m is not None)
    held = groups is not None and np.unique(groups).size >= 2
    grid = _prior_grid(basis_prior, held)
    held = held and (calibrate or len(grid) > 1)  # flights held out only for what reads them
    kc = np.arange(X.shape[0]) if cal is None else cal
    factors, scores, widths = np.ones(n_out), np.zeros((n_out, len(grid))), np.ones(n_out)
    shares = np.ones(n_out)
    coverage: list[list[float]] = []
    spreads: list[list[float] | None] = []
    for j in range(n_out):
        H = _basis_columns(mu if fixed_rho is None else None, m, phys, j)
        y = Y[:, j] - (0.0 if fixed_rho is None else float(fixed_rho)) * mu[:, j]
        # β first under its prior with the labels' own noise (plus the same 1e-3 floor as
        # the regression), so that the GP's hyperparameters see what the basis leaves; each
        # candidate prior of the physical terms scored on the flights held out in turn.
        w = 1.0 / (V[:, j] + 1e-3)
        best = None
        for i, f in enumerate(grid):
            sd = _scale_terms(sd0, f)
            beta0, _ = posterior(H, H * w[:, None], y * w, b, sd)
            hyper = _delta_hyper(X, y - H @ beta0, V[:, j], subset_size, max_steps, seed + j, Zh)
            c, nlpd, cover, q, J = (1.0, 0.0, [], 1.0, None)
            if held:
                share = None  # ρ² var_prior, ρ as first estimated, and the prior's domain
                if prior_band is not None:
                    r2 = (beta0[0] if fixed_rho is None else float(fixed_rho)) ** 2
                    share = (r2 * prior_band[0][:, j], prior_band[1])
                c, nlpd, cover, q, J = _held_out_scale(
                    X[kc], H[kc], y[kc], V[kc, j], hyper, b, sd, groups[kc], calibrate, share
                )
            scores[j, i] = nlpd
            if best is None or nlpd < best[0]:
                best = (nlpd, f, sd, hyper, c, cover, q, J if spread else None)
        _, factors[j], sd, hyper, c, cover, shares[j], J = best
        coverage.append(cover)
        if Z is None:
            both = ExactGP.fit(X, np.column_stack([H, y]), hyper=hyper, row_noise=V[:, j])
            alpha = np.asarray(both.alpha)
            beta, chol = posterior(H, alpha[:, :-1], alpha[:, -1], b, sd)
            gp = ExactGP.fit(X, (y - H @ beta)[:, None], hyper=hyper, row_noise=V[:, j])
            G = alpha[:, :-1]
        else:
            p = project(X, np.column_stack([H, y]), Z, hyper=hyper, row_noise=V[:, j])
            P, pw = H.shape[1], np.asarray(p.weights)
            beta, chol = posterior_gram(np.asarray(p.gram)[:P, :P], np.asarray(p.gram)[:P, P],
                                        b, sd)  # fmt: skip
            # δ on y − Hβ̄: its weights are linear in the targets
            gp = InducingGP(X=p.Z, weights=jnp.asarray((pw[:, P] - pw[:, :P] @ beta)[:, None]),
                            whiten=p.whiten, post=p.post, hyper=hyper,
                            output_scale=jnp.ones(1), n_cases=int(X.shape[0]))  # fmt: skip
            G = pw[:, :P]
        widths[j] = c
        c = c if calibrate else 1.0  # the choice above scored under c all the same
        deltas.append(gp.with_output_scale(jnp.full(1, c)))
        chol = chol * np.sqrt(c)
        if J is not None:  # the posterior's (calibrated) and the spread between the groups
            cov = chol @ chol.T + J
            chol = np.linalg.cholesky(0.5 * (cov + cov.T))
        spreads.append(None if J is None else np.sqrt(np.diag(J)).tolist())
        k = 0
        if fixed_rho is None:
            rho[j], k = beta[0], 1
        if m is not None:
            kappa[j], k = beta[k], k + 1
        betas.append(beta[k:])
        Gs.append(G)
        chols.append(chol)
    explicit = Explicit(
        physics=physics,
        beta=jnp.asarray(np.stack(betas)),
        G=jnp.asarray(np.stack(Gs)),
        cov_chol=jnp.asarray(np.stack(chols)),
        with_prior=fixed_rho is None,
        with_simple=m is not None,
    )
    choice = {"grid": list(grid), "factors": factors.tolist()}
    if held:
        choice["held_out_nlpd"] = scores.tolist()
        choice["held_out_coverage95"] = coverage
        choice["held_out_factor"] = widths.tolist()  # c per output, applied or not
        choice["prior_share"] = shares.tolist()  # q per output, applied or not
        choice["coefficient_spread"] = spreads  # per output: the spread's sd per column
    return rho, kappa, tuple(deltas), explicit, choice


def _coefficient_prior(with_prior: bool, with_simple: bool) -> tuple[np.ndarray, np.ndarray]:
    """The physical basis's coefficients' prior mean and standard deviations (:data:`PRIORS`,
    physical units), in the columns' order: the prior's mean (``ρ``, about 1), ``M``'s loads
    (``κ``), then :data:`TERMS`."""
    names = (["prior"] if with_prior else []) + (["simple"] if with_simple else []) + list(TERMS)
    sd = np.array([PRIORS[n] for n in names])
    return np.array([1.0 if n == "prior" else 0.0 for n in names]), sd


def _chosen_prior(sur: Surrogate, with_prior: bool, with_simple: bool) -> np.ndarray:
    """(6, P) the coefficients' prior standard deviations per load output as ``sur`` was
    corrected with them: :func:`_coefficient_prior`'s, the physical terms' times the factor
    ``basis_prior`` chose (1 for a model corrected before there was a choice)."""
    _, sd = _coefficient_prior(with_prior, with_simple)
    choice = sur.config.get("flight_correction", {}).get("basis_prior") or {}
    factors = np.asarray(choice.get("factors", np.ones(N_LOADS)), float)
    return _scale_terms(sd, factors[:, None])


def _scale_terms(sd: np.ndarray, factor) -> np.ndarray:
    """The prior standard deviations ``sd`` (P,) with the physical terms' (the last
    ``len(TERMS)``) times ``factor`` (a number, or (6, 1) for one per load output)."""
    terms = np.arange(sd.size) >= sd.size - len(TERMS)
    return np.where(terms, factor * sd, sd)


def _basis_columns(mu, m, phys, j: int) -> np.ndarray:
    """Load output ``j``'s columns ``H`` (N, P) at N rows: the prior's mean ``mu`` (N, 6; None:
    no column), ``M``'s loads ``m`` (N, 6; None: none) and the physical terms ``phys``
    (N, 6, T)."""
    cols = ([] if mu is None else [mu[:, j]]) + ([] if m is None else [m[:, j]])
    return np.column_stack([*cols, phys[:, j, :]])


def _regression(Y, V, mu, m, *, fit_rho: bool, use_prior: bool):
    """``ρ`` (6,) and ``κ`` (6,) by weighted least squares per load output, of the labels
    ``Y`` on the prior's mean ``μ`` (where ``fit_rho``; else ``ρ`` is 1, or 0 without the
    prior) and on ``M``'s own loads ``m`` (N, 6; None: no ``κ``); weights: the labels' noise plus a
    floor of 1e-3 (a label's variance is not known to better than that)."""
    rho = np.full(N_LOADS, 1.0 if use_prior else 0.0)
    kappa = np.zeros(N_LOADS)
    sw = np.sqrt(1.0 / (V + 1e-3))
    for j in range(N_LOADS):
        cols = ([mu[:, j]] if fit_rho else []) + ([m[:, j]] if m is not None else [])
        if not cols:
            continue
        target = Y[:, j] - (0.0 if fit_rho else rho[j] * mu[:, j])
        A = np.stack(cols, 1) * sw[:, j, None]
        coef, *_ = np.linalg.lstsq(A, target * sw[:, j], rcond=None)
        if fit_rho:
            rho[j], coef = coef[0], coef[1:]
        if m is not None:
            kappa[j] = coef[0]
    return rho, kappa


def _fit_delta(X, r, noise, subset_size: int, max_steps: int, seed: int, Z=None, Zh=None):
    """One discrepancy: its hyperparameters (:func:`_delta_hyper`, refined through ``Zh`` on
    every row where given), then the exact GP, or the inducing-point GP through ``Z`` on
    every row."""
    hyper = _delta_hyper(X, r, noise, subset_size, max_steps, seed, Zh)
    if Z is None:
        gp = ExactGP.fit(X, r[:, None], hyper=hyper, row_noise=noise)
    else:
        gp = InducingGP.fit(X, r, Z, hyper=hyper, row_noise=noise)
    # The fitted σ is each discrepancy's own amplitude: no second, closed-form one.
    return gp.with_output_scale(jnp.ones(1))


def _delta_hyper(X, r, noise, subset_size: int, max_steps: int, seed: int, Z=None) -> Hyper:
    """A discrepancy's hyperparameters by marginal likelihood on ``subset_size`` rows drawn
    at random (:func:`gpg.gp.fit.fit_hyperparameters`), then, with inducing inputs ``Z``
    (``hyperparameters="all"``), refined on every row by the collapsed bound
    (:func:`gpg.gp.inducing.fit_collapsed`); lengthscales kept in range."""
    var = float(max(np.var(r), 1e-6))
    init = Hyper(variance=var, lengthscale=np.full(X.shape[1], 0.7), noise=1e-2 * var)
    opts = FitOptions(subset_size=subset_size, seed=seed, max_steps=max_steps, on_failure="ignore")
    fit = fit_hyperparameters(X, r[:, None], init=init, options=opts, row_noise=noise)
    h = _in_range(fit.hyper, init)
    if Z is not None and X.shape[0] > subset_size:
        h = _in_range(fit_collapsed(X, r, Z, init=h, row_noise=noise, max_steps=max_steps)[0], h)
    return h


def _in_range(h: Hyper, fallback: Hyper) -> Hyper:
    """``h`` with its lengthscales clipped to range, or ``fallback`` where σ or ``ν²`` is not
    a positive number."""
    # An input the discrepancy does not vary along drives its lengthscale toward infinity: at
    # LENGTHSCALE_MAX (normalised inputs span 2) the kernel is already flat along it.
    ls = np.nan_to_num(np.asarray(h.lengthscale), nan=LENGTHSCALE_MAX, posinf=LENGTHSCALE_MAX)
    ls = np.clip(ls, LENGTHSCALE_MIN, LENGTHSCALE_MAX)
    ok = all(np.isfinite(float(v)) and float(v) > 0 for v in (h.variance, h.noise))
    return Hyper(variance=h.variance, lengthscale=ls, noise=h.noise) if ok else fallback


@float64
def adapt(
    sur: Surrogate,
    *,
    inducing: int = 48,
    tau: float | Sequence[float] = 5.0,
    variance: float | Sequence[float] | None = None,
    lengthscale: float | None = None,
    inputs: ArrayLike | None = None,
    t0: float = 0.0,
    seed: int = 0,
    band: str = "added",
) -> Surrogate:
    """``sur`` (corrected or not) with an online term ready to be updated (:func:`update`).

    Args:
        sur: the model to adapt.
        inducing: ``m``, the inducing inputs (fixed cost ``O(m²)`` per label and output).
        tau: s, the forgetting time constant (what was learnt ``τ`` seconds ago weighs
            ``1/e``), one for every load output or six (:attr:`gpg.flight.Forgetting.tau`
            fitted per output).
        variance: ``η``'s signal variance (normalised units), one for every load output or
            six (:attr:`gpg.flight.Forgetting.variance`, fitted); default: each ``δ``'s own,
            else 0.1 (a tenth of the data's variance).
        lengthscale: ``η``'s lengthscale (normalised inputs); default: each ``δ``'s own, else 1.
        inputs: (n, D) normalised inputs to place ``Z`` among (k-means); default: ``δ``'s
            training inputs, else the prior box's Latin hypercube.
        t0: s, the time of the first update.
        seed: k-means' seed.
        band: how ``η``'s variance enters the loads' band: ``"added"`` to the offline
            model's ``b`` (the band only ever widens), or ``"shared"``: ``η``'s prior is taken
            as a share of ``b``, the band ``max(b − ψᵀψ, 0) + ψᵀΣψ``, which starts as ``b``
            and narrows where the flight has told ``η`` (:class:`Online`'s ``shared``).

    Returns:
        A :class:`~gpg.Surrogate` whose :class:`Corrected` model carries the online term.

    Raises:
        ValueError: ``inducing`` under 1, ``tau`` or ``variance`` neither one nor six
            positive numbers, ``band`` neither ``"added"`` nor ``"shared"``, ``inputs``
            not (n, D), or a model that already tracks its coefficients
            (:func:`gpg.flight.track`).
    """
    if band not in ("added", "shared"):
        raise ValueError(f"band must be 'added' or 'shared', got {band!r}")
    if inducing < 1:
        raise ValueError(f"inducing must be >= 1, got {inducing}")
    tau = _one_or_six(tau, "tau")
    variance = None if variance is None else _one_or_six(variance, "variance")
    m = sur.model if isinstance(sur.model, Corrected) else None
    if m is None:
        ones = jnp.ones(sur.model.n_outputs)
        m = Corrected(prior=sur.model, scale=ones, delta=())
        sur = dataclasses.replace(sur, model=m, model_name=f"{sur.model_name}+flight")
    if m.tracker is not None:
        raise ValueError(
            "adapt: the model already follows its basis's coefficients online "
            "(gpg.flight.track); adapt the model before tracking, not both"
        )
    Z = _inducing_inputs(m, inducing, inputs, seed)
    k, d = Z.shape
    if m.delta:
        var = np.array([float(g.hyper.variance) for g in m.delta])
        ls = np.stack([np.broadcast_to(np.asarray(g.hyper.lengthscale), (d,)) for g in m.delta])
        nu = np.array([float(g.hyper.noise) for g in m.delta])
    else:
        var, ls, nu = np.full(N_LOADS, 0.1), np.ones((N_LOADS, d)), np.full(N_LOADS, 1e-3)
    if variance is not None:
        var = np.broadcast_to(variance, (N_LOADS,)).copy()
    if lengthscale is not None:
        ls = np.full((N_LOADS, d), float(lengthscale))
    whiten = _whitening(Z, var, ls)
    online = Online(
        Z=jnp.asarray(Z),
        whiten=jnp.asarray(whiten),
        variance=jnp.asarray(var),
        lengthscale=jnp.asarray(ls),
        noise=jnp.asarray(nu),
        mean=jnp.zeros((N_LOADS, k)),
        cov=jnp.broadcast_to(jnp.eye(k), (N_LOADS, k, k)),
        t=jnp.asarray(t0, float),  # not weak: else a step's second call compiles it again
        tau=jnp.asarray(tau, float),
        shared=band == "shared",
    )
    return dataclasses.replace(
        sur, model=eqx.tree_at(lambda c: c.online, m, online, is_leaf=lambda x: x is None)
    )


@highest
def update(
    sur: Surrogate,
    t: Float[ArrayLike, ""],
    rpm: Float[ArrayLike, " 4"],
    euler: Float[ArrayLike, " 3"],
    v_air: Float[ArrayLike, " 3"],
    force: Float[ArrayLike, " 3"],
    torque: Float[ArrayLike, " 3"],
    force_var: Float[ArrayLike, " 3"],
    torque_var: Float[ArrayLike, " 3"],
) -> Surrogate:
    """``sur`` (from :func:`adapt` or :func:`gpg.flight.track`) after one labelled sample at
    time ``t``.

    The online state (``η``'s weights, or the tracked coefficients' drift) is relaxed since
    its last update and conditioned on the label's residual against the offline model (prior,
    ``κ``, the basis and ``δ``). Pure and jittable: a ``lax.scan`` over labels carries the
    surrogate (:meth:`gpg.flight.Labels.columns` gives its ``xs``); from Python,
    :func:`update_jit` or :func:`online_step`.

    Args:
        sur: a surrogate prepared by :func:`adapt` or :func:`gpg.flight.track`.
        t: the label's time, s.
        rpm: (4,) rotor speeds, rpm.
        euler: (3,) (yaw, pitch, roll), rad.
        v_air: (3,) air velocity, world, m/s.
        force: (3,) measured aerodynamic force, world, N (as :class:`~gpg.flight.Labels`).
        torque: (3,) measured aerodynamic torque, world, N·m.
        force_var: (3,) the force's noise variances.
        torque_var: (3,) the torque's noise variances.

    Returns:
        The surrogate with its online state updated.

    Raises:
        ValueError: ``sur`` carries no online state (not from :func:`adapt` or ``track``).
    """
    state = online_state(sur, "update")
    args = (jnp.asarray(a) for a in (rpm, euler, v_air, force, torque, force_var, torque_var))
    return with_online(sur, advance(sur, state, t, *args))


update_jit = jax.jit(update)


def online_state(sur: Surrogate, who: str = "online_state") -> Online | eqx.Module:
    """The online state of an adapted or tracked surrogate.

    Args:
        sur: a surrogate prepared by :func:`adapt` or :func:`gpg.flight.track`.
        who: the caller's name, for the error.

    Returns:
        Its :class:`Online` term or its :class:`~gpg.flight.tracking.Tracker`.

    Raises:
        ValueError: ``sur`` carries neither.
    """
    m = sur.model
    if isinstance(m, Corrected):
        if m.online is not None:
            return m.online
        if m.tracker is not None:
            return m.tracker
    raise ValueError(f"{who} needs a surrogate prepared by gpg.flight.adapt or gpg.flight.track")


def advance(sur: Surrogate, state, t, rpm, euler, v_air, force, torque, force_var, torque_var):
    """The online ``state`` (:func:`online_state`'s kind) after one label: relaxed to ``t``,
    then conditioned on the label's residual against ``sur``'s offline mean (its own online
    part is not read). Pure: the step of :func:`update`, :func:`online_step` and
    :func:`gpg.flight.prequential`."""
    m = sur.model
    label = (force, torque, force_var, torque_var)
    state = state.relaxed(t)

    def rows(g):
        x, y, r = gp_rows(sur, rpm, euler, v_air + g, *label)
        prior_mean, cols = m.prior.mean_one(x), m._columns(x)
        return x, (prior_mean, cols), y - m._offline_mean(x, prior_mean, cols)[:N_LOADS], r

    if isinstance(state, Online):
        x, _, resid, r = rows(0.0)
        return state.measured(x, resid, r)
    if getattr(state, "needs_band", False):  # a gpg.flight.Bank: its members are scored
        # under the offline band at the label
        x, y, r = gp_rows(sur, rpm, euler, v_air, *label)
        mean, band = offline_model(m).offline_moments(x)
        return state.measured(x, y - mean[:N_LOADS], r, band)

    def columns(st, x, at):  # at: the prior's mean and the basis's columns at x (rows)
        with_state = eqx.tree_at(lambda c: c.tracker, m, st, is_leaf=lambda a: a is None)
        return with_state._tracker_columns(x, *at)

    def wind_rows(g):
        x, at, resid, r = rows(g)
        # The wind's innovation counts what δ does not know at the label (the tracked band
        # has it): without it the wind state takes δ's errors for wind. The coefficients'
        # gain leaves it out, as their drift was fitted.
        return resid, r + m._delta_latent_at(x), columns(state, x, at)

    g = 0.0
    if getattr(state, "wind_mean", None) is not None:
        # The wind first, its residual's band the coefficients' own; then the coefficients
        # at the air velocity it implies.
        state, g = state.wind_measured(wind_rows)
    x, at, resid, r = rows(g)
    return state.measured(columns(state, x, at), resid, r)


def offline_model(m: Corrected) -> Corrected:
    """``m`` without its online parts (``η``, the tracked drift): what the residuals of online
    updates are taken against.

    Args:
        m: a corrected model.

    Returns:
        The same model with ``online`` and ``tracker`` None.
    """
    return eqx.tree_at(lambda c: (c.online, c.tracker), m, (None, None),
                       is_leaf=lambda a: a is None)  # fmt: skip


def with_online(sur: Surrogate, online: Online | eqx.Module) -> Surrogate:
    """``sur`` (from :func:`adapt` or :func:`gpg.flight.track`) carrying the online state
    ``online``.

    Puts back a state that :func:`online_step` advanced, for predictions.

    Args:
        sur: a surrogate prepared by :func:`adapt` or :func:`gpg.flight.track`.
        online: the state to carry, of the kind ``sur`` has.

    Returns:
        The surrogate with ``online`` in place of its own.
    """
    none = lambda a: a is None  # noqa: E731
    if not hasattr(online, "wind_mean"):  # an Online or a gpg.flight.Bank, not a Tracker
        return eqx.tree_at(lambda s: s.model.online, sur, online, is_leaf=none)
    return eqx.tree_at(lambda s: s.model.tracker, sur, online, is_leaf=none)


def online_step(
    sur: Surrogate, *, stack: bool = True, donate: bool = False
) -> Callable[..., Online | eqx.Module]:
    """A compiled step for loops that update once a step from Python.

    ``step(state, t, rpm, euler, v_air, force, torque, force_var, torque_var) -> state`` is
    :func:`update` on the online state alone (:class:`Online` or the tracked coefficients').
    The offline model's arrays are flattened once here (the mean's only, the
    discrepancies' variance where the state has a wind, the whole band for a
    :class:`gpg.flight.Bank`), not at every call, and only the
    small online state goes in and out; :func:`with_online` puts a state back
    into the surrogate for predictions. Of the state, only the arrays an update moves come
    back from the compiled program (a filter's weights and covariance, not its inducing
    inputs or their factor, which the new state shares with the old): found by tracing the
    step once, at its first call.

    Args:
        sur: a surrogate prepared by :func:`adapt` or :func:`gpg.flight.track` (its online
            state is the start state only).
        stack: read the inducing-point discrepancies ``δ`` through one
            :class:`~gpg.gp.inducing.StackedInducing` (:meth:`Corrected.stacked`), where
            they can be; False reads them one by one, as :func:`update` does. The same step
            to rounding.
        donate: write each new state over the arrays of the one this step returned before
            (JAX's buffer donation), not into new ones: a state this step returned is then
            used up when passed back in, so keep only the newest. A state from elsewhere
            (:func:`online_state`, a checkpoint) is copied before its first step, never
            used up. For a large state (a bank's), in loops that keep no earlier states.

    Returns:
        The step function.

    Raises:
        ValueError: ``sur`` carries no online state; at a call, a ``state`` of another
            structure than ``sur``'s.
    """
    state = online_state(sur, "online_step")
    # A wind state's update reads the discrepancies' variance at the label (advance)
    wind = getattr(state, "wind_mean", None) is not None
    view = offline_model(sur.model)
    if getattr(state, "needs_band", False):  # a Bank scores under the offline band: δ's
        view = view.variance_views()  # variance in one triangle each
    else:
        view = view.mean_view(wind)
    if stack:  # six kernel rows in one program, not six: fewer, larger operations a step
        view = view.stacked()
    offline = eqx.tree_at(lambda s: s.model, sur, view)
    leaves, treedef = jax.tree_util.tree_flatten(offline)
    leaves = tuple(leaves)
    kind = jax.tree_util.tree_structure(state)
    built: dict[str, Any] = {}  # the moving leaves and their program, at the first call

    def step(online, t, rpm, euler, v_air, force, torque, force_var, torque_var):
        label = (t, rpm, euler, v_air, force, torque, force_var, torque_var)
        flat, got = jax.tree_util.tree_flatten(online)
        if got != kind:
            raise ValueError("online_step: the state passed to the step is not of the "
                             f"structure of {type(state).__name__}, which the surrogate "
                             "carries")  # fmt: skip
        if not built:
            built["moving"] = _moving_leaves(treedef, leaves, kind, flat, label)
            built["fn"] = _online_step_fn(treedef, kind, built["moving"], donate)
            built["last"] = ()
        moving = built["moving"]
        fixed = tuple(a for i, a in enumerate(flat) if i not in moving)
        dyn = tuple(flat[i] for i in moving)
        if donate and not _same_arrays(dyn, built["last"]):  # not this step's: copy
            dyn = tuple(jnp.array(a, copy=True) for a in dyn)
        new = built["fn"](leaves, fixed, dyn, *label)
        built["last"] = new if donate else ()
        out = list(flat)
        for i, a in zip(moving, new, strict=True):
            out[i] = a
        return jax.tree_util.tree_unflatten(kind, out)

    return step


def _same_arrays(a: tuple, b: tuple) -> bool:
    return len(a) == len(b) and all(x is y for x, y in zip(a, b, strict=True))


def _moving_leaves(treedef, leaves, kind, flat, label) -> tuple[int, ...]:
    """The positions of the state's leaves that :func:`advance` does not hand back as they
    came in (traced once, not compiled)."""

    def full(leaves, flat, *label):
        sur = jax.tree_util.tree_unflatten(treedef, leaves)
        online = jax.tree_util.tree_unflatten(kind, flat)
        return jax.tree_util.tree_leaves(highest(advance)(sur, online, *label))

    jaxpr = jax.make_jaxpr(full)(leaves, flat, *label).jaxpr
    ins = jaxpr.invars[len(leaves) : len(leaves) + len(flat)]
    outs = jaxpr.outvars
    return tuple(i for i in range(len(flat)) if outs[i] is not ins[i])


@lru_cache(maxsize=16)
def _online_step_fn(treedef, kind, moving: tuple[int, ...], donate: bool):
    def fn(leaves, fixed, dyn, t, rpm, euler, v_air, force, torque, force_var, torque_var):
        sur = jax.tree_util.tree_unflatten(treedef, leaves)
        flat, f, d = [], iter(fixed), iter(dyn)
        for i in range(kind.num_leaves):
            flat.append(next(d) if i in moving else next(f))
        online = jax.tree_util.tree_unflatten(kind, flat)
        new = advance(sur, online, t, rpm, euler, v_air, force, torque, force_var, torque_var)
        out = jax.tree_util.tree_leaves(new)
        return tuple(out[i] for i in moving)

    return jax.jit(highest(fn), donate_argnums=(2,) if donate else ())


def _one_or_six(values, name: str) -> np.ndarray:
    """:func:`adapt`'s ``tau`` or ``variance`` (``name``): one or six positive numbers."""
    v = np.asarray(values, float)
    if v.shape not in ((), (N_LOADS,)) or not np.all(v > 0):
        raise ValueError(f"{name} must be one or {N_LOADS} positive numbers, got {v.tolist()}")
    return v


def _inducing_inputs(m: Corrected, inducing: int, inputs, seed: int) -> np.ndarray:
    """``Z``: k-means centres of ``inputs`` (default: ``δ``'s training inputs, else the prior
    box's Latin hypercube), at most ``inducing`` of them."""
    from scipy.cluster.vq import kmeans2
    from scipy.stats import qmc

    d = m.n_inputs
    if inputs is None:
        if m.delta:
            inputs = np.asarray(m.delta[0].X)
        else:
            inputs = 2 * qmc.LatinHypercube(d=d, seed=seed).random(max(4 * inducing, 256)) - 1
    pts = np.asarray(inputs, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != d:
        raise ValueError(f"inputs must be (n, {d}) normalised inputs, got {pts.shape}")
    k = min(inducing, len(np.unique(pts, axis=0)))
    Z, _ = kmeans2(pts, k, seed=seed, minit="++")
    return Z


def _whitening(Z: np.ndarray, var: np.ndarray, ls: np.ndarray) -> np.ndarray:
    """``L⁻¹`` of each output's ``K_ZZ`` (6, m, m), a little jitter on the diagonal."""
    out = []
    for j in range(N_LOADS):
        K = np.array(_cross_jit(Z, Z, var[j], ls[j]))
        K[np.diag_indices_from(K)] += 1e-8 * var[j]
        out.append(np.linalg.solve(np.linalg.cholesky(K), np.eye(Z.shape[0])))
    return np.stack(out)


def _cross(A: Float[Array, "P D"], B: Float[Array, "Q D"], var, ls) -> Float[Array, "P Q"]:
    """The RBF kernel (:func:`gpg.gp.kernels.rbf`) between every row of ``A`` and of ``B``."""
    return jax.vmap(lambda a: jax.vmap(lambda b: kernels.rbf(a, b, var, ls))(B))(A)


# On the host (a factor's set-up): one compiled program for the six outputs, where the nested
# vmap outside a trace compiled each of its operations on its own.
_cross_jit = jax.jit(_cross)
