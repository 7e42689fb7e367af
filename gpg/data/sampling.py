"""Latin-hypercube sampling over the paper's bounds and finite-difference gradients.

Paper, Section "Data Collection": inputs are sampled by a Latin hypercube over airspeed
0–20 m/s, rotor speeds 0–7000 rpm, yaw ±90°, pitch ±60°, roll ±90°; gradients come from forward
differences with each rotor speed raised by 10 % and each angle by 1°. The seven perturbed
evaluations plus the base point are the "raw 8X samples" of the non-gradient baselines.

The paper's rpm step is undefined at 0 rpm (a 10 % step of nothing); here the step is
``max(0.1 r, rpm_floor)`` with a 10 rpm floor by default.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.stats import qmc

from gpg._dtype import float64
from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.quadrotor.generator import Generator, evaluate_batch


def latin_hypercube(
    n: int, bounds: Bounds | tuple[np.ndarray, np.ndarray], seed: int
) -> np.ndarray:
    """``n`` inputs (n, 8) from a scrambled Latin hypercube (``scipy.stats.qmc``) over
    ``bounds``, or over a box given as its lower and upper corners (8,) each."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    lo, hi = bounds.arrays() if isinstance(bounds, Bounds) else bounds
    unit = qmc.LatinHypercube(d=8, rng=np.random.default_rng(seed)).random(n)
    return qmc.scale(unit, lo, hi)


@dataclass(frozen=True)
class FDSteps:
    """Forward-difference steps: rotor speeds by ``rpm_rel`` (floored), angles by ``angle_deg``."""

    rpm_rel: float = 0.10
    rpm_floor: float = 10.0
    angle_deg: float = 1.0

    def __post_init__(self):
        for k, v in asdict(self).items():
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"fd.{k} must be > 0, got {v}")

    def steps(self, x: np.ndarray) -> np.ndarray:
        """Step of each of the 7 gradient inputs at each point (N, 7)."""
        h_rpm = np.maximum(self.rpm_rel * x[:, :4], self.rpm_floor)
        h_ang = np.full((x.shape[0], 3), math.radians(self.angle_deg))
        return np.concatenate([h_rpm, h_ang], axis=1)


def raw_samples(x: np.ndarray, fd: FDSteps) -> tuple[np.ndarray, np.ndarray]:
    """The 8 raw inputs per point (8N, 8), point-major, and the steps (N, 7)."""
    h = fd.steps(x)
    pert = np.repeat(x[:, None, :], 8, axis=1)  # (N, 8, 8): base + 7 perturbations
    idx = np.arange(7)
    pert[:, 1 + idx, idx] += h
    return pert.reshape(-1, 8), h


@float64
def generate(
    gen: Generator,
    n: int,
    *,
    bounds: Bounds = Bounds(),  # noqa: B008  (frozen: one shared default is safe)
    seed: int = 0,
    gradients: str = "fd",
    fd: FDSteps = FDSteps(),
    keep_raw: bool = True,
    noise: bool = True,
    chunk: int = 512,
    progress: bool | str = False,
    meta: Mapping[str, Any] | None = None,
    workers: int = 1,
) -> Dataset:
    """Sample ``n`` inputs and evaluate the generator.

    ``gradients``: ``"fd"`` (the paper's forward differences; also yields the raw 8X samples),
    ``"exact"`` (forward-mode autodiff through the generator) or ``"none"``. ``workers``
    processes share the evaluations; the dataset is bit-identical for any number of them.
    """
    if gradients not in ("fd", "exact", "none"):
        raise ValueError(f"gradients must be 'fd', 'exact' or 'none', got {gradients!r}")
    if keep_raw and gradients != "fd":
        raise ValueError("raw 8X samples come from the finite differences: use gradients='fd'")
    x = latin_hypercube(n, bounds, seed)
    jac = x_raw = y_raw = None
    if gradients == "fd":
        x_raw, h = raw_samples(x, fd)
        y_raw = evaluate_batch(gen, x_raw, chunk=chunk, progress=progress, workers=workers)
        y8 = y_raw.reshape(n, 8, 9)
        y = y8[:, 0]
        jac = (y8[:, 1:] - y[:, None]).transpose(0, 2, 1) / h[:, None, :]  # (N, 9, 7)
    elif gradients == "exact":
        y, jac = evaluate_batch(
            gen, x, chunk=chunk, with_jacobian=True, progress=progress, workers=workers
        )
    else:
        y = evaluate_batch(gen, x, chunk=chunk, progress=progress, workers=workers)
    out = slice(None) if noise else slice(0, 6)
    info = {
        # The dataset names its vehicle (Surrogate.fit reads it); callers may record more.
        "generator": {"name": "gpg BEMT + tonal acoustics", "vehicle": gen.vehicle.name},
        "bounds": asdict(bounds),
        "seed": seed,
        "gradients": gradients,
        "fd": asdict(fd) if gradients == "fd" else None,
        "raw_layout": "point-major: row 8i is point i, rows 8i+1..8i+7 perturb x_0..x_6"
        if keep_raw
        else None,
        **dict(meta or {}),
    }
    return Dataset(
        x=x,
        y_aero=y[:, :6],
        jac_aero=None if jac is None else jac[:, :6],
        y_noise=y[:, 6:] if noise else None,
        jac_noise=None if jac is None or not noise else jac[:, 6:],
        x_raw=x_raw if keep_raw else None,
        y_raw=y_raw[:, out] if keep_raw else None,
        meta=info,
    )
