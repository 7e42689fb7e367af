"""Bench suite ``export``: the C export of the mean (gpg/export.py) compiled with the system
``cc -O2`` and timed per query on one core by a small C driver (median of many calls), beside
``Surrogate.realtime`` in the same run, and the CasADi function: its own evaluation from Python
and the C its code generator writes, timed by the same kind of driver; the constants' bytes
and the sources' sizes.

The C code's cost depends only on the model's sizes (training points N, gradient dims G,
outputs M), not on the values, so the suite builds a ``gpgs_hybrid`` surrogate of the sizes
asked for on synthetic smooth data with fixed hyperparameters (seconds, no dataset needed):
N = 1000, G = 7, M = 9 is data=default's model, N = 5000 data=paper's.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from gpg.runs.common import latency, report, stats, table

# The drivers' common part: headers, a sort for the percentiles, and query states inside the
# data's box from a fixed linear congruential sequence.
PRELUDE = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static int cmp(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

static double uniform(unsigned long long *s, double lo, double hi) {
  *s = *s * 6364136223846793005ULL + 1442695040888963407ULL;
  return lo + (hi - lo) * (double)(*s >> 11) / 9007199254740992.0;
}

static void state(unsigned long long *s, double rpm[4], double e[3], double v[3]) {
  int j;
  for (j = 0; j < 4; j++) rpm[j] = uniform(s, 3000.0, 4000.0);
  for (j = 0; j < 3; j++) e[j] = uniform(s, -0.3, 0.3);
  v[0] = uniform(s, 3.0, 12.0); v[1] = uniform(s, -1.0, 1.0); v[2] = uniform(s, -1.0, 1.0);
}

static void summary(double *t, int n, int inside, double sink) {
  qsort(t, n, sizeof(double), cmp);
  printf("{\"median_us\": %.4f, \"p05_us\": %.4f, \"p95_us\": %.4f, \"n\": %d, "
         "\"in_domain\": %d, \"sink\": %.3g}\n", t[n / 2], t[n / 20], t[(19 * n) / 20], n,
         inside, sink);
}
"""

DRIVER = (
    PRELUDE
    + r"""
#include "quad.h"

int main(int argc, char **argv) {
  int n = atoi(argv[1]), i, inside = 0;
  unsigned long long s = 12345;
  double *t = malloc(n * sizeof(double)), rpm[4], euler[3], v[3], f[3], tq[3], lv[8], sink = 0;
  struct timespec a, b;
  for (i = 0; i < n; i++) {
    state(&s, rpm, euler, v);
    clock_gettime(CLOCK_MONOTONIC, &a);
    inside += quad_mean(rpm, euler, v, f, tq, lv);
    clock_gettime(CLOCK_MONOTONIC, &b);
    sink += f[0] + tq[2];
    t[i] = (b.tv_sec - a.tv_sec) * 1e6 + (b.tv_nsec - a.tv_nsec) * 1e-3;
  }
  summary(t, n, inside, sink);
  free(t);
  return 0;
}
"""
)


CASADI_DRIVER = (
    PRELUDE
    + r"""
#include "quad_ca.h"

int main(int argc, char **argv) {
  int n = atoi(argv[1]), i, inside = 0;
  unsigned long long s = 12345;
  casadi_int na, nr, niw, nw;
  quad_ca_work(&na, &nr, &niw, &nw);
  casadi_int *iw = malloc((niw + 1) * sizeof(casadi_int));
  double *w = malloc((nw + 1) * sizeof(double)), *t = malloc(n * sizeof(double));
  double rpm[4], e[3], v[3], f[3], tq[3], lv[8], dom, sink = 0;
  const double *arg[8] = {rpm, e, v};
  double *res[8] = {f, tq, lv, &dom};
  struct timespec a, b;
  for (i = 0; i < n; i++) {
    state(&s, rpm, e, v);
    clock_gettime(CLOCK_MONOTONIC, &a);
    quad_ca(arg, res, iw, w, 0);
    clock_gettime(CLOCK_MONOTONIC, &b);
    sink += f[0] + tq[2];
    inside += dom > 0.5;
    t[i] = (b.tv_sec - a.tv_sec) * 1e6 + (b.tv_nsec - a.tv_nsec) * 1e-3;
  }
  summary(t, n, inside, sink);
  return 0;
}
"""
)


def _compile_and_time(cc: str, flags, where: Path, sources, calls: int) -> dict[str, Any]:
    """Build ``driver`` from ``sources`` in ``where``, run it for ``calls`` queries."""
    import time

    t0 = time.perf_counter()
    built = subprocess.run(
        [cc, *flags, "-I", str(where), "-o", str(where / "driver"), *map(str, sources), "-lm"],
        capture_output=True, text=True,
    )  # fmt: skip
    if built.returncode != 0:
        raise RuntimeError(f"{cc} failed: {built.stderr[-2000:]}")
    compile_s = time.perf_counter() - t0
    res = subprocess.run(
        [str(where / "driver"), str(calls)], check=True, capture_output=True, text=True
    )
    return {**json.loads(res.stdout), "compile_s": compile_s}


def _casadi(sur, cc: str, flags, where: Path, states, cfg) -> dict[str, Any]:
    """The CasADi function: its own evaluation from Python, and its generated C."""
    from gpg import export
    from gpg.runs.common import time_calls

    f = export.to_casadi(sur, name="quad_ca")
    calls = iter(states * (cfg["jax_calls"] // len(states) + 2))
    python = stats(time_calls(lambda: f(*next(calls)), cfg["jax_calls"], warmup=3))
    where.mkdir(parents=True, exist_ok=True)
    import casadi as ca

    gen = ca.CodeGenerator("quad_ca.c", {"with_header": True})
    gen.add(f)
    gen.generate(f"{where}/")
    (where / "driver.c").write_text(CASADI_DRIVER)
    timing = _compile_and_time(
        cc, flags, where, [where / "driver.c", where / "quad_ca.c"], cfg["c_calls"]
    )
    return {
        "python_call": python,
        "generated_c": {**timing, "source_bytes": (where / "quad_ca.c").stat().st_size},
    }


def bench_export(cfg: dict[str, Any]) -> dict[str, Any]:
    """Per model size: C latency (double, float), constants' bytes, source bytes, compile
    seconds, and the realtime closure's mean latency in the same run."""
    from gpg import export
    from gpg.surrogate import Surrogate

    cc = shutil.which(cfg["cc"])
    if cc is None:
        raise ValueError(f"export.cc: no C compiler {cfg['cc']!r} on PATH")
    out: dict[str, Any] = {"cc": cc, "flags": cfg["flags"], "sizes": {}}
    for n in cfg["n_points"]:
        report(f"export: {n} training points")
        sur = Surrogate.fit(
            _smooth_dataset(n, cfg["seed"]),
            "gpgs_hybrid",
            {"hyper": {"fit": False, "lengthscale": 0.8}},
        )
        rng = np.random.default_rng(cfg["seed"])
        states = [
            (
                rng.uniform(3000, 4000, 4),
                rng.uniform(-0.3, 0.3, 3),
                np.r_[rng.uniform(3, 12), rng.uniform(-1, 1, 2)],
            )
            for _ in range(64)
        ]
        row: dict[str, Any] = {
            "realtime_mean": latency(sur.realtime(with_var=False), states, cfg["jax_calls"])
        }
        with tempfile.TemporaryDirectory() as tmp:
            for dtype in ("double", "float"):
                where = Path(tmp) / dtype
                info = export.to_c(sur, where, name="quad", dtype=dtype)
                (where / "driver.c").write_text(DRIVER)
                timing = _compile_and_time(
                    cc, cfg["flags"], where, [where / "driver.c", info["c"]], cfg["c_calls"]
                )
                row[dtype] = {
                    **timing,
                    "constant_bytes": info["constant_bytes"],
                    "source_bytes": info["c"].stat().st_size,
                }
            if cfg["casadi"]:
                row["casadi"] = _casadi(sur, cc, cfg["flags"], Path(tmp) / "casadi", states, cfg)
        median_rt = row["realtime_mean"]["median_s"] * 1e6
        row["realtime_over_c_double"] = median_rt / row["double"]["median_us"]
        out["sizes"][str(n)] = row
    return out


def export_table(res: dict[str, Any]) -> str:
    rows = []
    for n, r in res["sizes"].items():
        for dtype in ("double", "float"):
            rows.append(
                {
                    "n": n,
                    "dtype": dtype,
                    "us": r[dtype]["median_us"],
                    "p95": r[dtype]["p95_us"],
                    "kb": r[dtype]["constant_bytes"] / 1e3,
                    "rt": r["realtime_mean"]["median_s"] * 1e6,
                }
            )
        if "casadi" in r:
            c = r["casadi"]
            rows.append(
                {
                    "n": n,
                    "dtype": "CasADi codegen (double)",
                    "us": c["generated_c"]["median_us"],
                    "p95": c["generated_c"]["p95_us"],
                    "kb": float("nan"),
                    "rt": c["python_call"]["median_s"] * 1e6,
                }
            )
    cols = [
        ("n", "points", ""),
        ("dtype", "C type", ""),
        ("us", "C mean µs (median)", ".2f"),
        ("p95", "p95 µs", ".2f"),
        ("kb", "constants kB", ".0f"),
        ("rt", "realtime µs (CasADi: its Python call)", ".1f"),
    ]
    return table(rows, cols)


def _smooth_dataset(n: int, seed: int):
    """N cases in the paper's box with the 9 outputs and their gradients of a smooth random
    function (a linear map of the scaled inputs through a sine): the sizes of a real model."""
    from gpg.data import Bounds, Dataset, latin_hypercube
    from gpg.quadrotor.vehicle import vehicle_config

    rng = np.random.default_rng(seed)
    W = rng.normal(scale=0.5, size=(8, 9))
    lo, hi = Bounds().arrays()
    x = latin_hypercube(n, Bounds(), seed)
    z = (2 * (x - lo) / (hi - lo) - 1) @ W
    y = np.sin(z) + 0.3 * z
    jac = (np.cos(z) + 0.3)[:, :, None] * (W.T[None, :, :7] * (2 / (hi - lo))[None, None, :7])
    return Dataset(
        x=x,
        y_aero=y[:, :6],
        jac_aero=jac[:, :6],
        y_noise=y[:, 6:] + 60.0,
        jac_noise=jac[:, 6:],
        meta={"name": "smooth", "vehicle": vehicle_config("sui_endurance"),
              "simple_model": {"P_F": 5.3e-7, "T_z": 8.4e-9}},
    )  # fmt: skip
