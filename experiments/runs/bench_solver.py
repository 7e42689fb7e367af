"""The ``solver`` suite of ``python -m experiments.bench``: the default model's exact mean by a
dense Cholesky factorisation and by matrix-free conjugate gradients, on one dataset.

Per solver: the build's seconds and peak memory, CG's iterations, setup and solve seconds; the
test predictions of each CG model against the Cholesky model's in units of each output's
standard deviation (the normalised outputs), and every model's test MAE in physical units.
The CG runs come first: a process's peak memory only grows, so the dense run cannot hide
theirs.
"""

from __future__ import annotations

import time
from typing import Any

import jax.numpy as jnp
import numpy as np

from experiments.runs.config import conf
from experiments.runs.output import table
from gpg import models
from gpg.conf import deep_merge
from gpg.data.cache import ensure_datasets
from gpg.data.preprocess import prepare, restore, simple_model_for
from gpg.linalg import memory
from gpg.quadrotor.vehicle import Vehicle

MODEL = "gpgs_hybrid"


def _mean(model, Xn: np.ndarray, chunk: int = 512) -> np.ndarray:
    return np.concatenate(
        [
            np.asarray(model.predict_mean(jnp.asarray(Xn[s : s + chunk])))
            for s in range(0, len(Xn), chunk)
        ]
    )


def bench_solver(cfg: dict[str, Any]) -> dict[str, Any]:
    """See the module docstring; ``cfg``: ``tols`` (CG tolerances tried), ``cholesky`` (also
    the dense solve), ``model`` (overrides of the model's config), ``cache_dir``."""
    train, test, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    training = prepare(train, simple_model_for(train, Vehicle.from_config(cfg["vehicle"])))
    base = deep_merge(conf(MODEL, "model"), cfg.get("model"))
    t0 = time.perf_counter()
    hyper = models.fit_hyper(MODEL, training, models.resolve_config(MODEL, base))[0]
    out: dict[str, Any] = {
        "dataset": info["key"],
        "n_train": train.n,
        "rows": int(training.X.shape[0] * (1 + training.dY.shape[2])),
        "hyper_s": time.perf_counter() - t0,
        "runs": {},
    }
    Xn = np.asarray(training.normalizer.x(test.x))
    means = {}
    runs = [("cg", t) for t in cfg["tols"]] + ([("cholesky", None)] if cfg["cholesky"] else [])
    for method, tol in runs:
        label = method if tol is None else f"cg tol={tol:g}"
        solver = {"method": method, **({} if tol is None else {"tol": float(tol)})}
        mcfg = models.resolve_config(MODEL, deep_merge(base, {"solver": solver}))
        with memory.PeakRSS() as mem:
            t0 = time.perf_counter()
            built = models.build(MODEL, training, mcfg, hyper=hyper)
            seconds = time.perf_counter() - t0
        means[label] = _mean(built.model, Xn)
        y = restore(training, test.x, means[label])
        mae = np.mean(np.abs(y - test.y[:, : y.shape[1]]), axis=0)
        out["runs"][label] = {
            "build_s": seconds,
            "peak_bytes": mem.peak_delta,
            **built.diagnostics,
            "mae": dict(zip(training.output_names, mae.tolist(), strict=True)),
        }
    if "cholesky" in means:
        for label, m in means.items():
            diff = np.max(np.abs(m - means["cholesky"]), axis=0)  # normalised: units of std
            out["runs"][label]["max_diff_std"] = dict(
                zip(training.output_names, diff.tolist(), strict=True)
            )
    return out


def solver_table(res: dict[str, Any]) -> str:
    rows = []
    for label, r in res["runs"].items():
        rows.append(
            {
                "label": label,
                "build": r["build_s"],
                "peak": (r["peak_bytes"] or 0) / 2**30,
                "it": r.get("cg_iterations"),
                "diff": max(r["max_diff_std"].values()) if "max_diff_std" in r else None,
                "fx": r["mae"].get("Fx"),
            }
        )
    cols = [
        ("label", "solver", ""),
        ("build", "build s", ".1f"),
        ("peak", "peak GiB", ".2f"),
        ("it", "CG iterations", "d"),
        ("diff", "max |Δmean|/std", ".1e"),
        ("fx", "MAE Fx", ".4g"),
    ]
    head = f"{res['dataset']}: {res['n_train']} points, K̄ {res['rows']} rows\n\n"
    return head + table(rows, cols)
