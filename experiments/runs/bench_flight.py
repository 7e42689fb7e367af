"""Bench suite ``flight``: how fast a PX4 log is read and labelled against how long it flew,
and what one adaptation update costs (:mod:`gpg.flight`).

* ``log``: :func:`gpg.flight.read_ulog` plus :func:`gpg.flight.label` of a ULog file (the test
  fixture by default: a real PX4 log), timed together, median of ``repeats`` after a warm-up
  (the one-off calibration of ``M`` to the log's hover timed apart), as seconds flown per
  second of work; and the checks that reading runs, each timed alone as a share of reading
  and labelling: the signals against each other (:func:`gpg.flight.consistency`) and the
  walk over the file's messages that finds a file cut short.
* ``update``: :func:`gpg.flight.online_step` from Python, once per label, on a model of the
  sizes a user has: a ``gpgs_hybrid`` prior of ``n_points`` (data=default's 1000 by default, on
  synthetic data with fixed hyperparameters: the cost depends on the sizes only) corrected by
  ``labels`` labels (60 s at 10 Hz), with ``inducing`` inducing inputs (today's term,
  :func:`gpg.flight.adapt`) and with its physical basis's coefficients tracked instead
  (:func:`gpg.flight.track`); median and spread of ``updates`` calls each, and the online
  state's bytes before and after them.
  With ``stacked``: the tracked step, and the step with a wind state, on a correction of
  ``stacked.labels`` labels whose discrepancies are inducing-point GPs of
  ``stacked.inducing`` inputs, read through one stack and one by one
  (``online_step(stack=...)``), and stacked with each new state written over the last
  (``online_step(donate=True)``), the three taking the same ``block`` labels in turn, in
  ``rounds`` rounds: the median of the ratios paired by block, per round.
* ``parallel``: :func:`gpg.flight.label_logs` of a directory of ``logs`` CSV logs of
  ``seconds`` s each (``distinct`` flights of the nominal vehicle flown by
  :func:`gpg.flight.synthetic.fly` through the default sensors, 200 Hz with rotor speeds and an
  IMU, each written ``logs / distinct`` times: labelling a copy is the same work), in this
  process (``workers=1``) and on ``workers`` spawned processes, alternated ``repeats`` times;
  the speed-up is the ratio of the medians, the labels compared bit for bit.
* ``c``: a corrected and adapted model in C (:func:`gpg.export.to_c`), per query or label on
  one core, timed by the export suite's C driver (median and percentiles of ``c_calls``): the
  corrected model's mean and mean + variance (the ``gpgs_hybrid`` prior of ``n_points``, the
  physical basis, discrepancies through ``inducing`` inducing inputs fitted on ``labels``
  synthetic labels: the cost depends on the sizes only), the online term's update and
  prediction (``online`` inducing inputs), and the same two calls of the corrected model
  tracked (:func:`gpg.flight.track`, the default drift with a second, one-second bias
  member: a bank of two filters), tracked with a wind state (:func:`gpg.flight.gusts`,
  ``wind_*``) and adapted by a bank of online terms (:func:`gpg.flight.adapt_bank`, ``bank``:
  its members' forgetting times and ``ahead``; ``bank_*``), in double and in float. With
  ``python_calls``: the tracked, wind and bank models' update and prediction called
  from Python through :func:`gpg.export.to_native` (``<kind>_python``), one label per call
  cycling through the synthetic labels, the foreign call included: what a user's loop pays.
* ``every_label``: :func:`gpg.flight.correct` (the physical basis, discrepancies through
  ``inducing`` inducing inputs) on ``hours`` of labels at 10 Hz (36 000 an hour; synthetic
  labels of a vehicle 10 % stronger than the prior, drawn in its box: the cost depends on the
  sizes), each timed once after a warm-up on ``warmup`` labels that compiles the programs, on
  JAX's default device; the process's peak resident memory above its start and, on an
  accelerator, its peak device memory.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any

import jax
import numpy as np

from experiments.runs.output import table
from experiments.runs.timing import stats


def bench_flight(cfg: dict[str, Any]) -> dict[str, Any]:
    """Both measurements of the module docstring."""
    out: dict[str, Any] = {}
    if cfg.get("log"):  # each part can be left out (null), e.g. on an accelerator
        out["log"] = _log(cfg["log"])
    if cfg.get("update"):
        out["update"] = _update(cfg["update"])
    if cfg.get("parallel"):
        out["parallel"] = _parallel(cfg["parallel"])
    if cfg.get("c"):
        out["c"] = _c(cfg["c"])
    if cfg.get("every_label"):
        out["every_label"] = _every_label(cfg["every_label"])
    return out


def _every_label(cfg: dict[str, Any]) -> dict[str, Any]:
    from gpg import flight
    from gpg.linalg import memory

    prior = _prior(int(cfg["n_points"]))
    opts = {"basis": "physical", "inducing": int(cfg["inducing"]), "subset_size": 400}
    flight.correct(prior, _synthetic_labels(prior, int(cfg["warmup"]), 1), exact_labels=1, **opts)
    dev = jax.devices()[0]
    rows = []
    for hours in cfg["hours"]:
        labels = _synthetic_labels(prior, int(round(36000 * float(hours))), 2)
        with memory.PeakRSS() as mem:
            t0 = time.perf_counter()
            sur = flight.correct(prior, labels, **opts)
            jax.block_until_ready(jax.tree.leaves(sur.model))
            seconds = time.perf_counter() - t0
        stats_ = dev.memory_stats() or {}
        rows.append({"hours": float(hours), "labels": len(labels), "seconds": seconds,
                     "peak_rss_mib": mem.peak_delta / 2**20,
                     "device_peak_mib": stats_.get("peak_bytes_in_use", 0) / 2**20,
                     "inducing": sur.config["flight_correction"]["inducing"]})  # fmt: skip
    return {"device": str(dev), "n_points": int(cfg["n_points"]), "runs": rows}


def _prior(n_points: int):
    """A ``gpgs_hybrid`` of ``n_points`` synthetic cases with fixed hyperparameters: the sizes
    of a user's model (data=default's at 1000), in seconds, no dataset needed."""
    from experiments.runs.bench_export import smooth_dataset
    from gpg.surrogate import Surrogate

    return Surrogate.fit(smooth_dataset(n_points, 0), "gpgs_hybrid",
                         {"hyper": {"fit": False, "lengthscale": 0.8}})  # fmt: skip


def _synthetic_labels(prior, n: int, seed: int):
    """``n`` labels of a vehicle 10 % stronger than ``prior`` with noise, in its box."""
    from gpg import flight

    rng = np.random.default_rng(seed)
    rpm = rng.uniform(3000, 4000, (n, 4))
    euler = np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.1, n),
                             rng.uniform(-0.2, 0.2, n)])  # fmt: skip
    speed = rng.uniform(3, 12, n)
    v_air = np.column_stack([speed * np.cos(euler[:, 0]), speed * np.sin(euler[:, 0]), 0 * speed])
    p = prior.predict_batch(rpm, euler, v_air, mean_only=True)
    return flight.Labels(
        t=np.arange(n) / 10.0, rpm=rpm, euler=euler, v_air=v_air,
        force=np.asarray(p.force) * 1.1 + 0.05 * rng.normal(size=(n, 3)),
        torque=np.asarray(p.torque) + 0.005 * rng.normal(size=(n, 3)),
        force_var=np.full((n, 3), 0.05**2), torque_var=np.full((n, 3), 0.005**2),
        model_force=np.zeros((n, 3)), model_torque=np.zeros((n, 3)),
    )  # fmt: skip


# The online update's driver: a state of the caller's and one label (held) per call.
ONLINE_HEADER = """#include "quad.h"
static quad_online ST;
static double FM[3] = {0.5, -0.3, -20.0}, TM[3] = {0.01, -0.02, 0.005};
static double FV[3] = {0.01, 0.01, 0.01}, TV[3] = {1e-4, 1e-4, 1e-4};
"""
ONLINE_CALLS = (
    ("online_update", "(i == 0 ? (quad_online_init(&ST), 0) : 0) + "
     "quad_online_update(&ST, i * 0.1, rpm, e, v, FM, TM, FV, TV)"),
    ("online_predict", "(i == 0 ? (quad_online_init(&ST), 0) : 0) + "
     "quad_online_predict(&ST, rpm, e, v, f, tq, lv, var)"),
)  # fmt: skip


def _c(cfg: dict[str, Any]) -> dict[str, Any]:
    import shutil
    import tempfile
    from pathlib import Path

    from experiments.runs.export import c_driver, compile_and_time
    from gpg import flight
    from gpg.export import to_c

    cc = shutil.which(cfg["cc"])
    if cc is None:
        raise ValueError(f"flight.c.cc: no C compiler {cfg['cc']!r} on PATH")
    prior = _prior(int(cfg["n_points"]))
    labels = _synthetic_labels(prior, int(cfg["labels"]), 0)
    corrected = flight.correct(prior, labels, basis="physical", exact_labels=1500,
                               inducing=int(cfg["inducing"]), subset_size=400)  # fmt: skip
    adapted = flight.adapt(corrected, inducing=int(cfg["online"]), t0=0.0)
    drift = dataclasses.replace(flight.default_drift(corrected), fast=(1.0,))
    tracked = {"tracked": flight.track(corrected, drift),
               "wind": flight.track(corrected, flight.gusts(drift))}  # fmt: skip
    if cfg.get("bank"):  # its members scored under the offline band at each label
        members = [(float(tau), None) for tau in cfg["bank"]["taus"]]
        tracked["bank"] = flight.adapt_bank(corrected, members, ahead=int(cfg["bank"]["ahead"]),
                                            inducing=int(cfg["online"]), t0=0.0)  # fmt: skip
    calls = (("mean", "quad_mean(rpm, e, v, f, tq, lv)"),
             ("predict", "quad_predict(rpm, e, v, f, tq, lv, var)"))  # fmt: skip
    out: dict[str, Any] = {"cc": cc, "flags": cfg["flags"], "n_points": int(cfg["n_points"]),
                           "labels": int(cfg["labels"]), "inducing": int(cfg["inducing"]),
                           "online": int(cfg["online"])}  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="gpg_bench_c_") as tmp:
        for dtype in ("double", "float"):
            where = Path(tmp) / dtype
            info = to_c(adapted, where, name="quad", dtype=dtype)
            (where / "online_bench.h").write_text(ONLINE_HEADER)
            row = {"constant_bytes": info["constant_bytes"]}
            for key, call in calls + ONLINE_CALLS:
                header = "online_bench.h" if key.startswith("online") else "quad.h"
                (where / "driver.c").write_text(c_driver(header, call))
                sources = [where / "driver.c", info["c"]]
                row[key] = compile_and_time(cc, cfg["flags"], where, sources, int(cfg["c_calls"]))
            for kind, model in tracked.items():  # the tracked filter, with a wind state, a bank
                where = Path(tmp) / f"{dtype}_{kind}"
                if cfg.get("python_calls"):
                    row[f"{kind}_python"] = _from_python(
                        model, Path(tmp) / f"{dtype}_{kind}_py", dtype, cc, cfg, labels
                    )
                info = to_c(model, where, name="quad", dtype=dtype)
                (where / "online_bench.h").write_text(ONLINE_HEADER)
                for key, call in ONLINE_CALLS:
                    (where / "driver.c").write_text(c_driver("online_bench.h", call))
                    sources = [where / "driver.c", info["c"]]
                    row[f"{kind}_{key.removeprefix('online_')}"] = compile_and_time(
                        cc, cfg["flags"], where, sources, int(cfg["c_calls"])
                    )
            out[dtype] = row
    return out


def _from_python(model, where, dtype: str, cc: str, cfg: dict[str, Any], labels):
    """``model``'s online update and prediction in C, called from Python
    (:func:`gpg.export.to_native`): ``python_calls`` labels, each timed alone, after five
    untimed (median, 5th and 95th percentile, µs)."""
    from experiments.runs.export import _us
    from gpg.export import to_native

    nat = to_native(model, where, name="quad", dtype=dtype, cc=cc, flags=tuple(cfg["flags"]))
    cols = [np.asarray(c, float) for c in labels.columns()]
    n, calls = len(cols[0]), int(cfg["python_calls"])
    times = np.empty((2, calls + 5))
    for i in range(calls + 5):
        row = [c[i % n] for c in cols]
        t0 = time.perf_counter()
        nat.update(i * 0.1, *row[1:])
        t1 = time.perf_counter()
        nat.predict(*row[1:4])
        times[:, i] = t1 - t0, time.perf_counter() - t1
    return {key: {**_us(stats(t)), "n": t.size}
            for key, t in zip(("update", "predict"), times[:, 5:], strict=True)}  # fmt: skip


def _parallel(cfg: dict[str, Any]) -> dict[str, Any]:
    import shutil
    import tempfile
    from pathlib import Path

    from gpg.flight import label_logs, write_csv
    from gpg.flight.identify import hover_coefficients
    from gpg.flight.synthetic import fly, random_plan
    from gpg.quadrotor.control import GeometricController
    from gpg.quadrotor.dynamics import Wind
    from gpg.quadrotor.simple_model import SimpleModel
    from gpg.quadrotor.vehicle import load_vehicle

    veh = load_vehicle(cfg["vehicle"])
    M = SimpleModel.from_vehicle(veh, *hover_coefficients(veh))  # M of the vehicle's hover
    ctrl = GeometricController.create(veh, M)
    n, distinct, dur = int(cfg["logs"]), int(cfg["distinct"]), float(cfg["seconds"])
    with tempfile.TemporaryDirectory(prefix="gpg_bench_logs_") as tmp:
        root = Path(tmp)
        for k in range(distinct):
            rng = np.random.default_rng(k)
            plan = random_plan(rng, dur, box=10.0, step=(3.0, 8.0), leg_time=(3.0, 5.0))
            f = fly(veh, ctrl, plan, Wind.constant(np.array([2.0, -1.0, 0.0])), dur, seed=k,
                    name=f"flight{k}")  # fmt: skip
            write_csv(f.log, root / f"log{k:03d}.csv")
        for i in range(distinct, n):
            shutil.copy(root / f"log{i % distinct:03d}.csv", root / f"log{i:03d}.csv")
        opts = {"reference": M, "rate": 10.0, "source": "imu"}
        warnings.simplefilter("ignore")  # the copies' warnings, a hundred times over
        # Warm-up: this process compiles label's pieces once (each spawned worker does too,
        # and that is timed: it is what a user's call pays).
        label_logs([root / "log000.csv"], veh, progress=False, workers=1, **opts)
        times: dict[int, list[float]] = {1: [], int(cfg["workers"]): []}
        results = {}
        for _ in range(int(cfg["repeats"])):
            for w in times:
                t0 = time.perf_counter()
                results[w] = label_logs(root, veh, workers=w, progress=False, **opts)
                times[w].append(time.perf_counter() - t0)
    one, many = results[1], results[int(cfg["workers"])]
    same = list(one.labels) == list(many.labels) and all(
        np.array_equal(getattr(one.labels[k], f), getattr(many.labels[k], f))
        for k in one.labels for f in ("t", "rpm", "force", "torque", "force_var", "torque_var")
    )  # fmt: skip
    st = {w: stats(np.asarray(v)) for w, v in times.items()}
    return {
        "logs": n,
        "distinct": distinct,
        "seconds_each": dur,
        "labels": int(sum(len(lb) for lb in one.labels.values())),
        "failed": len(one.failed),
        "workers": int(cfg["workers"]),
        "wall_s": {str(w): v for w, v in st.items()},
        "speedup": st[1]["median_s"] / st[int(cfg["workers"])]["median_s"],
        "same_labels": bool(same),
    }


def _log(cfg: dict[str, Any]) -> dict[str, Any]:
    from gpg.flight import FlightLogWarning, calibrate_simple, consistency, label, read_ulog
    from gpg.quadrotor.vehicle import load_vehicle

    veh = load_vehicle(cfg["vehicle"])
    rate = cfg["rate"]
    # The log's own warnings (the estimator's resets) once, not once a repetition.
    log = read_ulog(cfg["path"], rate=rate)
    warnings.simplefilter("ignore", FlightLogWarning)
    t0 = time.perf_counter()
    M = calibrate_simple(log, veh, torque_ratio=cfg["torque_ratio"])
    calibrate_s = time.perf_counter() - t0
    label(log, veh, reference=M)  # warm-up: the compiled pieces
    seconds = []
    for _ in range(int(cfg["repeats"])):
        t0 = time.perf_counter()
        lab = label(read_ulog(cfg["path"], rate=rate), veh, reference=M)
        seconds.append(time.perf_counter() - t0)
    s = stats(np.asarray(seconds))
    from gpg.flight.ulog import cut_bytes

    checks, walks = [], []
    for _ in range(10 * int(cfg["repeats"])):  # a millisecond's work: more repeats
        t0 = time.perf_counter()
        consistency(log)
        t1 = time.perf_counter()
        cut_bytes(cfg["path"])
        checks.append(t1 - t0)
        walks.append(time.perf_counter() - t1)
    c, w = stats(np.asarray(checks)), stats(np.asarray(walks))
    return {
        "path": str(cfg["path"]),
        "flown_s": log.duration,
        "rate_hz": log.rate,
        "samples": int(log.t.size),
        "labels": len(lab),
        "dropped": lab.dropped,
        "read_and_label_s": s,
        "calibrate_s": calibrate_s,
        "times_faster_than_flown": log.duration / s["median_s"],
        "consistency_s": c,
        "consistency_share": c["median_s"] / s["median_s"],
        "integrity_s": w,
        "integrity_share": w["median_s"] / s["median_s"],
    }


def _update(cfg: dict[str, Any]) -> dict[str, Any]:
    from gpg import flight

    prior = _prior(int(cfg["n_points"]))
    n = int(cfg["labels"])
    labels = _synthetic_labels(prior, n, 0)
    corrected = flight.correct(prior, labels, subset_size=min(n, 400))
    terms = {
        "inducing": flight.adapt(corrected, inducing=int(cfg["inducing"]), t0=0.0),
        "tracked": flight.track(corrected, t0=0.0),  # the default drift: one filter
    }
    out = {
        "n_points": int(cfg["n_points"]),
        "labels": n,
        "inducing": int(cfg["inducing"]),
        "terms": {k: _updates(sur, labels, int(cfg["updates"])) for k, sur in terms.items()},
    }
    if cfg.get("stacked"):
        out["stacked"] = _stacked(prior, cfg["stacked"])
    return out


def _stacked(prior, cfg: dict[str, Any]) -> dict[str, Any]:
    """The tracked step (and with a wind state, and a bank of inducing-point terms where
    ``bank`` is set) on a correction whose discrepancies are inducing-point GPs, its six ``δ``
    read through one stack (``online_step(stack=True)``), one by one, and stacked with the
    state donated (``donate=True``), the forms interleaved in blocks of ``block`` labels
    (:func:`_interleaved`) in each of ``rounds`` rounds: each form's per-round median of its
    blocks' medians and, per round, the median of the ratios paired by block (one by one over
    stacked, stacked over donated)."""
    from gpg import flight

    n = int(cfg["labels"])
    labels = _synthetic_labels(prior, n, 1)
    corrected = flight.correct(prior, labels, basis="physical", exact_labels=n - 1,
                               inducing=int(cfg["inducing"]), subset_size=min(n, 400))  # fmt: skip
    drift = flight.default_drift(corrected)
    models = {"tracked": flight.track(corrected, drift, t0=0.0),
              "wind_state": flight.track(corrected, flight.gusts(drift), t0=0.0)}  # fmt: skip
    out: dict[str, Any] = {"labels": n, "inducing": int(cfg["inducing"])}
    bank = cfg.get("bank")
    if bank:  # scored under the offline band at each label: δ's variance read at every step
        members = [(float(tau), None) for tau in bank["taus"]]
        models["bank"] = flight.adapt_bank(corrected, members, ahead=int(bank["ahead"]),
                                           inducing=int(bank["inducing"]), t0=0.0)  # fmt: skip
        out["bank"] = {k: bank[k] for k in ("taus", "inducing", "ahead")}
    forms = {"stacked": {"stack": True}, "one_by_one": {"stack": False},
             "donated": {"stack": True, "donate": True}}  # fmt: skip
    for name, sur in models.items():
        med: dict[str, list[float]] = {form: [] for form in forms}
        ratio, donated = [], []
        for _ in range(int(cfg["rounds"])):
            sec = _interleaved(sur, labels, int(cfg["updates"]), forms, int(cfg["block"]))
            for form in forms:
                med[form].append(float(np.median(sec[form])))
            ratio.append(float(np.median(sec["one_by_one"] / sec["stacked"])))
            donated.append(float(np.median(sec["stacked"] / sec["donated"])))
        out[name] = {**out.get(name, {}), **{f"{k}_median_s": v for k, v in med.items()},
                     "ratio": ratio, "ratio_median": float(np.median(ratio)),
                     "donated_ratio": donated,
                     "donated_ratio_median": float(np.median(donated))}  # fmt: skip
    if "bank" in models:  # what of the bank's step is the offline band it scores under
        band = _band_alone(models["bank"], labels, int(cfg["updates"]))
        step = float(np.median(out["bank"]["stacked_median_s"]))
        band["share_of_stacked"] = band["update_s"]["median_s"] / step
        out["bank"]["offline_band"] = band
    return out


def _band_alone(sur, labels, updates: int) -> dict[str, Any]:
    """The offline model's mean and band at each label (``Corrected.offline_moments`` on the
    view :func:`gpg.flight.online_step` reads for a bank: δ folded and stacked), compiled once
    and called once a label from Python over the step's labels (each label's normalised input
    formed beforehand, untimed; the first 10 calls left out), and the bytes of the view's
    arrays (a call reads some of them: one bin of the prior's factor, δ's triangles)."""
    from gpg.flight import correction as fc

    view = fc.offline_model(sur.model).variance_views().stacked()
    rows = jax.jit(lambda s, *a: fc.gp_rows(s, *a)[0])
    cols = labels.columns()
    xs = [rows(sur, *(c[k % len(labels)] for c in cols[1:])) for k in range(updates + 10)]
    band = jax.jit(lambda m, x: m.offline_moments(x))
    seconds = []
    for x in xs:
        t0 = time.perf_counter()
        jax.block_until_ready(band(view, x))
        seconds.append(time.perf_counter() - t0)
    return {"update_s": stats(np.asarray(seconds[10:])),
            "view_bytes": int(sum(a.nbytes for a in jax.tree.leaves(view)))}  # fmt: skip


def _interleaved(sur, labels, updates: int, forms: dict[str, dict], block: int) -> dict:
    """Each form of the compiled step (``forms``: its ``online_step`` options) over the same
    ``updates`` labels, each with its own state, in blocks: each form takes ``block`` labels
    in a row, then the next form the same ones (the forms' order reversed every block).
    Returns each form's median seconds a call per block (its first calls in a block left out:
    they find the cache the form before left), paired by block, so that a machine whose
    speed drifts within a run moves every form alike, and each form runs from its own warm
    cache as a loop of one form does."""
    from gpg import flight

    if not 0 < block <= updates:
        raise ValueError(f"flight.update.stacked: block ({block}) must be from 1 to updates "
                         f"({updates})")  # fmt: skip
    n, skip = len(labels), min(5, block // 4)
    steps = {form: flight.online_step(sur, **kw) for form, kw in forms.items()}
    states = {form: flight.online_state(sur) for form in forms}
    cols = labels.columns()
    out: dict[str, list[float]] = {form: [] for form in forms}
    for b in range(-1, updates // block):  # block -1 compiles, not timed
        for form in list(forms)[:: 1 if b % 2 else -1]:
            seconds = []
            for k in range(max(b, 0) * block, (max(b, 0) + 1) * block):
                args = [c[k % n] for c in cols]
                args[0] = args[0] + (k // n) * n / 10.0
                t0 = time.perf_counter()
                states[form] = steps[form](states[form], *args)
                jax.block_until_ready(states[form])
                seconds.append(time.perf_counter() - t0)
            if b >= 0:
                out[form].append(float(np.median(seconds[skip:])))
    return {form: np.asarray(v) for form, v in out.items()}


def _updates(sur, labels, updates: int) -> dict[str, Any]:
    """``updates`` calls of the compiled step, once a label from Python (the labels replayed,
    time moving on), and the state's bytes before and after."""
    from gpg import flight

    n = len(labels)
    step = flight.online_step(sur)
    state = flight.online_state(sur)
    cols = labels.columns()
    before = sum(x.nbytes for x in jax.tree.leaves(state))
    seconds = []
    for k in range(updates + 10):
        i = k % n
        args = [c[i] for c in cols]
        args[0] = args[0] + (k // n) * n / 10.0
        t0 = time.perf_counter()
        state = step(state, *args)
        jax.block_until_ready(state)
        seconds.append(time.perf_counter() - t0)
    after = sum(x.nbytes for x in jax.tree.leaves(state))
    return {
        "update_s": stats(np.asarray(seconds[10:])),  # the first calls compile
        "online_bytes": {"before": int(before), "after": int(after)},
    }


def flight_table(res: dict[str, Any]) -> str:
    """The suite's figures, of the parts it ran."""
    rows = []
    if "log" in res:
        lg = res["log"]
        rows += [
            {"what": f"read_ulog + label, {lg['flown_s']:.1f} s flown at {lg['rate_hz']:.0f} Hz",
             "median": lg["read_and_label_s"]["median_s"] * 1e3,
             "note": f"{lg['times_faster_than_flown']:.0f}x faster than flown"},
            {"what": "of which the signals' consistency checks",
             "median": lg["consistency_s"]["median_s"] * 1e3,
             "note": f"{100 * lg['consistency_share']:.2f} % of read + label"},
            {"what": "of which the file's integrity walk (a message cut short?)",
             "median": lg["integrity_s"]["median_s"] * 1e3,
             "note": f"{100 * lg['integrity_share']:.2f} % of read + label"},
        ]  # fmt: skip
    if "update" in res:
        up = res["update"]
        for name, what in (("inducing", f"{up['inducing']} inducing"),
                           ("tracked", "tracked coefficients")):  # fmt: skip
            u = up["terms"][name]
            rows.append({"what": f"online update, prior of {up['n_points']} points, "
                                 f"{up['labels']} labels, {what}",
                         "median": u["update_s"]["median_s"] * 1e3,
                         "note": f"state {u['online_bytes']['before']} -> "
                                 f"{u['online_bytes']['after']} bytes"})  # fmt: skip
    if "stacked" in res.get("update", {}):
        st = res["update"]["stacked"]
        for name in ("tracked", "wind_state", "bank"):
            if "ratio" not in st.get(name, {}):
                continue
            r = st[name]
            rows.append({"what": f"online update, {name}, {st['labels']} labels, "
                                 f"{st['inducing']}-inducing δ stacked",
                         "median": float(np.median(r["stacked_median_s"])) * 1e3,
                         "note": f"one by one {np.median(r['one_by_one_median_s']) * 1e3:.3f} "
                                 f"ms; ratio {r['ratio_median']:.2f} (rounds "
                                 f"{', '.join(f'{v:.2f}' for v in r['ratio'])})"})  # fmt: skip
            if "offline_band" in r:
                b = r["offline_band"]
                note = (f"{100 * b['share_of_stacked']:.0f} % of the stacked step; the view's "
                        f"arrays {b['view_bytes'] / 1e6:.1f} MB")  # fmt: skip
                rows.append({"what": f"online update, {name}: the offline band at the label",
                             "median": b["update_s"]["median_s"] * 1e3, "note": note})  # fmt: skip
            if "donated_median_s" in r:
                rounds = ", ".join(f"{v:.2f}" for v in r["donated_ratio"])
                rows.append({"what": f"online update, {name}, stacked, donate=True",
                             "median": float(np.median(r["donated_median_s"])) * 1e3,
                             "note": f"stacked over donated {r['donated_ratio_median']:.2f} "
                                     f"(rounds {rounds})"})  # fmt: skip
    if "parallel" in res:
        pa = res["parallel"]
        for w, st in pa["wall_s"].items():
            rows.append({"what": f"label_logs, {pa['logs']} CSV logs of {pa['seconds_each']:g} s, "
                                 f"workers={w}",
                         "median": st["median_s"] * 1e3,
                         "note": (f"{pa['speedup']:.2f}x on {pa['workers']}; labels "
                                  f"{'equal' if pa['same_labels'] else 'DIFFER'} bit for bit"
                                  if w != "1" else "in this process")})  # fmt: skip
    for r in res.get("every_label", {}).get("runs", []):
        rows.append({"what": f"correct on {r['hours']:g} h of labels ({r['labels']}), "
                             f"{r['inducing']} inducing, {res['every_label']['device']}",
                     "median": r["seconds"] * 1e3,
                     "note": f"peak RSS +{r['peak_rss_mib']:.0f} MiB, device "
                             f"{r['device_peak_mib']:.0f} MiB; one run"})  # fmt: skip
    if "c" in res:
        c = res["c"]
        for dtype in ("double", "float"):
            keys = ("mean", "predict", "online_update", "online_predict", "tracked_update",
                    "tracked_predict", "wind_update", "wind_predict", "bank_update",
                    "bank_predict")  # fmt: skip
            for key in (k for k in keys if k in c[dtype]):
                t = c[dtype][key]
                what = f"C {dtype}: corrected model's {key}, {c['inducing']} inducing"
                note = f"p05 {t['p05_us']:.1f} us, p95 {t['p95_us']:.1f} us"
                rows.append({"what": f"{what} ({c['online']} online)",
                             "median": t["median_us"] * 1e-3, "note": note})  # fmt: skip
    return table(rows, [("what", "flight", ""), ("median", "ms (median)", ".3f"), ("note", "", "")])


__all__ = ["bench_flight", "flight_table"]
