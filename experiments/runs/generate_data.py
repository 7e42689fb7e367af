"""Dataset generation (``python -m experiments.generate_data data=<scale> vehicle=<name>``).

Writes the training and test datasets into the run directory and into a cache keyed by the
configuration (so ``experiments.compare`` reuses them), plus sanity figures: thrust vs rpm,
forces and moments vs airspeed, OASPL vs rpm, and finite-difference vs exact gradients.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from experiments.runs.config import check_options
from experiments.runs.output import report
from gpg.data.cache import ensure
from gpg.data.dataset import Dataset
from gpg.data.preprocess import simple_model_for
from gpg.quadrotor.generator import Generator, evaluate_batch
from gpg.runtime import float64, write_json


def _gradient_check(gen: Generator, ds: Dataset, n: int) -> dict[str, Any]:
    """Finite-difference gradients of the dataset against exact ones on ``n`` of its points."""
    if ds.jac is None:
        return {}
    idx = np.arange(min(n, ds.n))
    _, exact = evaluate_batch(gen, ds.x[idx], chunk=32, with_jacobian=True, frame=ds.frame)
    fd = ds.jac[idx]
    exact = exact[:, : fd.shape[1]]
    scale = np.std(exact, axis=0, keepdims=True) + 1e-12  # per output and input
    err = np.abs(fd - exact) / scale
    return {"idx": idx, "fd": fd, "exact": exact, "scaled_error": err}


@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Generate (or load from cache) the configured datasets, copy them to ``outdir``, plot."""
    outdir = Path(outdir)
    check_options(cfg, {"figures": "bool", "sanity_points": "index", "cache_dir": "path"})
    data_cfg, vehicle_cfg = cfg["data"], cfg["vehicle"]
    gen, train, test, where, info = ensure(data_cfg, vehicle_cfg, cfg["cache_dir"])
    for split in ("train", "test"):
        for ext in (".npz", ".json"):
            shutil.copyfile(where / f"{split}{ext}", outdir / f"{split}{ext}")
    simple = simple_model_for(train, gen.vehicle)
    result: dict[str, Any] = {
        "dataset": info,
        "train": train.summary(),
        "test": test.summary(),
        "simple_model": train.meta["simple_model"],
        "hover_rpm_simple_model": float(simple.hover_rpm(float(gen.vehicle.weight))),
    }
    if cfg.get("figures", True):
        from experiments.runs import plots

        check = _gradient_check(gen, train, int(cfg.get("sanity_points", 200)))
        figs = plots.data_sanity(gen, simple, check, outdir / "figures")
        result["figures"] = [str(p.relative_to(outdir)) for p in figs]
        if check:
            med = np.median(check["scaled_error"], axis=0)  # (M, 7)
            result["fd_vs_exact_median_scaled_error"] = {
                name: med[m].round(5).tolist() for m, name in enumerate(train.output_names)
            }
    write_json(outdir / "results.json", {"config": cfg, **result})
    report(f"dataset {info['key']}: {result['train']}")
    if info["generate_s"] is not None:
        report(f"generated in {info['generate_s']:.1f} s; cached at {where}")
    else:
        report(f"loaded from cache {where}")
    return result


__all__ = ["run"]
