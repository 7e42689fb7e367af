"""New cases without a refit: a fitted surrogate conditioned on more cases.

:func:`condition` (also :meth:`gpg.Surrogate.condition`) gives the surrogate on more cases,
hyperparameters, normaliser and bins kept, equal to a rebuild with the same hyperparameters
(:func:`rebuild`, the reference the tests compare against). Exact (``gp``, ``gpg``): a
bordered Cholesky update (:meth:`gpg.gp.exact.ExactGP.condition`); hybrid: ``α`` re-formed
and the bins whose near set changed refactorised (:meth:`gpg.kinds.hybrid.Hybrid.condition`).
The model is read only through its kind (:meth:`gpg.kinds.base.Kind.cases`,
:meth:`~gpg.kinds.base.Kind.condition`, :meth:`~gpg.kinds.base.Kind.posterior`).

When to refit the hyperparameters instead of conditioning: conditioning keeps the
lengthscales that the old cases implied. Refit (``Surrogate.fit``) once the data have grown
by half since the last fit, or when the new cases fall where the model's ``in_domain`` was
False or its errors on them exceed what its variance promised (``experiments.design`` refits
at the first of those it can check: growth by half); otherwise condition.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from gpg import models
from gpg._dtype import float64
from gpg.data.dataset import Dataset
from gpg.data.preprocess import normalised_gradients, residuals
from gpg.gp.exact import ExactGP
from gpg.gp.hyper import Hyper
from gpg.gp.predictor import Predictor
from gpg.kinds.base import Arrays, Cases, Kind

__all__ = [
    "condition",
    "merge_datasets",
    "new_cases",
    "posterior",
    "rebuild",
    "training_cases",
]

# Normalised distance (in lengthscales) below which a new case duplicates a training case.
DUPLICATE_TOL = 1e-6


def training_cases(sur: Any) -> Cases:
    """The normalised training inputs, hyperparameters and gradient dims of a surrogate's model.

    Read through the model's kind (:meth:`gpg.kinds.base.Kind.cases`), so :mod:`gpg.design`
    never looks inside a model itself.

    Args:
        sur: a fitted :class:`gpg.Surrogate`.

    Returns:
        The :class:`~gpg.kinds.base.Cases` ``(X, hyper, grad_dims)`` of its model.

    Raises:
        ValueError: if the model's kind cannot condition (the kind raises it).
    """
    return _kind(sur).cases(sur.model)


def _kind(sur) -> Kind:
    return models.SPECS[sur.model_name].kind


def new_cases(sur: Any, dataset: Dataset, *, tol: float = 1e-9) -> Arrays:
    """New cases as the normalised arrays the surrogate was trained on, after every check.

    Every check that can fail runs here, before anything is changed. Refused: something other
    than a :class:`gpg.data.Dataset`; other outputs than the surrogate's (names), or cases in
    the other frame (airflow or body); inputs outside its domain, the box (and for the body
    frame the ball of air velocities ``|v| ≤ V``) behind ``in_domain`` (rows named: other
    units, degrees for radians or km/h for m/s, land there; to extend the domain, refit with
    wider ``bounds``); a case that duplicates a training case or another new case (closer than
    ``DUPLICATE_TOL`` lengthscales). NaN is refused by the dataset itself, except for a
    gradient whose perturbation was not run. A model that trains on the raw 8X samples
    (``gp``) gets the new cases' raw samples.

    Args:
        sur: the fitted :class:`gpg.Surrogate` the cases are for.
        dataset: the new cases, in dataset units.
        tol: how far outside the box an input may lie, as a fraction of the box's span (and
            of the ball's radius), before it is refused: room for rounding.

    Returns:
        The :class:`~gpg.kinds.base.Arrays` of the new cases, normalised with the surrogate's
        normaliser and with ``M`` subtracted; gradient rows only when both the cases and the
        model have gradients.

    Raises:
        ValueError: if ``dataset`` is not a Dataset, has other outputs or another frame, has a
            case outside the domain or a duplicate case, or lacks the raw samples the model
            trains on; naming the rows.
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
def condition(sur: Any, dataset: Dataset) -> Any:
    """A surrogate conditioned on the cases of a dataset (:meth:`gpg.Surrogate.condition`).

    The hyperparameters, normaliser, ``M`` and bins are kept; the result equals
    :func:`rebuild` on all the cases to rounding. Without fitted output scales
    (``hyper.output_scales`` off) the model's output scale stays 1.

    Args:
        sur: the fitted :class:`gpg.Surrogate`; it is not changed.
        dataset: the new cases (checked by :func:`new_cases`).

    Returns:
        A new :class:`gpg.Surrogate` whose model is conditioned on the new cases.

    Raises:
        ValueError: if the cases are refused (:func:`new_cases`), the model's kind cannot
            condition, or the conditioned model is not finite.
    """
    new = new_cases(sur, dataset)
    cfg = models.resolve_config(sur.model_name, sur.config)
    kind = models.SPECS[sur.model_name].kind
    model = kind.condition(sur.model, new, cfg)
    if not cfg.hyper.output_scales:
        model = model.with_output_scale(jnp.ones_like(model.output_scale))
    models.check_finite_model(sur.model_name, model)
    return eqx.tree_at(lambda s: s.model, sur, model)


@float64
def posterior(sur: Any, dataset: Dataset | None = None, *, hyper: Hyper | None = None) -> ExactGP:
    """The exact GP-G over the surrogate's training cases, the one the acquisition reads.

    Without ``hyper`` it is the kind's (:meth:`gpg.kinds.base.Kind.posterior`: the model
    itself for ``gpg``, one factorisation of its training record for the hybrid); with
    ``hyper`` (other hyperparameters, e.g. those fitted to the outputs that
    :func:`gpg.design.propose`'s ``weights`` name) it is rebuilt from ``dataset``, the
    training set.

    Args:
        sur: the fitted :class:`gpg.Surrogate`.
        dataset: the surrogate's training set; needed only with ``hyper``.
        hyper: hyperparameters to rebuild the GP-G with; None keeps the model's.

    Returns:
        The :class:`~gpg.gp.exact.ExactGP` on the normalised training cases.

    Raises:
        ValueError: if ``hyper`` is given without ``dataset``.
    """
    if hyper is None:
        return _kind(sur).posterior(sur.model)
    if dataset is None:
        raise ValueError("rebuilding the posterior with other hyperparameters needs the dataset")
    arrays = training_arrays(sur, dataset)
    return ExactGP.fit(arrays.X, arrays.Y, arrays.dY, grad_dims=arrays.dims or None,
                       hyper=hyper, observed=arrays.observed, bases=arrays.bases)  # fmt: skip


@float64
def rebuild(sur: Any, dataset: Dataset) -> Predictor:
    """The model a surrogate would have on all of a dataset, its fit's choices kept.

    Hyperparameters, normaliser and bins stay those of ``sur``: what :func:`condition` must
    equal (the reference of the tests and of the ``design`` bench suite).

    Args:
        sur: the fitted :class:`gpg.Surrogate`.
        dataset: all the cases, old and new (:func:`merge_datasets`).

    Returns:
        The predictor built by the model's kind on ``dataset``.
    """
    arrays = dataclasses.replace(training_arrays(sur, dataset), partition=sur.model.partition)
    cfg = models.resolve_config(sur.model_name, sur.config)
    return _kind(sur).build(arrays, training_cases(sur).hyper, cfg).model


def training_arrays(sur: Any, dataset: Dataset) -> Arrays:
    """A dataset normalised as the surrogate's training data, with no box or duplicate checks.

    Args:
        sur: the fitted :class:`gpg.Surrogate` whose ``M``, ``M_noise`` and normaliser apply.
        dataset: the cases, in dataset units.

    Returns:
        The :class:`~gpg.kinds.base.Arrays`: residuals against ``M`` normalised, and the
        gradient rows when ``dataset`` has gradients.
    """
    y, J, _ = residuals(dataset, sur.simple, sur.noise_model)
    norm = sur.normalizer
    X, Y = np.asarray(norm.x(dataset.x)), np.asarray(norm.y(y))
    if J is None:
        return Arrays(X, Y, None, ())
    return models.gradient_arrays(X, Y, *normalised_gradients(norm, J, dataset.grad_dirs))


def merge_datasets(a: Dataset, b: Dataset) -> Dataset:
    """The cases of one dataset followed by those of another.

    Gradients are NaN (not run) where a side has none, and the directions of the gradient
    columns are the inputs' own where a side has no ``grad_dirs``. Raw samples are dropped:
    an active design's cases have no fixed set of 8 runs. Noise is kept only when both sides
    have it; the metadata are ``a``'s.

    Args:
        a: the first cases (e.g. the training set).
        b: the cases appended after them (e.g. the told cases).

    Returns:
        The merged :class:`~gpg.data.Dataset`.
    """

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
