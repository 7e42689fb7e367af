"""Bench suite ``export``: the C export (gpg/export), mean and mean plus variance, compiled
with the system ``cc -O2`` and timed per query on one core by a small C driver (median of
many calls), beside ``Surrogate.realtime`` in the same run, and the CasADi function's mean:
its own evaluation from Python and the C its code generator writes, timed by the same kind
of driver; the constants' bytes and the sources' sizes.

The C code's cost depends only on the model's sizes (training points N, gradient dims G,
outputs M), not on the values, so the suite builds a ``gpgs_hybrid`` surrogate of the sizes
asked for on synthetic smooth data with fixed hyperparameters (seconds, no dataset needed):
N = 1000, G = 7, M = 9 is data=default's model, N = 5000 data=paper's.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from experiments.runs.export import CASADI_DRIVER, c_driver, compile_and_time
from experiments.runs.output import report, table
from experiments.runs.timing import latency, stats

CALLS = (
    ("mean", "quad_mean(rpm, e, v, f, tq, lv)"),
    ("predict", "quad_predict(rpm, e, v, f, tq, lv, var)"),
)  # what the C driver times, one query per call


def _casadi(sur, cc: str, flags, where: Path, states, cfg) -> dict[str, Any]:
    """The CasADi function: its own evaluation from Python, and its generated C."""
    from experiments.runs.timing import time_calls
    from gpg import export

    f = export.to_casadi(sur, name="quad_ca", variance=False)
    calls = iter(states * (cfg["jax_calls"] // len(states) + 2))
    python = stats(time_calls(lambda: f(*next(calls)), cfg["jax_calls"], warmup=3))
    where.mkdir(parents=True, exist_ok=True)
    import casadi as ca

    gen = ca.CodeGenerator("quad_ca.c", {"with_header": True})
    gen.add(f)
    gen.generate(f"{where}/")
    (where / "driver.c").write_text(CASADI_DRIVER)
    timing = compile_and_time(
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
            smooth_dataset(n, cfg["seed"]),
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
                try:
                    info = export.to_c(sur, where, name="quad", dtype=dtype)
                except ValueError as e:  # the variance over max_bytes (data=paper's size)
                    if "max_bytes" not in str(e):
                        raise
                    info = export.to_c(sur, where, name="quad", dtype=dtype, variance=False)
                timing = {}
                for label, call in CALLS[: 1 + info["variance"]]:
                    (where / "driver.c").write_text(c_driver("quad.h", call))
                    timing[label] = compile_and_time(
                        cc, cfg["flags"], where, [where / "driver.c", info["c"]], cfg["c_calls"],
                        runs=cfg["runs"] if label == "mean" else 1,
                    )  # fmt: skip
                row[dtype] = {
                    **timing["mean"],
                    "predict": timing.get("predict"),
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
                    "pred": (r[dtype]["predict"] or {}).get("median_us"),
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
        ("pred", "C mean + variance µs", ".1f"),
        ("kb", "constants kB", ".0f"),
        ("rt", "realtime µs (CasADi: its Python call)", ".1f"),
    ]
    return table(rows, cols)


def smooth_dataset(n: int, seed: int):
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
