"""Latin-hypercube sampling over the paper's bounds and finite-difference gradients.

Paper, Section "Data Collection": inputs are sampled by a Latin hypercube over airspeed
0–20 m/s, rotor speeds 0–7000 rpm, yaw ±90°, pitch ±60°, roll ±90°; gradients come from forward
differences with each rotor speed raised by 10 % and each angle by 1°. The seven perturbed
evaluations plus the base point are the "raw 8X samples" of the non-gradient baselines.

The paper's rpm step is undefined at 0 rpm (a 10 % step of nothing); here the step is
``max(0.1 r, rpm_floor)`` with a 10 rpm floor by default.

The body frame (``frame="body"``, the whole flight envelope): rotor speeds as above and the air
velocity in the body frame from every direction, ``(u, v, w) = s·d`` with the speed ``s``
uniform in ``[airspeed]`` and the direction ``d`` uniform on the sphere (one Latin hypercube
over rotor speeds, speed, ``d_z`` and the azimuth of ``d``): hover, axial climb and descent and
air from behind are all inside. Forward differences step each rotor speed as above and each
air-velocity component by ``fd.velocity`` (m/s): the same 8 runs a case as the paper's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from functools import partial
from typing import Any

import numpy as np
from scipy.stats import qmc

from gpg._dtype import float64
from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.quadrotor.generator import Generator, evaluate_batch

__all__ = [
    "FDSteps",
    "fd_meta",
    "forward_differences",
    "generate",
    "latin_hypercube",
    "raw_samples",
]


def latin_hypercube(
    n: int, bounds: Bounds | tuple[np.ndarray, np.ndarray], seed: int, frame: str = "airflow"
) -> np.ndarray:
    """Inputs from a scrambled Latin hypercube (``scipy.stats.qmc``).

    In the airflow frame the hypercube spans the box; in the body frame it gives rotor speeds
    in ``bounds.rpm`` and air velocities ``s·d``, ``s`` uniform in ``bounds.airspeed``, ``d``
    uniform on the sphere (see the module docstring).

    Args:
        n: the number of inputs.
        bounds: a :class:`~gpg.data.Bounds`, or (airflow frame only) a box given as its lower
            and upper corners, (8,) each.
        seed: the hypercube's seed.
        frame: ``"airflow"`` or ``"body"``.

    Returns:
        (n, 8) inputs in rpm, rad and m/s; (n, 7) in the body frame.

    Raises:
        ValueError: if ``n < 1``, ``frame`` is unknown, or the body frame gets corners
            instead of a Bounds.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if frame == "body":
        if not isinstance(bounds, Bounds):
            raise ValueError("the body frame samples from a Bounds (rpm and airspeed)")
        unit = qmc.LatinHypercube(d=7, rng=np.random.default_rng(seed)).random(n)
        rpm = qmc.scale(unit[:, :4], [bounds.rpm[0]] * 4, [bounds.rpm[1]] * 4)
        s = bounds.airspeed[0] + (bounds.airspeed[1] - bounds.airspeed[0]) * unit[:, 4]
        dz = 2.0 * unit[:, 5] - 1.0  # uniform on the sphere: d_z uniform in [-1, 1]
        az = 2.0 * np.pi * unit[:, 6]
        rho = np.sqrt(np.maximum(1.0 - dz**2, 0.0))
        vel = s[:, None] * np.stack([rho * np.cos(az), rho * np.sin(az), dz], axis=1)
        return np.concatenate([rpm, vel], axis=1)
    if frame != "airflow":
        raise ValueError(f"frame must be 'airflow' or 'body', got {frame!r}")
    lo, hi = bounds.arrays() if isinstance(bounds, Bounds) else bounds
    unit = qmc.LatinHypercube(d=8, rng=np.random.default_rng(seed)).random(n)
    return qmc.scale(unit, lo, hi)


@dataclass(frozen=True)
class FDSteps:
    """Forward-difference steps: rotor speeds by ``rpm_rel`` (floored), angles by ``angle_deg``,
    body-frame air-velocity components by ``velocity`` (m/s)."""

    rpm_rel: float = 0.10
    rpm_floor: float = 10.0
    angle_deg: float = 1.0
    velocity: float = 0.1

    def __post_init__(self):
        for k, v in asdict(self).items():
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"fd.{k} must be > 0, got {v}")

    def steps(self, x: np.ndarray) -> np.ndarray:
        """The forward-difference step of each of the 7 gradient inputs at each point.

        Rotor speeds step by ``rpm_rel`` of their value, at least ``rpm_floor``; the angles
        by ``angle_deg`` in the airflow frame (``x`` with 8 columns), the air velocity by
        ``velocity`` in the body frame (7 columns).

        Args:
            x: (N, 8) or (N, 7) points in dataset units.

        Returns:
            (N, 7) steps in the inputs' units (rpm, rad or m/s).
        """
        h_rpm = np.maximum(self.rpm_rel * x[:, :4], self.rpm_floor)
        h = math.radians(self.angle_deg) if x.shape[1] == 8 else self.velocity
        return np.concatenate([h_rpm, np.full((x.shape[0], 3), h)], axis=1)


def raw_samples(x: np.ndarray, fd: FDSteps) -> tuple[np.ndarray, np.ndarray]:
    """The 8 raw inputs per point: the point, then one forward step of each gradient input.

    Args:
        x: (N, D) points in dataset units.
        fd: the steps.

    Returns:
        ``(x_raw, h)``: (8N, D) inputs, point-major (rows ``8i..8i+7`` are point ``i`` and its
        seven perturbations), and the (N, 7) steps.
    """
    h = fd.steps(x)
    d = x.shape[1]
    pert = np.repeat(x[:, None, :], 8, axis=1)  # (N, 8, D): base + 7 perturbations
    idx = np.arange(7)
    pert[:, 1 + idx, idx] += h
    return pert.reshape(-1, d), h


def forward_differences(y_raw: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The base outputs and their forward-difference gradients from the raw samples.

    Args:
        y_raw: (8N, M) outputs at the point-major raw inputs of :func:`raw_samples`.
        h: (N, 7) their steps.

    Returns:
        ``(y, J)``: the (N, M) base outputs and the (N, M, 7) gradients.
    """
    y8 = y_raw.reshape(h.shape[0], 8, -1)
    y = y8[:, 0]
    return y, (y8[:, 1:] - y[:, None]).transpose(0, 2, 1) / h[:, None, :]


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
    frame: str = "airflow",
) -> Dataset:
    """Sample inputs and evaluate the generator on them: a dataset.

    In the airflow frame (the paper's) or the body frame (``frame="body"``: the whole
    envelope, see the module docstring). The metadata record the generator, bounds, seed and
    steps.

    Args:
        gen: the generator (BEMT and tonal acoustics of a vehicle).
        n: the number of cases.
        bounds: the sampling box.
        seed: the Latin hypercube's seed.
        gradients: ``"fd"`` (the paper's forward differences; also yields the raw 8X
            samples), ``"exact"`` (forward-mode autodiff through the generator) or ``"none"``.
        fd: the forward-difference steps.
        keep_raw: keep the raw 8X samples (needs ``gradients="fd"``).
        noise: keep the levels (noise outputs).
        chunk: cases per batch of evaluations.
        progress: a progress bar, or its label.
        meta: more metadata to record.
        workers: processes that share the evaluations; the dataset is bit-identical for any
            number of them.
        frame: ``"airflow"`` or ``"body"``.

    Returns:
        The :class:`~gpg.data.Dataset`.

    Raises:
        ValueError: if ``gradients`` is unknown, or ``keep_raw`` is asked for without
            ``gradients="fd"``.
    """
    if gradients not in ("fd", "exact", "none"):
        raise ValueError(f"gradients must be 'fd', 'exact' or 'none', got {gradients!r}")
    if keep_raw and gradients != "fd":
        raise ValueError("raw 8X samples come from the finite differences: use gradients='fd'")
    x = latin_hypercube(n, bounds, seed, frame)
    jac = x_raw = y_raw = None
    ev = partial(evaluate_batch, gen, chunk=chunk, progress=progress, workers=workers, frame=frame)
    if gradients == "fd":
        x_raw, h = raw_samples(x, fd)
        y_raw = ev(x_raw)
        y, jac = forward_differences(y_raw, h)
    elif gradients == "exact":
        y, jac = ev(x, with_jacobian=True)
    else:
        y = ev(x)
    out = slice(None) if noise else slice(0, 6)
    info = {
        # The dataset names its vehicle (Surrogate.fit reads it); callers may record more.
        "generator": {"name": "gpg BEMT + tonal acoustics", "vehicle": gen.vehicle.name},
        "bounds": _bounds_meta(bounds, frame),
        "seed": seed,
        "gradients": gradients,
        "fd": fd_meta(fd, frame) if gradients == "fd" else None,
        "raw_layout": "point-major: row 8i is point i, rows 8i+1..8i+7 perturb x_0..x_6"
        if keep_raw
        else None,
        **({"frame": frame} if frame != "airflow" else {}),
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


def _bounds_meta(bounds: Bounds, frame: str) -> dict[str, Any]:
    """The bounds a dataset records: the body frame's are the rotor speeds and the ball."""
    out = asdict(bounds)
    return out if frame == "airflow" else {k: out[k] for k in ("rpm", "airspeed")}


def fd_meta(fd: FDSteps, frame: str) -> dict[str, Any]:
    """The steps a dataset records, those its frame uses.

    Args:
        fd: the steps.
        frame: ``"airflow"`` (the angle step is kept) or ``"body"`` (the velocity step).

    Returns:
        The fields of ``fd`` without the step the frame does not use.
    """
    out = asdict(fd)
    out.pop("velocity" if frame == "airflow" else "angle_deg")
    return out
