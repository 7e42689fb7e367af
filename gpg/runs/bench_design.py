"""The ``design`` suite of ``python -m experiments.bench``: conditioning on new cases against a
rebuild, and one acquisition round, on one dataset.

The training set's last ``added`` points are the new cases. Per model (``gpg``,
``gpgs_hybrid``): the surrogate fitted on the others, then (a) conditioned on the added points
and (b) rebuilt on all points with the same hyperparameters, normaliser and bins; the seconds
and peak memory of each, and the largest difference of their test predictions (mean and
latent variance, normalised). Then one :func:`gpg.design.propose` round (``candidates``,
``batch``) on the conditioned ``gpg`` surrogate, timed whole.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from gpg import design
from gpg.data.cache import ensure_datasets
from gpg.linalg import memory
from gpg.runs.common import table
from gpg.surrogate import Surrogate


def bench_design(cfg: dict[str, Any]) -> dict[str, Any]:
    """See the module docstring; ``cfg``: ``added``, ``models``, ``propose`` (also the
    acquisition round), ``candidates``, ``batch``, ``reference``, ``cache_dir``."""
    train, test, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    train = train.without("raw samples") if train.has_raw else train
    n_old = train.n - int(cfg["added"])
    old, new = train.subset(np.arange(n_old)), train.subset(np.arange(n_old, train.n))
    out: dict[str, Any] = {"dataset": info["key"], "n_old": n_old, "added": int(cfg["added"])}
    conditioned = None
    for name in cfg["models"]:
        sur = Surrogate.fit(old, name)
        Xq = np.asarray(sur.normalizer.x(test.x))
        with memory.PeakRSS() as mem_c:
            t0 = time.perf_counter()
            grown = sur.condition(new)
            cond_s = time.perf_counter() - t0
        with memory.PeakRSS() as mem_r:
            t0 = time.perf_counter()
            ref = design.rebuild(sur, train)
            refit_s = time.perf_counter() - t0
        (m1, v1), (m2, v2) = grown.model.predict(Xq), ref.predict(Xq)
        out[name] = {
            "condition_s": cond_s,
            "rebuild_s": refit_s,
            "ratio": cond_s / refit_s,
            "condition_peak_bytes": mem_c.peak_delta,
            "rebuild_peak_bytes": mem_r.peak_delta,
            "max_diff_mean": float(np.max(np.abs(np.asarray(m1) - np.asarray(m2)))),
            "max_diff_var": float(np.max(np.abs(np.asarray(v1) - np.asarray(v2)))),
        }
        if name == "gpg":
            conditioned = grown
    if conditioned is not None and cfg.get("propose", True):
        kw = {k: int(cfg[k]) for k in ("candidates", "reference")}
        t0 = time.perf_counter()
        p = design.propose(conditioned, train, int(cfg["batch"]), seed=0, **kw)
        seconds = time.perf_counter() - t0
        picked = {"batch": int(cfg["batch"]), "gradient_runs": int(p.gradients.sum())}
        out["propose"] = {"seconds": seconds, "runs": p.runs, **kw, **picked}
    return out


def design_table(res: dict[str, Any]) -> str:
    rows = [{"model": k, **v} for k, v in res.items() if isinstance(v, dict) and "condition_s" in v]
    cols = [
        ("model", "model", ""),
        ("condition_s", "condition s", ".2f"),
        ("rebuild_s", "rebuild s", ".2f"),
        ("ratio", "ratio", ".3f"),
        ("max_diff_mean", "max |Δmean|", ".1e"),
        ("max_diff_var", "max |Δvar|", ".1e"),
    ]
    head = f"{res['dataset']}: {res['n_old']} points + {res['added']} added\n\n"
    tail = ""
    if "propose" in res:
        p = res["propose"]
        tail = (
            f"\n\npropose: {p['batch']} of {p['candidates']} candidates over "
            f"{p['reference']} reference states in {p['seconds']:.1f} s ({p['runs']} runs)"
        )
    return head + table(rows, cols) + tail
