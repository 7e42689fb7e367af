"""Spending the simulator's budget: conditioning on new cases, choosing the next ones.

* :func:`condition` (also :meth:`gpg.Surrogate.condition`): a fitted surrogate on more cases,
  hyperparameters, normaliser and bins kept, equal to a rebuild with the same
  hyperparameters. Exact (``gp``, ``gpg``): a bordered Cholesky update
  (:meth:`gpg.gp.exact.ExactGP.condition`); hybrid: ``α`` re-formed and the bins whose near
  set changed refactorised (:meth:`gpg.kinds.hybrid.Hybrid.condition`).
* :func:`propose`: the next batch of cases, with the gradient perturbations worth running at
  each (:mod:`gpg.design.acquisition`).
* :mod:`gpg.design.cases`: the ask/tell CSV files for an external solver.

When to refit the hyperparameters instead of conditioning: conditioning keeps the
lengthscales that the old cases implied. Refit (``Surrogate.fit``) once the data have grown
by half since the last fit, or when the new cases fall where the model's ``in_domain`` was
False or its errors on them exceed what its variance promised (``experiments.design`` refits
at the first of those it can check: growth by half); otherwise condition.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from gpg import models
from gpg._dtype import float64
from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.data.preprocess import normalised_gradients, residuals
from gpg.data.sampling import latin_hypercube
from gpg.design.acquisition import GRADIENTS, Batch, subsets
from gpg.design.acquisition import propose as propose_rows
from gpg.gp.exact import ExactGP
from gpg.gp.fit import fit_hyperparameters
from gpg.gp.hyper import Hyper
from gpg.kinds.base import Arrays, Cases, Kind
from gpg.names import GRAD_DIMS

__all__ = [
    "GRADIENTS",
    "Batch",
    "Proposal",
    "condition",
    "merge_datasets",
    "new_cases",
    "posterior",
    "propose",
    "rebuild",
    "subsets",
    "training_cases",
]

# Normalised distance (in lengthscales) below which a new case duplicates a training case.
DUPLICATE_TOL = 1e-6


def training_cases(sur) -> Cases:
    """The normalised training inputs, hyperparameters and gradient dims of ``sur``'s model,
    read through its kind (:meth:`gpg.kinds.base.Kind.cases`); a ``ValueError`` for models
    that cannot condition."""
    return _kind(sur).cases(sur.model)


def _kind(sur) -> Kind:
    return models.SPECS[sur.model_name].kind


def new_cases(sur, dataset: Dataset, *, tol: float = 1e-9) -> Arrays:
    """``dataset``'s cases as the normalised arrays ``sur`` was trained on, after every check
    that can fail: a ``ValueError`` naming the problem, before anything is changed.

    Refused: something other than a :class:`gpg.data.Dataset`; other outputs than the
    surrogate's (names), or cases in the other frame (airflow or body); inputs outside its
    domain, the box (and for the body frame the ball of air velocities ``|v| ≤ V``) behind
    ``in_domain`` (rows named: other units, degrees for radians or km/h for m/s, land there;
    to extend the domain, refit with wider ``bounds``); a case that duplicates a training case
    or another new case. NaN is refused by the dataset itself, except for a gradient whose
    perturbation was not run.
    """
    if not isinstance(dataset, Dataset):
        raise ValueError(f"new cases must be a gpg.data.Dataset, got {type(dataset).__name__}")
    if tuple(dataset.output_names) != tuple(sur.output_names):
        raise ValueError(
            f"the new cases have outputs {list(dataset.output_names)} but the surrogate "
            f"predicts {list(sur.output_names)}"
        )
    if dataset.frame != sur.frame:
        raise ValueError(
            f"the new cases are in the {dataset.frame} frame but the surrogate was fitted in "
            f"the {sur.frame} frame (gpg.data.convert.to_body converts airflow-frame cases)"
        )
    known = training_cases(sur)
    lo, hi = np.asarray(sur.box_lo), np.asarray(sur.box_hi)
    outside = _outside(sur, dataset.x, tol)
    out = np.any(outside, axis=1)
    if out.any():
        rows = np.flatnonzero(out)
        names = [dataset.inputs[i] for i in np.flatnonzero(np.any(outside[rows], 0))]
        where = "box" if sur.frame == "airflow" else "domain (rotor box, ball |u, v, w| <= V)"
        raise ValueError(
            f"new case(s) {rows[:10].tolist()} lie outside the surrogate's input {where} "
            f"(inputs {names}; box {lo.round(4).tolist()} .. {hi.round(4).tolist()} in rpm, "
            "rad, m/s): check the units (degrees for radians, km/h for m/s), or refit with "
            "wider bounds"
        )
    y, J, y_raw = residuals(dataset, sur.simple, sur.noise_model)
    norm = sur.normalizer
    spec = models.SPECS.get(sur.model_name)
    if spec is not None and spec.raw:  # gp trains on the raw 8X samples: so do its new cases
        if not dataset.has_raw:
            raise ValueError(
                f"model {sur.model_name!r} trains on the raw 8X samples, which the new cases lack"
            )
        x, y, J = dataset.x_raw, y_raw, None
    else:
        x = dataset.x
    X = np.asarray(norm.x(x))
    ls = np.broadcast_to(np.asarray(known.hyper.lengthscale, float), (X.shape[1],))
    _check_duplicates(X / ls, known.X / ls)
    Y = np.asarray(norm.y(y))
    if J is None or not known.grad_dims:
        return Arrays(X, Y, None, ())
    return models.gradient_arrays(X, Y, *normalised_gradients(norm, J, dataset.grad_dirs))


def _outside(sur, x: np.ndarray, tol: float) -> np.ndarray:
    """(n, d): which inputs of each state leave the domain ``in_domain`` describes (for the
    body frame the ball of air velocities marks all three of u, v, w)."""
    lo, hi = np.asarray(sur.box_lo), np.asarray(sur.box_hi)
    span = np.maximum(hi - lo, 1e-300)
    outside = (x < lo - tol * span) | (x > hi + tol * span)
    if sur.frame == "body":
        ball = np.linalg.norm(x[:, 4:], axis=1) > float(sur.ball_radius) * (1.0 + tol)
        outside[:, 4:] |= ball[:, None]
    return outside


def _check_duplicates(Xn: np.ndarray, Xo: np.ndarray) -> None:
    d_old = _min_distance(Xn, Xo)
    dup = np.flatnonzero(d_old < DUPLICATE_TOL)
    if dup.size:
        raise ValueError(
            f"new case(s) {dup[:10].tolist()} duplicate training cases (closer than "
            f"{DUPLICATE_TOL:g} lengthscales): a repeated case adds no information; drop it"
        )
    if Xn.shape[0] > 1:
        d = np.sqrt(np.maximum(np.sum((Xn[:, None] - Xn[None]) ** 2, -1), 0.0))
        d[np.diag_indices_from(d)] = np.inf
        same = np.flatnonzero(d.min(axis=1) < DUPLICATE_TOL)
        if same.size:
            raise ValueError(f"new cases {same[:10].tolist()} duplicate one another; keep one")


def _min_distance(A: np.ndarray, B: np.ndarray, chunk: int = 4096) -> np.ndarray:
    out = np.empty(A.shape[0])
    bb = np.sum(B * B, axis=1)
    for a in range(0, A.shape[0], chunk):
        Ac = A[a : a + chunk]
        d2 = np.sum(Ac * Ac, 1)[:, None] + bb[None] - 2 * Ac @ B.T
        out[a : a + chunk] = np.sqrt(np.maximum(d2.min(axis=1), 0.0))
    return out


@float64
def condition(sur, dataset: Dataset):
    """``sur`` conditioned on the cases of ``dataset`` (:meth:`gpg.Surrogate.condition`)."""
    new = new_cases(sur, dataset)
    cfg = models.resolve_config(sur.model_name, sur.config)
    kind = models.SPECS[sur.model_name].kind
    model = kind.condition(sur.model, new, cfg)
    if not cfg.hyper.output_scales:
        model = model.with_output_scale(jnp.ones_like(model.output_scale))
    models.check_finite_model(sur.model_name, model)
    return eqx.tree_at(lambda s: s.model, sur, model)


@float64
def posterior(sur, dataset: Dataset | None = None, *, hyper: Hyper | None = None) -> ExactGP:
    """The exact GP-G over the surrogate's training cases that the acquisition reads
    (:meth:`gpg.kinds.base.Kind.posterior`: the model itself for ``gpg``, one factorisation of
    its training record for the hybrid); with ``hyper`` (other hyperparameters), rebuilt from
    ``dataset``."""
    if hyper is None:
        return _kind(sur).posterior(sur.model)
    if dataset is None:
        raise ValueError("rebuilding the posterior with other hyperparameters needs the dataset")
    arrays = training_arrays(sur, dataset)
    return ExactGP.fit(arrays.X, arrays.Y, arrays.dY, grad_dims=arrays.dims or None,
                       hyper=hyper, observed=arrays.observed, bases=arrays.bases)  # fmt: skip


@float64
def rebuild(sur, dataset: Dataset):
    """The model ``sur`` would have on all of ``dataset`` with its hyperparameters, normaliser
    and bins kept: what :func:`condition` must equal (the reference of the tests and of the
    ``design`` bench suite)."""
    arrays = dataclasses.replace(training_arrays(sur, dataset), partition=sur.model.partition)
    cfg = models.resolve_config(sur.model_name, sur.config)
    return _kind(sur).build(arrays, training_cases(sur).hyper, cfg).model


def training_arrays(sur, dataset: Dataset) -> Arrays:
    """``dataset`` normalised as ``sur``'s training data (no box or duplicate checks)."""
    y, J, _ = residuals(dataset, sur.simple, sur.noise_model)
    norm = sur.normalizer
    X, Y = np.asarray(norm.x(dataset.x)), np.asarray(norm.y(y))
    if J is None:
        return Arrays(X, Y, None, ())
    return models.gradient_arrays(X, Y, *normalised_gradients(norm, J, dataset.grad_dirs))


def output_hyper(sur, dataset: Dataset, weights: Mapping[str, float]) -> Hyper:
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


def merge_datasets(a: Dataset, b: Dataset) -> Dataset:
    """The cases of ``a`` then ``b``; gradients NaN where a side has none (raw samples
    dropped: an active design's cases have no fixed set of 8 runs)."""

    def jac(ds, part, n_out):
        j = getattr(ds, part)
        return np.full((ds.n, n_out, 7), np.nan) if j is None else j

    def dirs(ds):  # directional gradient columns (converted data) or the inputs' own
        return np.broadcast_to(np.eye(7), (ds.n, 7, 7)) if ds.grad_dirs is None else ds.grad_dirs

    noise = a.has_noise and b.has_noise
    grads = a.jac_aero is not None or b.jac_aero is not None
    directional = grads and (a.grad_dirs is not None or b.grad_dirs is not None)
    return Dataset(
        x=np.concatenate([a.x, b.x]),
        y_aero=np.concatenate([a.y_aero, b.y_aero]),
        y_noise=np.concatenate([a.y_noise, b.y_noise]) if noise else None,
        jac_aero=np.concatenate([jac(a, "jac_aero", 6), jac(b, "jac_aero", 6)]) if grads else None,
        jac_noise=np.concatenate([jac(a, "jac_noise", 3), jac(b, "jac_noise", 3)])
        if grads and noise
        else None,
        meta=a.meta,
        grad_dirs=np.concatenate([dirs(a), dirs(b)]) if directional else None,
    )


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
        return self.batch.runs


def box_samples(sur, n: int, seed: int) -> np.ndarray:
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
    sur,
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
    """The next ``batch`` cases for the simulator, for the surrogate ``sur`` fitted (or
    conditioned) on ``dataset``.

    ``candidates`` and ``reference``: arrays of states (·, 8), or (·, 7) in the body frame,
    in dataset units, or counts drawn from the surrogate's domain; pass visited states
    (flights, rollouts, those with ``in_domain`` False mapped into the box) as ``reference``
    to aim at them, weighted by ``reference_weights``. ``gradients``: ``all``, ``none`` or
    ``choose`` (per case, the
    perturbations worth their run). ``weights``: per-output weights (``{"Fx": 1, ...}``) whose
    fitted kernel the acquisition uses (:func:`output_hyper`); default, the surrogate's.
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
