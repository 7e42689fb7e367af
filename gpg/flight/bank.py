"""A bank of inducing-point terms of different memories, mixed by their predictions made ahead.

One forgetting time cannot serve a steady new wind and a gust: fitted on steady training winds
the term keeps what it learnt for minutes, and a wind that turns within seconds leaves it
behind; fitted to follow, it forgets what a steady wind keeps telling it. :func:`adapt_bank`
flies ``K`` terms ``η_k`` (:func:`gpg.flight.adapt`'s, each with its own ``τ_k`` and prior
variance, e.g. the :class:`gpg.flight.Forgetting` fits scored one step and ``L`` samples
ahead) side by side on the same labels, and predicts with their mixture, each load output
``j`` weighted by how well member ``k`` has lately predicted that output's labels.

The weights are Bayesian model averaging with forgetting: ``log w_kj`` adds each label's log
density under member ``k``'s band (the offline model's ``b`` with ``η_k`` in it, as
:func:`gpg.flight.adapt`'s ``band`` composes them, plus the label's noise) and decays by
``e^{−Δt/τ_w}`` between labels. A label is scored by member ``k``'s prediction from the
labels ``L`` and more samples before it, not from the one just before: labels whose errors
correlate from one sample to the next (a velocity differentiated over a window) reward the
member that follows their noise one step ahead, and a mixture weighted by one-step densities
picks the shortest memory everywhere. Each member therefore runs twice: as it is, for the
predictions, and ``L`` labels behind (its updates waiting in a ring of the last ``L``
labels), for the scores. Fixed cost and memory: ``2K`` filters of ``6 m²`` and ``L`` labels.

The mixture's mean per output is ``Σ_k w_k η̄_k``; its band ``Σ_k w_k (band_k + η̄_k²) −
(Σ_k w_k η̄_k)²``, each member's band composed with the offline one as its own term's is
(the moments of the mixture, exact).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from gpg._precision import highest
from gpg.flight import correction as fc
from gpg.surrogate import Surrogate

__all__ = ["Bank", "adapt_bank"]

N_LOADS = 6


class Bank(eqx.Module):
    """A bank of online terms mixed by their predictions ``ahead`` labels ahead (module
    docstring): a :class:`gpg.flight.Corrected` model's online part, in place of one
    :class:`gpg.flight.Online`.

    Attributes:
        members: the ``K`` terms as one :class:`gpg.flight.Online` whose arrays carry a
            leading axis of ``K`` (each its own ``τ_k``, prior variance and state).
        lagged: the same terms, each updated with the labels up to ``ahead`` before the
            newest: what scores them.
        ring_x: (L, D) the last ``L`` labels' normalised inputs, waiting for ``lagged``.
        ring_y: (L, 6) their residuals against the offline model.
        ring_r: (L, 6) their noise variances.
        ring_t: (L,) their times (s).
        ring_live: (L,) which ring slots hold a label.
        count: the labels seen.
        log_weight: (K, 6) each member's log weight per load output (up to a constant).
        weight_tau: s, ``τ_w``, the weights' forgetting time.
        ahead: ``L``, the labels ahead each member is scored from.
    """

    members: fc.Online
    lagged: fc.Online
    ring_x: Float[Array, "L D"]
    ring_y: Float[Array, "L 6"]
    ring_r: Float[Array, "L 6"]
    ring_t: Float[Array, " L"]
    ring_live: Bool[Array, " L"]
    count: Int[Array, ""]
    log_weight: Float[Array, "K 6"]
    weight_tau: Float[Array, ""]
    ahead: int = eqx.field(static=True, default=10)
    # gpg.flight.correction.advance passes the offline band at each label to `measured`
    needs_band: ClassVar[bool] = True

    @property
    def shared(self) -> bool:
        """Whether the members' prior is a share of the offline band (their ``band``)."""
        return bool(self.members.shared)

    @property
    def size(self) -> int:
        """``K``, the members."""
        return int(self.log_weight.shape[0])

    @property
    def t(self) -> Float[Array, ""]:
        """The time of the last update (s)."""
        return self.members.t[0]

    @property
    def n_parts(self) -> int:
        """The entries :meth:`latent` adds to the corrected model's latent variance."""
        return N_LOADS * (3 * self.size + 1)

    def describe(self) -> dict[str, Any]:
        """Plain values for a checkpoint's metadata.

        Returns:
            Each member's :meth:`gpg.flight.Online.describe`, ``ahead``, ``τ_w`` and the
            current weights.
        """
        k = self.size
        one = [jax.tree.map(lambda a, i=i: a[i], self.members).describe() for i in range(k)]
        return {"bank": one, "ahead": self.ahead, "weight_tau": float(self.weight_tau),
                "weights": np.asarray(self.weights()).tolist()}  # fmt: skip

    def weights(self) -> Float[Array, "K 6"]:
        """Each member's weight per load output, normalised over the members.

        Returns:
            (K, 6) the weights (each column sums to one).
        """
        return jax.nn.softmax(self.log_weight, axis=0)

    @highest
    def latent(self, x: Float[Array, " D"]) -> tuple[Float[Array, " 6"], Float[Array, " P"]]:
        """The mixture's mean at ``x`` and its parts of the corrected model's latent
        variance, which :meth:`band` composes with the offline band.

        Args:
            x: (D,) a normalised input.

        Returns:
            The (6,) mean ``Σ_k w_k η̄_k`` and the (:attr:`n_parts`,) parts: the weights,
            each member's ``ψᵀΣψ`` and ``ψᵀψ`` (K × 6 each), then the spread of the members'
            means, ``Σ_k w_k η̄_k² − (Σ_k w_k η̄_k)²``.
        """
        mean, var, prior = jax.vmap(lambda o: o.moments(o.features(x)))(self.members)
        w = self.weights()
        mix = jnp.sum(w * mean, 0)
        spread = jnp.maximum(jnp.sum(w * mean**2, 0) - mix**2, 0.0)
        return mix, jnp.concatenate([w.ravel(), var.ravel(), prior.ravel(), spread])

    def band(
        self, offline: Float[Array, "*Q 6"], parts: Float[Array, "*Q P"]
    ) -> Float[Array, "*Q 6"]:
        """The loads' band of the mixture from the offline model's ``b`` and :meth:`latent`'s
        parts: ``Σ_k w_k band_k`` plus the spread of the members' means, ``band_k`` composed as
        each member's own term composes it (:meth:`gpg.flight.Online.band`).

        Args:
            offline: (..., 6) ``b``, the offline model's predictive variance of the loads.
            parts: (..., :attr:`n_parts`) the parts.

        Returns:
            (..., 6) the loads' predictive variance (normalised units).
        """
        k = self.size
        lead = parts.shape[:-1]
        w, var, prior = (parts[..., i * k * N_LOADS : (i + 1) * k * N_LOADS].reshape(
            (*lead, k, N_LOADS)) for i in range(3))  # fmt: skip
        member = _member_band(offline[..., None, :], var, prior, self.shared)
        return jnp.sum(w * member, -2) + jnp.maximum(parts[..., -N_LOADS:], 0.0)

    @highest
    def relaxed(self, t: Float[ArrayLike, ""]) -> Bank:
        """The bank at time ``t``: each member relaxed toward its prior
        (:meth:`gpg.flight.Online.relaxed`), the log weights decayed by ``e^{−Δt/τ_w}``.

        Args:
            t: the time (s) to relax to; before the last update counts as ``Δt = 0``.

        Returns:
            The relaxed bank (``lagged`` relaxes as its waiting labels are applied).
        """
        dt = jnp.maximum(jnp.asarray(t, self.t.dtype) - self.t, 0.0)
        members = jax.vmap(lambda o: o.relaxed(t))(self.members)
        decay = jnp.exp(-dt / self.weight_tau)
        return eqx.tree_at(lambda b: (b.members, b.log_weight), self,
                           (members, decay * self.log_weight))  # fmt: skip

    @highest
    def measured(
        self,
        x: Float[Array, " D"],
        y: Float[Array, " 6"],
        r: Float[Array, " 6"],
        offline: Float[Array, " 6"],
    ) -> Bank:
        """One label: the label ``L`` before applied to ``lagged``, each member scored by
        ``lagged``'s prediction of this label (its log weight adds the log density), then
        every member updated (:meth:`gpg.flight.Online.measured`). Call :meth:`relaxed`
        first, as :func:`gpg.flight.update` does.

        Args:
            x: (D,) the label's normalised input.
            y: (6,) its residual against the offline model, normalised, in the GP's frame.
            r: (6,) the residual's noise variance (normalised units).
            offline: (6,) ``b``, the offline model's predictive variance of the loads at
                ``x`` (each member's band is composed with it).

        Returns:
            The bank conditioned on the label.
        """
        t = self.t
        j = self.count % self.ahead
        live = self.ring_live[j]

        def apply(o):  # the waiting label, to the members that are L behind
            done = o.relaxed(self.ring_t[j]).measured(self.ring_x[j], self.ring_y[j],
                                                      self.ring_r[j])  # fmt: skip
            # only what an update moves: the rest stays the same array (online_step then
            # passes it in and leaves it out of what the step returns)
            new, old = (done.mean, done.cov, done.t), (o.mean, o.cov, o.t)
            moved = tuple(jnp.where(live, a, b) for a, b in zip(new, old, strict=True))
            return eqx.tree_at(lambda u: (u.mean, u.cov, u.t), o, moved)

        lagged = jax.vmap(apply)(self.lagged)

        def score(o):
            o = o.relaxed(t)
            mean, var, prior = o.moments(o.features(x))
            s = _member_band(offline, var, prior, self.shared) + r
            return -0.5 * (jnp.log(2 * jnp.pi * s) + (y - mean) ** 2 / s)

        log_weight = self.log_weight + jax.vmap(score)(lagged)
        log_weight = log_weight - jnp.max(log_weight, 0)  # a constant per output: kept small
        members = jax.vmap(lambda o: o.measured(x, y, r))(self.members)
        return dataclasses.replace(
            self,
            members=members,
            lagged=lagged,
            ring_x=self.ring_x.at[j].set(x),
            ring_y=self.ring_y.at[j].set(y),
            ring_r=self.ring_r.at[j].set(r),
            ring_t=self.ring_t.at[j].set(t),
            ring_live=self.ring_live.at[j].set(True),
            count=self.count + 1,
            log_weight=log_weight,
        )


def _member_band(offline, var, prior, shared: bool):
    """Each member's band from the offline one (:meth:`gpg.flight.Online.band`)."""
    var = jnp.maximum(var, 0.0)
    if not shared:
        return offline + var
    return jnp.maximum(offline - jnp.maximum(prior, 0.0), 0.0) + var


def adapt_bank(
    sur: Surrogate,
    members: Sequence,
    *,
    ahead: int = 10,
    weight_tau: float = 2.0,
    inducing: int = 48,
    t0: float = 0.0,
    seed: int = 0,
    band: str = "shared",
) -> Surrogate:
    """``sur`` with a :class:`Bank` of online terms ready to be updated
    (:func:`gpg.flight.update`, :func:`gpg.flight.online_step`, :func:`gpg.flight.prequential`
    take it as they take :func:`gpg.flight.adapt`'s term).

    Args:
        sur: the model to adapt (corrected by flights, or not).
        members: ``K`` memories: each a :class:`gpg.flight.Forgetting` (its ``tau`` and
            ``variance``) or a pair ``(tau, variance)`` as :func:`gpg.flight.adapt` takes
            them (``variance`` None: each discrepancy's own).
        ahead: ``L``, the labels ahead each member's score is predicted from (past the
            labels' correlated noise; 1: one step).
        weight_tau: s, ``τ_w``, how long a member's past scores count (its log weight decays
            by ``e^{−Δt/τ_w}``).
        inducing: ``m``, each term's inducing inputs (the same for every member).
        t0: s, the time of the first update.
        seed: the inducing inputs' k-means seed.
        band: ``"shared"`` or ``"added"``, as :func:`gpg.flight.adapt` takes it.

    Returns:
        A :class:`~gpg.Surrogate` whose corrected model carries the bank as its online term.

    Raises:
        ValueError: no member, a member neither a ``Forgetting`` nor a pair, a
            ``Forgetting`` fitted for another ``band`` or number of inducing inputs (as
            placed: ``inducing``, or fewer on few data), ``ahead`` not a
            whole number >= 1, ``weight_tau`` not positive, or what :func:`gpg.flight.adapt`
            refuses (a bad ``tau``, ``variance``, ``inducing`` or ``band``).
    """
    if isinstance(ahead, bool) or int(ahead) != ahead or ahead < 1:
        raise ValueError(f"adapt_bank: ahead must be a whole number >= 1, got {ahead!r}")
    if not (np.isfinite(weight_tau) and weight_tau > 0):
        raise ValueError(f"adapt_bank: weight_tau must be a positive time (s), got {weight_tau}")
    pairs = [_pair(mb, i, band) for i, mb in enumerate(members)]
    if not pairs:
        raise ValueError("adapt_bank: members is empty; give at least one (tau, variance)")
    terms = [fc.adapt(sur, inducing=inducing, tau=tau, variance=var, t0=t0, seed=seed,
                      band=band) for tau, var in pairs]  # fmt: skip
    ons = [a.model.online for a in terms]
    for i, mb in enumerate(members):  # a fit's τ and prior are for its own inducing inputs
        if hasattr(mb, "inducing") and mb.inducing != ons[0].Z.shape[0]:
            raise ValueError(f"adapt_bank: members[{i}] was fitted with {mb.inducing} inducing "
                             f"inputs, the bank places {ons[0].Z.shape[0]}")  # fmt: skip
    # τ may be one number or six per member: stack them at one shape, one per weight
    ons = [eqx.tree_at(lambda o: o.tau, o, o.tau_per_weight()) for o in ons]
    stack = jax.tree.map(lambda *a: jnp.stack(a), *ons)
    k, L, d = len(ons), int(ahead), int(ons[0].Z.shape[1])
    dtype = ons[0].mean.dtype
    bank = Bank(
        members=stack,
        lagged=stack,
        ring_x=jnp.zeros((L, d), dtype),
        ring_y=jnp.zeros((L, N_LOADS), dtype),
        ring_r=jnp.ones((L, N_LOADS), dtype),
        ring_t=jnp.full((L,), float(t0), dtype),
        ring_live=jnp.zeros(L, bool),
        count=jnp.asarray(0, jnp.int32),
        log_weight=jnp.zeros((k, N_LOADS), dtype),
        weight_tau=jnp.asarray(float(weight_tau), dtype),
        ahead=L,
    )
    return fc.with_online(terms[0], bank)


def _pair(member, i: int, band: str):
    """``(tau, variance)`` of :func:`adapt_bank`'s member ``i``; a fit for another band is
    refused (its ``τ`` and prior are that band's term's)."""
    if hasattr(member, "tau") and hasattr(member, "variance"):  # a Forgetting
        if member.band != band:
            raise ValueError(f"adapt_bank: members[{i}] was fitted with band={member.band!r}, "
                             f"the bank runs band={band!r}")  # fmt: skip
        return member.tau, member.variance
    if isinstance(member, tuple | list) and len(member) == 2:
        return member[0], member[1]
    raise ValueError(
        f"adapt_bank: members[{i}] must be a gpg.flight.Forgetting or a (tau, variance) pair, "
        f"got {type(member).__name__}"
    )
