"""Speed measurements (``python -m experiments.bench``): ratios within one run, written to JSON.

Suites:

* ``exact_gp``: cost of assembling ``K̄`` and factorising it against the Cholesky of a ready
  matrix of the same size, and the latency of a jitted ``ExactGP.predict``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from tqdm.auto import tqdm

from gpg import linalg
from gpg.gp import ExactGP, Hyper, assemble_gram
from gpg.runs.common import machine, stats, table, time_calls, write_json


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
    hyper = Hyper(variance=1.0, lengthscale=cfg["lengthscale"], jitter=1e-8, grad_noise=1e-6)
    hyper = hyper.validate(d, len(dims))
    Xj = jnp.asarray(X)
    rows = n * (1 + len(dims))

    ready = assemble_gram(Xj, hyper, dims)  # also compiles the Gram builder
    out: dict[str, Any] = {"rows": rows, "n_points": n, "grad_dims": list(dims)}

    t_chol = []
    for _ in tqdm(range(reps), desc="Cholesky of a ready K̄", leave=False):
        buf = ready.copy()
        t_chol.append(time_calls(lambda b=buf: linalg.cholesky_inplace(b), 1, warmup=0)[0])
    del buf
    t_asm = time_calls(lambda: assemble_gram(Xj, hyper, dims), reps, warmup=1)
    t_asm_chol = time_calls(
        lambda: linalg.cholesky_inplace(assemble_gram(Xj, hyper, dims)), reps, warmup=0
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
    queries = [jnp.asarray(rng.uniform(-1, 1, (1, d))) for _ in range(cfg["n_queries"])]
    it = iter(range(10**9))

    def one(fn):
        return lambda: fn(queries[next(it) % len(queries)])

    out["predict_mean_1"] = stats(time_calls(one(model.predict_mean), cfg["n_queries"], warmup=3))
    out["predict_mean_var_1"] = stats(time_calls(one(model.predict), cfg["n_queries"], warmup=3))
    batch = jnp.asarray(rng.uniform(-1, 1, (cfg["batch"], d)))
    tb = time_calls(lambda: model.predict_mean(batch), 20, warmup=2)
    out[f"predict_mean_batch{cfg['batch']}"] = stats(tb)
    out["predict_mean_batch_throughput_per_s"] = cfg["batch"] / float(np.median(tb))
    return out


SUITES = {"exact_gp": bench_exact_gp}


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


def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Run the suites named in ``cfg['suites']`` and write ``cfg['output']`` into ``outdir``."""
    unknown = [s for s in cfg["suites"] if s not in SUITES]
    if unknown:
        raise ValueError(f"unknown bench suite(s) {unknown}; valid: {sorted(SUITES)}")
    results: dict[str, Any] = {"machine": machine(), "config": cfg}
    for name in cfg["suites"]:
        results[name] = SUITES[name](cfg[name])
        if name == "exact_gp":
            print(_exact_gp_table(results[name]))
    write_json(Path(outdir) / cfg["output"], results)
    print(f"wrote {Path(outdir) / cfg['output']}")
    return results
