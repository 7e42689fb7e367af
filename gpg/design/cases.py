"""Ask and tell: the next cases as a CSV for an external solver, and its results read back.

:func:`write_ask` writes one row per simulator run: the case number, the run (``base``, or
the input whose forward-difference perturbation it is) and the inputs, in the user's column
names and units. The solver runs every row and adds its outputs as columns; :func:`read_tell`
reads that file through :func:`gpg.data.from_csv` (names, units and every value checked
there) and forms each case's forward-difference gradients, NaN for perturbations that were
not asked for, giving a :class:`gpg.data.Dataset` ready for :meth:`gpg.Surrogate.condition`.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from gpg._io import atomic_write
from gpg.data.dataset import Dataset, from_csv, unit_factor
from gpg.data.sampling import FDSteps
from gpg.names import AERO, GRAD_DIMS, GRAD_INPUTS, INPUTS, NOISE

__all__ = ["read_tell", "write_ask"]

CASE, RUN, BASE = "case", "run", "base"


def runs(x: np.ndarray, gradients: np.ndarray, fd: FDSteps) -> tuple[np.ndarray, list, list]:
    """The runs of cases ``x`` (B, 8) with perturbations ``gradients`` (B, 7): inputs (n, 8),
    case numbers and run labels."""
    steps = fd.steps(x)
    rows, case, label = [], [], []
    for i in range(x.shape[0]):
        rows.append(x[i])
        case.append(i)
        label.append(BASE)
        for g in np.flatnonzero(gradients[i]):
            p = x[i].copy()
            p[GRAD_DIMS[g]] += steps[i, g]
            rows.append(p)
            case.append(i)
            label.append(GRAD_INPUTS[g])
    return np.asarray(rows), case, label


def write_ask(
    path: str | Path,
    x: np.ndarray,
    gradients: np.ndarray,
    *,
    fd: FDSteps = FDSteps(),  # noqa: B008  (frozen)
    columns: Mapping[str, str] | None = None,
    units: Mapping[str, str] | None = None,
) -> Path:
    """Write the ask file: one row per simulator run of the proposed cases.

    Each case has its ``base`` run, then one run per perturbation asked for, labelled by the
    input it raises by its forward-difference step. The columns are ``case``, ``run`` and the
    inputs; the file is written atomically.

    Args:
        path: the CSV file to write (its folder is made).
        x: (B, 8) the cases, in dataset units (:attr:`gpg.design.Proposal.x`).
        gradients: (B, 7) which perturbations to run at each
            (:attr:`gpg.design.Proposal.gradients`).
        fd: the forward-difference steps.
        columns: the header each input is written under (default: the schema names).
        units: the unit each input is written in (default: rpm, rad, m/s).

    Returns:
        The path written.

    Raises:
        ValueError: if ``x`` is not (B, 8) or ``gradients`` not (B, 7), or a unit is unknown.
    """
    columns, units = dict(columns or {}), dict(units or {})
    x = np.asarray(x, dtype=float)
    gradients = np.asarray(gradients, dtype=bool)
    if x.ndim != 2 or x.shape[1] != 8 or gradients.shape != (x.shape[0], 7):
        raise ValueError(f"x must be (B, 8) and gradients (B, 7), got {x.shape}, {gradients.shape}")
    X, case, label = runs(x, gradients, fd)
    heads = [columns.get(f, f) for f in INPUTS]
    scale = np.array([unit_factor(f, units.get(f)) for f in INPUTS])
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([CASE, RUN, *heads])
    for c, lab, row in zip(case, label, X / scale, strict=True):
        w.writerow([c, lab, *(repr(float(v)) for v in row)])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, buf.getvalue().encode())
    return path


def read_tell(
    path: str | Path,
    columns: Mapping[str, str] | None = None,
    *,
    units: Mapping[str, str] | None = None,
    vehicle: Any = None,
    bounds: Mapping[str, Any] | None = None,
    meta: Mapping[str, Any] | None = None,
) -> Dataset:
    """The cases of an answered ask file, as a dataset with their gradients.

    Each case's ``base`` run gives its inputs and outputs, each perturbed run one column of
    its gradients (forward differences, in the dataset's units); perturbations not run are
    NaN. The file is read through :func:`gpg.data.from_csv`, which checks names, units and
    every value.

    Args:
        path: the answered ask file (:func:`write_ask`'s, with the outputs added).
        columns: schema fields to the file's headers (default: the schema names, with
            ``L1..L3`` if the file has them).
        units: the file's units where not the schema's, as for :func:`gpg.data.from_csv`.
        vehicle: the vehicle to record, as for :func:`gpg.data.from_csv`.
        bounds: the input box to record, as for :func:`gpg.data.from_csv`.
        meta: more metadata to record; ``meta["cases"]`` becomes the case numbers.

    Returns:
        The :class:`~gpg.data.Dataset` of the cases, in the order of their numbers.

    Raises:
        ValueError: if the file is missing or lacks the ``case`` or ``run`` column, a case
            number is not an integer or has no base run or two, a run is neither ``base``
            nor a gradient input, a perturbed run does not raise its input alone above the
            base run's or repeats one, or :func:`gpg.data.from_csv` refuses the file.
    """
    path = Path(path)
    header = _header(path)
    if columns is None:
        outs = AERO + (NOISE if all(n in header for n in NOISE) else ())
        columns = {f: f for f in INPUTS + outs}
    runs_ds = from_csv(path, columns, units=units, vehicle=vehicle, bounds=bounds, meta=meta)
    case, label = _labels(path, header)
    y = runs_ds.y
    bases: dict[int, int] = {}
    for i, (c, lab) in enumerate(zip(case, label, strict=True)):
        if lab == BASE:
            if c in bases:
                raise ValueError(f"{path.name}: case {c} has two base runs")
            bases[c] = i
    order = sorted(bases)
    missing = sorted(set(case) - set(bases))
    if missing:
        raise ValueError(f"{path.name}: case(s) {missing[:10]} have no base run")
    pos = {c: k for k, c in enumerate(order)}
    jac = np.full((len(order), y.shape[1], 7), np.nan)
    for i, (c, lab) in enumerate(zip(case, label, strict=True)):
        if lab == BASE:
            continue
        if lab not in GRAD_INPUTS:
            raise ValueError(
                f"{path.name}, data row {i + 1}: run {lab!r} is neither 'base' nor one of "
                f"{list(GRAD_INPUTS)}"
            )
        g = GRAD_INPUTS.index(lab)
        b = bases[c]
        dx = runs_ds.x[i] - runs_ds.x[b]
        d = GRAD_DIMS[g]
        others = np.delete(np.abs(dx), d)
        if not dx[d] > 0 or np.any(others > 1e-9 * (1 + np.abs(np.delete(runs_ds.x[b], d)))):
            raise ValueError(
                f"{path.name}, data row {i + 1}: run {lab!r} of case {c} must raise {lab} "
                "alone above the base run's"
            )
        if not np.isnan(jac[pos[c], 0, g]):
            raise ValueError(f"{path.name}: case {c} has two {lab!r} runs")
        jac[pos[c], :, g] = (y[i] - y[b]) / dx[d]
    idx = np.asarray([bases[c] for c in order])
    has_noise = runs_ds.has_noise
    return Dataset(
        x=runs_ds.x[idx],
        y_aero=runs_ds.y_aero[idx],
        y_noise=runs_ds.y_noise[idx] if has_noise else None,
        jac_aero=jac[:, :6],
        jac_noise=jac[:, 6:] if has_noise else None,
        meta={**runs_ds.meta, "cases": order},
    )


def _header(path: Path) -> list[str]:
    if not path.is_file():
        raise ValueError(f"CSV file {path} does not exist")
    with path.open(newline="", encoding="utf-8-sig") as f:
        return next(csv.reader(f), [])


def _labels(path: Path, header: list[str]) -> tuple[list[int], list[str]]:
    for col in (CASE, RUN):
        if col not in header:
            raise ValueError(f"{path.name} lacks the column {col!r} of an ask file")
    ci, ri = header.index(CASE), header.index(RUN)
    case, label = [], []
    with path.open(newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        next(reader)
        for row in reader:
            if not row:
                continue
            try:
                case.append(int(row[ci]))
            except ValueError:
                raise ValueError(
                    f"{path.name}, line {reader.line_num}: case {row[ci]!r} is not an integer"
                ) from None
            label.append(row[ri].strip())
    return case, label
