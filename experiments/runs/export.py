"""Export a surrogate to C, CasADi and ONNX, check each against JAX and time it
(``python -m experiments.export``).

From a checkpoint (``surrogate_checkpoint``) or a model fitted on the configured data, writes
into ``<run dir>/export/``: ``<name>_double.c/.h`` and ``<name>_float.c/.h``
(:func:`gpg.export.to_c`), ``<name>.casadi`` (:func:`gpg.export.to_casadi`, loaded back with
``casadi.Function.load``) and ``<name>.onnx`` (:func:`gpg.export.to_onnx`). Each is checked
against :meth:`Surrogate.predict` at ``checks.n_states`` random states inside the domain
(largest error relative to each output vector's scale for the mean, relative to the variance
for the variance; CasADi's Jacobians against ``jax.jacrev``), and timed on this machine, one
query per call: the C through a small C driver (median of ``c.calls``, compiled with
``c.flags``), the CasADi function's own evaluation, ONNX Runtime (one state per run, and a
batch, and the one-state graph of ``to_onnx(batch=False)``) and ``Surrogate.realtime`` in the
same run. ``results.json`` holds the record, sizes, checks and latencies.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from experiments.runs.common import surrogate_from_config
from experiments.runs.config import check_options
from experiments.runs.output import report, table
from experiments.runs.timing import latency, machine, set_dispatch, stats, time_calls
from gpg.quadrotor.frames import R_WB
from gpg.runtime import float64, write_json

FORMATS = ("c", "casadi", "onnx")
OPTIONS = {
    "sync_dispatch": "bool",
    "cache_dir": "path",
    "surrogate_checkpoint": "path?",
    "variance": "bool",
    "name": "path",
}  # the run's own keys besides its config groups (runs.common.check_options)

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


def compile_and_time(cc: str, flags, where: Path, sources, calls: int,
                     runs: int = 1) -> dict[str, Any]:  # fmt: skip
    """Build ``driver`` from ``sources`` in ``where``, run it ``runs`` times for ``calls``
    queries each. With several runs the figures are those of the run whose median is the
    median of the runs' (``median_us``: the median of ``runs_median_us``)."""
    import time

    t0 = time.perf_counter()
    built = subprocess.run(
        [cc, *flags, "-I", str(where), "-o", str(where / "driver"), *map(str, sources), "-lm"],
        capture_output=True, text=True,
    )  # fmt: skip
    if built.returncode != 0:
        raise RuntimeError(f"{cc} failed: {built.stderr[-2000:]}")
    compile_s = time.perf_counter() - t0
    each = [
        json.loads(
            subprocess.run(
                [str(where / "driver"), str(calls)], check=True, capture_output=True, text=True
            ).stdout
        )
        for _ in range(max(1, int(runs)))
    ]
    mid = sorted(each, key=lambda r: r["median_us"])[len(each) // 2]
    out = {**mid, "compile_s": compile_s}
    if len(each) > 1:
        out["runs_median_us"] = [r["median_us"] for r in each]
    return out


def c_driver(header: str, call: str) -> str:
    """A C program timing ``call`` (``rpm, e, v`` in, ``f, tq, lv, var`` out) per query."""
    return (
        PRELUDE
        + f'#include "{header}"\n'
        + r"""
int main(int argc, char **argv) {
  int n = atoi(argv[1]), i, inside = 0;
  unsigned long long s = 12345;
  double *t = malloc(n * sizeof(double)), rpm[4], e[3], v[3], f[3], tq[3], lv[64], var[64];
  double sink = 0;
  struct timespec a, b;
  for (i = 0; i < n; i++) {
    state(&s, rpm, e, v);
    clock_gettime(CLOCK_MONOTONIC, &a);
    inside += """
        + call
        + r""";
    clock_gettime(CLOCK_MONOTONIC, &b);
    sink += f[0] + tq[2] + var[0];
    t[i] = (b.tv_sec - a.tv_sec) * 1e6 + (b.tv_nsec - a.tv_nsec) * 1e-3;
  }
  summary(t, n, inside, sink);
  free(t);
  return 0;
}
"""
    )


def domain_states(sur, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` world-frame states inside the surrogate's domain, kept where
    :meth:`Surrogate.predict` says ``in_domain`` (drawn until ``n`` are). Airflow frame:
    ``x_H`` uniform in its box, the air along +x (where the airflow frame is the world frame).
    Body frame: rotor speeds uniform in their box, the body-frame air uniform in the ball
    (every direction, hover included), any attitude (``R_WB`` takes it to the world)."""
    lo, hi = np.asarray(sur.box_lo), np.asarray(sur.box_hi)
    rng = np.random.default_rng(seed)
    flag = jax.jit(jax.vmap(lambda r, e, v: sur.predict_mean(r, e, v).in_domain))
    rotate = jax.jit(jax.vmap(lambda e, v: R_WB(e) @ v))
    kept: list[np.ndarray] = []
    while sum(len(k) for k in kept) < n:
        if sur.frame == "body":
            rpm = rng.uniform(lo[:4], hi[:4], (2 * n, 4))
            e = rng.uniform([-np.pi, -1.2, -np.pi], [np.pi, 1.2, np.pi], (2 * n, 3))
            d = rng.normal(size=(2 * n, 3))
            r = float(sur.ball_radius) * rng.uniform(0, 1, (2 * n, 1)) ** (1 / 3)
            v = np.asarray(rotate(e, d / np.linalg.norm(d, axis=1, keepdims=True) * r))
            x = np.c_[rpm, e]
        else:
            x = rng.uniform(lo, hi, (2 * n, 8))
            v = np.c_[x[:, 7], np.zeros((2 * n, 2))]
        ok = np.asarray(flag(x[:, :4], x[:, 4:7], v))
        kept.append(np.c_[x[ok, :7], v[ok]])
    s = np.concatenate(kept)[:n]
    return s[:, :4], s[:, 4:7], s[:, 7:]


def _errors(got: dict[str, np.ndarray], ref) -> dict[str, float]:
    """Largest error of the mean (relative to each vector's scale, at least 1) and of the
    variance (relative) over the states."""
    out = {}
    for key in ("force", "torque", "levels"):
        want = np.asarray(getattr(ref, key))
        if want.shape[-1]:
            scale = np.maximum(1.0, np.abs(want).max(axis=1, keepdims=True))
            out[key] = float((np.abs(got[key] - want) / scale).max())
    if "variance" in got and ref.variance is not None:
        want = np.asarray(ref.variance)
        out["variance"] = float((np.abs(got["variance"] - want) / want).max())
    if "in_domain" in got:
        out["in_domain_disagree"] = int(np.sum(got["in_domain"] != np.asarray(ref.in_domain)))
    return out


def _c(sur, cfg, where: Path, name: str, states, ref, variance: bool) -> dict[str, Any]:
    """Per dtype: write, compile as a shared library (checks through ctypes) and as a timing
    driver."""
    import ctypes

    from gpg import export

    cc = shutil.which(cfg["cc"])
    if cc is None:
        raise ValueError(f"c.cc: no C compiler {cfg['cc']!r} on PATH")
    out = {}
    for dtype in cfg["dtypes"]:
        stem = f"{name}_{dtype}"
        t0 = time.perf_counter()
        info = export.to_c(sur, where, name=stem, dtype=dtype, variance=variance)
        write_s = time.perf_counter() - t0
        obj, so = where / f"{stem}.o", where / f"{stem}.so"
        t0 = time.perf_counter()
        _cc(cc, [*cfg["flags"], "-fPIC", "-c", "-o", str(obj), str(info["c"])], link=False)
        compile_s = time.perf_counter() - t0  # once: the library and the drivers link it
        _cc(cc, ["-shared", "-o", str(so), str(obj)])
        lib = ctypes.CDLL(str(so))
        fn = getattr(lib, f"{stem}_predict" if info["variance"] else f"{stem}_mean")
        got = _call_c(fn, states, len(sur.output_names) - 6, info["variance"])
        timing = {}
        calls = [("mean", f"{stem}_mean(rpm, e, v, f, tq, lv)")]
        if info["variance"]:
            calls.append(("predict", f"{stem}_predict(rpm, e, v, f, tq, lv, var)"))
        for label, call in calls:
            (where / "driver.c").write_text(c_driver(f"{stem}.h", call))
            exe = where / f"time_{stem}_{label}"
            _cc(cc, [*cfg["flags"], "-I", str(where), "-o", str(exe), str(where / "driver.c"),
                     str(obj)])  # fmt: skip
            res = subprocess.run([str(exe), str(cfg["calls"])], check=True, capture_output=True,
                                 text=True)  # fmt: skip
            timing[label] = json.loads(res.stdout)
        out[dtype] = {
            "files": [info["c"].name, info["h"].name],
            "source_bytes": info["c"].stat().st_size,
            "constant_bytes": info["constant_bytes"],
            "write_s": write_s,
            "compile_s": compile_s,
            "errors": _errors(got, ref),
            "latency_us": timing,
        }
        report(f"C {dtype}: {out[dtype]['errors']}; {timing['mean']['median_us']:.1f} µs mean")
    return out


def _cc(cc: str, args: list[str], link: bool = True) -> None:
    built = subprocess.run([cc, *args, *(["-lm"] if link else [])], capture_output=True, text=True)
    if built.returncode != 0:
        raise RuntimeError(f"{cc} failed: {built.stderr[-2000:]}")


def _call_c(fn, states, n_levels: int, variance: bool) -> dict[str, np.ndarray]:
    import ctypes

    D = ctypes.POINTER(ctypes.c_double)
    rpm, euler, v = states
    n = len(rpm)
    f, t, lv = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, max(n_levels, 1)))
    var, ok = np.zeros((n, 6 + n_levels)), np.zeros(n, bool)
    for i in range(n):
        args = [np.ascontiguousarray(a[i], dtype=float).ctypes.data_as(D) for a in (rpm, euler, v)]
        outs = [a[i].ctypes.data_as(D) for a in (f, t, lv, var)][: 4 if variance else 3]
        ok[i] = fn(*args, *outs)
    got = {"force": f, "torque": t, "levels": lv[:, :n_levels], "in_domain": ok}
    return {**got, "variance": var} if variance else got


def _casadi(sur, cfg, where: Path, name: str, states, ref, variance: bool) -> dict[str, Any]:
    """Build, save, load back, check values and Jacobians, time its evaluation."""
    import casadi as ca

    from gpg import export
    from gpg.surrogate import predict_state

    t0 = time.perf_counter()
    built = export.to_casadi(sur, name=name, variance=variance)
    build_s = time.perf_counter() - t0
    path = where / f"{name}.casadi"
    built.save(str(path))
    f = ca.Function.load(str(path))
    rpm, euler, v = states
    res = [f(rpm[i], euler[i], v[i]) for i in range(len(rpm))]
    names = f.name_out()
    got = {k: np.array([np.asarray(r[j]).ravel() for r in res]) for j, k in enumerate(names)}
    got["in_domain"] = got["in_domain"][:, 0] > 0.5
    syms = [ca.MX.sym(k, n) for k, n in (("rpm", 4), ("euler", 3), ("v_air", 3))]
    o = f(*syms)
    jf = ca.Function(
        "jacobian_wrench", syms, [ca.jacobian(ca.vertcat(o[0], o[1]), ca.vertcat(*syms))]
    )

    def wrench(r, e, w):
        p = predict_state(sur, r, e, w, False)
        return jnp.concatenate([p.force, p.torque])

    jj = jax.jit(jax.jacrev(wrench, argnums=(0, 1, 2)))
    worst = 0.0
    for i in range(min(cfg["n_jacobians"], len(rpm))):
        Jj = np.concatenate([np.asarray(a) for a in jj(rpm[i], euler[i], v[i])], axis=1)
        Jc = np.asarray(jf(rpm[i], euler[i], v[i]))
        worst = max(worst, float(np.abs(Jc - Jj).max() / np.abs(Jj).max()))
    one = [(rpm[i], euler[i], v[i]) for i in range(min(64, len(rpm)))]
    calls = iter(one * (cfg["calls"] // len(one) + 2))
    timing = stats(time_calls(lambda: f(*next(calls)), cfg["calls"], warmup=3))
    out = {
        "file": path.name,
        "file_bytes": path.stat().st_size,
        "build_s": build_s,
        "errors": {**_errors(got, ref), "jacobian": worst},
        "latency_us": _us(timing),
    }
    report(f"CasADi: {out['errors']}; {out['latency_us']['median_us']:.0f} µs a call")
    return out


def _onnx(sur, cfg, where: Path, name: str, states, ref, variance: bool) -> dict[str, Any]:
    import onnxruntime as ort

    from gpg import export

    t0 = time.perf_counter()
    info = export.to_onnx(sur, where / f"{name}.onnx", variance=variance)
    build_s = time.perf_counter() - t0
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1  # one core, as the C driver
    sess = ort.InferenceSession(str(info["onnx"]), opts, providers=["CPUExecutionProvider"])
    names = ("rpm", "euler", "v_air")
    feeds = {k: np.asarray(a, np.float32) for k, a in zip(names, states, strict=True)}
    res = sess.run(None, feeds)
    got = dict(zip([o.name for o in sess.get_outputs()], res, strict=True))
    n = len(states[0])
    singles = [{k: a[i : i + 1] for k, a in feeds.items()} for i in range(min(64, n))]
    calls = iter(singles * (cfg["calls"] // len(singles) + 2))
    one = stats(time_calls(lambda: sess.run(None, next(calls)), cfg["calls"], warmup=3))
    batch = stats(time_calls(lambda: sess.run(None, feeds), 5, warmup=1))
    # The one-state graph (batch=False: the bin by If nodes), checked and timed the same way.
    single = export.to_onnx(sur, where / f"{name}_one.onnx", variance=variance, batch=False)
    sess1 = ort.InferenceSession(str(single["onnx"]), opts, providers=["CPUExecutionProvider"])
    names = [o.name for o in sess1.get_outputs()]
    rows = [sess1.run(None, {k: a[i : i + 1] for k, a in feeds.items()}) for i in range(n)]
    got1 = {k: np.concatenate([r[j] for r in rows]) for j, k in enumerate(names)}
    calls = iter(singles * (cfg["calls"] // len(singles) + 2))
    one1 = stats(time_calls(lambda: sess1.run(None, next(calls)), cfg["calls"], warmup=3))
    out = {
        "file": info["onnx"].name,
        "file_bytes": info["bytes"],
        "build_s": build_s,
        "errors": _errors(got, ref),
        "latency_us": {
            "one_state": _us(one),
            "per_state_in_batch": 1e6 * batch["median_s"] / n,
        },
        "one_state_graph": {
            "file": single["onnx"].name,
            "file_bytes": single["bytes"],
            "errors": _errors(got1, ref),
            "latency_us": _us(one1),
        },
    }
    report(
        f"ONNX: {out['errors']}; {out['latency_us']['one_state']['median_us']:.0f} µs a run, "
        f"the one-state graph {out['one_state_graph']['latency_us']['median_us']:.0f} µs"
    )
    return out


WRITERS = {"c": _c, "casadi": _casadi, "onnx": _onnx}


@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Load or fit the surrogate, export it in ``cfg["formats"]``, check and time each, and
    write ``results.json`` into ``outdir`` (the exports into ``outdir/export``)."""
    from gpg.export import spec
    from gpg.quadrotor.vehicle import Vehicle

    check_options(cfg, OPTIONS)
    bad = [f for f in cfg["formats"] if f not in FORMATS]
    if bad or not cfg["formats"]:
        raise ValueError(
            f"formats must be a non-empty list of {list(FORMATS)}, got {cfg['formats']!r}"
        )
    set_dispatch(cfg)
    sur = surrogate_from_config(cfg, Vehicle.from_config(cfg["vehicle"]))
    record = spec(sur, variance=cfg["variance"]).record  # refuses before anything is written
    outdir = Path(outdir)
    where = outdir / "export"
    where.mkdir(parents=True, exist_ok=True)
    chk = cfg["checks"]
    states = domain_states(sur, chk["n_states"], chk["seed"])
    with_var = bool(cfg["variance"] and record["variance"])
    ref = jax.jit(jax.vmap(sur.predict if with_var else sur.predict_mean))(*states)
    one = [tuple(a[i] for a in states) for i in range(min(64, chk["n_states"]))]
    realtime = {
        "mean": latency(sur.realtime(with_var=False), one, cfg["latency_calls"]),
        **({"predict": latency(sur.realtime(), one, cfg["latency_calls"])} if with_var else {}),
    }
    formats = {}
    for fmt in cfg["formats"]:
        sub = {**cfg.get(fmt, {}), "calls": cfg["latency_calls"], "n_jacobians": chk["n_jacobians"]}
        if fmt == "c":
            sub["calls"] = cfg["c"]["calls"]
        formats[fmt] = WRITERS[fmt](sur, sub, where, cfg["name"], states, ref, with_var)
    out = {
        "machine": machine(),
        "record": record,
        "surrogate": {"model": sur.model_name, "bytes": sur.nbytes()},
        "states": {"n": chk["n_states"], "seed": chk["seed"]},
        "realtime_us": {k: _us(v) for k, v in realtime.items()},
        "formats": formats,
        "config": cfg,
    }
    write_json(outdir / "results.json", out)
    report(summary_table(out))
    return out


def _us(timing: dict[str, float]) -> dict[str, float]:
    """:func:`experiments.runs.common.stats` (seconds) in microseconds."""
    return {k[:-2] + "_us": 1e6 * v for k, v in timing.items() if k.endswith("_s")}


def summary_table(res: dict[str, Any]) -> str:
    """One row per export: largest errors against JAX, latency of one query, size."""
    f, rows = res["formats"], []

    def row(what, r, mean_us, predict_us, kb):
        e = r["errors"] if r else {"force": 0.0, "variance": 0.0}
        rows.append({"what": what, "mean": e.get("force"), "var": e.get("variance"),
                     "us_mean": mean_us, "us_pred": predict_us, "kb": kb})  # fmt: skip

    for dtype, r in f.get("c", {}).items():
        lat = r["latency_us"]
        pred = lat.get("predict", {}).get("median_us")
        row(f"C {dtype}", r, lat["mean"]["median_us"], pred, r["constant_bytes"] / 1e3)
    if "casadi" in f:
        r = f["casadi"]
        row("CasADi (its own call)", r, None, r["latency_us"]["median_us"], r["file_bytes"] / 1e3)
    if "onnx" in f:
        r = f["onnx"]
        one = r["latency_us"]["one_state"]["median_us"]
        row("ONNX Runtime (one state a run)", r, None, one, r["file_bytes"] / 1e3)
        if "one_state_graph" in r:
            r1 = r["one_state_graph"]
            one = r1["latency_us"]["median_us"]
            row("ONNX Runtime, one-state graph", r1, None, one, r1["file_bytes"] / 1e3)
    rt = res["realtime_us"]
    pred = rt.get("predict", {}).get("median_us")
    kb = res["surrogate"]["bytes"] / 1e3
    row("Surrogate.realtime (JAX)", None, rt["mean"]["median_us"], pred, kb)
    cols = [
        ("what", "export", ""),
        ("mean", "force error (rel.)", ".1e"),
        ("var", "variance error (rel.)", ".1e"),
        ("us_mean", "mean µs", ".1f"),
        ("us_pred", "mean + variance µs", ".1f"),
        ("kb", "kB", ".0f"),
    ]
    return table(rows, cols)
