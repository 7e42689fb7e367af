"""Bench suite ``export``: the C export of the mean (gpg/export.py) compiled with the system
``cc -O2`` and timed per query on one core by a small C driver (median of many calls), beside
``Surrogate.realtime`` in the same run; the constants' bytes and the source's size.

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

from gpg.runs.common import latency, report, table

DRIVER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "quad.h"

static int cmp(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

/* states inside the data's box, from a fixed linear congruential sequence */
static double uniform(unsigned long long *s, double lo, double hi) {
  *s = *s * 6364136223846793005ULL + 1442695040888963407ULL;
  return lo + (hi - lo) * (double)(*s >> 11) / 9007199254740992.0;
}

int main(int argc, char **argv) {
  int n = atoi(argv[1]), i, j, inside = 0;
  unsigned long long s = 12345;
  double *t = malloc(n * sizeof(double)), rpm[4], euler[3], v[3], f[3], tq[3], lv[8], sink = 0;
  struct timespec a, b;
  for (i = 0; i < n; i++) {
    for (j = 0; j < 4; j++) rpm[j] = uniform(&s, 3000.0, 4000.0);
    for (j = 0; j < 3; j++) euler[j] = uniform(&s, -0.3, 0.3);
    v[0] = uniform(&s, 3.0, 12.0); v[1] = uniform(&s, -1.0, 1.0); v[2] = uniform(&s, -1.0, 1.0);
    clock_gettime(CLOCK_MONOTONIC, &a);
    inside += quad_mean(rpm, euler, v, f, tq, lv);
    clock_gettime(CLOCK_MONOTONIC, &b);
    sink += f[0] + tq[2];
    t[i] = (b.tv_sec - a.tv_sec) * 1e6 + (b.tv_nsec - a.tv_nsec) * 1e-3;
  }
  qsort(t, n, sizeof(double), cmp);
  printf("{\"median_us\": %.4f, \"p05_us\": %.4f, \"p95_us\": %.4f, \"n\": %d, "
         "\"in_domain\": %d, \"sink\": %.3g}\n", t[n / 2], t[n / 20], t[(19 * n) / 20], n,
         inside, sink);
  free(t);
  return 0;
}
"""


def bench_export(cfg: dict[str, Any]) -> dict[str, Any]:
    """Per model size: C latency (double, float), constants' bytes, source bytes, compile
    seconds, and the realtime closure's mean latency in the same run."""
    import time

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
                t0 = time.perf_counter()
                built = subprocess.run(
                    [cc, *cfg["flags"], "-o", str(where / "driver"), str(where / "driver.c"),
                     str(info["c"]), "-lm"],
                    capture_output=True, text=True,
                )  # fmt: skip
                if built.returncode != 0:
                    raise RuntimeError(f"{cc} failed on the export: {built.stderr[-2000:]}")
                compile_s = time.perf_counter() - t0
                res = subprocess.run(
                    [str(where / "driver"), str(cfg["c_calls"])],
                    check=True, capture_output=True, text=True,
                )  # fmt: skip
                timing = json.loads(res.stdout)
                row[dtype] = {
                    **timing,
                    "constant_bytes": info["constant_bytes"],
                    "source_bytes": info["c"].stat().st_size,
                    "compile_s": compile_s,
                }
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
    cols = [
        ("n", "points", ""),
        ("dtype", "C type", ""),
        ("us", "C mean µs (median)", ".2f"),
        ("p95", "p95 µs", ".2f"),
        ("kb", "constants kB", ".0f"),
        ("rt", "realtime µs", ".1f"),
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
