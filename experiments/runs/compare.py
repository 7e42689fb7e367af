"""The paper's comparison (``python -m experiments.compare``): every baseline, one dataset.

For each model: build it on the training set (hyperparameters by marginal likelihood, shared by
models trained on the same points), predict the held-out test set, and record per-output MAE,
RMSE, NLPD and 95 % coverage, the error against airspeed, training time, single-query
prediction time (median and p95) with its ratio to ``gp`` as in the paper's Table
"Computational Time Comparison", model bytes and the peak memory of the build. Writes
``results.json``, ``results.md`` and the figures into the run directory.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from experiments.runs.common import fit_model, world_states
from experiments.runs.config import check_options
from experiments.runs.output import report, table
from experiments.runs.timing import latency, machine, set_dispatch
from gpg import models
from gpg.conf import deep_merge
from gpg.config import ModelConfig
from gpg.data.cache import load_data
from gpg.data.dataset import Dataset
from gpg.data.preprocess import prepare, restore, simple_model_for
from gpg.gp import partition
from gpg.linalg import memory
from gpg.quadrotor.simple_noise import SimpleNoise
from gpg.quadrotor.vehicle import Vehicle
from gpg.results import Comparison, ModelRun, Run, Skipped, write_results
from gpg.runtime import check_interrupt, float64
from gpg.surrogate import Surrogate

AIRSPEED_BINS = 10


def metrics(
    y: np.ndarray, mean: np.ndarray, var: np.ndarray, names, valid: np.ndarray | None = None
) -> dict[str, Any]:
    """Per-output MAE, RMSE, NLPD (Gaussian) and 95 % interval coverage.

    ``valid`` (Q,) marks the queries whose variance the model could compute (a Schur model's
    negative variances are not); NLPD and coverage are taken over those only, and are None
    when there is none. The errors are taken over every query.
    """
    err = mean - y
    valid = np.ones(y.shape[0], bool) if valid is None else np.asarray(valid, bool)
    out: dict[str, Any] = {
        "mae": dict(zip(names, np.mean(np.abs(err), 0).tolist(), strict=True)),
        "rmse": dict(zip(names, np.sqrt(np.mean(err**2, 0)).tolist(), strict=True)),
        "nlpd": None,
        "nlpd_mean": None,
        "coverage95": None,
        "coverage95_mean": None,
    }
    if valid.any():
        e, v = err[valid], var[valid]
        z = np.abs(e) / np.sqrt(v)
        nlpd = 0.5 * np.log(2 * np.pi * v) + 0.5 * e**2 / v
        out.update(
            nlpd=dict(zip(names, np.mean(nlpd, 0).tolist(), strict=True)),
            nlpd_mean=float(np.mean(nlpd)),
            coverage95=dict(zip(names, np.mean(z <= 1.959964, 0).tolist(), strict=True)),
            coverage95_mean=float(np.mean(z <= 1.959964)),
        )
    return out


def continuity(
    model, part: partition.Partition, Xn: np.ndarray, y_std: np.ndarray, names
) -> dict[str, Any]:
    """Largest jump of the mean and of the predictive standard deviation across the bin
    boundaries of ``part``, per output in physical units, over pairs of inputs straddling each
    boundary (:func:`gpg.gp.partition.boundary_pairs`, built from the normalised test inputs
    ``Xn``). Integrators (RL, MPC) step through these boundaries."""
    A, C = partition.boundary_pairs(part, Xn)
    if A.shape[0] == 0:
        return {"pairs": 0, "mean_jump_max": None, "std_jump_max": None}
    (ma, va), (mc, vc) = (_predict_test(model, Z) for Z in (A, C))
    dm = np.abs(ma - mc) * y_std
    sa, sc = (np.sqrt(np.asarray(model.predictive_variance(v))) for v in (va, vc))
    ds = np.abs(sa - sc) * y_std
    return {
        "pairs": int(A.shape[0]),
        "boundaries": part.n_bins - 1,
        "mean_jump_max": dict(zip(names, dm.max(0).tolist(), strict=True)),
        "mean_jump_median": dict(zip(names, np.median(dm, 0).tolist(), strict=True)),
        "std_jump_max": dict(zip(names, ds.max(0).tolist(), strict=True)),
    }


def error_vs_airspeed(v: np.ndarray, abs_err: np.ndarray, lo: float, hi: float) -> dict[str, Any]:
    edges = np.linspace(lo, hi, AIRSPEED_BINS + 1)
    idx = np.clip(np.digitize(v, edges) - 1, 0, AIRSPEED_BINS - 1)
    rows = [
        np.mean(abs_err[idx == b], 0).tolist() if np.any(idx == b) else None  # empty bin
        for b in range(AIRSPEED_BINS)
    ]
    return {"edges": edges.tolist(), "mean_abs_error": rows}


def _predict_test(model, Xn: np.ndarray, chunk: int = 256):
    """Mean and unclipped latent variance in chunks (bounded memory for the exact models)."""
    means, vars_ = [], []
    for s in range(0, Xn.shape[0], chunk):
        m, v = model.predict_unclipped(jnp.asarray(Xn[s : s + chunk]))
        means.append(np.asarray(m))
        vars_.append(np.asarray(v))
    return np.concatenate(means), np.concatenate(vars_)


def _boundaries(part, X: np.ndarray):
    """The bins whose boundaries the jump metric crosses: the model's own, else the paper's 10
    slabs along the airspeed (body-frame data, without an airspeed input: 10 kd-tree bins)."""
    if part is not None and part.n_bins > 1:
        return part
    body = X.shape[1] == 7
    cfg = ModelConfig.from_dict({"partition": {"scheme": "kdtree"}}) if body else ModelConfig()
    return models.build_partition(X, cfg)


def evaluate(
    label: str,
    name: str,
    mcfg: ModelConfig,
    train: Dataset,
    test: Dataset,
    simple,
    hyper_cache: dict,
    n_queries: int,
    noise_model=None,
    devices=None,
) -> tuple[ModelRun, np.ndarray]:
    """Build one model and measure it (see module docstring): its :class:`ModelRun` and the
    absolute test errors (Q, M) the figures draw. ``noise_model`` is ``M_noise`` or None;
    ``devices`` spreads the local models' per-bin precompute (:mod:`gpg.parallel`)."""
    fitted = fit_model(
        name,
        mcfg,
        train,
        simple,
        hyper_cache,
        noise_model=noise_model,
        measure_memory=True,
        devices=devices,
    )
    training, built = fitted.training, fitted.built
    norm = training.normalizer
    Xn = np.asarray(norm.x(test.x))
    mean_n, var_n = _predict_test(built.model, Xn)
    y_pred = restore(training, test.x, mean_n)
    # A variance below zero is a model failure (Schur): counted, and kept out of NLPD/coverage.
    negative = var_n < -1e-10 * float(built.hyper.variance)
    # Predictive variance of an observation: output scale × (latent variance + noise ν²).
    var_y = np.asarray(built.model.predictive_variance(var_n)) * np.asarray(norm.y_std) ** 2
    y_true = test.y[:, : y_pred.shape[1]]
    names = list(training.output_names)
    part = _boundaries(built.model.partition, training.X)
    abs_err = np.abs(y_pred - y_true)
    lo, hi = float(train.airspeed.min()), float(train.airspeed.max())
    lat = _latencies(built.model, training, train, name, mcfg, test, n_queries)
    run = ModelRun(
        model=name,
        title=models.SPECS[name].title,
        config=mcfg.to_dict(),
        timings=dict(fitted.timings),
        train_s=float(sum(fitted.timings.values())),
        **metrics(y_true, y_pred, var_y, names, valid=~negative),
        negative_variance_count=int(negative.sum()),
        negative_variance_fraction=float(negative.mean()),
        continuity=continuity(built.model, part, Xn, np.asarray(norm.y_std), names),
        **_hyper_record(built, fitted.hyper_fit),
        model_bytes=built.model.nbytes(),
        peak_memory_bytes=fitted.peak_memory_bytes,
        error_vs_airspeed=error_vs_airspeed(test.airspeed, abs_err, lo, hi),
        **lat,
    )
    return run, abs_err


def _hyper_record(built: models.Built, fit_res) -> dict[str, Any]:
    """The hyperparameters, output scales and near sets of a built model, as recorded."""
    hyper = built.hyper
    near = built.near
    return {
        "output_scale": np.asarray(built.model.output_scale).tolist(),
        "hyper_converged": None if fit_res is None else bool(fit_res.converged),
        "lengthscale": np.asarray(hyper.lengthscale).tolist(),
        "signal_variance": float(hyper.variance),
        "noise_variance": float(hyper.noise),
        "noise_ratio": float(hyper.noise / hyper.variance),
        "diagnostics": built.diagnostics,
        "near_fraction": None if near is None else float(np.mean(near.fraction)),
        # The smallest kernel correlation admitted to a near set (mean over bins): far points
        # correlate up to about this with the bin, so the Schur forms' k_qf ≈ 0 needs it ≪ 1.
        "near_epsilon": None if near is None else float(np.mean(near.epsilon)),
    }


def _latencies(model, training, train, name, mcfg, test, n_queries) -> dict[str, float]:
    """Single world-frame query latency (ms) of the assembled surrogate, with and without
    the variance."""
    sur = Surrogate.assemble(model, training, train, name, mcfg)
    states = world_states(test.x, n_queries)
    lat = latency(sur.realtime(with_var=True), states, n_queries)
    fast = latency(sur.realtime(with_var=False), states, n_queries)
    return {
        "predict_ms_median": lat["median_s"] * 1e3,
        "predict_ms_p95": lat["p95_s"] * 1e3,
        "predict_mean_ms_median": fast["median_s"] * 1e3,
        "predict_mean_ms_p95": fast["p95_s"] * 1e3,
    }


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _variant_label(name: str, over: dict[str, Any]) -> str:
    return name + "[" + ",".join(f"{k}={v}" for k, v in sorted(_flat(over).items())) + "]"


def _rows(results: dict[str, Run], names: list[str]) -> list[dict[str, Any]]:
    rows = []
    ref = results.get("gp")
    ref_ms = ref.predict_ms_median if isinstance(ref, ModelRun) else None
    for label, r in results.items():
        if not isinstance(r, ModelRun):
            continue
        jm = r.continuity.get("mean_jump_max") or {}
        js = r.continuity.get("std_jump_max") or {}
        row = {
            "label": label,
            "train": r.train_s,
            "pm": r.predict_ms_median,
            "pmm": r.predict_mean_ms_median * 1e3,
            "p95": r.predict_ms_p95,
            "ratio": 100 * r.predict_ms_median / ref_ms if ref_ms else None,
            "nlpd": r.nlpd_mean,
            "cov": r.coverage95_mean,
            "neg": r.negative_variance_count,
            "jump": jm.get(names[0]),
            "sjump": js.get(names[0]),
            "near": r.near_fraction,
            "eps": r.near_epsilon,
            "mb": r.model_bytes / 2**20,
            "peak": r.peak_memory_bytes / 2**20,
        }
        for n in names:
            row[n] = r.mae[n]
        rows.append(row)
    return rows


def _skipped(results: dict[str, Run]) -> str:
    lines = [f"- {k}: skipped ({r.reason})" for k, r in results.items() if isinstance(r, Skipped)]
    return "\n\n" + "\n".join(lines) if lines else ""


def _table_md(results: dict[str, Run], names: list[str]) -> str:
    """Every column (results.md)."""
    cols = [
        ("label", "model", ""),
        ("train", "train s", ".1f"),
        ("pm", "predict ms", ".3f"),
        ("p95", "p95 ms", ".3f"),
        ("pmm", "mean µs", ".0f"),
        ("ratio", "% of gp", ".1f"),
        *[(n, f"MAE {n}", ".3g") for n in names],
        ("nlpd", "NLPD", ".3g"),
        ("cov", "cover95", ".3f"),
        ("neg", "var<0", "d"),
        ("jump", f"jump {names[0]}", ".2g"),
        ("sjump", f"σ jump {names[0]}", ".2g"),
        ("near", "near", ".3f"),
        ("eps", "ε", ".2f"),
        ("mb", "model MiB", ".1f"),
        ("peak", "peak MiB", ".0f"),
    ]
    return table(_rows(results, names), cols) + _skipped(results)


def _table_short(results: dict[str, Run], names: list[str]) -> str:
    """The columns that fit a terminal (printed and logged; results.md has them all)."""
    show = [n for n in ("Fx", "Mx", "L1") if n in names] or names[:3]
    cols = [
        ("label", "model", ""),
        ("train", "train s", ".0f"),
        ("pm", "predict ms", ".2f"),
        *[(n, f"MAE {n}", ".3g") for n in show],
        ("nlpd", "NLPD", ".3g"),
        ("cov", "cover95", ".2f"),
        ("neg", "var<0", "d"),
        ("jump", f"jump {names[0]}", ".2g"),
    ]
    return table(_rows(results, names), cols) + _skipped(results)


def noise_flags(setting: Any) -> tuple[bool, ...]:
    """``noise_model``: false (the paper), true (levels against ``M_noise``) or ``both`` (every
    model twice, the runs with ``M_noise`` labelled ``+M_noise``)."""
    if setting == "both":
        return (False, True)
    if isinstance(setting, bool):
        return (setting,)
    raise ValueError(f"noise_model must be true, false or both, got {setting!r}")


def noise_reference(noise: SimpleNoise, train: Dataset, test: Dataset) -> dict[str, dict]:
    """Test MAE of the levels predicted by ``M_noise`` alone and by the training mean: what a
    model has to beat."""
    names = list(test.output_names[6:9])
    y = test.y[:, 6:9]
    alone = np.abs(np.asarray(noise.batch(test.x)[0]) - y).mean(0)
    mean = np.abs(train.y[:, 6:9].mean(0) - y).mean(0)
    return {
        "m_noise_alone": dict(zip(names, alone.tolist(), strict=True)),
        "training_mean": dict(zip(names, mean.tolist(), strict=True)),
    }


@float64
def run(cfg: dict[str, Any], outdir: Path, model_cfgs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Compare the models of ``model_cfgs`` (name -> config) on the configured data; returns
    what ``results.json`` holds (:func:`gpg.results.write_results`)."""
    outdir = Path(outdir)
    check_options(cfg, OPTIONS)
    resolved = resolve_models(model_cfgs, cfg.get("model_overrides"))
    flags = noise_flags(cfg.get("noise_model", False))
    # Devices only overlap with JAX's asynchronous CPU dispatch (fixed when JAX starts).
    set_dispatch(
        {**cfg, "sync_dispatch": cfg.get("sync_dispatch", True) and not cfg.get("devices")}
    )
    t_start = time.perf_counter()
    train, test, data_info = load_data(cfg)
    vehicle = Vehicle.from_config(cfg["vehicle"])
    simple = simple_model_for(train, vehicle)
    report(f"data: {train.summary()}\ntest: {test.n} points")
    noise = None
    if any(flags) and train.has_noise:
        noise = SimpleNoise.from_vehicle(vehicle, simple)
    jobs = _jobs(resolved, cfg.get("variants"), flags)
    single = len(resolved) == 1
    # Everything that can fail from sizes alone (missing data, bins or inducing points beyond
    # the data, memory) fails here, before any model is trained.
    training = prepare(train, simple, None)  # sizes only: the same with or without M_noise
    ready, results = _feasible(jobs, training, single)
    errors = _run_jobs(ready, results, cfg, train, test, simple, noise, single)
    comp = _record(cfg, resolved, results, errors, train, test, data_info, noise, outdir)
    comp = dataclasses.replace(comp, wall_s=time.perf_counter() - t_start)
    write_results(outdir / "results.json", comp)
    _write_tables(outdir, comp, train, test)
    return json.loads((outdir / "results.json").read_text())


OPTIONS = {
    "n_queries": "count",
    "figures": "bool",
    "sync_dispatch": "bool",
    "model_overrides": "mapping?",
    "variants": "mapping?",
    "devices": "devices",
    "cache_dir": "path",
}


def resolve_models(
    model_cfgs: dict[str, dict[str, Any]], overrides: dict[str, Any] | None
) -> dict[str, ModelConfig]:
    """Each model's resolved config with the keys of ``overrides`` it reads merged in (a key
    that no model of the run reads is an error: it would change nothing). Unknown names, keys
    and values fail here, before any data is generated or loaded."""
    if not model_cfgs:
        raise ValueError(f"no model to compare; valid names: {list(models.NAMES)}")
    overrides = dict(overrides or {})
    for name in model_cfgs:
        models.resolve_config(name)  # an unknown name fails before the overrides are read
    read = {k for name in model_cfgs for k in models.reads(name)}
    unread = sorted(set(overrides) - read)
    if unread:
        raise ValueError(
            f"model_overrides {unread} are read by none of the models {list(model_cfgs)}"
        )
    out = {}
    for name, mc in model_cfgs.items():
        out[name] = models.resolve_config(name, deep_merge(mc, models.restrict(name, overrides)))
    return out


def _jobs(resolved, variants, flags) -> list[tuple[str, str, ModelConfig, bool]]:
    """(label, name, config, with M_noise) of every run: each model, its variants, and each
    of them once per ``noise_model`` flag."""
    jobs = []
    for name, mc in resolved.items():
        runs = [(name, mc)]
        for over in (variants or {}).get(name, []):
            label = _variant_label(name, over)
            runs.append((label, models.resolve_config(name, deep_merge(mc.to_dict(), over))))
        for with_noise in flags:
            # With both, the M_noise runs carry a suffix; the runs without keep the plain label.
            tag = "+M_noise" if with_noise and len(flags) == 2 else ""
            jobs += [(label + tag, name, m, with_noise) for label, m in runs]
    return jobs


def _feasible(jobs, training, single: bool):
    """The jobs that pass :func:`gpg.models.check_feasible`, and a :class:`Skipped` for each
    other one (or the error itself when only one model was asked for)."""
    ready, results = [], {}
    for label, name, mc, with_noise in jobs:
        try:
            models.check_feasible(name, mc, training)
            ready.append((label, name, mc, with_noise))
        except (ValueError, memory.InsufficientMemory) as exc:
            if single:
                raise
            results[label] = Skipped(name, str(exc))
            report(f"{label}: skipped: {exc}")
    return ready, results


def _run_jobs(ready, results, cfg, train, test, simple, noise, single) -> dict[str, np.ndarray]:
    """Build and measure every ready job into ``results``; the absolute errors by label."""
    # Hyperparameters are shared between the models fitted on the same targets only: the
    # residuals against M_noise are other targets than the levels themselves.
    hyper_caches: dict[bool, dict] = {False: {}, True: {}}
    errors = {}
    bar = tqdm(ready, desc="models", unit="model")
    for label, name, mc, with_noise in bar:
        bar.set_postfix_str(label)
        check_interrupt()  # a deferred Ctrl-C stops between models
        try:
            results[label], errors[label] = evaluate(
                label,
                name,
                mc,
                train,
                test,
                simple,
                hyper_caches[with_noise],
                cfg["n_queries"],
                noise if with_noise else None,
                cfg.get("devices"),
            )
        except (ValueError, memory.InsufficientMemory) as exc:
            if single:
                raise
            results[label] = Skipped(name, str(exc))
            report(f"{label}: skipped: {exc}")
    if not errors:
        raise ValueError("no model could run: " + "; ".join(r.reason for r in results.values()))
    return errors


def _record(cfg, resolved, results, errors, train, test, data_info, noise, outdir) -> Comparison:
    """The :class:`Comparison` of a finished run (figures drawn, latency ratios to ``gp``)."""
    names = list(next(r for r in results.values() if isinstance(r, ModelRun)).mae)
    figures = []
    if cfg.get("figures", True):
        from experiments.runs import plots

        figures = plots.compare_figures(results, errors, names, outdir / "figures")
    ref = results.get("gp")
    if isinstance(ref, ModelRun):
        for label, r in results.items():
            if isinstance(r, ModelRun):
                ratio = r.predict_ms_median / ref.predict_ms_median
                results[label] = dataclasses.replace(r, predict_ratio_to_gp=ratio)
    return Comparison(
        models=results,
        outputs=names,
        n_train=train.n,
        n_test=test.n,
        data=data_info,
        noise_reference=noise_reference(noise, train, test) if noise is not None else None,
        figures=[str(p.relative_to(outdir)) for p in figures],
        wall_s=0.0,
        machine=machine(),
        config={**cfg, "models": {k: v.to_dict() for k, v in resolved.items()}},
    )


def _write_tables(outdir: Path, comp: Comparison, train: Dataset, test: Dataset) -> None:
    """``results.md`` (every column) and the short table on the terminal and in the log."""
    names, reference = comp.outputs, comp.noise_reference
    header = (
        f"# Comparison on {comp.data.get('key') or comp.data.get('train')}\n\n"
        f"{train.n} training points, {test.n} test points; errors in N, N·m and dB; "
        "predict = one world-frame query, mean and variance (`Surrogate.realtime`).\n\n"
    )
    if reference is not None:
        header += (
            "Levels' test MAE (dB) of `M_noise` alone: "
            + ", ".join(f"{k} {v:.3g}" for k, v in reference["m_noise_alone"].items())
            + "; of the training mean: "
            + ", ".join(f"{k} {v:.3g}" for k, v in reference["training_mean"].items())
            + ".\n\n"
        )
    (outdir / "results.md").write_text(header + _table_md(comp.models, names) + "\n")
    report(_table_short(comp.models, names))
    report(f"wrote {outdir / 'results.json'} and {outdir / 'results.md'} ({comp.wall_s:.0f} s)")
