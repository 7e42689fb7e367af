"""The ``design`` suite of ``python -m experiments.bench``: conditioning on new cases against a
rebuild, and one acquisition round, on one dataset.

The training set's last ``added`` points are the new cases. Per model (``gpg``,
``gpgs_hybrid``): the surrogate fitted on the others, then (a) conditioned on the added points
and (b) rebuilt on all points with the same hyperparameters, normaliser and bins; the seconds
and peak memory of each (the first call, which compiles, and the median of ``repeats − 1``
more: a loop conditions again and again), and the largest difference of their test
predictions (mean and latent variance, normalised). With ``refit``, also (c) the refit a user
without ``condition`` runs: :meth:`Surrogate.fit` on all points, hyperparameters fitted
again, timed once. Then one :func:`gpg.design.propose`
round (``candidates``, ``batch``) on the conditioned ``gpg`` surrogate, timed whole. The
conditioning and the rebuild each run in a fresh process (``isolate``, see :func:`bench_design`).
"""

from __future__ import annotations

import time
from typing import Any

import equinox as eqx
import jax
import numpy as np

from experiments.runs.design import release_memory
from experiments.runs.output import table
from gpg import design
from gpg.data.cache import ensure_datasets
from gpg.linalg import memory
from gpg.surrogate import Surrogate


def bench_design(cfg: dict[str, Any]) -> dict[str, Any]:
    """See the module docstring; ``cfg``: ``added``, ``models``, ``repeats``, ``propose``
    (also the acquisition round), ``candidates``, ``batch``, ``reference``, ``cache_dir``,
    ``isolate``, ``refit`` (also time a refit with the hyperparameters fitted again).

    With ``isolate`` (the default) each model's conditioning (with the acquisition round) and
    its rebuild run in two fresh processes, one after the other: at data=paper a process that
    has held a 12.8 GB factor keeps several GB of it (measured: about 7 GB after every array
    was dropped and the heap trimmed), and a rebuild's ``K̄`` then does not fit beside it. Each
    figure is then also that of a process doing nothing else."""
    train, _, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    n_old = train.n - int(cfg["added"])
    out: dict[str, Any] = {"dataset": info["key"], "n_old": n_old, "added": int(cfg["added"])}
    isolate = bool(cfg.get("isolate", True))
    for name in cfg["models"]:
        cond, light, m1, v1 = _call(isolate, _condition_part, cfg, name)
        rebuild_s, peak_r, m2, v2 = _call(isolate, _rebuild_part, cfg, light)
        refit_s = _call(isolate, _refit_part, cfg, name) if cfg.get("refit", False) else None
        del light
        res = {
            "condition_first_s": cond["seconds"][0],
            "rebuild_first_s": rebuild_s[0],
            "condition_s": float(np.median(cond["seconds"][1:] or cond["seconds"])),
            "rebuild_s": float(np.median(rebuild_s[1:] or rebuild_s)),
            "condition_runs_s": cond["seconds"],
            "rebuild_runs_s": rebuild_s,
            "condition_peak_bytes": cond["peak_bytes"],
            "rebuild_peak_bytes": peak_r,
            "max_diff_mean": float(np.max(np.abs(m1 - m2))),
            "max_diff_var": float(np.max(np.abs(v1 - v2))),
            "isolated": isolate,
        }
        res["ratio"] = res["condition_s"] / res["rebuild_s"]
        if refit_s is not None:
            res["refit_s"] = refit_s
            res["ratio_refit"] = res["condition_s"] / refit_s
        out[name] = res
        if "propose" in cond:
            out["propose"] = cond["propose"]
    return out


def _call(isolate: bool, fn, *args):
    """``fn(*args)``, in a fresh (spawned) process when ``isolate``."""
    if not isolate:
        return fn(*args)
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # A spawned process starts with JAX's default precision. It is set by the initializer,
    # before the task's arguments are unpickled: set inside the task, it came after, and the
    # surrogate passed to the rebuild arrived as float32 (the rebuild then differed by 5e-7).
    x64 = bool(jax.config.read("jax_enable_x64"))
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx, initializer=_x64, initargs=(x64,)) as pool:
        return pool.submit(fn, *args).result()


def _x64(on: bool) -> None:
    jax.config.update("jax_enable_x64", on)


def _split(cfg):
    train, test, _, _ = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    train = train.without("raw samples") if train.has_raw else train
    n_old = train.n - int(cfg["added"])
    return train, test, train.subset(np.arange(n_old)), train.subset(np.arange(n_old, train.n))


def _condition_part(cfg: dict[str, Any], name: str):
    """Fit ``name`` on the old points, time its conditioning on the added ones (and, for
    ``gpg``, one acquisition round on the result); the fitted surrogate without its factor
    (what a rebuild reads) and the conditioned model's test predictions."""
    train, test, old, new = _split(cfg)
    sur = Surrogate.fit(old, name)
    Xq = np.asarray(sur.normalizer.x(test.x))
    with memory.PeakRSS() as mem:
        seconds, grown = _timed(lambda: sur.condition(new), int(cfg.get("repeats", 1)))
    m, v = (np.asarray(a) for a in grown.model.predict(Xq))
    out: dict[str, Any] = {"seconds": seconds, "peak_bytes": mem.peak_delta}
    if name == "gpg" and cfg.get("propose", True):
        kw = {k: int(cfg[k]) for k in ("candidates", "reference")}
        t0 = time.perf_counter()
        p = design.propose(grown, train, int(cfg["batch"]), seed=0, **kw)
        picked = {"batch": int(cfg["batch"]), "gradient_runs": int(p.gradients.sum())}
        out["propose"] = {"seconds": time.perf_counter() - t0, "runs": p.runs, **kw, **picked}
    return out, _without_factor(sur), m, v


def _rebuild_part(cfg: dict[str, Any], sur):
    """Time the rebuild of ``sur`` on all the points; its test predictions."""
    train, test, _, _ = _split(cfg)
    release_memory()  # in-process runs: what the conditioning freed goes back first
    with memory.PeakRSS() as mem:
        seconds, ref = _timed(lambda: design.rebuild(sur, train), int(cfg.get("repeats", 1)))
    m, v = (np.asarray(a) for a in ref.predict(np.asarray(sur.normalizer.x(test.x))))
    return seconds, mem.peak_delta, m, v


def _refit_part(cfg: dict[str, Any], name: str) -> float:
    """Seconds of one :meth:`Surrogate.fit` of ``name`` on all the points (the likelihood fit
    and the build: what adding cases costs without ``condition``)."""
    train, _, _, _ = _split(cfg)
    release_memory()
    t0 = time.perf_counter()
    jax.block_until_ready(Surrogate.fit(train, name).model)
    return time.perf_counter() - t0


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
    seconds: list[float] = []
    out = None
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
        ("refit_s", "refit s", ".2f"),
        ("ratio_refit", "condition / refit", ".3f"),
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
