"""The inducing-point term's forgetting time and signal variance, fitted on training flights.

:func:`gpg.flight.adapt`'s term ``η`` (whitened weights on ``m`` inducing inputs, one set per
load output) forgets at the rate ``1/τ``: between labels ``Δt`` apart its weights relax toward
their prior, ``μ ← aμ``, ``Σ ← a²Σ + (1 − a²)I`` with ``a = e^{−Δt/τ}``. Its prior variance is
each discrepancy's signal variance ``σ²_δ`` times a factor ``c`` (whitened features scale with
``√c``). :func:`fit_forgetting` chooses ``τ`` and ``c`` as :func:`gpg.flight.fit_drift`
chooses the tracked coefficients' drift: each training part (a flight, or the flights of one
wind) is predicted by a model that did not see it (the physical basis and discrepancy refitted
on the other parts with the corrected model's hyperparameters, or the corrected model itself
where it did not take the part), the term runs over the part from its prior, restarting at
each flight, and ``(τ, c)`` maximise the sum of the one-step-ahead log densities of the
labels, each under the band the adapted model gives it (:func:`gpg.flight.adapt`'s ``band``):
the held-out model's band ``b`` (its discrepancy's and coefficients' variance with ``ν²``,
not the prior's latent variance), plus ``η``'s ``ψᵀΣψ`` (``"added"``) or with ``η``'s prior
``ψᵀψ`` taken out of it first (``"shared"``), and the label's own noise. A grid first, then
Nelder-Mead (optimistix) on the logarithms: the scan's reverse-mode derivative would store
six ``m × m`` covariances per row, a gigabyte for a stream of ten thousand samples at
``m = 48``.

With ``per_output`` each load output gets its own pair: the outputs' weights are independent
filters and the likelihood a sum over them, so each pair is searched on its output's columns
alone (on the hard scenario the forces keep minutes, the torques seconds).

With ``ahead = L`` each label is scored by the term's prediction from the labels ``L`` and
more rows before it (the update with each label applied ``L − 1`` rows late): labels'
errors that correlate over fewer samples than that (a velocity differentiated over a window)
cannot be learnt from the samples just before, which the one-step likelihood rewards.

Steady training winds favour a long memory (the residual they show stays); a gust asks for a
short one. What the flights cannot show, the fit cannot choose: the guide ("Adaptation at the
unseen winds") measures what each band's fit gives at the hard scenario's test winds.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from gpg._dtype import float64
from gpg._precision import highest
from gpg.flight import correction as fc
from gpg.flight import tracking as tk
from gpg.flight.bank import adapt_bank
from gpg.flight.labels import Labels
from gpg.surrogate import Surrogate

__all__ = ["FACTOR_RANGE", "BankFit", "Forgetting", "fit_bank", "fit_forgetting"]

N_LOADS = fc.N_LOADS
FACTOR_RANGE = (1e-3, 1e2)
"""The fitted factor ``c`` on each discrepancy's signal variance: from a thousandth (a term
that barely moves) to a hundred times (a term free to take what the discrepancy did not)."""
# The grid the Nelder-Mead search starts from: τ from a second to a day (a term that never
# forgets, within the flights' length), c around the discrepancy's own variance.
_TAU_GRID = (1.0, 3.0, 10.0, 30.0, 100.0, 1000.0, 86400.0)
_FACTOR_GRID = (0.1, 1.0, 10.0)
WEIGHT_TAU_RANGE = (0.02, 86400.0)
"""s, the range :func:`fit_bank`'s weight forgetting time ``τ_w`` is searched in: from a
sample at 50 Hz (the weights read the last score alone) to a day (every score counts)."""
_WEIGHT_TAU_GRID = (0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 100.0, 1000.0, 86400.0)


@dataclass(frozen=True)
class Forgetting:
    """The inducing-point term's fitted forgetting time and prior (:func:`fit_forgetting`);
    pass ``tau`` and ``variance`` to :func:`gpg.flight.adapt`, with ``inducing``.

    Attributes:
        tau: s, the forgetting time ``τ``; six, one per load output, when fitted per output.
        factor: ``c``, the factor on each discrepancy's signal variance (six when per output).
        variance: (6,) ``η``'s signal variance per load output, ``c σ²_δ`` (normalised).
        inducing: the inducing inputs it was fitted with (``m``).
        band: the adapted band it was fitted for (:func:`gpg.flight.adapt`'s ``band``).
        log_likelihood: the labels' mean log density, each predicted ``ahead`` rows ahead
            (nats per label, the six load outputs summed) at the fit.
        grid: ``((τ, c, log likelihood), ...)``: the grid the search started from, each point's
            score with every output at that point (how much the choice matters).
        labels: the rows the likelihood summed over.
        ahead: the rows ahead each label was predicted from (1: one step).
    """

    tau: float | tuple[float, ...]
    factor: float | tuple[float, ...]
    variance: tuple[float, ...]
    inducing: int
    band: str
    log_likelihood: float
    grid: tuple[tuple[float, float, float], ...]
    labels: int
    ahead: int = 1


@dataclass(frozen=True)
class BankFit:
    """A bank's weight forgetting time fitted on training flights (:func:`fit_bank`); pass
    ``weight_tau`` and ``ahead`` to :func:`gpg.flight.adapt_bank` with the same members.

    Attributes:
        weight_tau: s, ``τ_w``, how long a member's past scores count.
        ahead: ``L``, the labels ahead each label is scored from (the members' weights and the
            mixture's score alike).
        log_likelihood: the labels' mean log density under the mixture, each label predicted
            by the members ``L`` labels behind under the weights before it (nats per label, the
            six load outputs summed), at the fit.
        members: each member alone, scored the same way (nats per label).
        grid: ``((τ_w, log likelihood), ...)``: the grid the search started from.
        labels: the rows the likelihood summed over.
        coverage95: per load output, the share of those rows' labels inside the bank's
            95-percent band at the fitted ``τ_w`` (``Z95`` standard deviations of the
            mixture's moments of the members' predictions made at each row, as the bank
            predicts, the label's own noise added).
    """

    weight_tau: float
    ahead: int
    log_likelihood: float
    members: tuple[float, ...]
    grid: tuple[tuple[float, float], ...]
    labels: int
    coverage95: tuple[float, ...] = ()


@float64
def fit_bank(
    sur: Surrogate,
    labels: Sequence[Labels],
    members: Sequence,
    *,
    ahead: int = 10,
    inducing: int = 48,
    max_labels: int = 1500,
    max_steps: int = 40,
    read: Sequence[Labels] | None = None,
    seed: int = 0,
    band: str = "shared",
) -> BankFit:
    """The weight forgetting time ``τ_w`` of :func:`gpg.flight.adapt_bank` that best predicts
    new flights, label by label.

    The members run over the held-out rows :func:`fit_forgetting` scores (each training part
    predicted by a model that did not see it, restarting at each flight), each row scored under
    every member ``ahead`` rows behind, and ``τ_w`` maximises the sum over rows of the
    mixture's log density ``log Σ_k w_k p_k(y)`` with the weights before the row (a grid, then
    Nelder-Mead on ``log τ_w``). The members' runs do not depend on ``τ_w``: they are scanned
    once.

    Args:
        sur: a corrected model (:func:`gpg.flight.correct`).
        labels: two or more parts (flights, or the flights of one wind), in time order.
        members: the bank's memories, as :func:`gpg.flight.adapt_bank` takes them.
        ahead: ``L``, as :func:`gpg.flight.adapt_bank` takes it.
        inducing: ``m``, each term's inducing inputs.
        max_labels: at most this many labels, taken as :func:`fit_forgetting` takes them.
        max_steps: Nelder-Mead steps after the grid.
        read: what the bank will read of each part (:func:`fit_forgetting`'s ``read``).
        seed: the inducing inputs' k-means seed.
        band: ``"shared"`` or ``"added"`` (:func:`gpg.flight.adapt`'s ``band``).

    Returns:
        The fitted :class:`BankFit`.

    Raises:
        ValueError: what :func:`gpg.flight.adapt_bank` or :func:`fit_forgetting` refuse.
    """
    # the members first: a bad one is refused before the held-out rows are computed
    offline = dataclasses.replace(sur, model=fc.offline_model(sur.model))
    bank = adapt_bank(offline, members, ahead=ahead, inducing=inducing, seed=seed, band=band)
    on = bank.model.online.members
    _, template, rows = _held_out_rows(sur, labels, read, inducing, max_labels, seed, band,
                                       "fit_bank")  # fmt: skip
    t, start = rows[:2]
    factor = on.variance / template.variance  # each member's c per output
    ll, err, var = _bank_rows_loglik(on.tau, factor, rows, template.shared, int(ahead))
    scored = [(w, -float(_mixture_neg_loglik(jnp.log(w), (ll, t, start))))
              for w in _WEIGHT_TAU_GRID]  # fmt: skip
    w0, best = max(scored, key=lambda s: s[1])
    sol = optx.minimise(_mixture_neg_loglik, optx.NelderMead(rtol=1e-4, atol=1e-4),
                        jnp.log(jnp.asarray([w0])), args=(ll, t, start), max_steps=max_steps,
                        throw=False)  # fmt: skip
    found = -float(_mixture_neg_loglik(sol.value, (ll, t, start)))
    if found > best:
        w0, best = float(_weight_tau(sol.value[0])), found
    mean, band = _mixture_moments(jnp.log(jnp.asarray(w0)), ll, err, var, t, start)
    inside = np.asarray(mean) ** 2 <= fc.Z95**2 * np.asarray(band)
    return BankFit(
        weight_tau=float(w0),
        ahead=int(ahead),
        log_likelihood=best,
        members=tuple(float(v) for v in jnp.mean(jnp.sum(ll, -1), 0)),
        grid=tuple(scored),
        labels=int(t.shape[0]),
        coverage95=tuple(float(v) for v in inside.mean(0)),
    )


def _weight_tau(log_tau: Float[Array, ""]) -> Float[Array, ""]:
    lo, hi = np.log(WEIGHT_TAU_RANGE)
    return jnp.exp(jnp.clip(log_tau, lo, hi))


def _log_weights(ll, t, start, tw):
    """The members' normalised log weights before each row, (N, K, 6), from each row's log
    densities ``ll`` (N, K, 6): each row's added after it, all decayed by ``e^{−Δt/τ_w}``
    between rows, reset where a flight starts."""

    def body(carry, row):
        lw, t_prev = carry
        lr, ti, st = row
        lw = jnp.where(st, 0.0, lw * jnp.exp(-jnp.maximum(ti - t_prev, 0.0) / tw))
        return (lw + lr, ti), lw - jax.nn.logsumexp(lw, axis=0)

    return jax.lax.scan(body, (jnp.zeros(ll.shape[1:], ll.dtype), t[0]), (ll, t, start))[1]


@jax.jit
def _mixture_neg_loglik(log_tau, args):
    """Minus the mean log density per row of the mixture with ``τ_w = e^{log_tau}`` from each
    row's members' log densities ``ll`` (N, K, 6), the weights before the row (reset where a
    flight starts)."""
    ll, t, start = args
    logw = _log_weights(ll, t, start, _weight_tau(jnp.reshape(log_tau, ())))
    return -jnp.mean(jnp.sum(jax.nn.logsumexp(logw + ll, axis=1), -1))


@jax.jit
def _mixture_moments(log_tau, ll, err, var, t, start):
    """Each row's mixture of the members' predictions at it, weighted as :func:`fit_bank`'s
    score weighs them with ``τ_w = e^{log_tau}``: the (N, 6) mean of the residual's errors
    ``Σ w_k e_k`` and the variance ``Σ w_k (v_k + e_k²) − (Σ w_k e_k)²`` (``e``, ``v`` (N, K,
    6) each member's error and band with the label's noise)."""
    w = jnp.exp(_log_weights(ll, t, start, _weight_tau(jnp.reshape(log_tau, ()))))
    mean = jnp.sum(w * err, 1)
    return mean, jnp.sum(w * (var + err**2), 1) - mean**2


@partial(jax.jit, static_argnums=(3, 4))
@highest
def _bank_rows_loglik(tau, factor, rows, shared: bool, ahead: int):
    """Each row's log density under each member ``ahead`` rows behind, (N, K, 6): the members'
    weights (``τ`` (K, 6, m), factors ``c`` (K, 6)) as :class:`gpg.flight.bank.Bank` runs
    them, on :func:`_rows_neg_loglik`'s rows. The members behind take each waiting row
    relaxed to its own time, as the bank does; a flight's start empties the ring. Also each
    member's own prediction at the row (from the rows before it): its error and its band
    with the label's noise, (N, K, 6) each."""
    t, start, psi, prior, resid, gain_noise, held, noise = rows
    k, m = factor.shape[0], psi.shape[-1]
    eye = jnp.eye(m, dtype=psi.dtype)
    fresh = (jnp.zeros((k, N_LOADS, m), psi.dtype), jnp.broadcast_to(eye, (k, N_LOADS, m, m)))
    root = jnp.sqrt(factor)[:, :, None]
    ring0 = (jnp.zeros((ahead, N_LOADS, m), psi.dtype), jnp.zeros((ahead, N_LOADS), psi.dtype),
             jnp.ones((ahead, N_LOADS), psi.dtype), jnp.zeros(ahead, bool),
             jnp.zeros(ahead, psi.dtype))  # fmt: skip

    def relax(state, dt):
        a = jnp.exp(-dt / tau)
        return a * state[0], a[..., None] * state[1] * a[..., None, :] + (1 - a**2)[..., None] * eye

    def per_member(fn, state, p, *a):
        return jax.vmap(fn, in_axes=(0, 0, 0) + (None,) * len(a))(*state, p, *a)

    def body(carry, row):
        cur, lag, t_cur, t_lag, ring, i = carry
        ti, st, p0, q0, e, r, b, n = row
        rp, re, rr, live, rt = ring
        cur = jax.tree.map(lambda f, x: jnp.where(st, f, x), fresh,
                           relax(cur, jnp.maximum(ti - t_cur, 0.0)))  # fmt: skip
        lag = jax.tree.map(lambda f, x: jnp.where(st, f, x), fresh, lag)
        live, t_lag = jnp.where(st, False, live), jnp.where(st, ti, t_lag)
        j = i % ahead
        waiting = relax(lag, jnp.maximum(rt[j] - t_lag, 0.0))
        done = per_member(lambda mu, S, p, e_, r_: _updated(mu, S, *_predicted(mu, S, p, e_), r_),
                          waiting, root * rp[j], re[j], rr[j])  # fmt: skip
        lag = jax.tree.map(lambda d, x: jnp.where(live[j], d, x), done, lag)
        t_lag = jnp.where(live[j], rt[j], t_lag)
        p = root * p0
        _, q, err = per_member(_predicted, relax(lag, jnp.maximum(ti - t_lag, 0.0)), p, e)
        offline = (jnp.maximum(b - factor * q0, 0.0) if shared else b) + n
        ll = -0.5 * (jnp.log(2 * jnp.pi * (offline + q)) + err**2 / (offline + q))
        Sp, q1, err1 = per_member(_predicted, cur, p, e)
        cur = jax.vmap(_updated, in_axes=(0, 0, 0, 0, 0, None))(*cur, Sp, q1, err1, r)
        ring = (rp.at[j].set(p0), re.at[j].set(e), rr.at[j].set(r), live.at[j].set(True),
                rt.at[j].set(ti))  # fmt: skip
        return (cur, lag, ti, t_lag, ring, i + 1), (ll, err1, offline + q1)

    init = (fresh, fresh, t[0], t[0], ring0, 0)
    return jax.lax.scan(body, init, rows)[1]


@float64
def fit_forgetting(
    sur: Surrogate,
    labels: Sequence[Labels],
    *,
    inducing: int = 48,
    max_labels: int = 1500,
    max_steps: int = 60,
    read: Sequence[Labels] | None = None,
    seed: int = 0,
    band: str = "added",
    per_output: bool = False,
    ahead: int = 1,
) -> Forgetting:
    """The forgetting time ``τ`` and prior factor ``c`` of :func:`gpg.flight.adapt`'s term
    that best predict new flights, label by label (module docstring).

    Args:
        sur: a corrected model (:func:`gpg.flight.correct`; an adapted or tracked one is read
            without its online part).
        labels: two or more parts (flights, or the flights of one wind), in time order within
            each.
        inducing: ``m``, the term's inducing inputs, placed as :func:`gpg.flight.adapt`
            places them (with ``seed``).
        max_labels: at most this many labels, taken as :func:`gpg.flight.fit_drift` takes them.
        max_steps: Nelder-Mead steps after the grid.
        read: what the term will read of each part, one per part in the same order (every
            sample of the same flights, as :func:`gpg.flight.fit_drift` reads them); None:
            the labels themselves.
        seed: the inducing inputs' k-means seed.
        band: the adapted band the labels are scored by, as :func:`gpg.flight.adapt` takes
            it: ``"added"`` (the held-out band plus ``η``'s ``ψᵀΣψ``) or ``"shared"``
            (``max(b − ψᵀψ, 0) + ψᵀΣψ``, ``b`` the held-out band).
        per_output: a ``(τ, c)`` for each load output. The outputs' weights are independent
            and the likelihood a sum over them, so each output's pair is its own search
            (the six together cost what one joint search does).
        ahead: ``L``: each label scored by the prediction from the labels ``L`` and more rows
            before it (module docstring); 1: the one-step-ahead likelihood.

    Returns:
        The fitted :class:`Forgetting`.

    Raises:
        ValueError: fewer than two parts, ``sur`` not corrected by flights, ``inducing``
            under 1, ``band`` neither ``"added"`` nor ``"shared"``, ``read`` not one
            non-empty part per part of ``labels``, or ``ahead`` not a whole number >= 1.
    """
    if inducing < 1:
        raise ValueError(f"fit_forgetting: inducing must be >= 1, got {inducing}")
    if isinstance(ahead, bool) or int(ahead) != ahead or ahead < 1:
        raise ValueError(f"fit_forgetting: ahead must be a whole number >= 1, got {ahead!r}")
    _, template, rows = _held_out_rows(sur, labels, read, inducing, max_labels, seed, band,
                                       "fit_forgetting")  # fmt: skip
    t = rows[0]
    if per_output:
        fits = [_search((*_output(rows, j), template.shared, int(ahead)), max_steps)
                for j in range(N_LOADS)]  # fmt: skip
        theta = jnp.stack([f[0] for f in fits])
        best = sum(f[1] for f in fits)
        # every output at one grid point: the joint grid's score, the outputs' sum
        scored = [(pt, sum(f[2][i][1] for f in fits)) for i, (pt, _) in enumerate(fits[0][2])]
    else:
        theta, best, scored = _search((*rows, template.shared, int(ahead)), max_steps)
    tau, c = (np.asarray(v, float) for v in _unpack(theta.T))
    per = np.broadcast_to(c, (N_LOADS,)) * np.asarray(template.variance)
    return Forgetting(
        tau=tuple(tau.tolist()) if per_output else float(tau),
        factor=tuple(c.tolist()) if per_output else float(c),
        variance=tuple(float(v) for v in per),
        inducing=int(template.Z.shape[0]),
        band=band,
        log_likelihood=-best,
        grid=tuple((a, b, ll) for (a, b), ll in scored),
        labels=int(t.shape[0]),
        ahead=int(ahead),
    )


def _held_out_rows(sur, labels, read, inducing: int, max_labels: int, seed: int, band: str,
                   who: str):  # fmt: skip
    """The offline model, the term :func:`gpg.flight.adapt` builds on it (``c = 1``) and
    :func:`_rows_neg_loglik`'s rows: each training part predicted by a model that did not
    see it (``read``'s rows where given), the term's features at each."""
    parts = tk._parts(sur, labels, who)
    stream = tk._checked_read(parts, read, who)
    offline = dataclasses.replace(sur, model=fc.offline_model(sur.model))
    template = fc.adapt(offline, inducing=inducing, seed=seed, band=band).model.online
    data, _, (X, held) = tk._held_out_sequences(offline, parts, max_labels, stream, inputs=True)
    t, start, _, resid, noise, *_ = data
    psi = jax.jit(jax.vmap(template.features))(jnp.asarray(X))
    prior = jnp.sum(psi * psi, -1)  # ψᵀψ at c = 1: the share of the band η's prior takes
    return offline, template, (t, start, psi, prior, resid, noise + template.noise, held, noise)


def _search(args, max_steps: int) -> tuple[Float[Array, " 2"], float, list]:
    """The best ``θ`` from the grid, improved by Nelder-Mead, its minus log likelihood and the
    grid's scores ``[((τ, c), log likelihood), ...]``."""
    scored = [((tau, c), -float(_neg_loglik(_pack(tau, c), args)))
              for tau, c in itertools.product(_TAU_GRID, _FACTOR_GRID)]  # fmt: skip
    (tau0, c0), ll0 = max(scored, key=lambda s: s[1])
    theta = _pack(tau0, c0)
    sol = optx.minimise(_neg_loglik, optx.NelderMead(rtol=1e-4, atol=1e-4), theta, args=args,
                        max_steps=max_steps, throw=False)  # fmt: skip
    found = float(_neg_loglik(sol.value, args))
    return (sol.value, found, scored) if found < -ll0 else (theta, -ll0, scored)


def _output(rows, j: int):
    """:func:`_rows_neg_loglik`'s rows of load output ``j`` alone."""
    t, start, *per = rows
    return (t, start, *(r[:, j : j + 1] for r in per))


def _pack(tau: float, factor: float) -> Float[Array, " 2"]:
    """``θ = (log τ, log c)``."""
    return jnp.log(jnp.asarray([tau, factor], float))


def _unpack(theta: Float[Array, " 2"]) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """:func:`_pack`'s ``θ`` (or the rows of a stack of them, ``θᵀ``) to ``(τ, c)``, each
    kept in its range."""
    (t_lo, t_hi), (c_lo, c_hi) = np.log(tk.TAU_RANGE), np.log(FACTOR_RANGE)
    return jnp.exp(jnp.clip(theta[0], t_lo, t_hi)), jnp.exp(jnp.clip(theta[1], c_lo, c_hi))


def _predicted(mean, cov, p, e):
    """The term at features ``p`` of one row: ``Σψ``, ``ψᵀΣψ`` and the residual ``e``'s error
    per output (what the row's score and its update both read)."""
    Sp = jnp.einsum("jmn,jn->jm", cov, p)
    return Sp, jnp.einsum("jm,jm->j", p, Sp), e - jnp.einsum("jm,jm->j", p, mean)


def _updated(mean, cov, Sp, q, err, r):
    """The Kalman update of each output's weights with one row's ``Σψ``, ``ψᵀΣψ``, error and
    update noise ``r``."""
    k = Sp / (q + r)[:, None]
    cov = cov - k[:, :, None] * Sp[:, None, :]
    return mean + k * err[:, None], 0.5 * (cov + jnp.swapaxes(cov, 1, 2))


@partial(jax.jit, static_argnums=(2, 3))
@highest
def _rows_neg_loglik(theta, rows, shared: bool, ahead: int = 1):
    """Minus the mean log density per row of the term with ``θ`` over the held-out rows:
    ``t``, whether a flight starts, the whitened features ``ψ`` at ``c = 1`` (N, 6, m) and
    their ``ψᵀψ`` (N, 6), the residual against the held-out model, the update's noise (the
    label's and the term's ``ν²``), the held-out model's band ``b`` and the label's noise;
    ``shared``: ``η``'s prior a share of ``b`` (:func:`gpg.flight.adapt`'s ``band``). Each row
    is predicted from the rows ``ahead`` and more before it: with ``ahead > 1`` the updates
    wait in a ring of ``ahead`` rows, each applied (to the state relaxed to the row it waited
    for) just before the row ``ahead`` later is predicted, the ring emptied where a flight
    starts."""
    t, start, psi, prior, resid, gain_noise, held, noise = rows
    tau, c = _unpack(theta)
    k, m = psi.shape[1:]  # the outputs scored (six, or one of them) and the inducing inputs
    eye = jnp.eye(m, dtype=psi.dtype)
    mean0, cov0 = jnp.zeros((k, m), psi.dtype), jnp.broadcast_to(eye, (k, m, m))
    lag = ahead if ahead > 1 else 0  # 1: each row's update right after its prediction
    ring0 = (jnp.zeros((max(lag, 1), k, m), psi.dtype), jnp.zeros((max(lag, 1), k), psi.dtype),
             jnp.ones((max(lag, 1), k), psi.dtype), jnp.zeros(max(lag, 1), bool))  # fmt: skip

    def body(carry, row):
        mean, cov, t_prev, ring, i = carry
        ti, st, p0, q0, e, r, b, n = row
        a = jnp.exp(-jnp.maximum(ti - t_prev, 0.0) / tau)
        mean, cov = a * mean, a**2 * cov + (1.0 - a**2) * eye
        mean, cov = jnp.where(st, mean0, mean), jnp.where(st, cov0, cov)
        p = jnp.sqrt(c) * p0
        if lag:  # the row `ahead` before: its update now, then this row predicted
            rp, re, rr, live = ring
            j = i % lag
            live = jnp.where(st, jnp.zeros_like(live), live)
            done = _updated(mean, cov, *_predicted(mean, cov, rp[j], re[j]), rr[j])
            mean, cov = (jnp.where(live[j], x, y) for x, y in zip(done, (mean, cov), strict=True))
            ring = (rp.at[j].set(p), re.at[j].set(e), rr.at[j].set(r), live.at[j].set(True))
        Sp, q, err = _predicted(mean, cov, p, e)
        s = (jnp.maximum(b - c * q0, 0.0) if shared else b) + q + n
        ll = -0.5 * (jnp.log(2 * jnp.pi * s) + err**2 / s)
        if not lag:
            mean, cov = _updated(mean, cov, Sp, q, err, r)
        return (mean, cov, ti, ring, i + 1), jnp.sum(ll)

    _, ll = jax.lax.scan(body, (mean0, cov0, t[0], ring0, 0), rows)
    return -jnp.mean(ll)


def _neg_loglik(theta, args):
    """:func:`_rows_neg_loglik` with ``args = (*rows, shared, ahead)``: the form optimistix
    calls."""
    return _rows_neg_loglik(theta, args[:-2], bool(args[-2]), int(args[-1]))
