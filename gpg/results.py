"""The comparison's results as typed records, and the one pair of functions that writes and reads
them (``results.json`` of ``python -m experiments.compare``).

A model's run is a :class:`ModelRun` (everything measured) or a :class:`Skipped` (why it could
not run); the file holds them under ``"models"`` by label, beside the run's own facts
(:class:`Comparison`). The table, the figures and the notebooks read these records, never the
raw JSON keys, so a field added here reaches all of them.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gpg.runtime import write_json

__all__ = ["TIMINGS", "Comparison", "ModelRun", "Run", "Skipped", "read_results", "write_results"]

TIMINGS = ("hyper_s", "partition_s", "fit_s")  # build steps, written flat as before


@dataclass(frozen=True)
class ModelRun:
    """One model's measured run (units: outputs' own, N, N·m, dB; seconds; bytes).

    ``timings`` are the build's steps (:data:`TIMINGS`) and ``train_s`` their sum; ``mae``,
    ``rmse``, ``nlpd`` and ``coverage95`` map each output to its test value (NLPD and coverage
    over the queries with a computable variance, None when none has one); ``continuity`` the
    largest jumps across bin boundaries; ``noise_variance`` the fitted value noise ``ν²``
    (normalised); ``diagnostics`` what the build measured (Schur far-set correlations, PIC's
    inducing points); the ``predict_*`` latencies are single world-frame queries."""

    model: str
    title: str
    config: dict[str, Any]
    timings: dict[str, float]
    train_s: float
    mae: dict[str, float]
    rmse: dict[str, float]
    nlpd: dict[str, float] | None
    nlpd_mean: float | None
    coverage95: dict[str, float] | None
    coverage95_mean: float | None
    negative_variance_count: int
    negative_variance_fraction: float
    continuity: dict[str, Any]
    output_scale: list[float]
    hyper_converged: bool | None
    lengthscale: Any
    signal_variance: float
    noise_variance: float
    noise_ratio: float
    diagnostics: dict[str, Any]
    near_fraction: float | None
    near_epsilon: float | None
    model_bytes: int
    peak_memory_bytes: int | None
    error_vs_airspeed: dict[str, Any]
    predict_ms_median: float
    predict_ms_p95: float
    predict_mean_ms_median: float
    predict_mean_ms_p95: float
    predict_ratio_to_gp: float | None = None

    def to_json(self) -> dict[str, Any]:
        """The entry as ``results.json`` holds it.

        Returns:
            The fields as plain values, the build's timings flat beside ``train_s``.
        """
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "timings":
                out.update(value)
            elif f.name != "predict_ratio_to_gp" or value is not None:
                out[f.name] = value
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ModelRun:
        """An entry of ``results.json`` read back (:meth:`to_json`'s inverse).

        Args:
            d: the entry, its timings flat.

        Returns:
            The record.

        Raises:
            ValueError: if ``d`` has keys the record does not know (a newer file's).
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names - set(TIMINGS)
        if unknown:
            raise ValueError(f"results entry has unknown keys {sorted(unknown)}")
        kw = {k: v for k, v in d.items() if k in names}
        return cls(timings={k: d[k] for k in TIMINGS if k in d}, **kw)


@dataclass(frozen=True)
class Skipped:
    """A model that could not run (too little data, memory, a failed fit) and why."""

    model: str
    reason: str

    def to_json(self) -> dict[str, Any]:
        """The entry as ``results.json`` holds it.

        Returns:
            ``{"model": ..., "skipped": reason}``.
        """
        return {"model": self.model, "skipped": self.reason}


Run = ModelRun | Skipped


@dataclass(frozen=True)
class Comparison:
    """A whole ``results.json``: the runs by label and the facts of the comparison."""

    models: dict[str, Run]
    outputs: list[str]
    n_train: int
    n_test: int
    data: dict[str, Any]
    noise_reference: dict[str, Any] | None
    figures: list[str]
    wall_s: float
    machine: dict[str, Any]
    config: dict[str, Any]
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def ran(self) -> dict[str, ModelRun]:
        """The runs that produced results, by label."""
        return {k: r for k, r in self.models.items() if isinstance(r, ModelRun)}


_HEADER = ("machine", "data", "noise_reference", "n_train", "n_test", "outputs")


def write_results(path: str | Path, comp: Comparison) -> None:
    """Write a comparison's ``results.json``, atomically (:func:`gpg.runtime.write_json`).

    Args:
        path: the file to write.
        comp: the comparison.
    """
    out: dict[str, Any] = {k: getattr(comp, k) for k in _HEADER}
    out["models"] = {k: r.to_json() for k, r in comp.models.items()}
    out.update(figures=comp.figures, wall_s=comp.wall_s, config=comp.config, **comp.extra)
    write_json(Path(path), out)


def read_results(path: str | Path) -> Comparison:
    """A comparison read back from its ``results.json``.

    Args:
        path: the ``results.json``, or the run directory that holds it.

    Returns:
        The :class:`Comparison`, each model a :class:`ModelRun` or a :class:`Skipped`.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "results.json"
    d = json.loads(path.read_text(encoding="utf-8"))
    runs: dict[str, Run] = {}
    for label, r in d["models"].items():
        runs[label] = Skipped(r["model"], r["skipped"]) if "skipped" in r else ModelRun.from_json(r)
    known = {*_HEADER, "models", "figures", "wall_s", "config"}
    return Comparison(
        models=runs,
        outputs=d["outputs"],
        n_train=d["n_train"],
        n_test=d["n_test"],
        data=d["data"],
        noise_reference=d["noise_reference"],
        figures=d["figures"],
        wall_s=d["wall_s"],
        machine=d["machine"],
        config=d["config"],
        extra={k: v for k, v in d.items() if k not in known},
    )
