"""The ``design`` suite of ``python -m experiments.bench``: conditioning on new cases against a
rebuild, and one acquisition round, on one dataset.

The training set's last ``added`` points are the new cases. Per model (``gpg``,
``gpgs_hybrid``): the surrogate fitted on the others, then (a) conditioned on the added points
and (b) rebuilt on all points with the same hyperparameters, normaliser and bins; the seconds
and peak memory of each (the first call, which compiles, and the median of ``repeats − 1``
more: a loop conditions again and again), and the largest difference of their test
predictions (mean and latent variance, normalised). Then one :func:`gpg.design.propose`
round (``candidates``, ``batch``) on the conditioned ``gpg`` surrogate, timed whole.
"""

from __future__ import annotations

import time
from typing import Any

import equinox as eqx
import jax
import numpy as np

from gpg import design
from gpg.data.cache import ensure_datasets
from gpg.linalg import memory
from gpg.runs.common import table
from gpg.runs.design import release_memory
from gpg.surrogate import Surrogate


def bench_design(cfg: dict[str, Any]) -> dict[str, Any]:
    """See the module docstring; ``cfg``: ``added``, ``models``, ``repeats``, ``propose``
    (also the acquisition round), ``candidates``, ``batch``, ``reference``, ``cache_dir``."""
    train, test, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    train = train.without("raw samples") if train.has_raw else train
    n_old = train.n - int(cfg["added"])
    old, new = train.subset(np.arange(n_old)), train.subset(np.arange(n_old, train.n))
    out: dict[str, Any] = {"dataset": info["key"], "n_old": n_old, "added": int(cfg["added"])}
    conditioned = None
    for name in cfg["models"]:
        sur = Surrogate.fit(old, name)
        Xq = np.asarray(sur.normalizer.x(test.x))
        repeats = int(cfg.get("repeats", 1))
        with memory.PeakRSS() as mem_c:
            cond_s, grown = _timed(lambda sur=sur: sur.condition(new), repeats)
        m1, v1 = grown.model.predict(Xq)
        if name == "gpg" and cfg.get("propose", True):
            conditioned = grown  # the acquisition round's model
        # Each model is freed before the next is built, and the surrogate's own factor too:
        # at data=paper a rebuild's K̄ does not fit beside them.
        del grown
        sur = _without_factor(sur)
        release_memory()  # what was freed goes back to the system the check reads
        with memory.PeakRSS() as mem_r:
            refit_s, ref = _timed(lambda sur=sur: design.rebuild(sur, train), repeats)
        m2, v2 = ref.predict(Xq)
        del ref
        out[name] = {
            "condition_first_s": cond_s[0],
            "rebuild_first_s": refit_s[0],
            "condition_s": float(np.median(cond_s[1:] or cond_s)),
            "rebuild_s": float(np.median(refit_s[1:] or refit_s)),
            "condition_runs_s": cond_s,
            "rebuild_runs_s": refit_s,
            "condition_peak_bytes": mem_c.peak_delta,
            "rebuild_peak_bytes": mem_r.peak_delta,
            "max_diff_mean": float(np.max(np.abs(np.asarray(m1) - np.asarray(m2)))),
            "max_diff_var": float(np.max(np.abs(np.asarray(v1) - np.asarray(v2)))),
        }
        out[name]["ratio"] = out[name]["condition_s"] / out[name]["rebuild_s"]
    if conditioned is not None and cfg.get("propose", True):
        kw = {k: int(cfg[k]) for k in ("candidates", "reference")}
        t0 = time.perf_counter()
        p = design.propose(conditioned, train, int(cfg["batch"]), seed=0, **kw)
        seconds = time.perf_counter() - t0
        picked = {"batch": int(cfg["batch"]), "gradient_runs": int(p.gradients.sum())}
        out["propose"] = {"seconds": seconds, "runs": p.runs, **kw, **picked}
    return out


def _without_factor(sur):
    """``sur`` with its model's mean view where a rebuild can still be read from that (the
    exact model's inputs and hyperparameters stay; the factor, R²/2 floats, goes)."""
    light = eqx.tree_at(lambda s: s.model, sur, sur.model.mean_view())
    try:
        design.training_cases(light)
    except ValueError:  # the hybrid's mean view drops the record the rebuild reads
        return sur
    return light


def _timed(fn, repeats: int) -> tuple[list[float], Any]:
    """Seconds of ``repeats`` calls of ``fn`` (the first one compiles) and its last result."""
    seconds, out = [], None
    for _ in range(max(repeats, 1)):
        out = None  # the last result freed first: the peak memory is one call's
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        seconds.append(time.perf_counter() - t0)
    return seconds, out


def design_table(res: dict[str, Any]) -> str:
    rows = [{"model": k, **v} for k, v in res.items() if isinstance(v, dict) and "condition_s" in v]
    cols = [
        ("model", "model", ""),
        ("condition_first_s", "condition s (first)", ".2f"),
        ("rebuild_first_s", "rebuild s (first)", ".2f"),
        ("condition_s", "condition s (again)", ".2f"),
        ("rebuild_s", "rebuild s (again)", ".2f"),
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
