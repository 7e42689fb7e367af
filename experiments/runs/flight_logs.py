"""The sim-to-real benchmark with known truth (``python -m experiments.flight_logs``).

The prior is the surrogate of the nominal vehicle (``model``, fitted on the configured data, or
``surrogate_checkpoint``). The "real" vehicle differs from it (``real.changes`` to the vehicle
file: airfoil, drag areas, mass, motor lag; ``real.wake_gain`` and ``real.interference`` of the
physics) and is flown by the closed-loop simulator through the sensors of ``sensors``
(:mod:`gpg.flight.synthetic`): training flights, held-out test flights on other trajectories and
winds, each written as a CSV log and read back (:func:`gpg.flight.read_csv`), then labelled
(:func:`gpg.flight.label`).

Measured, against the truth (the wrench the simulator applied, at the test flights' label
instants): the residual-force RMSE (the norm's RMS, N) and residual-torque RMSE of the
simulator-only prior, the prior corrected by ``seconds`` of flight (:func:`gpg.flight.correct`)
and a values-only GP on the same seconds without the prior (``use_prior=False``; and the same
with ``κ``, the fitted coefficient of ``M``'s own loads, ``values_only_m``), the
corrected model's 95 % coverage (per component), for each number of seconds (the curve);
then adaptation: a flight into a wind none of the training flights had, the model corrected
on calm flights updated label by label by the inducing-point term (:func:`gpg.flight.adapt`)
and by its tracked coefficients (:func:`gpg.flight.track`, the drift fitted on ``track.
fit_flights`` training flights), each label predicted before it is used (at the labels'
states), against an offline correction fitted on another flight in that wind; the same
prequential scores on the test flights; each update's cost and the online state's size over a
10-minute stream. ``results.json`` holds everything with the
resolved config; ``figures/`` the curve and a flight's force against the prediction with its
95 % band.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm.auto import tqdm

from experiments.runs.common import flight_setup
from experiments.runs.config import check_options
from experiments.runs.output import report, table
from experiments.runs.timing import machine
from gpg import checkpoint
from gpg.flight import correction as fc
from gpg.flight.labels import Labels, estimate_delay, label
from gpg.flight.log import FlightLog, read_csv, write_csv
from gpg.flight.synthetic import Flight, Sensors, fly, perturbed, random_plan
from gpg.flight.tracking import default_drift, fit_drift, gusts, prequential, track
from gpg.linalg import memory
from gpg.quadrotor.bemt import BEMTConfig
from gpg.quadrotor.control import GeometricController
from gpg.quadrotor.dynamics import Wind
from gpg.runtime import float64, write_json

OPTIONS = {
    "cache_dir": "path",
    "surrogate_checkpoint": "path?",
    "default_seconds": "count",
    "figures": "bool",
    "progress": "bool",
    "keep_logs": "bool",
}


@dataclasses.dataclass
class Truth:
    """A test flight at its label instants: the states and the true loads."""

    rpm: np.ndarray
    euler: np.ndarray
    v_air: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    t: np.ndarray


@dataclasses.dataclass
class _Bench:
    """What every flight of a run shares: the real vehicle and its physics, the controller,
    the sensors, the prior (its ``M`` is the labels' reference), the options, the draws."""

    cfg: dict[str, Any]
    prior: Any
    real: Any
    physics: BEMTConfig
    sensors: Sensors
    ctrl: GeometricController
    rng: np.random.Generator
    logs: Path

    @classmethod
    def create(cls, cfg: dict[str, Any], out: Path) -> _Bench:
        nominal, prior = flight_setup(cfg, OPTIONS)
        r = cfg["real"]
        sensors = {k: (tuple(v) if isinstance(v, list) else v) for k, v in cfg["sensors"].items()}
        return cls(
            cfg=cfg,
            prior=prior,
            real=perturbed(cfg["vehicle"], r.get("changes") or {}),
            physics=BEMTConfig(
                wake_gain=float(r["wake_gain"]), interference=bool(r["interference"])
            ),
            sensors=Sensors(**sensors),
            ctrl=GeometricController.create(nominal, prior.simple),
            rng=np.random.default_rng(int(cfg["flights"]["seed"])),
            logs=out / "logs",
        )

    def flight(self, name: str, duration: float, wind) -> Flight:
        """A flight written as a CSV log and read back (what a user's CSV would give)."""
        seed = int(self.rng.integers(2**31))
        fl = self.cfg["flights"]
        plan = random_plan(np.random.default_rng(seed), duration, box=float(fl["box"]),
                           step=tuple(fl["step"]), leg_time=tuple(fl["leg_time"]))  # fmt: skip
        f = fly(self.real, self.ctrl, plan, Wind.constant(wind), duration, sensors=self.sensors,
                seed=seed, bemt_config=self.physics, name=name)  # fmt: skip
        path = write_csv(f.log, self.logs / f"{name}.csv")
        return dataclasses.replace(f, log=read_csv(path))

    def calm_wind(self) -> list[float]:
        """A horizontal wind up to ``flights.wind_max`` from any direction."""
        a, speed = self.rng.uniform(0, 2 * np.pi), self.rng.uniform()
        w = float(self.cfg["flights"]["wind_max"]) * speed
        return [w * np.cos(a), w * np.sin(a), 0.0]

    def labelled(self, f: Flight | FlightLog, stream: bool = False) -> Labels:
        """The flight's (or its log's) labels; ``stream``: what an online filter reads instead
        (every sample at ``adapt.stream``'s rate, a saturated rotor's too), holding the
        labels' instants."""
        opts = self.cfg["label"]
        rate, more = float(opts["rate"]), {}
        if stream:
            st = self.cfg["adapt"]["stream"]
            rate, more = float(st["rate"]), {"saturation": float(st["saturation"])}
        log = f if isinstance(f, FlightLog) else f.log
        return label(log, self.real, reference=self.prior.simple, rate=rate,
                     source=opts["source"], **more)  # fmt: skip

    def correct(self, labels, **kw):
        c = self.cfg["correct"]
        opts = {"max_labels": None if c["max_labels"] is None else int(c["max_labels"]),
                "exact_labels": int(c["exact_labels"]), "inducing": int(c["inducing"]),
                "subset_size": int(c["subset_size"]), "hyperparameters": c["hyperparameters"],
                "basis_prior": basis_prior(c["basis_prior"]),
                "calibrate": bool(c["calibrate"]),
                "coefficient_spread": bool(c["coefficient_spread"])}  # fmt: skip
        return fc.correct(self.prior, labels, **{**opts, **kw})

    @property
    def progress(self) -> bool:
        return bool(self.cfg.get("progress", True))


def basis_prior(value) -> float | str:
    """``correct.basis_prior`` as :func:`gpg.flight.correct` takes it."""
    return value if value in ("auto", "held_out") else float(value)


@float64
def run(cfg: dict[str, Any], out: Path) -> dict[str, Any]:
    """The benchmark (module docstring); returns what ``results.json`` holds."""
    check_options(cfg, OPTIONS)
    scenario = cfg.get("scenario", "nominal")
    if scenario not in ("nominal", "hard"):
        raise ValueError(f"scenario must be 'nominal' or 'hard', got {scenario!r}")
    if scenario == "hard":
        from experiments.runs import flight_hard

        flight_hard.training_plan(cfg["hard"])  # checked before any work
        _, prior = flight_setup(cfg, OPTIONS)
        return flight_hard.run(cfg, out, prior)
    fl = cfg["flights"]
    seconds = sorted(float(s) for s in cfg["seconds"])
    base_s = float(cfg["default_seconds"])
    if base_s not in seconds:
        raise ValueError(f"default_seconds {cfg['default_seconds']} must be one of seconds")
    if seconds[-1] > fl["train_s"]:
        raise ValueError(f"seconds go to {seconds[-1]} s but flights.train_s is {fl['train_s']}")
    t_start = time.perf_counter()
    bench = _Bench.create(cfg, out)
    train_labels, tests, label_s, train_logs = _fly_all(bench)
    # the rotor speeds' lag from the training logs at once (gpg.flight.estimate_delay): a
    # telemetry's lag is every log's; each label above estimated its flight's alone
    pooled = {f"{k}_flights": estimate_delay(train_logs[:k], bench.real,
                                             reference=bench.prior.simple)
              for k in sorted({min(10, len(train_logs)), len(train_logs)})}  # fmt: skip
    # what the filters reading every sample of a flight are fitted on (track.fit_stream)
    n_fit = int(cfg["track"]["fit_flights"])
    train_streams = None
    if cfg["track"].get("fit_stream") and min(n_fit, len(train_logs)) >= 2:
        train_streams = [bench.labelled(log, stream=True) for log in train_logs[:n_fit]]
    del train_logs
    curve, corrected = _curve(bench, train_labels, tests, seconds, base_s)
    checkpoint.save(out / "corrected", corrected, overwrite=True)
    default = next(r for r in curve if r["seconds"] == base_s)
    adapt = _adaptation(bench, corrected, _first(train_labels, base_s), train_labels, tests,
                        train_streams)  # fmt: skip
    targets = {
        "corrected_vs_sim_only": default["corrected_force_rmse"] / default["sim_only_force_rmse"],
        "corrected_vs_values_only": default["corrected_force_rmse"]
        / default["values_only_force_rmse"],
        "corrected_vs_values_only_m": default["corrected_force_rmse"]
        / default["values_only_m_force_rmse"],
        "coverage95": default["corrected_coverage95"],
        "adaptation_vs_offline": adapt["models"]["inducing"]["ratio"],
        "tracked_vs_offline": adapt["models"]["tracked"]["ratio"],
        "label_speed": float(sum(d for _, d in label_s) / sum(s for s, _ in label_s)),
    }
    train_all = Labels.concatenate(train_labels)
    results = {
        "config": cfg,
        "machine": machine(),
        "labels": {
            "train": len(train_all),
            "dropped": train_all.dropped,
            "delay_s": [lb.delay for lb in train_labels],
            "delay_pooled_s": pooled,
            "delay_true_s": float(bench.sensors.rpm_delay),
        },
        "curve": curve,
        "default": default,
        "adaptation": adapt,
        "targets": targets,
        "seconds_total": time.perf_counter() - t_start,
    }
    write_json(out / "results.json", results)
    report(_report(curve, default, adapt, targets))
    if cfg.get("figures", True):
        _figures(out / "figures", curve, corrected, bench.prior, tests[0])
    if not cfg.get("keep_logs", True):
        for p in bench.logs.glob("*.csv"):
            p.unlink()
    return results


def _fly_all(bench: _Bench):
    """The training flights' labels, the test flights with their truth, for each training
    flight the seconds its labelling took and the seconds it lasted, and the training logs."""
    fl = bench.cfg["flights"]
    n_train = int(np.ceil(fl["train_s"] / fl["flight_s"]))
    bar = tqdm(total=n_train + int(fl["test"]), desc="flying", disable=not bench.progress)
    train_labels, label_s, logs = [], [], []
    for i in range(n_train):
        f = bench.flight(f"train{i:02d}", float(fl["flight_s"]), bench.calm_wind())
        logs.append(f.log)
        t0 = time.perf_counter()
        train_labels.append(bench.labelled(f))
        label_s.append((time.perf_counter() - t0, f.log.duration))
        bar.update()
    tests = []
    for i in range(int(fl["test"])):
        f = bench.flight(f"test{i:02d}", float(fl["test_s"]), bench.calm_wind())
        tests.append((f, _truth(f, bench.labelled(f))))
        bar.update()
    bar.close()
    return train_labels, tests, label_s, logs


def _curve(bench: _Bench, train_labels, tests, seconds, base_s):
    """The error against seconds of flight for the three models; the corrected model at
    ``base_s``."""
    curve, corrected = [], None
    unscaled = bench.cfg["correct"].get("compare_unscaled", True)
    for s in tqdm(seconds, desc="corrections", disable=not bench.progress):
        lab = _first(train_labels, s)
        row: dict[str, Any] = {"seconds": s, "labels": len(lab)}
        scale = bool(bench.cfg["correct"]["scale"])
        with memory.PeakRSS() as mem:
            t0 = time.perf_counter()
            main = bench.correct(lab, scale=scale)
            row["corrected_fit_s"] = time.perf_counter() - t0
        row["corrected_peak_mib"] = mem.peak_delta / 2**20
        row["corrected_inducing"] = main.config["flight_correction"]["inducing"]
        models = {
            "corrected": main,
            "values_only": bench.correct(lab, use_prior=False, simple_term=False),
            "values_only_m": bench.correct(lab, use_prior=False),
        }
        exact_at = bench.cfg["correct"].get("compare_exact_at")
        if exact_at is not None and s == float(exact_at):
            # the exact GP on every label, where it still fits: the inducing inputs' price
            t0 = time.perf_counter()
            models["corrected_exact"] = bench.correct(lab, scale=scale, exact_labels=len(lab))
            row["corrected_exact_fit_s"] = time.perf_counter() - t0
        thinned = bench.cfg["correct"].get("compare_thinned")
        if thinned and len(lab) > int(thinned):
            # today's model beside it: the labels thinned evenly to an exact GP's size
            models["corrected_thinned"] = bench.correct(lab, scale=scale, max_labels=int(thinned))
        if unscaled and s == base_s:
            models["corrected_unscaled"] = bench.correct(lab, scale=False)
            # the physical basis where the flights went (the hard scenario: where they did not)
            models["corrected_physical"] = bench.correct(lab, basis="physical")
        for name, sur in (("sim_only", bench.prior), *models.items()):
            row.update({f"{name}_{k}": v for k, v in _scores(sur, tests).items()})
        curve.append(row)
        if s == base_s:
            corrected = models["corrected"]
        # Each model of each size compiles its own programs; kept, they exhausted the
        # process's memory maps over a whole curve (LLVM: cannot allocate memory).
        jax.clear_caches()
    return curve, corrected


def _first(parts: list[Labels], seconds: float) -> Labels:
    """The first ``seconds`` of labelled flight over the training flights in order."""
    out, left = [], seconds
    for p in parts:
        if left <= 0:
            break
        take = p.first(left)
        out.append(take)
        left -= take.seconds
    return Labels.concatenate(out)


def _truth(f: Flight, lab: Labels) -> Truth:
    i = np.searchsorted(f.log.t, lab.t)
    return Truth(f.rpm[i], f.euler[i], f.v_air[i], f.force[i], f.torque[i], lab.t)


def _scores(sur, tests) -> dict[str, float]:
    e_f, e_t, inside = [], [], []
    for _, tr in tests:
        p = sur.predict_batch(tr.rpm, tr.euler, tr.v_air)
        ef = np.asarray(p.force) - tr.force
        e_f.append(ef)
        e_t.append(np.asarray(p.torque) - tr.torque)
        sd = np.sqrt(np.asarray(p.variance)[:, :3])
        inside.append(np.abs(ef) <= 1.959964 * sd)
    ef, et = np.concatenate(e_f), np.concatenate(e_t)
    return {
        "force_rmse": float(np.sqrt(np.mean(np.sum(ef**2, 1)))),
        "torque_rmse": float(np.sqrt(np.mean(np.sum(et**2, 1)))),
        "coverage95": float(np.mean(np.concatenate(inside))),
    }


def _adaptation(bench: _Bench, corrected, base_labels: Labels, train_labels, tests,
                train_streams=None):  # fmt: skip
    """Into a wind no training flight had: the corrected model adapted label by label (each
    label predicted before it is used, :func:`gpg.flight.prequential`) by today's inducing-point
    term and by the tracked coefficients (their drift fitted on training flights; and with a
    wind state beside them), against an
    offline correction fitted on another flight in that wind; the same on the held-out test
    flights; each also reading every sample of the log (``stream_*``: ``adapt.stream``),
    scored at the same labels, and with ``train_streams`` (every sample of the training
    flights the drift is fitted on) the tracked models with a drift fitted on those
    (``*_fit_stream``); then the updates' cost over a long stream."""
    a, g = bench.cfg["adapt"], bench.cfg["track"]["gusts"]
    wind = [float(v) for v in a["wind"]]
    f_off = bench.flight("windy_offline", float(a["offline_s"]), wind)
    f_ad = bench.flight("windy_adapt", float(a["flight_s"]), wind)
    l_off, l_ad = bench.labelled(f_off), bench.labelled(f_ad)
    offline = bench.correct([base_labels, l_off])
    parts = train_labels[: int(bench.cfg["track"]["fit_flights"])]
    # one training flight (a short run) has no held-out flight to fit the drift on
    drift = (
        fit_drift(corrected, parts, max_labels=int(bench.cfg["track"]["max_labels"]))
        if len(parts) >= 2
        else default_drift(corrected)
    )
    # the labels' flight-long offset (a sensor's bias): in the band, which no label tells
    offset = label_offset(bench.cfg["track"]["label_offset"], bench.sensors, bench.real.mass,
                          base_labels.source)  # fmt: skip
    drift = dataclasses.replace(drift, label_offset=offset)
    stream_drift = None
    if train_streams is not None:
        t1 = time.perf_counter()
        stream_drift = fit_drift(corrected, parts, read=train_streams,
                                 max_labels=int(bench.cfg["track"]["max_labels"]))  # fmt: skip
        stream_drift = dataclasses.replace(stream_drift, label_offset=offset)
        stream_fit_s = time.perf_counter() - t1

    def prepared(t0: float, stream: bool = False) -> dict[str, Any]:
        models = {
            "none": corrected,
            "inducing": fc.adapt(
                corrected, inducing=int(a["inducing"]), tau=float(a["tau"]), t0=t0
            ),  # fmt: skip
            "tracked": track(corrected, drift, t0=t0),
            # the same drift with a wind state (gpg.flight.gusts): a new wind as a state
            "tracked_gusts": track(corrected, gusts(drift, g["sd"], float(g["tau"])), t0=t0),
        }
        if stream and stream_drift is not None:  # fitted on what these filters read
            models["tracked_fit_stream"] = track(corrected, stream_drift, t0=t0)
            models["tracked_gusts_fit_stream"] = track(
                corrected, gusts(stream_drift, g["sd"], float(g["tau"])), t0=t0
            )
        return models

    truth = _truth(f_ad, l_ad)
    tt = l_ad.t - l_ad.t[0]
    after = tt >= float(a["check_s"])

    def rmse(sur):
        # at the labels' states, as the prequential predictions are (what a user's log gives)
        p = sur.predict_batch(l_ad.rpm[after], l_ad.euler[after], l_ad.v_air[after])
        return float(np.sqrt(np.mean(np.sum((np.asarray(p.force) - truth.force[after]) ** 2, 1))))

    off_rmse = rmse(offline)
    out: dict[str, Any] = {"wind": wind, "check_s": float(a["check_s"]), "offline_rmse": off_rmse,
                           "corrected_rmse": rmse(corrected), "sim_only_rmse": rmse(bench.prior),
                           "drift": dataclasses.asdict(drift), "models": {},
                           "stream_drift": None if stream_drift is None else
                           {**dataclasses.asdict(stream_drift), "fit_s": stream_fit_s},
                           "stream_models": {}}  # fmt: skip
    for name, sur in prepared(float(l_ad.t[0])).items():
        sc, e = prequential_scores(sur, l_ad, truth.force)
        err = np.sum(e**2, 1)
        windows = [
            {"from_s": float(lo), "rmse": float(np.sqrt(err[(tt >= lo) & (tt < lo + 5)].mean()))}
            for lo in np.arange(0.0, tt[-1], 5.0)
            if ((tt >= lo) & (tt < lo + 5)).any()
        ]
        adapted = float(np.sqrt(np.mean(err[after])))
        out["models"][name] = {**sc, "rmse_after": adapted, "ratio": adapted / off_rmse,
                               "windows": windows}  # fmt: skip
    # The same models reading every sample, scored at the same labels (after check_s too).
    s_ad = bench.labelled(f_ad, stream=True)
    at = np.isin(s_ad.t, l_ad.t)
    out["stream_labels"], out["stream_scored"] = len(s_ad), int(at.sum())
    for name, sur in prepared(float(s_ad.t[0]), stream=True).items():
        sc, e = prequential_scores(sur, s_ad, _truth(f_ad, s_ad).force, at=at)
        adapted = float(np.sqrt(np.mean(np.sum(e**2, 1)[after])))
        out["stream_models"][name] = {**sc, "rmse_after": adapted, "ratio": adapted / off_rmse}
    rows = []
    for f, _ in tests:
        lab, stream = bench.labelled(f), bench.labelled(f, stream=True)
        row: dict[str, Any] = {"test": f.log.name, "labels": len(lab),
                               "noise_floor": float(np.mean(np.sum(lab.force_var, 1))),
                               "stream_labels": len(stream)}  # fmt: skip
        for name, sur in prepared(float(lab.t[0])).items():
            sc, _ = prequential_scores(sur, lab, _truth(f, lab).force)
            row.update({f"{name}_{k}": v for k, v in sc.items()})
        at = np.isin(stream.t, lab.t)
        row["stream_scored"] = int(at.sum())
        for name, sur in prepared(float(stream.t[0]), stream=True).items():
            sc, _ = prequential_scores(sur, stream, _truth(f, stream).force, at=at)
            row.update({f"stream_{name}_{k}": v for k, v in sc.items()})
        rows.append(row)
    out["tests"] = rows
    seconds = float(a["stream_s"])
    models = prepared(float(l_ad.t[0]))
    out["cost"] = {m: update_cost(models[m], l_ad, seconds, bench.progress)
                   for m in ("inducing", "tracked", "tracked_gusts")}  # fmt: skip
    return out


def label_offset(value, sensors: Sensors, mass: float, source: str) -> tuple[float, float]:
    """The labels' offset a tracked filter's band states (:attr:`gpg.flight.Drift.label_offset`,
    N and N·m): ``value`` as given, or where it is ``"sensors"`` the accelerometer's bias (its
    σ, as a datasheet states it) times the vehicle's mass for labels from the IMU, nothing for
    labels from the velocity (the logs' attitude has no bias). The torque's is left out: a
    constant gyro bias does not enter ``ω̇``, only the small ``ω × J ω``."""
    if value == "sensors":
        return (float(sensors.accel_bias) * float(mass) if source == "imu" else 0.0, 0.0)
    force, torque = (float(v) for v in value)
    return force, torque


def prequential_scores(sur, lab: Labels, truth_force, extra_var=None, at=None):
    """The one-step-ahead force predictions of ``sur`` along a flight (:func:`gpg.flight.
    prequential`) scored: MSE against the truth and against the labels (N², the error vector's
    squared norm), the 95 % band's coverage of the truth (``extra_var``, (N, 3), added to the
    band: a wind known only as its RMS), both per component too; the labels' mean log
    predictive density (nats per label, the force's three components, the band plus the
    labels' own noise: the prequential score the labels alone can give, Dawid's); and each
    scored label's error vector. Every label is read; ``at`` (a boolean mask) scores only
    those rows."""
    pre = prequential(sur, lab)
    at = np.ones(len(lab), bool) if at is None else np.asarray(at, bool)
    e = (pre.force - truth_force)[at]
    var = (pre.variance[:, :3] + (0.0 if extra_var is None else extra_var))[at]
    inside = np.abs(e) <= 1.959964 * np.sqrt(var)
    s2 = var + np.asarray(lab.force_var)[at]
    e_lab = (pre.force - lab.force)[at]
    return {
        "mse": float(np.mean(np.sum(e**2, 1))),
        "mse_components": np.mean(e**2, 0).tolist(),
        "mse_labels": float(np.mean(np.sum(e_lab**2, 1))),
        "coverage95": float(np.mean(inside)),
        "coverage95_components": np.mean(inside, 0).tolist(),
        "lpd_labels": float(np.mean(np.sum(-0.5 * (np.log(2 * np.pi * s2) + e_lab**2 / s2), 1))),
    }, e


def update_cost(adapted, lab: Labels, seconds: float, progress: bool = False) -> dict[str, Any]:
    """Updates once a step from Python (:func:`gpg.flight.online_step`) over ``seconds`` of
    labels (the flight's replayed, time moving on): their cost in ms (median, 10th and 90th
    percentiles, the first ten calls left out: they compile), and the online state's bytes
    before and after. The loop keeps only the newest state, as a flight's does, so each new
    state is written over the last (``donate=True``)."""
    rate = 1.0 / float(np.median(np.diff(lab.t)))
    n = int(round(seconds * rate))
    step = fc.online_step(adapted, donate=True)
    cols = lab.columns()
    state = fc.online_state(adapted)
    nbytes0 = sum(x.nbytes for x in jax.tree.leaves(state))
    period = float(lab.t[-1] - lab.t[0]) + 1.0 / rate
    per = []
    for k in tqdm(range(n), desc="stream", disable=not progress):
        i = k % len(lab)
        args = [c[i] for c in cols]
        args[0] = args[0] + (k // len(lab)) * period
        t0 = time.perf_counter()
        state = step(state, *args)
        jax.block_until_ready(state)
        per.append(time.perf_counter() - t0)
    ms = np.asarray(per[10:]) * 1e3
    return {
        "median_ms": float(np.median(ms)),
        "p10_ms": float(np.percentile(ms, 10)),
        "p90_ms": float(np.percentile(ms, 90)),
        "n": int(ms.size),
        "bytes_start": int(nbytes0),
        "bytes_end": int(sum(x.nbytes for x in jax.tree.leaves(state))),
    }


def _report(curve, default, adapt, targets) -> str:
    cols = [("seconds", "flight s", ".0f"), ("labels", "labels", "d")]
    for name, head in (
        ("sim_only", "sim only"),
        ("corrected", "corrected"),
        ("corrected_thinned", "thinned"),
        ("corrected_exact", "exact, every label"),
        ("values_only", "values only"),
        ("values_only_m", "values only + κM"),
    ):
        cols.append((f"{name}_force_rmse", f"{head} F (N)", ".3f"))
    cols += [
        ("corrected_fit_s", "fit s", ".1f"),
        ("corrected_peak_mib", "peak MiB", ".0f"),
        ("corrected_torque_rmse", "corrected τ (N·m)", ".4f"),
        ("sim_only_torque_rmse", "sim only τ (N·m)", ".4f"),
        ("corrected_coverage95", "coverage 95 %", ".3f"),
    ]
    lines = ["residual-force RMSE on held-out flights against the truth:", table(curve, cols)]
    d = adapt["drift"]
    lines.append(
        f"adaptation into a {adapt['wind']} m/s wind (offline on that wind "
        f"{adapt['offline_rmse']:.3f} N, corrected on calm flights {adapt['corrected_rmse']:.3f}"
        f" N); drift fitted: tau {d['tau']:.3g} s, spread "
        f"{np.round(np.asarray(d['spread']), 3).tolist()}"
    )
    for name, r in adapt["models"].items():
        cost = adapt["cost"].get(name)
        lines.append(
            f"  {name}: after {adapt['check_s']:.0f} s {r['rmse_after']:.3f} N "
            f"(x{r['ratio']:.2f} of offline); prequential MSE {r['mse']:.3g} N², coverage "
            f"{r['coverage95']:.3f}"
            + ("" if cost is None else f"; update {cost['median_ms']:.3f} ms (median of "
               f"{cost['n']}), state {cost['bytes_start']} -> {cost['bytes_end']} bytes")
        )  # fmt: skip
    pcols = [("test", "test", "s")]
    for m in ("none", "inducing", "tracked", "tracked_gusts"):
        pcols += [(f"{m}_mse", f"{m} MSE", ".3g"), (f"{m}_coverage95", f"{m} cov95", ".3f")]
    pcols.append(("noise_floor", "noise", ".3g"))
    lines.append("prequential on the test flights:")
    lines.append(table(adapt["tests"], pcols))
    if adapt.get("stream_models"):
        lines.append(f"the same reading every sample ({adapt['stream_labels']} of the windy "
                     f"flight's, {adapt['stream_scored']} scored):")  # fmt: skip
        for name, r in adapt["stream_models"].items():
            lines.append(f"  {name}: after {adapt['check_s']:.0f} s {r['rmse_after']:.3f} N "
                         f"(x{r['ratio']:.2f} of offline); prequential MSE {r['mse']:.3g} N², "
                         f"coverage {r['coverage95']:.3f}")  # fmt: skip
        scols = [("test", "test", "s"), ("stream_labels", "stream labels", "d")]
        names = ("none", "inducing", "tracked", "tracked_gusts", "tracked_fit_stream",
                 "tracked_gusts_fit_stream")  # fmt: skip
        for m in [m for m in names if f"stream_{m}_mse" in adapt["tests"][0]]:
            scols += [(f"stream_{m}_mse", f"{m} MSE", ".3g"),
                      (f"stream_{m}_coverage95", f"{m} cov95", ".3f")]  # fmt: skip
        scols.append(("noise_floor", "noise", ".3g"))
        lines.append(table(adapt["tests"], scols))
    lines.append("targets: " + ", ".join(f"{k} {v:.3g}" for k, v in targets.items()))
    return "\n".join(lines)


def _figures(where: Path, curve, corrected, prior, test) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    where.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    lines = (
        ("sim_only", "simulator only", "k--"),
        ("values_only", "values-only GP (flights only)", "C1o-"),
        ("values_only_m", "values-only GP with κ M (flights only)", "C2s:"),
        ("corrected", "simulator prior + flight correction", "C0o-"),
        ("corrected_thinned", "the same, labels thinned to an exact GP's size", "C3^:"),
    )
    for name, label_, style in lines:
        pts = [(r["seconds"], r[f"{name}_force_rmse"]) for r in curve
               if f"{name}_force_rmse" in r]  # fmt: skip
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=label_)
    ax.set_xscale("log")
    ax.set_xlabel("seconds of flight data")
    ax.set_ylabel("residual-force RMSE on held-out flights (N)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(where / f"error_vs_seconds.{ext}", dpi=150)
    plt.close(fig)

    f, tr = test
    p = corrected.predict_batch(tr.rpm, tr.euler, tr.v_air)
    p0 = prior.predict_batch(tr.rpm, tr.euler, tr.v_air, mean_only=True)
    simple = prior.simple.values(np.concatenate([tr.rpm, tr.euler], 1))
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    t = tr.t - tr.t[0]
    for j, ax in enumerate(axes):
        m = np.asarray(p.force)[:, j] - np.asarray(simple)[:, j]
        sd = np.sqrt(np.asarray(p.variance)[:, j])
        ax.fill_between(t, m - 1.96 * sd, m + 1.96 * sd, color="C0", alpha=0.25, label="95 %")
        ax.plot(t, tr.force[:, j] - np.asarray(simple)[:, j], "k", lw=1, label="truth")
        ax.plot(
            t,
            np.asarray(p0.force)[:, j] - np.asarray(simple)[:, j],
            "C3--",
            lw=1,
            label="simulator only",
        )
        ax.plot(t, m, "C0", lw=1, label="corrected")
        ax.set_ylabel(f"F{'xyz'[j]} − M (N)")
    axes[0].legend(ncol=4, fontsize=8)
    axes[-1].set_xlabel(f"time along {f.log.name} (s)")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(where / f"force_along_flight.{ext}", dpi=150)
    plt.close(fig)


__all__ = ["run"]
