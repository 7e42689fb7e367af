"""The ``gpu`` suite of ``python -m experiments.bench``: gpg end to end on one accelerator.

What a user of one GPU asks, in one run (it runs on the CPU as well, with JAX's default
device, and says which): the fits end to end (the hyperparameter fit, the factorisations on
the device by ``solver.device=auto``, the near sets), the batched throughput of the mean and of
the mean with its variance in float64 and in a float32 program for several chunk sizes, the
float32 prediction against the float64 one in newtons over random in-domain states, the
environment's steps per second, and the device's peak memory. Data generation is not timed:
the datasets come from the cache (generated on first use).
"""

from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from experiments.runs.common import world_arrays
from experiments.runs.config import conf
from experiments.runs.output import report, table
from experiments.runs.timing import stats, time_calls
from gpg import models
from gpg.conf import deep_merge
from gpg.data.cache import ensure_datasets
from gpg.linalg import memory


def _block(p):
    return jax.block_until_ready(p)


def _peak_device_bytes(dev) -> int | None:
    stats_ = dev.memory_stats() if hasattr(dev, "memory_stats") else None
    return None if not stats_ else int(stats_.get("peak_bytes_in_use", 0)) or None


def _states(train, n: int, seed: int, device) -> tuple[jax.Array, ...]:
    """``n`` states drawn uniformly in the training box (the dataset's recorded bounds), as
    world-frame arrays placed on ``device``."""
    rng = np.random.default_rng(seed)
    x = train.x
    lo, hi = x.min(axis=0), x.max(axis=0)
    xs = lo + (hi - lo) * rng.random((n, x.shape[1]))
    return tuple(jax.device_put(jnp.asarray(a), device) for a in world_arrays(xs))


def _fit(spec: dict[str, Any], cfg: dict[str, Any]):
    from gpg.surrogate import Surrogate

    data = conf(spec["data"], "data")
    train, test, _, info = ensure_datasets(data, cfg["vehicle"], cfg["cache_dir"])
    name = spec["model"]
    mcfg = models.resolve_config(name, deep_merge(conf(name, "model"), spec.get("overrides")))
    t0 = time.perf_counter()
    sur = Surrogate.fit(train, name, mcfg)
    _block(jax.tree.leaves(sur))
    seconds = time.perf_counter() - t0
    g = 0 if train.jac_aero is None else train.jac_aero.shape[2]
    p = sur.predict_batch(*world_arrays(test.x))
    err = np.abs(np.asarray(p.force) - test.y_aero[:, :3])
    return (
        sur,
        (train, test),
        {
            "data": spec["data"],
            "dataset": info["key"],
            "model": name,
            "overrides": spec.get("overrides") or {},
            "n_train": int(train.n),
            "rows": int(train.n * (1 + g)),
            "fit_s": seconds,
            "force_mae_N": float(err.mean()),
        },
    )


def _throughput(sur, states, cfg) -> dict[str, Any]:
    out = {}
    for chunk in cfg["chunks"]:
        for mean_only in (True, False):
            label = f"{'mean' if mean_only else 'mean+var'}/chunk={chunk}"

            def call(c=chunk, m=mean_only):
                return sur.predict_batch(*states, mean_only=m, chunk=c)

            t = time_calls(call, cfg["repeats"], warmup=1)
            n = states[0].shape[0]
            out[label] = {
                **stats(t),
                "states_per_s": n / float(np.median(t)),
                "spread_per_s": [n / float(np.max(t)), n / float(np.min(t))],
            }
    return out


def _variance_methods(sur, cfg) -> dict[str, Any]:
    """The two executions of the batched variance (:func:`gpg.gp.binned.by_bin`) on the
    surrogate's own factors, random kernel rows and bins, ``states`` of them."""
    from gpg.gp.binned import METHODS, by_bin

    local = getattr(sur.model, "local", sur.model)
    factor = getattr(local, "factor", ())
    if not factor:
        return {}
    q = int(cfg["states"])
    key = jax.random.key(cfg["seed"])
    bins = jax.random.randint(key, (q,), 0, len(factor))
    K = jax.random.normal(jax.random.split(key)[0], (q, factor[0].n))
    out = {}
    runs = [(m, None) for m in METHODS[1:]]  # "every": B times the work, for a few queries
    runs += [("gather", int(t)) for t in cfg.get("tiles") or ()]
    for method, tile in runs:
        fn = jax.jit(
            lambda b, k, m=method, t=tile: by_bin(factor, b, k, with_grad=False, method=m, tile=t)[
                0
            ]
        )
        t = time_calls(lambda f=fn: f(bins, K), cfg["repeats"], warmup=1)
        key = method if tile is None else f"{method}/tile={tile}"
        out[key] = {**stats(t), "states_per_s": q / float(np.median(t))}
    return out


def _float32_error(sur, s32, states) -> dict[str, Any]:
    """The float32 program's prediction against float64's, in physical units."""
    p64 = sur.predict_batch(*states)
    with jax.enable_x64(False):
        p32 = s32.predict_batch(*(a.astype(jnp.float32) for a in states))
    out = {}
    for key in ("force", "torque"):
        e = np.abs(np.asarray(getattr(p32, key), np.float64) - np.asarray(getattr(p64, key)))
        out[f"{key}_max"] = float(e.max())
        out[f"{key}_p99"] = float(np.percentile(e, 99))
    v64 = np.asarray(p64.variance)
    rel = np.abs(np.asarray(p32.variance, np.float64) - v64) / np.maximum(v64, 1e-30)
    out["variance_relative_max"] = float(rel.max())
    out["variance_relative_p99"] = float(np.percentile(rel, 99))
    return out


def _env_steps(sur, train, cfg) -> dict[str, Any]:
    from gpg.data.preprocess import simple_model_for
    from gpg.envs import EnvParams, QuadrotorEnv
    from gpg.quadrotor.vehicle import Vehicle

    vehicle = Vehicle.from_config(cfg["vehicle"])
    env = QuadrotorEnv.create(vehicle, sur, simple=simple_model_for(train, vehicle))
    params = EnvParams.create("hover")
    T, out = int(cfg["env_steps"]), {}
    for n in cfg["n_envs"]:
        keys = jax.random.split(jax.random.key(cfg["seed"]), n)
        _, st = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)

        @jax.jit
        def roll(st, key, n=n):
            def body(st, k):
                a = jnp.zeros((n, 4), jnp.float32)
                step = jax.vmap(env.step, in_axes=(0, 0, 0, None))
                _, st, _, _, info = step(jax.random.split(k, n), st, a, params)
                return st, info["in_domain"]

            return jax.lax.scan(body, st, jax.random.split(key, T))

        ks = iter(jax.random.split(jax.random.key(cfg["seed"] + 1), cfg["repeats"] + 1))
        t = time_calls(lambda r=roll, s=st, k=ks: r(s, next(k)), cfg["repeats"], warmup=1)
        out[str(n)] = {**stats(t), "env_steps_per_s": n * T / float(np.median(t))}
    return out


def bench_gpu(cfg: dict[str, Any]) -> dict[str, Any]:
    """See the module docstring. ``cfg``: ``fits`` (data scale, model and its overrides; the
    first is the surrogate of the other figures), ``checkpoint`` (a saved surrogate measured
    instead, on the entry point's data), ``states`` and ``error_states`` (random states of the
    throughput and of the float32 error; the test set's too), ``chunks``, ``tiles`` (more tile
    sizes of the gathered variance), ``repeats``, ``n_envs``, ``env_steps``, ``seed``,
    ``cache_dir``."""
    dev = jax.devices()[0]
    out: dict[str, Any] = {
        "device": str(dev),
        "platform": dev.platform,
        "device_kind": getattr(dev, "device_kind", ""),
        "fits": {},
    }
    sur = data = None
    with memory.PeakRSS() as rss:
        for spec in cfg["fits"]:
            s, d, res = _fit(spec, cfg)
            out["fits"][f"{spec['model']}@{spec['data']}"] = res
            report(f"gpu suite: fitted {spec['model']} at data={spec['data']}: {res}")
            if sur is None:
                sur, data = s, d
            del s
        if cfg.get("checkpoint"):  # a saved model, the same on every machine
            from gpg import checkpoint

            sur = checkpoint.load(cfg["checkpoint"])
            data = ensure_datasets(cfg["data"], cfg["vehicle"], cfg["cache_dir"])[:2]
            out["checkpoint"] = str(cfg["checkpoint"])
        if sur is None:
            raise ValueError("gpu suite: no model to measure (fits is empty, no checkpoint)")
        train, test = data
        states = _states(train, int(cfg["states"]), cfg["seed"], dev)
        errs = _states(train, int(cfg["error_states"]), cfg["seed"] + 1, dev)
        s32 = sur.astype(jnp.float32)
        out["float32_error"] = _float32_error(sur, s32, errs)
        test_states = tuple(jax.device_put(jnp.asarray(a), dev) for a in world_arrays(test.x))
        out["float32_error_test_set"] = _float32_error(sur, s32, test_states)
        report(f"gpu suite: float32 against float64: {out['float32_error']}")
        out["throughput"] = {"float64": _throughput(sur, states, cfg)}
        report(f"gpu suite: float64 throughput {out['throughput']['float64']}")
        out["variance_methods"] = _variance_methods(sur, cfg)
        report(f"gpu suite: variance by bins {out['variance_methods']}")
        with jax.enable_x64(False):
            st32 = tuple(a.astype(jnp.float32) for a in states)
            out["throughput"]["float32"] = _throughput(s32, st32, cfg)
            out["env"] = _env_steps(s32, train, cfg)
    out["peak_device_bytes"] = _peak_device_bytes(dev)
    out["peak_rss_delta_bytes"] = int(rss.peak_delta)
    return out


def gpu_table(res: dict[str, Any]) -> str:
    fits = [{"what": k, **v} for k, v in res["fits"].items()]
    t1 = table(
        fits,
        [("what", "fit", ""), ("rows", "rows", "d"), ("fit_s", "seconds", ".1f"),
         ("force_mae_N", "force MAE N", ".3f")],
    )  # fmt: skip
    rows = [
        {"what": f"{dt} {k}", "per_s": v["states_per_s"] / 1e6}
        for dt, runs in res["throughput"].items()
        for k, v in runs.items()
    ]
    t2 = table(rows, [("what", "predict_batch", ""), ("per_s", "M states/s", ".3f")])
    env = [{"n": k, "per_s": v["env_steps_per_s"] / 1e6} for k, v in res["env"].items()]
    t3 = table(env, [("n", "environments", ""), ("per_s", "M steps/s", ".3f")])
    e = res["float32_error"]
    peak = res["peak_device_bytes"]
    return (
        f"{res['device']} ({res['device_kind']})\n\n{t1}\n\n{t2}\n\n{t3}\n\n"
        f"float32 against float64: force max {e['force_max']:.2e} N (p99 {e['force_p99']:.2e}), "
        f"torque max {e['torque_max']:.2e} N·m\n"
        f"peak device memory: {'n/a' if peak is None else f'{peak / 1e9:.2f} GB'}"
    )
