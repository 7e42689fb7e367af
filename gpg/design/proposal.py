"""Which cases to run next for a fitted surrogate, in dataset units.

:func:`propose` draws candidate and reference states from the surrogate's domain (or takes
the user's), checks them, and hands their normalised inputs to the acquisition
(:func:`gpg.design.acquisition.propose`) on the exact GP-G the surrogate's kind gives
(:func:`gpg.design.conditioning.posterior`); the picked cases come back as a
:class:`Proposal`, the gradient perturbations worth running at each included.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpg import models
from gpg._dtype import float64
from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.data.sampling import latin_hypercube
from gpg.design.acquisition import GRADIENTS, Batch
from gpg.design.acquisition import propose as propose_rows
from gpg.design.conditioning import (
    DUPLICATE_TOL,
    _min_distance,
    _outside,
    posterior,
    training_arrays,
    training_cases,
)
from gpg.gp.fit import fit_hyperparameters
from gpg.gp.hyper import Hyper
from gpg.names import GRAD_DIMS

__all__ = ["Proposal", "propose"]


def output_hyper(sur: Any, dataset: Dataset, weights: Mapping[str, float]) -> Hyper:
    """Hyperparameters fitted to the weighted outputs only (``{"L1": 1, ...}``): with one kernel
    shared by all outputs, the posterior variance, and so the acquisition, is the same for
    every output; asking for some outputs means using the kernel *they* imply."""
    names = tuple(sur.output_names)
    unknown = sorted(set(weights) - set(names))
    if unknown:
        raise ValueError(f"weights name unknown outputs {unknown}; the surrogate has {list(names)}")
    w = np.array([float(weights.get(k, 0.0)) for k in names])
    if np.any(w < 0) or not np.all(np.isfinite(w)) or not np.any(w > 0):
        raise ValueError(f"output weights must be finite, >= 0 and not all 0, got {dict(weights)}")
    arrays = training_arrays(sur, dataset)
    sel = np.flatnonzero(w > 0)
    r = np.sqrt(w[sel])
    dY = None if arrays.dY is None else arrays.dY[:, sel] * r[None, :, None]
    cfg = models.resolve_config(sur.model_name, sur.config).hyper
    res = fit_hyperparameters(
        arrays.X, arrays.Y[:, sel] * r, dY, grad_dims=arrays.dims or None,
        init=training_cases(sur).hyper, ard=cfg.ard, fit_noise=cfg.fit_noise,
        noise_floor=cfg.noise_floor, noise_init=cfg.noise_init, subset_size=cfg.subset,
        seed=cfg.seed, max_steps=cfg.max_steps, observed=arrays.observed, bases=arrays.bases,
    )  # fmt: skip
    return res.hyper


@dataclass(frozen=True)
class Proposal:
    """The next cases: inputs ``x`` (B, 8) in dataset units (rpm, rad, m/s; (B, 7) in the
    body frame), ``gradients`` (B, 7) which finite-difference perturbations to run at each
    (over the gradient inputs r1..r4, yaw, pitch, roll; in the body frame r1..r4, u, v, w),
    and the :class:`~gpg.design.acquisition.Batch` behind them."""

    x: np.ndarray
    gradients: np.ndarray
    batch: Batch

    @property
    def runs(self) -> int:
        """The simulator runs the proposal costs: per case one, plus one per perturbation."""
        return self.batch.runs


def box_samples(sur: Any, n: int, seed: int) -> np.ndarray:
    """``n`` states of the surrogate's domain by a scrambled Latin hypercube: (n, 8) over its
    input box, or in the body frame (n, 7) over its rotor box and ball of air velocities."""
    lo, hi = np.asarray(sur.box_lo), np.asarray(sur.box_hi)
    if sur.frame == "body":
        box = Bounds(rpm=(0.0, 1.0), airspeed=(0.0, float(sur.ball_radius)))
        x = latin_hypercube(n, box, seed, "body")
        # Each rotor in its own range: a box from the data's extent differs per rotor.
        x[:, :4] = lo[:4] + x[:, :4] * (hi[:4] - lo[:4])
        return x
    return latin_hypercube(n, (lo, hi), seed)


@float64
def propose(
    sur: Any,
    dataset: Dataset,
    batch: int,
    *,
    candidates: np.ndarray | int = 10_000,
    reference: np.ndarray | int = 512,
    reference_weights: np.ndarray | None = None,
    gradients: str = "choose",
    weights: Mapping[str, float] | None = None,
    seed: int = 0,
    keep: int | None = None,
) -> Proposal:
    """The next cases for the simulator, for a surrogate fitted (or conditioned) on a dataset.

    The acquisition is the reduction of the weighted integrated variance over the reference
    states per simulator run (:mod:`gpg.design.acquisition`). Candidates that duplicate a
    training case (closer than ``DUPLICATE_TOL`` lengthscales) are never picked. To aim at
    visited states (flights, rollouts, those with ``in_domain`` False mapped into the box),
    pass them as ``reference``.

    Args:
        sur: the fitted :class:`gpg.Surrogate`.
        dataset: the cases ``sur`` was fitted or conditioned on (read only with ``weights``).
        batch: how many cases to propose.
        candidates: the states to choose from, (·, 8) or in the body frame (·, 7) in dataset
            units, all inside the surrogate's domain; or a count drawn from that domain by a
            Latin hypercube (seeded by ``seed``).
        reference: the states whose predictive variance should fall, as ``candidates``; a
            count is drawn with the seed ``seed + 1``.
        reference_weights: (Z,) non-negative weight per reference state; default equal.
        gradients: ``all`` (every perturbation at every case), ``none`` (values only) or
            ``choose`` (per case, the perturbations worth their run).
        weights: per-output weights (``{"Fx": 1, ...}``) whose fitted kernel the acquisition
            uses (:func:`output_hyper`); default, the surrogate's kernel.
        seed: the seed of the drawn candidates and reference states.
        keep: candidates kept after the value-only ranking (default ``max(10·batch, 200)``).

    Returns:
        The :class:`Proposal`: the cases in dataset units and, per case, which of the seven
        gradient perturbations to run (none for a model without gradients).

    Raises:
        ValueError: if ``gradients`` is not one of ``GRADIENTS``, the candidates or reference
            states are not finite (n, D) arrays, a candidate lies outside the surrogate's
            domain, ``weights`` name unknown outputs or are all 0, ``reference_weights`` is
            not (Z,) finite and non-negative, or ``batch`` is below 1 or exceeds the candidates
            that may be picked (those not duplicating a training case).
    """
    if gradients not in GRADIENTS:
        raise ValueError(f"gradients must be one of {GRADIENTS}, got {gradients!r}")
    cand = box_samples(sur, candidates, seed) if isinstance(candidates, int) else candidates
    ref = box_samples(sur, reference, seed + 1) if isinstance(reference, int) else reference
    d = len(sur.box_lo)
    for name, arr in (("candidates", cand), ("reference", ref)):
        arr = np.asarray(arr, dtype=float)
        if arr.ndim != 2 or arr.shape[1] != d or not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite states of shape (n, {d}), got {arr.shape}")
    cand, ref = np.asarray(cand, float), np.asarray(ref, float)
    lo, hi = np.asarray(sur.box_lo), np.asarray(sur.box_hi)
    outside = np.flatnonzero(np.any(_outside(sur, cand, 0.0), axis=1))
    if outside.size:
        ball = f" and ball |u, v, w| <= {float(sur.ball_radius):g}" if sur.frame == "body" else ""
        raise ValueError(
            f"candidate(s) {outside[:10].tolist()} lie outside the surrogate's input box "
            f"{lo.round(4).tolist()} .. {hi.round(4).tolist()}{ball}: the simulator would be "
            "run where the surrogate does not answer"
        )
    hyper = None if weights is None else output_hyper(sur, dataset, weights)
    gp = posterior(sur, dataset if hyper is not None else None, hyper=hyper)
    norm = sur.normalizer
    Xc, Xr = np.asarray(norm.x(cand)), np.asarray(norm.x(ref))
    ls = np.broadcast_to(np.asarray(gp.hyper.lengthscale, float), (Xc.shape[1],))
    known = _min_distance(Xc / ls, np.asarray(gp.X) / ls) < DUPLICATE_TOL
    b = propose_rows(gp, Xc, Xr, batch, weights=reference_weights, gradients=gradients,
                     keep=keep, exclude=known)  # fmt: skip
    grads = np.zeros((batch, len(GRAD_DIMS)), dtype=bool)
    if gp.grad_dims:
        grads[:, list(gp.grad_dims)] = b.gradients
    return Proposal(x=cand[b.index], gradients=grads, batch=b)
