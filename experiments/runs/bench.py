"""Speed measurements (``python -m experiments.bench``): ratios within one run, written to JSON.

Suites:

* ``exact_gp``: cost of assembling ``K̄`` and factorising it against the Cholesky of a ready
  matrix of the same size, and the latency of a jitted ``ExactGP.predict``.
* ``models``: every model of :mod:`gpg.models` on a dataset (``data=default`` by default):
  training time (hyperparameter fit, partition, factorisation/precompute), single-query
  latency of the jitted mean+variance and mean-only predictors, mean-only throughput on
  batches, the same for the full :class:`gpg.Surrogate` pipeline, and model bytes. Ratios
  against ``gpg`` (exact GP-G) are taken within the run.
* ``devices``: the work :mod:`gpg.parallel` spreads, on 1, 2, … of the JAX devices present
  (start with ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` for virtual CPU
  devices): the build of ``gpgs`` and ``gpg_pic`` after their shared likelihood fit (against
  the one-process host path), batched surrogate predictions, and dataset generation with 1,
  2, … worker processes.
  Speed-ups against one device are taken within the run.
* ``derivatives``: for every model, ``jax.jacrev`` and ``jax.jacfwd`` of the whole
  :meth:`gpg.Surrogate.predict` (force, torque, levels and their variances, in rpm, Euler
  angles and airspeed) against central finite differences of the float64 copy, at test-set
  states, and the time of a batched ``jacrev``.
* ``envs``: environment steps per second of :class:`gpg.envs.QuadrotorEnv` (float32) on the
  surrogate and on ``M``, for several numbers of vmapped environments.
* ``gpu``: gpg end to end on one accelerator (:mod:`experiments.runs.bench_gpu`; runs on the
  CPU too).
* ``flight``: a PX4 log read and labelled against the time it flew, and the cost of one
  adaptation update (:mod:`experiments.runs.bench_flight`).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from tqdm.auto import tqdm

from experiments.runs.bench_design import bench_design, design_table
from experiments.runs.bench_export import bench_export, export_table
from experiments.runs.bench_flight import bench_flight, flight_table
from experiments.runs.bench_gpu import bench_gpu, gpu_table
from experiments.runs.bench_solver import bench_solver, solver_table
from experiments.runs.common import fit_model, world_arrays, world_states
from experiments.runs.config import conf
from experiments.runs.output import report, table
from experiments.runs.timing import latency, machine, set_dispatch, stats, time_calls
from gpg.conf import deep_merge
from gpg.gp.exact import ExactGP
from gpg.gp.gram import assemble_gram
from gpg.gp.hyper import Hyper
from gpg.linalg import dense
from gpg.runtime import float64, write_json


def _synthetic(n: int, d: int, dims: tuple[int, ...], n_out: int, seed: int):
    """Smooth outputs ``sin(X W)`` with exact gradients: realistic values, timing is all we use."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, d))
    W = rng.normal(scale=0.8, size=(d, n_out))
    Y = np.sin(X @ W)
    dY = np.cos(X @ W)[:, :, None] * W[list(dims)].T[None]
    return X, Y, dY


def _time_jax_cholesky(K: np.ndarray, repeats: int) -> np.ndarray:
    jchol = jax.jit(lambda A: jsl.cho_factor(A, lower=True)[0])
    Kj = jnp.asarray(K)
    return time_calls(lambda: jchol(Kj), repeats)


def bench_exact_gp(cfg: dict[str, Any]) -> dict[str, Any]:
    """Assembly + Cholesky vs Cholesky alone, fit time, and single-query predict latency."""
    n, d, dims = cfg["n_points"], cfg["n_inputs"], tuple(cfg["grad_dims"])
    reps = cfg["repeats"]
    X, Y, dY = _synthetic(n, d, dims, cfg["n_outputs"], cfg["seed"])
    hyper = Hyper(variance=1.0, lengthscale=cfg["lengthscale"], noise=1e-8, grad_noise=1e-6)
    hyper = hyper.validate(d, len(dims))
    Xj = jnp.asarray(X)
    rows = n * (1 + len(dims))

    ready = assemble_gram(Xj, hyper, dims)  # also compiles the Gram builder
    out: dict[str, Any] = {"rows": rows, "n_points": n, "grad_dims": list(dims)}

    t_chol = []
    for _ in tqdm(range(reps), desc="Cholesky of a ready K̄", leave=False):
        buf = ready.copy()
        t_chol.append(time_calls(lambda b=buf: dense.cholesky_inplace(b), 1, warmup=0)[0])
    del buf
    t_asm = time_calls(lambda: assemble_gram(Xj, hyper, dims), reps, warmup=1)
    t_asm_chol = time_calls(
        lambda: dense.cholesky_inplace(assemble_gram(Xj, hyper, dims)), reps, warmup=0
    )
    out["cholesky_ready_lapack"] = stats(np.array(t_chol))
    out["assemble"] = stats(t_asm)
    out["assemble_plus_cholesky"] = stats(t_asm_chol)
    out["ratio_assemble_plus_cholesky_to_cholesky"] = (
        out["assemble_plus_cholesky"]["median_s"] / out["cholesky_ready_lapack"]["median_s"]
    )

    # For reference: JAX's own CPU Cholesky of the same ready matrix.
    out["cholesky_ready_jax"] = stats(_time_jax_cholesky(ready, max(1, reps - 1)))
    del ready

    models = []
    t_fit = time_calls(
        lambda: models.append(ExactGP.fit(X, Y, dY, grad_dims=dims, hyper=hyper)), 1, warmup=0
    )
    out["exact_gp_fit"] = stats(t_fit)
    model = models[-1]

    rng = np.random.default_rng(cfg["seed"] + 1)
    queries = [(jnp.asarray(rng.uniform(-1, 1, (1, d))),) for _ in range(cfg["n_queries"])]
    out["predict_mean_1"] = latency(model.predict_mean, queries, cfg["n_queries"])
    out["predict_mean_var_1"] = latency(model.predict, queries, cfg["n_queries"])
    batch = jnp.asarray(rng.uniform(-1, 1, (cfg["batch"], d)))
    tb = time_calls(lambda: model.predict_mean(batch), 20, warmup=2)
    out[f"predict_mean_batch{cfg['batch']}"] = stats(tb)
    out["predict_mean_batch_throughput_per_s"] = cfg["batch"] / float(np.median(tb))
    return out


def _compile_seconds(sur, state, repeats: int) -> dict[str, float]:
    """Seconds to trace, lower and compile one query's prediction with its variance, a new
    ``jit`` each time: what the first call of every program built around ``predict`` costs
    (a controller's, a rollout's)."""
    out = np.empty(repeats)
    for i in range(repeats):
        f = jax.jit(lambda s, r, e, v: s.predict(r, e, v))
        t0 = time.perf_counter()
        f.lower(sur, *state).compile()
        out[i] = time.perf_counter() - t0
    return stats(out)


def _surrogate_latency(sur, states, n: int, compiles: int) -> dict[str, Any]:
    """The full pipeline: the realtime closures, and the plain method for comparison; the
    prediction's compile time, ``compiles`` times."""
    return {
        "surrogate_compile": _compile_seconds(sur, states[0], compiles),
        "surrogate_predict_1": latency(sur.realtime(with_var=True), states, n),
        "surrogate_predict_mean_1": latency(sur.realtime(with_var=False), states, n),
        "surrogate_predict_mean_1_method": latency(sur.predict_mean, states, n),
    }


def _float32_check(sur, test, states, n: int) -> dict[str, Any]:
    """``sur.astype(float32)`` against ``sur`` on the whole test set, run as a float32 program
    runs it (x64 off): errors relative to each output's spread over the test set, and the
    float32 single-query latency."""
    R, E, V = world_arrays(test.x)

    def stack(p):
        return np.concatenate([np.asarray(p.force), np.asarray(p.torque), np.asarray(p.levels)], 1)

    p64 = sur.predict_batch(R, E, V)
    with jax.enable_x64(False):
        s32 = sur.astype(jnp.float32)
        p32 = s32.predict_batch(R, E, V)
        lat = latency(s32.realtime(with_var=True), states, n)
    y64, y32 = stack(p64), stack(p32).astype(np.float64)
    spread = np.std(y64, axis=0)
    err = np.abs(y32 - y64) / spread
    verr = np.abs(np.asarray(p32.variance, np.float64) - np.asarray(p64.variance)) / spread**2
    return {
        "dtype": str(p32.force.dtype),
        "mean_error_over_std_max": float(err.max()),
        "mean_error_over_std_median": float(np.median(err)),
        "variance_error_over_var_max": float(verr.max()),
        "surrogate_predict_1": lat,
    }


def bench_models(cfg: dict[str, Any]) -> dict[str, Any]:
    """Training time, latency and throughput of every model on one dataset."""
    from gpg import models
    from gpg.data.cache import ensure_datasets
    from gpg.data.preprocess import simple_model_for
    from gpg.quadrotor.vehicle import Vehicle
    from gpg.surrogate import Surrogate

    train, test, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    vehicle = Vehicle.from_config(cfg["vehicle"])
    simple = simple_model_for(train, vehicle)
    out: dict[str, Any] = {"dataset": info["key"], "n_train": train.n, "models": {}}
    rng = np.random.default_rng(cfg["seed"])
    hyper_cache: dict[tuple, Any] = {}
    bar = tqdm(cfg["models"], desc="models")
    for name in bar:
        bar.set_postfix_str(name)
        # The model's own config file (as compare uses it), with the suite's overrides.
        mcfg = models.resolve_config(name, deep_merge(conf(name, "model"), cfg.get("model")))
        fitted = fit_model(name, mcfg, train, simple, hyper_cache)
        training, built = fitted.training, fitted.built
        model = built.model
        Xq = np.asarray(training.normalizer.x(test.x))
        queries = [(jnp.asarray(Xq[i]),) for i in rng.permutation(len(Xq))[: cfg["n_queries"]]]
        # The model's arrays are flattened once, as in Surrogate.realtime.
        leaves, treedef = jax.tree_util.tree_flatten(model)
        leaves = tuple(leaves)
        mv = jax.jit(lambda lv, x, t=treedef: jax.tree_util.tree_unflatten(t, lv).mean_var_one(x))
        mo = jax.jit(lambda lv, x, t=treedef: jax.tree_util.tree_unflatten(t, lv).mean_one(x))
        res = {
            **fitted.timings,
            "mean_var_1": latency(lambda x, f=mv, lv=leaves: f(lv, x), queries, cfg["n_queries"]),
            "mean_1": latency(lambda x, f=mo, lv=leaves: f(lv, x), queries, cfg["n_queries"]),
            "model_bytes": model.nbytes(),
            "near_fraction": None if built.near is None else float(np.mean(built.near.fraction)),
        }
        batch = jnp.asarray(Xq[: cfg["batch"]])
        mb = jax.jit(
            lambda lv, X, t=treedef: jax.vmap(jax.tree_util.tree_unflatten(t, lv).mean_one)(X)
        )
        tb = time_calls(lambda f=mb, lv=leaves, B=batch: f(lv, B), cfg["batch_repeats"], warmup=2)
        res["mean_batch"] = stats(tb)
        res["mean_batch_per_s"] = batch.shape[0] / float(np.median(tb))
        sur = Surrogate.assemble(model, training, train, name, mcfg)
        states = world_states(test.x, cfg["n_queries"])
        res.update(_surrogate_latency(sur, states, cfg["n_queries"], cfg["compile_repeats"]))
        res["float32"] = _float32_check(sur, test, states, cfg["n_queries"])
        out["models"][name] = res
    ref = out["models"].get("gpg")
    if ref is not None:
        ref_fit = ref["fit_s"]
        for res in out["models"].values():
            res["fit_ratio_to_gpg"] = res["fit_s"] / ref_fit
            res["mean_var_ratio_to_gpg"] = (
                res["mean_var_1"]["median_s"] / ref["mean_var_1"]["median_s"]
            )
    return out


# Long by design: a measurement script read top to bottom (set-up, each timed step, record).
def bench_devices(cfg: dict[str, Any]) -> dict[str, Any]:
    """Per-bin precompute, batched prediction and generation over 1..n devices or workers."""
    from gpg import models
    from gpg.data.cache import build_generator, ensure_datasets
    from gpg.data.preprocess import prepare, simple_model_for
    from gpg.quadrotor.generator import evaluate_batch
    from gpg.quadrotor.vehicle import Vehicle
    from gpg.surrogate import Surrogate

    counts = [c for c in cfg["device_counts"] if c <= len(jax.devices())]
    train, test, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    simple = simple_model_for(train, Vehicle.from_config(cfg["vehicle"]))
    out: dict[str, Any] = {"dataset": info["key"], "devices": [str(d) for d in jax.devices()]}

    # One hyperparameter fit for every model here (as the comparison shares it): what is
    # timed is the build after it (partition, near sets or blocks, per-bin precompute).
    training = prepare(train, simple)
    names = list(dict.fromkeys([*cfg["train_models"], cfg["predict_model"]]))
    hyper = models.fit_hyper(names[0], training, models.resolve_config(names[0], {}))[0]
    reps = cfg["repeats"]
    built: dict[str, Any] = {}
    out["build"] = {}
    bar = tqdm(total=len(cfg["train_models"]) * (1 + len(counts)), desc="builds", unit="build")
    for name in names:
        mcfg = models.resolve_config(name, deep_merge(conf(name, "model"), cfg.get("model")))
        if name not in cfg["train_models"]:
            built[name] = (models.build(name, training, mcfg, hyper=hyper), mcfg)
            continue
        per = {}
        for c in [None, *counts]:

            def one(c=c, n=name, m=mcfg):
                built[n] = (models.build(n, training, m, hyper=hyper, devices=c), m)

            bar.set_postfix_str(f"{name}, {'host' if c is None else f'{c} device(s)'}")
            per["host" if c is None else str(c)] = stats(time_calls(one, reps, warmup=0))
            bar.update()
        out["build"][name] = per
    bar.close()

    pm, pcfg = built[cfg["predict_model"]]
    sur = Surrogate.assemble(pm.model, training, train, cfg["predict_model"], pcfg)
    rng = np.random.default_rng(cfg["seed"])
    pred: dict[str, Any] = {}
    for batch in cfg["batches"]:
        idx = rng.integers(0, test.n, batch)
        states = world_states(test.x[idx], batch)
        rpm, euler, v = (np.stack([s[k] for s in states]) for k in range(3))
        for c in counts:
            rep = sur.replicate(c)
            for mean_only in (True, False):
                t = time_calls(
                    lambda rep=rep, m=mean_only, a=(rpm, euler, v): rep.predict_batch(
                        *a, mean_only=m, chunk=cfg["chunk"]
                    ),
                    cfg["batch_repeats"],
                    warmup=1,
                )
                key = f"{batch}/{'mean' if mean_only else 'mean_var'}/{c}"
                pred[key] = {**stats(t), "per_s": batch / float(np.median(t))}
    out["predict"] = pred

    gen = build_generator(cfg["data"], cfg["vehicle"])
    Xg = test.x[np.resize(np.arange(test.n), cfg["generate_rows"])]
    gen_t = {}
    for w in cfg["workers"]:
        # Once each: a worker's start-up (interpreter, import, compilation) is part of its cost.
        gen_t[str(w)] = stats(
            time_calls(
                lambda w=w: evaluate_batch(gen, Xg, chunk=cfg["chunk_generate"], workers=w),
                1,
                warmup=0,
            )
        )
    out["generate"] = {"rows": int(Xg.shape[0]), "seconds": gen_t}
    return out


def _prediction_fn(sur):
    """``z = (rpm, euler, v_air)`` (10,) ↦ force, torque, levels and variances (one vector)."""
    from gpg.surrogate import predict_state

    def f(z):
        p = predict_state(sur, z[:4], z[4:7], z[7:10], True)
        return jnp.concatenate([p.force, p.torque, p.levels, p.variance])

    return f


def _groups(n_levels: int) -> dict[str, slice]:
    k = 6 + n_levels
    return {
        "force": slice(0, 3),
        "torque": slice(3, 6),
        "levels": slice(6, k),
        "variance": slice(k, 2 * k),
    }


# Long by design: a measurement script read top to bottom (set-up, each timed step, record).
def bench_derivatives(cfg: dict[str, Any]) -> dict[str, Any]:
    """Autodiff Jacobians of every model's surrogate against central differences."""
    from gpg import models
    from gpg.data.cache import ensure_datasets
    from gpg.data.preprocess import simple_model_for
    from gpg.quadrotor.vehicle import Vehicle
    from gpg.surrogate import Surrogate

    train, test, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    simple = simple_model_for(train, Vehicle.from_config(cfg["vehicle"]))
    rng = np.random.default_rng(cfg["seed"])
    idx = rng.permutation(test.n)[: cfg["n_states"]]
    Z = jnp.asarray(
        np.concatenate([test.x[idx, :7], test.x[idx, 7:8], np.zeros((idx.size, 2))], axis=1)
    )
    rel = float(cfg["relative_step"])
    H = np.maximum(np.abs(np.asarray(Z)), 1.0) * rel  # per-input central-difference steps
    out: dict[str, Any] = {"dataset": info["key"], "n_states": int(idx.size), "models": {}}
    hyper_cache: dict[tuple, Any] = {}
    for name in tqdm(cfg["models"], desc="models"):
        mcfg = models.resolve_config(name, deep_merge(conf(name, "model"), cfg.get("model")))
        fitted = fit_model(name, mcfg, train, simple, hyper_cache)
        sur = Surrogate.assemble(fitted.built.model, fitted.training, train, name, mcfg)
        f, f64 = _prediction_fn(sur), _prediction_fn(sur.astype(jnp.float64))
        J_rev = jax.jit(jax.vmap(jax.jacrev(f)))
        J_fwd = jax.jit(jax.vmap(jax.jacfwd(f)))(Z)
        J_rev64 = jax.jit(jax.vmap(jax.jacrev(f64)))(Z)

        def central(z, h, f=f64):
            # Fourth-order central differences: truncation error O(h⁴), so the rounding of
            # f, not the stencil, sets the accuracy.
            E = jnp.diag(h)
            return jax.vmap(
                lambda e, hh: (
                    (-f(z + 2 * e) + 8 * f(z + e) - 8 * f(z - e) + f(z - 2 * e)) / (12 * hh)
                ),
                out_axes=1,
            )(E, h)

        J_fd = np.asarray(jax.jit(jax.vmap(central))(Z, jnp.asarray(H)))
        # A partitioned model jumps at its bins' boundaries: a stencil across one measures the
        # jump, not the derivative; such states are left out (and counted).
        across = _stencil_crosses_bins(sur, Z, jnp.asarray(H))
        Jr = np.asarray(J_rev(Z))
        J64 = np.asarray(J_rev64)
        values = np.asarray(jax.jit(jax.vmap(f64))(Z))
        res: dict[str, Any] = {"in_domain": float(np.mean(_in_domain(sur, Z)))}
        for g, sl in _groups(sur.n_levels).items():
            if sl.stop == sl.start:
                continue
            jmax = np.max(np.abs(J_fd[:, sl]), axis=(1, 2))
            # A Jacobian that vanishes (a variance clipped at zero) is compared in absolute
            # terms against the values' size: finite differences only give rounding there.
            flat = (np.max(np.abs(J64[:, sl]), axis=(1, 2)) == 0) & (
                jmax < 1e-8 * np.max(np.abs(values[:, sl]), axis=1)
            )
            keep = ~across
            scale = np.where(flat, np.max(np.abs(values[:, sl]), axis=1), jmax) + 1e-300
            err = np.max(np.abs(J64[:, sl] - J_fd[:, sl]), axis=(1, 2)) / scale
            stored = np.max(np.abs(Jr[:, sl] - J64[:, sl]), axis=(1, 2)) / scale
            fr = np.max(np.abs(Jr[:, sl] - np.asarray(J_fwd)[:, sl]), axis=(1, 2)) / scale
            res[g] = {
                "rev_vs_fd_max": float(err[keep].max()),
                "rev_vs_fd_median": float(np.median(err[keep])),
                "stored_dtype_vs_float64_max": float(stored.max()),
                "fwd_vs_rev_max": float(fr.max()),
                "flat_states": int(flat.sum()),
                "states_across_bins": int(across.sum()),
            }
        t = time_calls(lambda J=J_rev: J(Z), cfg["repeats"], warmup=1)
        res["jacrev_batch"] = {**stats(t), "states_per_s": Z.shape[0] / float(np.median(t))}
        out["models"][name] = res
    return out


def _stencil_crosses_bins(sur, Z, H) -> np.ndarray:
    """Per state: whether a finite-difference stencil point (±h, ±2h along any input) falls in
    another bin than the state itself (always False for an unpartitioned model)."""
    from gpg.quadrotor.frames import to_airflow_frame

    part = sur.model.partition
    if part is None:
        return np.zeros(Z.shape[0], bool)

    def bin_of(z):
        euler_h, speed, _ = to_airflow_frame(z[4:7], z[7:10], sur.hover_speed)
        return part.lookup(sur.normalizer.x(jnp.concatenate([z[:4], euler_h, speed[None]])))

    def crosses(z, h):
        steps = jnp.concatenate([jnp.diag(h) * k for k in (-2.0, -1.0, 1.0, 2.0)])
        return jnp.any(jax.vmap(lambda d: bin_of(z + d))(steps) != bin_of(z))

    return np.asarray(jax.jit(jax.vmap(crosses))(Z, H))


def _in_domain(sur, Z) -> np.ndarray:
    from gpg.surrogate import predict_state

    return np.asarray(
        jax.jit(jax.vmap(lambda z: predict_state(sur, z[:4], z[4:7], z[7:10], False).in_domain))(Z)
    )


def bench_envs(cfg: dict[str, Any]) -> dict[str, Any]:
    """Environment steps per second, float32, for each aerodynamics and number of envs."""
    from gpg import models
    from gpg.data.cache import ensure_datasets
    from gpg.data.preprocess import simple_model_for
    from gpg.envs import EnvParams, QuadrotorEnv
    from gpg.quadrotor.vehicle import Vehicle
    from gpg.surrogate import Surrogate

    train, _, _, info = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])
    vehicle = Vehicle.from_config(cfg["vehicle"])
    simple = simple_model_for(train, vehicle)
    name = cfg["model_name"]
    mcfg = models.resolve_config(name, deep_merge(conf(name, "model"), cfg.get("model")))
    fitted = fit_model(name, mcfg, train, simple, {})
    sur = Surrogate.assemble(fitted.built.model, fitted.training, train, name, mcfg)
    out: dict[str, Any] = {"dataset": info["key"], "model": name, "runs": {}}
    params = EnvParams.create(cfg["task"])
    T = int(cfg["steps"])
    for aero_name, aero in (("surrogate", sur), ("M", simple)):
        env = QuadrotorEnv.create(vehicle, aero, simple=simple, action=cfg["action"])
        for n in cfg["n_envs"]:
            keys = jax.random.split(jax.random.key(cfg["seed"]), n)
            _, st = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)

            @jax.jit
            def roll(st, key, env=env, n=n):
                def body(st, k):
                    a = jnp.zeros((n, 4), jnp.float32)
                    ks = jax.random.split(k, n)
                    _, st, _, _, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                        ks, st, a, params
                    )
                    return st, info["in_domain"]

                return jax.lax.scan(body, st, jax.random.split(key, T))

            keys = iter(jax.random.split(jax.random.key(cfg["seed"] + 1), cfg["repeats"] + 1))
            t = time_calls(lambda r=roll, s=st, k=keys: r(s, next(k)), cfg["repeats"], warmup=1)
            out["runs"][f"{aero_name}/{n}"] = {
                **stats(t),
                "env_steps_per_s": n * T / float(np.median(t)),
                "spread_per_s": [n * T / float(np.max(t)), n * T / float(np.min(t))],
            }
    return out


def _derivatives_table(res: dict[str, Any]) -> str:
    rows = []
    for name, r in res["models"].items():
        groups = [g for g in ("force", "torque", "levels", "variance") if g in r]
        rows.append(
            {
                "name": name,
                **{g: r[g]["rev_vs_fd_max"] for g in groups},
                "fr": max(r[g]["fwd_vs_rev_max"] for g in groups),
                "st": max(r[g]["stored_dtype_vs_float64_max"] for g in groups),
                "per_s": r["jacrev_batch"]["states_per_s"],
            }
        )
    cols = [
        ("name", "model", ""),
        ("force", "force: rev vs FD", ".1e"),
        ("torque", "torque", ".1e"),
        ("levels", "levels", ".1e"),
        ("variance", "variance", ".1e"),
        ("fr", "fwd vs rev", ".1e"),
        ("st", "stored dtype vs f64", ".1e"),
        ("per_s", "jacrev states/s", ",.0f"),
    ]
    return f"{res['n_states']} test states of {res['dataset']} (max relative error)\n\n" + table(
        rows, cols
    )


def _envs_table(res: dict[str, Any]) -> str:
    rows = []
    for key, r in res["runs"].items():
        aero, n = key.split("/")
        lo, hi = r["spread_per_s"]
        rows.append(
            {
                "aero": aero,
                "n": int(n),
                "per_s": r["env_steps_per_s"],
                "range": f"{lo:,.0f}-{hi:,.0f}",
            }
        )
    cols = [
        ("aero", "aerodynamics", ""),
        ("n", "environments", "d"),
        ("per_s", "env-steps/s (median)", ",.0f"),
        ("range", "range", ""),
    ]
    return f"QuadrotorEnv, float32, {res['model']} on {res['dataset']}\n\n" + table(rows, cols)


def _devices_table(res: dict[str, Any]) -> str:
    """One row per measurement, with its speed-up against one device (or one worker)."""
    rows = []
    for name, per in res["build"].items():
        one = per.get("1", per["host"])["median_s"]
        for k, v in per.items():
            where = "host LAPACK, one process" if k == "host" else f"{k} device(s)"
            rows.append(
                {"what": f"build {name} ({where})", "s": v["median_s"], "x": one / v["median_s"]}
            )
    for key, v in res["predict"].items():
        batch, kind, c = key.split("/")
        one = res["predict"][f"{batch}/{kind}/1"]["per_s"]
        what = f"predict {kind} batch {batch} ({c} device(s)), {v['per_s']:.0f}/s"
        rows.append({"what": what, "s": v["median_s"], "x": v["per_s"] / one})
    gen = res["generate"]["seconds"]
    for w, v in gen.items():
        what = f"generate {res['generate']['rows']} rows ({w} worker(s))"
        x = gen["1"]["median_s"] / v["median_s"] if "1" in gen else None
        rows.append({"what": what, "s": v["median_s"], "x": x})
    cols = [("what", "measurement", ""), ("s", "median s", ".3f"), ("x", "speed-up vs 1", ".2f")]
    return table(rows, cols)


def _models_table(res: dict[str, Any]) -> str:
    rows = []
    for name, r in res["models"].items():
        rows.append(
            {
                "name": name,
                "fit": r["fit_s"],
                "ratio": r.get("fit_ratio_to_gpg"),
                "mv": r["mean_var_1"]["median_s"] * 1e3,
                "mvr": 100 * r["mean_var_ratio_to_gpg"] if "mean_var_ratio_to_gpg" in r else None,
                "m": r["mean_1"]["median_s"] * 1e6,
                "thr": r["mean_batch_per_s"],
                "smv": r["surrogate_predict_1"]["median_s"] * 1e3,
                "jit": r["surrogate_compile"]["median_s"],
                "sm": r["surrogate_predict_mean_1"]["median_s"] * 1e6,
                "smm": r["surrogate_predict_mean_1_method"]["median_s"] * 1e6,
                "mb": r["model_bytes"] / 2**20,
                "f32": r["float32"]["mean_error_over_std_max"],
                "f32ms": r["float32"]["surrogate_predict_1"]["median_s"] * 1e3,
            }
        )
    cols = [
        ("name", "model", ""),
        ("fit", "factorise/precompute s", ".2f"),
        ("ratio", "÷ gpg fit", ".2f"),
        ("mv", "mean+var ms", ".3f"),
        ("mvr", "% of gpg", ".1f"),
        ("m", "mean µs", ".1f"),
        ("thr", "batch mean /s", ",.0f"),
        ("smv", "Surrogate.predict ms", ".3f"),
        ("jit", "its compile s", ".2f"),
        ("sm", "predict_mean µs", ".1f"),
        ("smm", "(method) µs", ".1f"),
        ("mb", "MiB", ".1f"),
        ("f32", "float32 max err/std", ".1e"),
        ("f32ms", "float32 predict ms", ".3f"),
    ]
    return f"dataset {res['dataset']} ({res['n_train']} training points)\n\n" + table(rows, cols)


SUITES = {
    "exact_gp": bench_exact_gp,
    "models": bench_models,
    "devices": bench_devices,
    "derivatives": bench_derivatives,
    "envs": bench_envs,
    "solver": bench_solver,
    "design": bench_design,
    "export": bench_export,
    "gpu": bench_gpu,
    "flight": bench_flight,
}


def _exact_gp_table(res: dict[str, Any]) -> str:
    rows = [
        {"what": "Cholesky of ready K̄ (LAPACK, in place)", **res["cholesky_ready_lapack"]},
        {"what": "Cholesky of ready K̄ (jax.scipy)", **res["cholesky_ready_jax"]},
        {"what": "assemble K̄", **res["assemble"]},
        {"what": "assemble K̄ + Cholesky", **res["assemble_plus_cholesky"]},
        {"what": "ExactGP.fit (assemble, factorise, solve, L⁻¹)", **res["exact_gp_fit"]},
    ]
    t1 = table(rows, [("what", "step", ""), ("median_s", "median s", ".3f"), ("n", "n", "d")])
    lat = [
        {"what": "predict mean, 1 query", **res["predict_mean_1"]},
        {"what": "predict mean+var, 1 query", **res["predict_mean_var_1"]},
    ]
    lat = [{**r, "med_ms": r["median_s"] * 1e3, "p95_ms": r["p95_s"] * 1e3} for r in lat]
    t2 = table(
        lat,
        [
            ("what", "jitted predict", ""),
            ("med_ms", "median ms", ".3f"),
            ("p95_ms", "p95 ms", ".3f"),
        ],
    )
    ratio = res["ratio_assemble_plus_cholesky_to_cholesky"]
    return (
        f"K̄ with {res['rows']} rows ({res['n_points']} points, grad dims {res['grad_dims']})\n\n"
        f"{t1}\n\nassemble + Cholesky / Cholesky = {ratio:.2f}\n\n{t2}\n"
        f"batch mean throughput: {res['predict_mean_batch_throughput_per_s']:.0f} predictions/s"
    )


@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Run the suites named in ``cfg['suites']`` and write ``cfg['output']`` into ``outdir``."""
    unknown = [s for s in cfg["suites"] if s not in SUITES]
    if unknown:
        raise ValueError(f"unknown bench suite(s) {unknown}; valid: {sorted(SUITES)}")
    # Real-time users should dispatch synchronously (see the README); devices only overlap
    # with JAX's asynchronous CPU dispatch, which is fixed when JAX starts.
    set_dispatch({**cfg, "sync_dispatch": cfg["sync_dispatch"] and "devices" not in cfg["suites"]})
    results: dict[str, Any] = {"machine": machine(), "config": cfg}
    for name in cfg["suites"]:
        # The models suite runs on the entry point's data and vehicle (data=..., vehicle=...).
        sub = (
            {**cfg[name], "data": cfg["data"], "vehicle": cfg["vehicle"]}
            if name in ("models", "devices", "derivatives", "envs", "solver", "design", "gpu")
            else cfg[name]
        )
        results[name] = SUITES[name](sub)
        report(TABLES[name](results[name]))
    write_json(Path(outdir) / cfg["output"], results)
    report(f"wrote {Path(outdir) / cfg['output']}")
    return results


TABLES = {
    "exact_gp": _exact_gp_table,
    "models": _models_table,
    "devices": _devices_table,
    "derivatives": _derivatives_table,
    "envs": _envs_table,
    "solver": solver_table,
    "design": design_table,
    "export": export_table,
    "gpu": gpu_table,
    "flight": flight_table,
}
