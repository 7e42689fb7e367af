"""Which cases to run next, and which of their gradients to pay for.

The criterion is the reduction of the integrated predictive variance over a reference set of
states ``Z`` with weights ``w`` (the input box, visited states, or states flagged out of the
domain), per unit of simulator cost. A case at ``x`` that runs the finite-difference
perturbations of the gradient dims ``S`` costs ``1 + |S|`` runs and yields the rows
``(f(x), ∂_S f(x))``. With ``Σ`` the posterior covariance of the current GP-G (shared by all
outputs: one kernel), the rows ``c`` of a case, ``P = Σ_cc + N_c`` (``N_c`` their noise) and
``Q = Σ_cZ``, conditioning on them lowers the latent variance at ``z`` by ``q_zᵀ P⁻¹ q_z``, so

    gain(x, S) = Σ_z w_z q_{S,z}ᵀ P_SS⁻¹ q_{S,z} = tr(P_SS⁻¹ C_SS),   C = Q diag(w) Qᵀ,

and every subset ``S`` of a case's gradient rows is scored from the same two
``(1+G) x (1+G)`` matrices: choosing the gradients is exhaustive over all ``2^G`` subsets and
costs next to nothing once ``P`` and ``C`` are known.

Batches (for cluster runs) are greedy with fantasised conditioning, done exactly in the joint
Gaussian of the kept candidates and the reference set: after a pick ``J``,
``Σ ← Σ − Σ_·J (Σ_JJ + N_J)⁻¹ Σ_J·``, which is what conditioning the GP on the pick would
give whatever its outcome (the posterior covariance does not depend on the observed values).
Greedy maximisation is the standard choice for this submodular-like criterion (emukit's
greedy batch, BoTorch's sequential ``q``-acquisition); it needs one rank-``|J|`` update per pick.

Cost: the candidates are first ranked by the gain of their value row alone (``O(C R²)`` with
``R`` training rows); the best ``keep`` go on with all their rows.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from gpg import _host
from gpg._dtype import float64
from gpg.gp import kernels
from gpg.gp.exact import ExactGP
from gpg.gp.gram import rows_gram

__all__ = ["GRADIENTS", "Batch", "propose", "subsets"]

GRADIENTS = ("all", "none", "choose")


@dataclass(frozen=True)
class Batch:
    """A proposed batch: ``index`` (B,) into the candidates, ``gradients`` (B, G) which gradient
    dims to run at each, ``gain`` (B,) each pick's integrated-variance reduction (normalised
    units, given the picks before it), ``cost`` (B,) its simulator runs (``1 + |S|``)."""

    index: np.ndarray
    gradients: np.ndarray
    gain: np.ndarray
    cost: np.ndarray

    @property
    def runs(self) -> int:
        """The simulator runs of the whole batch."""
        return int(self.cost.sum())


def subsets(n_grad: int, gradients: str) -> np.ndarray:
    """The row masks of the allowed choices of a case's rows.

    The value row is always run; of the gradient rows, all (``all``), none (``none``) or
    every subset (``choose``, ``2^G`` masks).

    Args:
        n_grad: ``G``, the model's gradient dims.
        gradients: ``all``, ``none`` or ``choose``.

    Returns:
        (S, 1+G) bool masks, the value row first.

    Raises:
        ValueError: if ``gradients`` is none of those.
    """
    if gradients not in GRADIENTS:
        raise ValueError(f"gradients must be one of {GRADIENTS}, got {gradients!r}")
    if gradients == "all" or n_grad == 0:
        return np.ones((1, 1 + n_grad), dtype=bool)
    if gradients == "none":
        return np.eye(1, 1 + n_grad, dtype=bool)
    grads = np.array(list(itertools.product([False, True], repeat=n_grad)), dtype=bool)
    return np.concatenate([np.ones((grads.shape[0], 1), dtype=bool), grads], axis=1)


def _whitened(gp: ExactGP, Xq: np.ndarray, dims: tuple[int, ...], chunk: int = 512) -> np.ndarray:
    """``(L⁻¹ K̄(A, rows))ᵀ`` for the rows of ``Xq`` with gradient dims ``dims`` (``()`` or the
    model's), point-major: (Q(1+G'), R_f). ``A`` are the factor's rows (``gp.order``), formed
    alone: a values-only case of the model is one column, not ``1 + G``."""
    X = np.asarray(gp.X)
    order = np.arange(gp.alpha.shape[0]) if gp.order is None else np.asarray(gp.order)
    bases = None if gp.bases is None else np.asarray(gp.bases)  # the model's rows' directions
    out = []
    for a in range(0, Xq.shape[0], chunk):
        Xc = np.asarray(Xq[a : a + chunk])
        q = Xc.shape[0]
        rows = np.arange(q * (1 + len(dims)))
        K = rows_gram(Xc, rows, X, order, gp.hyper, gp.grad_dims, bases2=bases)
        V = gp.chol_inv.rmatmul(_host.asarray(K))
        # dimension-major rows of this chunk -> point-major
        out.append(
            np.asarray(V)
            .reshape(1 + len(dims), q, -1)
            .transpose(1, 0, 2)
            .reshape(q * (1 + len(dims)), -1)
        )
    return np.concatenate(out)


def _prior(X1: np.ndarray, X2: np.ndarray, gp: ExactGP, dims1, dims2) -> np.ndarray:
    """Prior covariance, point-major on both sides."""
    h = gp.hyper
    K = np.asarray(
        kernels.gram(jnp.asarray(X1), jnp.asarray(X2), h.variance, h.lengthscale, dims1, dims2)
    )
    g1, g2 = 1 + len(dims1), 1 + len(dims2)
    n1, n2 = X1.shape[0], X2.shape[0]
    return K.reshape(g1, n1, g2, n2).transpose(1, 0, 3, 2).reshape(n1 * g1, n2 * g2)


@jax.jit
def _subset_gains(P: Array, C: Array, masks: Array) -> Array:
    """``tr(P_SS⁻¹ C_SS)`` for every candidate (k, g, g) and mask (S, g): (k, S)."""
    m = masks.astype(P.dtype)
    mm = m[:, :, None] * m[:, None, :]
    off = jnp.eye(P.shape[-1], dtype=P.dtype)[None] * (1.0 - m)[:, None, :]  # diag(1 − m)
    PS = P[:, None] * mm[None] + off[None]
    CS = C[:, None] * mm[None]
    sol = jnp.linalg.solve(PS, CS)
    return jnp.trace(sol, axis1=-2, axis2=-1)


@float64
def propose(
    gp: ExactGP,
    candidates: Float[np.ndarray, "C D"],
    reference: Float[np.ndarray, "Z D"],
    batch: int,
    *,
    weights: Float[np.ndarray, " Z"] | None = None,
    gradients: str = "choose",
    keep: int | None = None,
    exclude: np.ndarray | None = None,
) -> Batch:
    """The candidates that most reduce the integrated variance per simulator run, greedily.

    A batch of ``batch`` cases from ``candidates`` (normalised inputs, as ``gp.X``) that most
    reduce the weighted integrated variance over ``reference`` per simulator run, each pick
    fantasised into the posterior before the next (see the module docstring).

    Args:
        gp: the current exact GP-G (its posterior; the outcomes are not needed).
        candidates: (C, D) candidate inputs.
        reference: (Z, D) states whose predictive variance should fall.
        batch: cases to pick (distinct candidates).
        weights: (Z,) non-negative weight per reference state (default: equal, summing to 1).
        gradients: ``all`` (every case runs every gradient perturbation), ``none`` (values
            only) or ``choose`` (per case, the subset with the best gain per run).
        keep: candidates kept after the value-row ranking (default ``max(10·batch, 200)``).
        exclude: (C,) bool, candidates that may not be picked.

    Returns:
        The :class:`Batch`: the picks as indices into ``candidates``, in the order picked.

    Raises:
        ValueError: if ``reference`` is not (Z, D), ``batch`` is not in ``[1, C]``,
            ``weights`` is not (Z,) finite and non-negative, or fewer than ``batch``
            candidates may be picked.
        RuntimeError: if a candidate's posterior covariance is indefinite beyond rounding
            (the model's stored factor does not match its ``K̄``).
    """
    C, D = candidates.shape
    if reference.ndim != 2 or reference.shape[1] != D:
        raise ValueError(f"reference must have shape (Z, {D}), got {reference.shape}")
    if not 1 <= batch <= C:
        raise ValueError(f"batch must be in [1, {C}] (the number of candidates), got {batch}")
    w = (
        np.full(reference.shape[0], 1.0 / reference.shape[0])
        if weights is None
        else np.asarray(weights, float)
    )
    if w.shape != (reference.shape[0],) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("weights must be (Z,) finite and non-negative")
    dims = gp.grad_dims
    masks = subsets(len(dims), gradients)
    h = gp.hyper
    noise = np.concatenate(
        [[float(h.noise)], np.broadcast_to(np.asarray(h.grad_noise), (len(dims),))]
    )
    VZ = _whitened(gp, reference, ())  # (Z, R)
    value_gain = _value_gains(gp, candidates, reference, VZ, w)
    if exclude is not None:
        value_gain = np.where(np.asarray(exclude, bool), -np.inf, value_gain)
    k = min(C, max(10 * batch, 200) if keep is None else max(keep, batch))
    kept = np.argsort(-value_gain, kind="stable")[:k]
    kept = kept[np.isfinite(value_gain[kept])]
    if kept.size < batch:
        raise ValueError(f"only {kept.size} candidates may be picked, fewer than batch={batch}")
    # The joint posterior of the kept candidates' rows (point-major) and the reference set.
    Xt = candidates[kept]
    VT = _whitened(gp, Xt, dims)
    S_tt = _prior(Xt, Xt, gp, dims, dims) - VT @ VT.T
    S_tz = _prior(Xt, reference, gp, dims, ()) - VT @ VZ.T
    del VT
    picked, sub, gains = _greedy(S_tt, S_tz, w, masks, noise, batch)
    return Batch(index=kept[picked], gradients=sub[:, 1:], gain=gains, cost=sub.sum(axis=1))


def _value_gains(gp: ExactGP, candidates, reference, VZ, w, chunk: int = 2048) -> np.ndarray:
    """The gain of each candidate's value row alone (the ranking that picks ``keep``)."""
    h = gp.hyper
    out = np.empty(candidates.shape[0])
    for a in range(0, candidates.shape[0], chunk):
        Xc = candidates[a : a + chunk]
        Vc = _whitened(gp, Xc, ())
        p = float(h.variance) + float(h.noise) - np.sum(Vc * Vc, axis=1)
        q = _prior(Xc, reference, gp, (), ()) - Vc @ VZ.T
        out[a : a + chunk] = (q * q) @ w / np.maximum(p, 1e-300)
    return out


def _greedy(S_tt, S_tz, w, masks, noise, batch):
    """Greedy picks with fantasised conditioning in the joint Gaussian: (candidate, rows) of
    best gain per run, then ``Σ ← Σ − Σ_·J (Σ_JJ + N_J)⁻¹ Σ_J·`` (in place)."""
    g = masks.shape[1]
    k = S_tt.shape[0] // g
    prior_scale = float(np.max(np.abs(np.diag(S_tt)))) + float(np.max(noise))
    nd = np.tile(noise, k)
    picked, sub, gains = [], [], []
    alive = np.ones(k, dtype=bool)
    runs = masks.sum(axis=1)[None]
    for _ in range(batch):
        blocks = S_tt.reshape(k, g, k, g)[np.arange(k), :, np.arange(k), :]
        if not picked:  # before any downdate: the posterior as the model gives it
            _check_psd(blocks, prior_scale)
        blocks = _psd(blocks)
        Qz = S_tz.reshape(k, g, -1)
        Cm = np.einsum("kiz,z,kjz->kij", Qz, w, Qz)
        P = blocks + np.diag(noise)[None]
        score = np.asarray(_subset_gains(jnp.asarray(P), jnp.asarray(Cm), jnp.asarray(masks)))
        per_run = np.where(alive[:, None], score / runs, -np.inf)
        c, s = np.unravel_index(int(np.argmax(per_run)), per_run.shape)
        picked.append(c)
        sub.append(masks[s])
        gains.append(score[c, s])
        alive[c] = False
        J = c * g + np.flatnonzero(masks[s])
        Lj = np.linalg.cholesky(_psd(S_tt[np.ix_(J, J)]) + np.diag(nd[J]))
        A_t = np.linalg.solve(Lj, S_tt[J])  # (|J|, rows)
        A_z = np.linalg.solve(Lj, S_tz[J])
        S_tt -= A_t.T @ A_t
        S_tz -= A_t.T @ A_z
    return np.asarray(picked), np.asarray(sub), np.asarray(gains)


def _psd(A: np.ndarray) -> np.ndarray:
    """The symmetric part of ``A`` (…, g, g) with its eigenvalues clipped at 0: a posterior
    covariance block as it is, not as rounding leaves it (``Σ = K − VVᵀ`` near the data is a
    difference of nearly equal numbers). Clipping more than rounding would hide a model whose
    stored factor does not match its ``K̄``: that is an error (:func:`_check_psd`)."""
    A = 0.5 * (A + np.swapaxes(A, -1, -2))
    w, U = np.linalg.eigh(A)
    return (U * np.maximum(w, 0.0)[..., None, :]) @ np.swapaxes(U, -1, -2)


PSD_TOL = 1e-6  # a posterior variance may round below 0 by this much of the prior's, not more


def _check_psd(blocks: np.ndarray, prior_scale: float) -> None:
    """Raise when a candidate's posterior covariance block is indefinite beyond rounding."""
    low = float(np.min(np.linalg.eigvalsh(0.5 * (blocks + np.swapaxes(blocks, -1, -2)))))
    if low < -PSD_TOL * prior_scale:
        raise RuntimeError(
            f"a candidate's posterior covariance has the eigenvalue {low:.3g} (prior scale "
            f"{prior_scale:.3g}): the model's stored factor does not match its K̄"
        )
