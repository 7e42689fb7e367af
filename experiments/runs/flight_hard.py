"""The hard scenario of the sim-to-real benchmark (``python -m experiments.flight_logs
scenario=hard``): a vehicle no vehicle file describes, logged as real flights are, tested at
winds no training flight had.

The "real" vehicle (``hard.real``) differs strongly from every vehicle file: several times the
drag areas, a smaller rotor with wider blades (another thrust coefficient), more profile drag,
a stronger wake. The user's vehicle file (``hard.vehicle``) is the nearest built-in vehicle
with the measured mass. The closed-loop simulator flies the real vehicle through
``hard.sensors``: logged at 50 Hz, motor commands only (no rotor speeds), no IMU. Training
flights fly figure-eights and random walks (``hard.train_kinds``) in steady winds along x
(``hard.train_winds``, known as in a wind tunnel); test flights at a faster wind
(``hard.test_wind``) and in a gusting one (``hard.gust``) given to the models as its mean
only. The motor curve is fitted on the calm figure-eight's hover
(:meth:`gpg.flight.MotorCurve.fit_hover`) and the labels come from the velocity
(:func:`gpg.flight.label`, ``source="velocity"``).

Models, each predicting at the test labels' states (the curve's rotor speeds, the log's
attitude and air velocity), scored against the true force at those instants (MSE of the force
vector, N², and the 95 % coverage per component):

* ``prior``: the nominal vehicle's simulator prior alone;
* ``corrected_regression``: the correction before the physical basis
  (``correct(prior, labels, basis="regression")``);
* ``values_only``: the values-only GP on the flights alone (``use_prior=False``,
  ``basis="regression"``: residuals against ``M``);
* ``flights_physical``: the physical basis and the GP on the flights alone (``use_prior=False``);
* ``ridge``: a linear fit on (ground velocity, quaternion, commands), no wind;
* ``identified_prior``: the simulator prior of the identified vehicle
  (:func:`gpg.flight.identify`, :meth:`gpg.flight.Identification.prior`), alone;
* ``identified``: that prior corrected with the physical basis, its physics taken as it is
  (``scale=False``: ``ρ = 1``; the route of the guide);
* ``identified_rho``: the same with ``ρ`` fitted (``scale=True``), as for another vehicle's
  prior;
* ``identified_estimated_wind``: the same, corrected with labels whose wind was estimated
  (:func:`gpg.flight.estimate_wind`) instead of given;
* ``oracle``: the true vehicle's own simulator prior, uncorrected, at the true states;
  ``oracle_mean_air`` the same at the labels' air velocity (the gust's mean wind, as the
  models read it) with the wind's variance in its band: what the true physics errs by with
  the wind given as the models are given it.

Adaptation, prequential on each test flight (each label predicted before it is used): the
identified model adapted by the inducing-point term and by its tracked coefficients
(:func:`prequential_rows`), and today's adaptation as the tracking issue measured it, the
inducing-point term on ``corrected_regression`` (:func:`today_rows`), each reading the labels
and every sample of the log.

Also: the identified parameters against the truth; the identification again from the same
training flights, once with the ESC telemetry's rotor speeds in their logs
(``hard.with_speeds``, written as ``logs/<flight>_esc.csv``) and once with the commands read
through a motor curve measured on a bench (``hard.bench_curve``) in place of the hover's: what
each tells that the commands and a hover cannot; the wind estimates' RMS error per training
flight, and the seconds each stage took.
"""

from __future__ import annotations

import copy
import dataclasses
import time
import warnings
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from experiments.runs.flight_logs import basis_prior
from experiments.runs.output import report, table
from experiments.runs.timing import machine
from gpg import conf
from gpg.data.cache import ensure
from gpg.flight import correction as fc
from gpg.flight.bank import adapt_bank
from gpg.flight.forgetting import fit_bank, fit_forgetting
from gpg.flight.identify import Identification, hover_coefficients, identify, physics_loads
from gpg.flight.labels import Labels, MotorCurve, label
from gpg.flight.log import FlightLog, FlightLogWarning, read_csv, write_csv
from gpg.flight.synthetic import Flight, Sensors, figure_eight, fly, perturbed_config, random_plan
from gpg.flight.tracking import fit_drift, gusts, prequential, score_drift, track
from gpg.flight.wind import estimate_wind, wind_variance, with_wind
from gpg.quadrotor.bemt import BEMTConfig
from gpg.quadrotor.control import GeometricController, WaypointPlan
from gpg.quadrotor.dynamics import Wind
from gpg.quadrotor.vehicle import Vehicle, vehicle_config
from gpg.runtime import float64, write_json
from gpg.surrogate import Surrogate

__all__ = ["run"]


@dataclasses.dataclass
class _Test:
    """A test flight at its label instants: the labels, the truth there, the commands."""

    name: str
    labels: Labels
    force: np.ndarray
    rpm: np.ndarray
    euler: np.ndarray
    v_air: np.ndarray
    quaternion: np.ndarray
    command: np.ndarray
    wind_sd: np.ndarray | None = None


def _flight(
    h,
    real,
    ctrl,
    physics,
    sensors,
    name,
    wind: Wind,
    kind,
    seed,
    logs,
    wind_in_log,
    esc: bool = False,
) -> tuple[Flight, FlightLog | None]:
    """One flight of ``kind`` read back from its CSV log as ``sensors`` record it; with ``esc``
    also the same flight's log with the ESC telemetry's rotor speeds (``<name>_esc.csv``).
    The telemetry's noise is drawn whether or not it is logged: both logs are of one flight."""
    dur = float(h["flight_s"])
    rng = np.random.default_rng(seed)
    if kind == "eight":
        e = h["figure_eight"]
        if e["smooth"]:
            plan = figure_eight(size=tuple(e["size"]), period=float(e["period"]),
                                yaw=float(np.pi), hold_s=float(e["hold_s"]))  # fmt: skip
        else:  # stop and go: minimum-jerk legs between points of the lemniscate
            laps = int(np.ceil(dur / float(e["period"]))) + 1
            s = np.linspace(0.0, 2 * np.pi * laps, 16 * laps + 1)
            a, b = e["size"]
            w = np.column_stack([a * np.sin(s), b * np.sin(s) * np.cos(s), np.full(s.size, -10.0)])
            leg = float(e["period"]) / 16
            plan = WaypointPlan.create(w, start_time=float(e["hold_s"]), leg_time=leg,
                                       yaw=float(np.pi))  # fmt: skip
    else:
        r = h["random_walk"]
        plan = random_plan(rng, dur, box=float(r["box"]), step=tuple(r["step"]),
                           leg_time=tuple(r["leg_time"]))  # fmt: skip
    recorded = dataclasses.replace(sensors, rpm_logged=sensors.rpm_logged or esc)
    f = fly(real, ctrl, plan, wind, dur, sensors=recorded, seed=seed, bemt_config=physics,
            name=name, wind_in_log=wind_in_log)  # fmt: skip
    log = f.log if sensors.rpm_logged else f.log.replace(rpm=None)
    flight = dataclasses.replace(f, log=read_csv(write_csv(log, logs / f"{name}.csv")))
    return flight, (read_csv(write_csv(f.log, logs / f"{name}_esc.csv")) if esc else None)


def training_plan(h: dict[str, Any]) -> list[tuple[float, str]]:
    """The training flights as ``(wind, kind)``: each of ``hard.train_winds`` flown as each of
    ``hard.train_kinds`` in turn (the i-th flight's seed is ``hard.seed + i``).

    Raises:
        ValueError: if ``hard.train_kinds`` is empty or names a kind other than ``eight`` and
            ``walk``, or if no figure-eight flies at a wind of 0 (the motor curve is fitted on
            the calm figure-eight's hover).
    """
    kinds = list(h.get("train_kinds", ["eight", "walk"]))
    if not kinds or any(k not in ("eight", "walk") for k in kinds):
        raise ValueError(f"hard.train_kinds must name eight or walk (one or more), got {kinds!r}")
    winds = [float(w) for w in h["train_winds"]]
    if 0.0 not in winds or "eight" not in kinds:
        raise ValueError("hard.train_winds must hold 0 and hard.train_kinds eight: the motor "
                         f"curve is fitted on the calm figure-eight's hover (winds {winds}, "
                         f"kinds {kinds})")  # fmt: skip
    return [(w, k) for w in winds for k in kinds]


def _test(name: str, f: Flight, user, simple, opts, gust) -> _Test:
    """A test flight labelled (the gust given as its mean) with the truth at its labels."""
    log = f.log
    if name == "gust":  # the model is given the wind's mean only
        log = dataclasses.replace(log, wind=np.broadcast_to(log.wind.mean(0), log.wind.shape))
    lab = label(log, user, reference=simple, **opts)
    i = _at_labels(f, lab)
    # The gust is given as its mean and its RMS (what a forecast or a tunnel states).
    sd = np.array([float(gust["amplitude"]) / np.sqrt(2), 0.0, 0.0]) if name == "gust" else None
    return _Test(name, lab, f.force[i], f.rpm[i], f.euler[i], f.v_air[i], f.log.quaternion[i],
                 f.log.command[i], sd)  # fmt: skip


def _shared(a, b):
    """Two labellings of one flight (:class:`Labels` or :class:`_Test`) at the instants both
    have (their saturation tests read each curve's speeds and can drop a few apart)."""
    ta, tb = (x.labels.t if isinstance(x, _Test) else x.t for x in (a, b))
    ka, kb = np.isin(ta, tb), np.isin(tb, ta)

    def take(x, keep):
        if not isinstance(x, _Test):
            return x.take(keep)
        arrays = {f.name: getattr(x, f.name)[keep] for f in dataclasses.fields(x)
                  if f.name not in ("labels", "wind_sd") and isinstance(getattr(x, f.name),
                                                                        np.ndarray)}  # fmt: skip
        return dataclasses.replace(x, labels=x.labels.take(keep), **arrays)

    return take(a, ka), take(b, kb)


def _thrust_per_command(calm: Flight, identified, truth) -> dict[str, list[float]]:
    """Each rotor's hover thrust (N) at the calm flight's 10, 50 and 90 % commands, of the
    identified vehicle through the identified curve and of the real one through its own:
    with commands only the flights fix the thrust per command, not ``P_F`` alone (the curve
    and the rotor trade)."""
    q = (0.1, 0.5, 0.9)
    u = np.quantile(calm.log.command, q)[:, None] * np.ones((1, 4))
    volt = np.full(len(q), np.median(calm.log.voltage))
    out: dict[str, list[float]] = {"quantile": list(q), "command": u[:, 0].tolist()}
    for key, (veh, physics, curve) in (("identified", identified), ("truth", truth)):
        loads = physics_loads(veh, physics, jnp.asarray(curve.rpm(u, volt)),
                              jnp.zeros((len(q), 3)), jnp.zeros((len(q), 3)))  # fmt: skip
        out[key] = (-np.asarray(loads)[:, 2] / 4).tolist()
    out["relative_error"] = (np.array(out["identified"]) / out["truth"] - 1).tolist()
    return out


def _identify_with_speeds(esc_logs, user, user_cfg, simple, h) -> Identification:
    """:func:`gpg.flight.identify` on the training flights' logs with the ESC telemetry's
    rotor speeds (``hard.with_speeds``): no motor curve between the commands and the speeds,
    so no ``motor.*`` parameter is free, and the labels' delay is estimated."""
    labels = [label(log, user, reference=simple, rate=float(h["label_rate"]), source="velocity")
              for log in esc_logs]  # fmt: skip
    return _identify_variant(labels, user_cfg, h["with_speeds"], h["identify"])


def _bench_curve(spec, sensors: Sensors, user: Vehicle, seed: int) -> MotorCurve:
    """The real motors' curve as a bench measures it (``hard.bench_curve``): a tachometer's
    steady speeds at each command, ``readings`` times with a relative ``noise``, at the
    supply's ``voltage``, fitted by :meth:`MotorCurve.fit_speeds` with the motors' lag
    (``time_constant``; None: the vehicle file's): a bench curve is static, the flights'
    rotors lag it."""
    rng = np.random.default_rng(seed)
    u = np.repeat(np.asarray(spec["commands"], float), int(spec["readings"]))[:, None]
    u = u * np.ones((1, 4))
    volt = np.full(u.shape[0], float(spec["voltage"]))
    rpm = sensors.curve.rpm(u, volt) * (1 + float(spec["noise"]) * rng.normal(size=u.shape))
    tau = spec.get("time_constant")
    tau = float(user.motor_time_constant) if tau is None else float(tau)
    return MotorCurve.fit_speeds(u, rpm, volt, time_constant=tau)


def _identify_variant(labels, user_cfg, spec, idc) -> Identification:
    """:func:`gpg.flight.identify` with a variant's ``free`` and ``consider`` (``spec``), the
    main identification's label count, steps and body rates (``idc``)."""
    return identify(labels, user_cfg, free=tuple(spec["free"]),
                    max_labels=int(idc["max_labels"]), max_steps=int(idc["max_steps"]),
                    consider=dict(spec.get("consider") or {}),
                    body_rates=bool(idc.get("body_rates", True)))  # fmt: skip


def _identification(ident: Identification, truth: dict[str, float]) -> dict[str, Any]:
    """An identification for ``results.json``: each parameter and ``M``'s coefficients with
    its standard errors and the real vehicle's value (``truth``; None where it has none)."""
    return {
        "parameters": {k: {**v, "truth": truth.get(k)} for k, v in ident.parameters.items()},
        "unidentified": list(ident.unidentified),
        "steps": ident.steps,
        "converged": ident.converged,
        "residual_rms": ident.residual_rms.tolist(),
        **{
            k: {**c, "identified": c["value"], "truth": truth[k]}
            for k, c in ident.coefficients.items()
        },
    }


def _at_labels(f: Flight, lab: Labels):
    i = np.searchsorted(f.log.t, lab.t)
    return i


def _mse(pred_force, truth) -> float:
    return float(np.mean(np.sum((np.asarray(pred_force) - truth) ** 2, 1)))


def _score(sur: Surrogate, test: _Test, *, truth_states: bool = False,
           true_air: bool = False, mean_air: bool = False) -> dict[str, float]:  # fmt: skip
    """MSE of the force vector against the truth, and the 95 % band's coverage (both also per
    component, with the mean squared standardised error);
    the band includes the wind's uncertainty where the test gives one (a gust's RMS). At the
    true states (``truth_states``: the oracle's), or at the labels' rotor speeds and attitudes
    with the true air velocity (``true_air``: what the model errs by with the wind known);
    ``mean_air`` with ``truth_states``: the true rotor speeds and attitudes at the labels' air
    velocity, the wind's variance in the band (the oracle given the wind as the models are)."""
    lab = test.labels
    states = (lab.rpm, lab.euler, lab.v_air)
    if truth_states or true_air:
        states = (test.rpm if truth_states else lab.rpm, test.euler if truth_states else lab.euler,
                  lab.v_air if mean_air else test.v_air)  # fmt: skip
    p = sur.predict_batch(*states)
    var = np.asarray(p.variance)[:, :3]
    if test.wind_sd is not None and (mean_air or not (truth_states or true_air)):
        var = var + wind_variance(sur, *states, test.wind_sd)
    e = np.asarray(p.force) - test.force
    inside = np.abs(e) <= 1.959964 * np.sqrt(var)
    return {
        "mse": _mse(p.force, test.force),
        "mse_components": np.mean(e**2, 0).tolist(),
        "coverage95": float(np.mean(inside)),
        "coverage95_components": np.mean(inside, 0).tolist(),
        # the mean of e²/σ² per component: 1 for a band of the right width, under 1 too wide
        "z2_components": np.mean(e**2 / var, 0).tolist(),
    }


def _band_parts(sur: Surrogate, test: _Test) -> dict[str, Any]:
    """Where :func:`_score`'s band comes from: the mean over the test's labels of each term of
    the force's variance (:meth:`gpg.Surrogate.variance_parts`; the gust's wind term too), per
    world component, N²; over every label and over those in the prior's domain (outside it
    the prior's variance is its kernel's whole), with the coverage there."""
    lab = test.labels
    states = (lab.rpm, lab.euler, lab.v_air)
    parts = {k: np.asarray(v)[:, :3] for k, v in sur.variance_parts(*states).items()}
    if test.wind_sd is not None:
        parts["wind"] = np.asarray(wind_variance(sur, *states, test.wind_sd))[:, :3]
    p = sur.predict_batch(*states)
    inside = np.asarray(p.in_domain, bool)
    e2 = (np.asarray(p.force) - test.force) ** 2
    var = sum(parts.values())
    out: dict[str, Any] = {"share_in_domain": float(inside.mean())}
    for where, rows in (("all", np.ones_like(inside)), ("in_domain", inside)):
        if rows.any():
            out[where] = {k: np.mean(v[rows], 0).tolist() for k, v in sorted(parts.items())}
            out[where]["mse"] = np.mean(e2[rows], 0).tolist()
            out[where]["coverage95"] = np.mean(e2[rows] <= 1.959964**2 * var[rows], 0).tolist()
    return out


def _coefficients(sur: Surrogate) -> dict[str, list[float]]:
    """A physical-basis correction's scale ``ρ`` per load output, its held-out calibration
    factors per output (``c`` on the discrepancy's variance and the coefficients', ``q`` on
    the prior's share), ``κ`` and the physical coefficients ``β`` (outputs by
    :data:`gpg.flight.basis.TERMS`)."""
    m = sur.model
    return {"rho": np.asarray(m.scale)[:6].tolist(),
            "calibration": [float(d.output_scale[0]) for d in m.delta],
            "prior_share": sur.config["flight_correction"]["prior_share"],
            "kappa": np.asarray(m.kappa).tolist(),
            "beta": np.asarray(m.explicit.beta).tolist(),
            "basis_prior": sur.config["flight_correction"]["basis_prior"]}  # fmt: skip


def _ridge_features(v, q, u):
    return np.column_stack([np.ones(len(v)), v, q, u])


def _ridge(train: list[tuple[np.ndarray, np.ndarray]], lam: float):
    X = np.concatenate([a for a, _ in train])
    Y = np.concatenate([b for _, b in train])
    mu, sd = X.mean(0), X.std(0)
    sd[sd == 0] = 1.0
    Z = (X - mu) / sd
    Z[:, 0] = 1.0
    A = Z.T @ Z + lam * np.eye(Z.shape[1])
    A[0, 0] -= lam  # the intercept is not shrunk
    W = np.linalg.solve(A, Z.T @ Y)

    def predict(Xq):
        Zq = (Xq - mu) / sd
        Zq[:, 0] = 1.0
        return Zq @ W

    return predict


def _prior_of(vehicle_cfg, data_cfg, model, cache_dir, progress, half_turn) -> Surrogate:
    _, train, _, _, _ = ensure(data_cfg, vehicle_cfg, cache_dir, progress=progress)
    name = dict(model).pop("name")
    opts = {k: v for k, v in model.items() if k != "name"}
    return Surrogate.fit(train, name, opts or None, vehicle=Vehicle.from_config(vehicle_cfg),
                         half_turn=half_turn)  # fmt: skip


@float64
def run(cfg: dict[str, Any], out: Path, nominal_prior: Surrogate) -> dict[str, Any]:
    """The hard scenario (module docstring); returns what ``results.json`` holds."""
    h = cfg["hard"]
    progress = bool(cfg.get("progress", True))
    stages: dict[str, float] = {}
    t0 = time.perf_counter()
    logs = out / "logs"
    base_cfg = vehicle_config(h["vehicle"]["base"])
    user_cfg = copy.deepcopy(base_cfg)
    for k, v in (h["vehicle"].get("changes") or {}).items():
        user_cfg[k] = v
    if h["vehicle"].get("rotor_radius") is not None:  # measured: the propellers' size
        user_cfg["rotor"] = {**user_cfg["rotor"], "radius": float(h["vehicle"]["rotor_radius"])}
    user_cfg["name"] = f"{base_cfg['name']}_user"
    user = Vehicle.from_config(user_cfg)
    real_cfg = perturbed_config(base_cfg, h["real"]["changes"])
    real = Vehicle.from_config(real_cfg)
    physics = BEMTConfig(wake_gain=float(h["real"]["wake_gain"]),
                         interference=bool(h["real"]["interference"]))  # fmt: skip
    simple = nominal_prior.simple
    ctrl = GeometricController.create(user, simple)
    s = {k: (tuple(v) if isinstance(v, list) else v) for k, v in h["sensors"].items()}
    s["curve"] = MotorCurve(**{k: (tuple(v) if isinstance(v, list) else v)
                               for k, v in s["curve"].items()})  # fmt: skip
    sensors = Sensors(**s)
    seed = int(h["seed"])
    # Training flights: at each wind the kinds of hard.train_kinds; the wind known (a tunnel).
    plan = training_plan(h)
    bar = tqdm(total=len(plan) + 2, desc="flying", disable=not progress)
    train, esc_logs = [], []
    with_speeds = h.get("with_speeds")
    for i, (w, kind) in enumerate(plan):
        f, esc = _flight(
            h,
            real,
            ctrl,
            physics,
            sensors,
            f"train{i:02d}_{kind}_{w:g}",
            Wind.constant(np.array([float(w), 0.0, 0.0])),
            kind,
            seed + i,
            logs,
            True,
            esc=bool(with_speeds),
        )
        train.append((float(w), f))
        esc_logs.append(esc)
        bar.update()
    gust = h["gust"]
    tests_raw = {
        "steady": _flight(h, real, ctrl, physics, sensors, "test_steady",
                          Wind.constant(np.array([float(h["test_wind"]), 0.0, 0.0])), "eight",
                          seed + 100, logs, True)[0],
        "gust": _flight(h, real, ctrl, physics, sensors, "test_gust",
                        Wind(np.array([float(gust["mean"]), 0.0, 0.0]),
                             np.array([float(gust["amplitude"]), 0.0, 0.0]),
                             np.asarray(float(gust["period_s"])), np.asarray(0.0)),
                        "eight", seed + 101, logs, True)[0],
    }  # fmt: skip
    bar.update(2)
    bar.close()
    stages["fly_s"] = time.perf_counter() - t0

    # The motor curve from the calm figure-eight's hover, labels from the velocity.
    t1 = time.perf_counter()
    calm = train[plan.index((0.0, "eight"))][1]  # training_plan checked that it flies
    curve = MotorCurve.fit_hover(calm.log, user, simple, moments=h.get("hover_moments", False))

    def labelled(
        c: MotorCurve, veh: Vehicle = user, with_tests: bool = True
    ) -> tuple[list[Labels], dict[str, _Test]]:
        opts = {"rate": float(h["label_rate"]), "source": "velocity", "curve": c}
        with warnings.catch_warnings():  # the curve's range is the hover's: counted, not news
            warnings.filterwarnings("ignore", r".*command.*extrapolated", FlightLogWarning)
            return [label(f.log, veh, reference=simple, **opts) for _, f in train], {
                name: _test(name, f, veh, simple, opts, gust)
                for name, f in (tests_raw.items() if with_tests else ())
            }

    train_labels, tests = labelled(curve)
    stages["label_s"] = time.perf_counter() - t1

    # Identification on the training flights (their winds known).
    t1 = time.perf_counter()
    idc = h["identify"]
    ident = identify(
        train_labels,
        user_cfg,
        free=tuple(idc["free"]),
        max_labels=int(idc["max_labels"]),
        max_steps=int(idc["max_steps"]),
        consider=dict(idc.get("consider") or {}),
        body_rates=bool(idc.get("body_rates", True)),
    )
    ident.write(out / "identified_vehicle.yaml", overwrite=True)
    # The identified vehicle's rotor speeds are those of the identified curve: every model of
    # it is corrected and scored on the flights labelled again with that curve.
    # Labelled with the identified vehicle (its motor range is the identified curve's); the
    # test flights kept at the instants both labellings have: every model scored alike.
    id_curve = ident.curve(curve)
    id_train, id_tests = labelled(id_curve, ident.vehicle)
    for name in tests:
        tests[name], id_tests[name] = _shared(tests[name], id_tests[name])
    # What an online filter reads: every sample of each test log at the stream's rate, those
    # with a saturated rotor too (the offline fits drop them: their rotor speeds are less
    # sure); scored at the test labels' instants, which it holds.
    st = h["stream"]
    stream_opts = {"rate": float(st["rate"]), "source": "velocity", "curve": id_curve,
                   "saturation": float(st["saturation"])}  # fmt: skip
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", r".*command.*extrapolated", FlightLogWarning)
        id_streams = {name: _test(name, f, ident.vehicle, simple, stream_opts, gust)
                      for name, f in tests_raw.items()}  # fmt: skip
        # the same samples through the hover curve and the user's file: today's route
        streams = {name: _test(name, f, user, simple, {**stream_opts, "curve": curve}, gust)
                   for name, f in tests_raw.items()}  # fmt: skip
        # the training flights read the same way: what a drift for the stream's filters is
        # fitted on (gpg.flight.fit_drift's read; its seconds count in identify_s)
        id_train_streams = None
        if cfg["track"].get("fit_stream"):
            id_train_streams = [label(f.log, ident.vehicle, reference=simple, **stream_opts)
                                for _, f in train]  # fmt: skip
    stages["identify_s"] = time.perf_counter() - t1
    # The same training flights with their ESC telemetry: what logging the rotor speeds tells
    # that commands cannot (with commands only, the curve's gain and P_F trade).
    speeds_ident = None
    if with_speeds:
        t1 = time.perf_counter()
        speeds_ident = _identify_with_speeds(esc_logs, user, user_cfg, simple, h)
        stages["identify_speeds_s"] = time.perf_counter() - t1
    # The same commands through a curve measured on the bench, in place of the hover's.
    bench = None
    if h.get("bench_curve"):
        t1 = time.perf_counter()
        b_curve = _bench_curve(h["bench_curve"], sensors, user, seed + 200)
        b_labels, _ = labelled(b_curve, with_tests=False)  # the training flights only
        b_ident = _identify_variant(b_labels, user_cfg, h["bench_curve"], idc)
        bench = (b_curve, b_ident)
        stages["identify_bench_s"] = time.perf_counter() - t1

    data_cfg = conf.load(h["data"], "data")
    half = bool(h.get("half_turn", False))
    if half:  # the microphones are not their own images: a prior of the loads only
        data_cfg["noise"] = False
    t1 = time.perf_counter()
    model_opts = {k: v for k, v in cfg["model"].items() if k != "name"}
    id_prior = ident.prior(data_cfg, cfg["model"]["name"], model_opts or None, half_turn=half,
                           cache_dir=cfg["cache_dir"], progress=progress)  # fmt: skip
    stages["identified_prior_s"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    keys = ("max_labels", "exact_labels", "inducing", "subset_size", "hyperparameters",
            "calibrate", "coefficient_spread")  # fmt: skip
    corr = {k: v for k, v in cfg["correct"].items() if k in keys}
    corr["basis_prior"] = basis_prior(cfg["correct"]["basis_prior"])
    # One part per wind: the physical basis's band is calibrated by holding out a whole
    # condition (the fastest wind predicted from the slower ones), not one flight among
    # flights of the same wind.
    by_wind = _by_wind(train, train_labels)
    by_wind_id = _by_wind(train, id_train)
    models: dict[str, Surrogate] = {
        "prior": nominal_prior,
        "corrected_regression": fc.correct(nominal_prior, train_labels, basis="regression", **corr),
        "values_only": fc.correct(
            nominal_prior, train_labels, use_prior=False, simple_term=False, **corr
        ),  # fmt: skip
        "flights_physical": fc.correct(
            nominal_prior, by_wind, use_prior=False, basis="physical", **corr
        ),  # fmt: skip
        "identified_prior": id_prior,
        # The identified vehicle's physics taken as it is (ρ = 1, the guide's route); beside
        # it ρ fitted, as for another vehicle's prior.
        "identified": fc.correct(id_prior, by_wind_id, basis="physical", scale=False, **corr),
        "identified_rho": fc.correct(id_prior, by_wind_id, basis="physical", **corr),
    }
    stages["correct_s"] = time.perf_counter() - t1

    # The wind estimated on every training flight as if none had been logged.
    t1 = time.perf_counter()
    wind_rows, est_labels = [], []
    for (w, f), lab, lab_id in zip(train, train_labels, id_train, strict=True):
        lab, lab_id = _shared(lab, lab_id)
        wind_at = f.log.wind[np.searchsorted(f.log.t, lab.t)]
        blind = dataclasses.replace(lab, v_air=lab.v_air + wind_at)
        # The identification reads the first curve's speeds (it applies its own gain and
        # power), the corrections the identified curve's: the same instants, the same wind.
        est = estimate_wind(blind, ident, knot_s=float(h["wind"]["knot_s"]),
                            drift=float(h["wind"]["drift"]))  # fmt: skip
        true_w = f.log.wind[np.searchsorted(f.log.t, lab.t)]
        err = est.wind[:, :2] - true_w[:, :2]
        wind_rows.append({"flight": lab.name, "wind": w, "estimated_mean": est.mean.tolist(),
                          "rms_error": float(np.sqrt(np.mean(np.sum(err**2, 1)))),
                          "sd_median": float(np.median(est.sd[:, 0])),
                          "informed": est.informed.tolist()})  # fmt: skip
        est_labels.append(with_wind(dataclasses.replace(lab_id, v_air=lab_id.v_air + wind_at), est))
    models["identified_estimated_wind"] = fc.correct(
        id_prior, _by_wind(train, est_labels), basis="physical", scale=False, **corr
    )
    stages["wind_s"] = time.perf_counter() - t1

    t1 = time.perf_counter()
    oracle = _prior_of(real_cfg, data_cfg, cfg["model"], cfg["cache_dir"], progress, half)
    stages["oracle_prior_s"] = time.perf_counter() - t1

    # Adaptation, prequential: the identified and corrected model updated label by label on
    # each test flight, each label predicted before it is used.
    t1 = time.perf_counter()
    n_fit = int(cfg["track"]["max_labels"])
    drift = fit_drift(models["identified"], by_wind_id, max_labels=n_fit)
    stages["fit_drift_s"] = time.perf_counter() - t1
    other = fit_drift(models["identified"], by_wind_id, max_labels=n_fit,
                      fast=tuple(float(f) for f in cfg["track"]["compare_fast"]))  # fmt: skip
    # the drift as fitted before spreads per column: one spread for every column
    one_spread = fit_drift(models["identified"], by_wind_id, max_labels=n_fit, per_column=False)
    # the drift fitted on what the stream's filters read: every sample of the training
    # flights over the labels' span, each wind predicted from the others' labels
    stream_drift = None
    if id_train_streams is not None:
        t2 = time.perf_counter()
        stream_drift = fit_drift(models["identified"], by_wind_id, max_labels=n_fit,
                                 read=_by_wind(train, id_train_streams))  # fmt: skip
        stages["fit_drift_stream_s"] = time.perf_counter() - t2
    # the inducing-point term's forgetting time and prior fitted the same way: on every
    # sample of the training flights, each wind predicted from the others' labels
    # (each band of adapt.fit_forgetting: the term's variance added to the offline band, or
    # its prior a share of it)
    forgetting = {}
    if id_train_streams is not None and cfg["adapt"].get("fit_forgetting"):
        t2 = time.perf_counter()
        per_output = set(cfg["adapt"].get("fit_forgetting_per_output") or ())
        ahead = int(cfg["adapt"].get("fit_forgetting_ahead") or 1)
        fits = [(str(b), False, 1) for b in cfg["adapt"]["fit_forgetting"]]
        fits += [(str(b), True, 1) for b in cfg["adapt"]["fit_forgetting"] if b in per_output]
        if ahead > 1:  # scored past the labels' correlated noise
            fits += [(b, True, ahead) for b, own, _ in fits if own]
        for band, own, lead in fits:
            name = band + ("_per_output" if own else "") + (f"_ahead{lead}" if lead > 1 else "")
            forgetting[name] = fit_forgetting(
                models["identified"], by_wind_id, inducing=int(cfg["adapt"]["inducing"]),
                max_labels=n_fit, band=band, per_output=own, ahead=lead,
                read=_by_wind(train, id_train_streams))  # fmt: skip
        stages["fit_forgetting_s"] = time.perf_counter() - t2
    # the fitted memories flown together as one bank: with the configured weight forgetting
    # time, and with one fitted on the same rows (adapt.bank_fit)
    members = [forgetting[n] for n in cfg["adapt"].get("bank") or () if n in forgetting]
    banks, bank_fit = {}, None
    if members:
        banks["bank"] = float(cfg["adapt"]["bank_weight_tau"])
    if members and cfg["adapt"].get("bank_fit"):
        t2 = time.perf_counter()
        bank_fit = fit_bank(models["identified"], by_wind_id, members,
                            ahead=int(cfg["adapt"]["bank_ahead"]),
                            inducing=members[0].inducing, max_labels=n_fit,
                            read=_by_wind(train, id_train_streams))  # fmt: skip
        banks["bank_fitted"] = bank_fit.weight_tau
        stages["fit_bank_s"] = time.perf_counter() - t2
    t1 = time.perf_counter()
    curves: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}
    adaptive = prequential_rows(
        models["identified"],
        id_tests,
        drift,
        cfg["adapt"],
        out,
        progress,
        other=other,
        gust_cfg=cfg["track"]["gusts"],
        spreads=[float(v) for v in cfg["track"]["spread_sweep"]],
        one_spread=one_spread,
        streams=id_streams,
        curves=curves,
        stream_drift=stream_drift,
        hindsight=bool(cfg["track"].get("hindsight")),
        forgetting=forgetting,
        banks=banks,
    )
    if bank_fit is not None:
        adaptive["bank_fit"] = dataclasses.asdict(bank_fit)
    adaptive["today"] = today_rows(models["corrected_regression"], tests, streams,
                                   cfg["adapt"], progress, curves)  # fmt: skip
    _prequential_figure(out / "figures", curves)
    # Each swept spread's score on the training winds held out (what fit_drift maximises),
    # beside its prequential scores on the test flights: whether the flights could tell it.
    swept = [(f"tracked_spread_{s:g}", dataclasses.replace(drift, spread=s, columns=()))
             for s in adaptive["spreads"]]  # fmt: skip
    adaptive["spread_sweep"] = [
        {"model": key, "spread": d.spread, "columns": list(d.columns),
         "held_out_log_likelihood": score_drift(models["identified"], by_wind_id, d,
                                                max_labels=n_fit)}
        for key, d in [*swept, ("tracked", drift), ("tracked_one_spread", one_spread)]
    ]  # fmt: skip
    stages["prequential_s"] = time.perf_counter() - t1

    # Scores.
    def features(f: Flight, lb: Labels) -> np.ndarray:
        i = _at_labels(f, lb)
        return _ridge_features(f.log.velocity[i], f.log.quaternion[i], f.log.command[i])

    ridge = _ridge(
        [(features(f, lb), lb.force) for (_, f), lb in zip(train, train_labels, strict=True)],
        float(h["ridge_lambda"]),
    )
    rows = []
    for name, test in tests.items():
        row: dict[str, Any] = {"test": name, "labels": len(test.labels)}
        for m, sur in models.items():
            own = id_tests[name] if m.startswith("identified") else test
            row.update({f"{m}_{k}": v for k, v in _score(sur, own).items()})
        row.update({f"oracle_{k}": v for k, v in _score(oracle, test, truth_states=True).items()})
        given = _score(oracle, test, truth_states=True, mean_air=True)
        row.update({f"oracle_mean_air_{k}": v for k, v in given.items()})
        # the guide's model with the wind known at every label: what a wind state could reach
        wind_known = _score(models["identified"], id_tests[name], true_air=True)
        row.update({f"identified_true_air_{k}": v for k, v in wind_known.items()})
        row["identified_band_parts"] = _band_parts(models["identified"], id_tests[name])
        v_ground = test.labels.v_air + tests_raw[name].log.wind[
            np.searchsorted(tests_raw[name].log.t, test.labels.t)]  # fmt: skip
        if name == "gust":
            v_ground = test.labels.v_air + float(gust["mean"]) * np.array([1.0, 0, 0])
        pr = ridge(_ridge_features(v_ground, test.quaternion, test.command))
        row["ridge_mse"] = _mse(pr, test.force)
        row["noise_floor"] = float(np.mean(np.sum(test.labels.force_var, 1)))
        rows.append(row)
        jax.clear_caches()
    truth = {**_truth_parameters(real_cfg, base_cfg, h["real"]),
             **dict(zip(("thrust_coefficient", "torque_coefficient"),
                        hover_coefficients(real, BEMTConfig()), strict=True))}  # fmt: skip
    thrust = _thrust_per_command(calm, (ident.vehicle, ident.physics, id_curve),
                                 (real, physics, sensors.curve))  # fmt: skip
    results = {
        "config": cfg,
        "machine": machine(),
        "tests": rows,
        "adaptation": adaptive,
        "identification": {**_identification(ident, truth), "thrust_per_command": thrust},
        "identification_with_speeds": (
            None if speeds_ident is None else _identification(speeds_ident, truth)
        ),
        "identification_with_bench_curve": None
        if bench is None
        else {
            **_identification(bench[1], truth),
            "curve": dataclasses.asdict(bench[0]),
            "thrust_per_command": _thrust_per_command(
                calm,
                (bench[1].vehicle, bench[1].physics, bench[1].curve(bench[0])),
                (real, physics, sensors.curve),
            ),
        },
        "curve": dataclasses.asdict(curve),
        "wind": wind_rows,
        "labels": {"train": int(sum(len(lb) for lb in train_labels))},
        "coefficients": {
            m: _coefficients(models[m])
            for m in ("identified", "identified_rho", "identified_estimated_wind")
        },
        "stages_s": stages,
        "seconds_total": time.perf_counter() - t0,
    }
    write_json(out / "results.json", results)
    report(_report(results))
    return results


def prequential_rows(offline: Surrogate, tests: dict[str, Any], drift, adapt_cfg, out: Path,
                     progress: bool, other=None, gust_cfg=None, spreads=(),
                     one_spread=None, streams=None, curves=None,
                     stream_drift=None, hindsight=False,
                     forgetting=None, banks=None) -> dict[str, Any]:  # fmt: skip
    """Each test flight through the offline model, today's inducing-point adaptation and the
    tracked coefficients (the fitted drift, the default one, ``other``, a drift fitted
    with another bank, where given, the fitted drift with a wind state, horizontal and
    with vertical gusts, where ``gust_cfg`` gives them, the fitted drift with each of
    ``spreads`` for every column in place of its own: ``tracked_spread_<s>``, and
    ``one_spread``, a drift fitted with one spread for all columns, where given), each label
    predicted
    before it is used (:func:`gpg.flight.prequential`); where ``streams`` gives a test flight
    labelled at every sample (saturated rotors too), the offline model, the inducing-point
    term, the tracked coefficients and the wind state also read that stream, scored at the
    test labels' instants (``stream_<model>_...``; with ``stream_drift``, a drift fitted on
    the training flights' streams, the tracked coefficients and the wind state with it too,
    ``stream_tracked_fit_stream`` and ``stream_tracked_gusts_fit_stream``; with
    ``forgetting`` (band, or band with ``_per_output``, to :class:`gpg.flight.Forgetting`),
    the inducing-point term with each fitted forgetting time and prior,
    ``stream_inducing_fitted`` (the band added), ``stream_inducing_fitted_shared``,
    ``stream_inducing_fitted_shared_per_output`` and, fitted on predictions ``N`` samples
    ahead, ``..._ahead<N>``; with ``banks`` (model key to a weight forgetting time), the
    fitted memories of ``adapt_cfg["bank"]`` flown as one bank, ``stream_<key>``; with
    ``hindsight``, the tracked coefficients and the inducing-point term fitted on the whole
    stream without forgetting and scored at the labels, ``stream_hindsight_<term>_mse``: at a
    steady wind the least error each term reaches): the force MSE
    against the truth and
    against the labels, the 95 % coverage of the truth (the band with the gust's RMS where the
    test gives one, as offline), the labels' log predictive density, the labels' noise floor;
    the per-label update cost from Python; the error along the flights into ``curves``
    (``(test, model) -> (seconds since the first label, squared error)``; not given: drawn
    here as the figure)."""
    from experiments.runs.flight_logs import prequential_scores, update_cost

    draw = curves is None
    rows, curves = [], {} if curves is None else curves
    for name, test in tqdm(tests.items(), desc="prequential", disable=not progress):
        lab = test.labels
        t0 = float(lab.t[0])
        models = {
            "none": offline,
            "inducing": fc.adapt(
                offline, inducing=int(adapt_cfg["inducing"]), tau=float(adapt_cfg["tau"]), t0=t0
            ),  # fmt: skip
            "tracked": track(offline, drift, t0=t0),
            "tracked_default": track(offline, None, t0=t0),
        }
        if other is not None:
            models["tracked_other"] = track(offline, other, t0=t0)
        if one_spread is not None:
            models["tracked_one_spread"] = track(offline, one_spread, t0=t0)
        if gust_cfg is not None:
            tau = float(gust_cfg["tau"])
            for m, key in (("tracked_gusts", "sd"), ("tracked_gusts_vertical", "sd_vertical")):
                models[m] = track(offline, gusts(drift, gust_cfg[key], tau), t0=t0)
        for sp in spreads:
            models[f"tracked_spread_{sp:g}"] = track(
                offline, dataclasses.replace(drift, spread=sp), t0=t0
            )
        extra = None
        if test.wind_sd is not None:
            extra = wind_variance(offline, lab.rpm, lab.euler, lab.v_air, test.wind_sd)
        # labels that follow a stretch without labels (over 1.5 label periods): what was
        # learnt before it is as old as the stretch is long
        step = np.diff(lab.t)
        gap = np.r_[False, step > 1.5 * np.median(step)]
        row: dict[str, Any] = {"test": name, "labels": len(lab),
                               "noise_floor": float(np.mean(np.sum(lab.force_var, 1))),
                               "after_gap_share": float(gap.mean())}  # fmt: skip
        for m, sur in models.items():
            sc, e = prequential_scores(sur, lab, test.force, extra)
            row.update({f"{m}_{k}": v for k, v in sc.items()})
            err = np.sum(e**2, 1)
            row[f"{m}_mse_after_gap"] = float(err[gap].mean()) if gap.any() else None
            row[f"{m}_mse_no_gap"] = float(err[~gap].mean())
            # the first 10 s in the flight's conditions against the rest: what the filter's
            # start from its stationary law costs before the flight has told it much
            early = lab.t - t0 < 10.0
            row[f"{m}_mse_first_10s"] = float(err[early].mean())
            row[f"{m}_mse_after_10s"] = float(err[~early].mean()) if (~early).any() else None
            curves[(name, m)] = (lab.t - t0, np.sum(e**2, 1))
            row[f"{m}_lag1"] = _lag1(lab.t, e)
        if streams is not None:
            row.update(_stream_scores(offline, streams[name], lab, drift, adapt_cfg, gust_cfg,
                                      curves, (name, t0), stream_drift, forgetting,
                                      banks))  # fmt: skip
            if hindsight:
                row.update(_hindsight(offline, streams[name], lab, drift, adapt_cfg))
        rows.append(row)
        jax.clear_caches()
    steady = tests["steady"].labels
    cost = update_cost(track(offline, drift, t0=float(steady.t[0])), steady, 600.0)
    out_ = {
        "drift": dataclasses.asdict(drift),
        "tests": rows,
        "tracked_update": cost,
        "other": None if other is None else dataclasses.asdict(other),
        "one_spread": None if one_spread is None else dataclasses.asdict(one_spread),
        "spreads": list(spreads),
        "stream_drift": None if stream_drift is None else dataclasses.asdict(stream_drift),
        "forgetting": {b: dataclasses.asdict(f) for b, f in (forgetting or {}).items()},
    }
    if gust_cfg is not None:
        with_gusts = gusts(drift, gust_cfg["sd"], float(gust_cfg["tau"]))
        out_["gusts"] = {"sd": list(with_gusts.wind_sd), "tau": with_gusts.wind_tau}
        out_["tracked_gusts_update"] = update_cost(
            track(offline, with_gusts, t0=float(steady.t[0])), steady, 600.0
        )
    if banks:  # two filters a member and the offline band at every label
        bank = _bank(offline, adapt_cfg, forgetting, float(steady.t[0]), banks["bank"])
        out_["bank_update"] = update_cost(bank, steady, 120.0)
    if draw:
        _prequential_figure(out / "figures", curves)
    return out_


def today_rows(
    regression: Surrogate,
    tests: dict[str, _Test],
    streams: dict[str, _Test],
    adapt_cfg,
    progress: bool,
    curves=None,
) -> dict[str, Any]:
    """Today's adaptation, as the tracking issue measured it on real flights: the
    inducing-point term (:func:`gpg.flight.adapt`, ``adapt_cfg["inducing"]`` inputs) with each
    forgetting time of ``adapt_cfg["today_taus"]``, on the correction before the physical
    basis (the nearest file's prior corrected, ``regression``; its labels from the hover
    curve), prequential on each test flight's labels and on every sample of it (``streams``,
    scored at the labels' instants), against the same truth as every other row. ``best`` is
    the least MSE over the forgetting times, per flight and per reading: the baseline the
    issue's "a third of today's adaptation" is measured against, taken at its best; its
    error along each flight goes into ``curves`` (``today`` and ``stream_today``), where
    given."""
    from experiments.runs.flight_logs import prequential_scores

    taus = [float(v) for v in adapt_cfg["today_taus"]]
    rows = []
    for name, test in tqdm(tests.items(), desc="today's adaptation", disable=not progress):
        lab, s = test.labels, streams[name].labels
        at = np.isin(s.t, lab.t)
        row: dict[str, Any] = {"test": name, "stream_scored": int(at.sum())}
        t0 = float(lab.t[0])
        for reading, seq, truth, mask, wind_sd in (
            ("labels", lab, test.force, None, test.wind_sd),
            ("stream", s, streams[name].force, at, streams[name].wind_sd),
        ):
            extra = None
            if wind_sd is not None:
                extra = wind_variance(regression, seq.rpm, seq.euler, seq.v_air, wind_sd)
            best = None
            for tau in taus:
                sur = fc.adapt(regression, inducing=int(adapt_cfg["inducing"]), tau=tau,
                               t0=float(seq.t[0]))  # fmt: skip
                sc, e = prequential_scores(sur, seq, truth, extra, at=mask)
                row.update({f"{reading}_tau_{tau:g}_{k}": v for k, v in sc.items()})
                if best is None or sc["mse"] < row[f"{reading}_best_mse"]:
                    best = tau
                    row.update({f"{reading}_best_{k}": v for k, v in sc.items()})
                    if curves is not None:
                        key = "today" if reading == "labels" else "stream_today"
                        curves[(name, key)] = (lab.t - t0, np.sum(e**2, 1))
            row[f"{reading}_best_tau"] = best
        rows.append(row)
        jax.clear_caches()
    return {"taus": taus, "tests": rows}


def _fitted_key(name: str) -> str:
    """The model key of the inducing-point term with the forgetting fit ``name`` (a band,
    ``_per_output``, ``_ahead<N>``): ``inducing_fitted`` for the added band's, else
    ``inducing_fitted_<name>``."""
    return "inducing_fitted" + ("" if name == "added" else f"_{name}")


def _stream_scores(
    offline: Surrogate,
    stream: _Test,
    lab: Labels,
    drift,
    adapt_cfg,
    gust_cfg,
    curves,
    where: tuple[str, float],
    stream_drift=None,
    forgetting=None,
    banks=None,
) -> dict[str, Any]:
    """The offline model and the online ones reading ``stream`` (every sample of the test
    flight whose labels are ``lab``; the inducing-point term also with each forgetting time of
    ``adapt_cfg["stream_taus"]``, and with each of ``forgetting``'s fitted times and priors,
    ``inducing_fitted``, ``inducing_fitted_<name>``), each scored at ``lab``'s instants: the
    same labels and truth as the rows read from ``lab`` alone. The error curves go into
    ``curves`` under the test's name, timed from ``lab``'s first label (``where``)."""
    from experiments.runs.flight_logs import prequential_scores

    s = stream.labels
    at = np.isin(s.t, lab.t)
    out: dict[str, Any] = {"stream_labels": len(s), "stream_scored": int(at.sum())}
    start = float(s.t[0])
    models = {"none": offline,
              "inducing": fc.adapt(offline, inducing=int(adapt_cfg["inducing"]),
                                   tau=float(adapt_cfg["tau"]), t0=start),
              "tracked": track(offline, drift, t0=start)}  # fmt: skip
    if gust_cfg is not None:
        models["tracked_gusts"] = track(
            offline, gusts(drift, gust_cfg["sd"], float(gust_cfg["tau"])), t0=start
        )
    for tau in adapt_cfg.get("stream_taus") or ():  # the term with other forgetting times
        models[f"inducing_tau_{float(tau):g}"] = fc.adapt(
            offline, inducing=int(adapt_cfg["inducing"]), tau=float(tau), t0=start
        )
    for name, fo in (forgetting or {}).items():
        models[_fitted_key(name)] = fc.adapt(offline, inducing=fo.inducing, tau=fo.tau,
                                             variance=fo.variance, t0=start,
                                             band=fo.band)  # fmt: skip
    for key, weight_tau in (banks or {}).items():
        models[key] = _bank(offline, adapt_cfg, forgetting, start, weight_tau)
    if stream_drift is not None:
        models["tracked_fit_stream"] = track(offline, stream_drift, t0=start)
        if gust_cfg is not None:
            models["tracked_gusts_fit_stream"] = track(
                offline, gusts(stream_drift, gust_cfg["sd"], float(gust_cfg["tau"])), t0=start
            )
    extra = None
    if stream.wind_sd is not None:
        extra = wind_variance(offline, s.rpm, s.euler, s.v_air, stream.wind_sd)
    for m, sur in models.items():
        sc, e = prequential_scores(sur, s, stream.force, extra, at=at)
        out.update({f"stream_{m}_{k}": v for k, v in sc.items()})
        curves[(where[0], f"stream_{m}")] = (s.t[at] - where[1], np.sum(e**2, 1))
    return out


def _bank(offline: Surrogate, adapt_cfg, forgetting, t0: float, weight_tau: float) -> Surrogate:
    """``adapt_cfg["bank"]``'s fitted memories (names of ``forgetting``) flown together as one
    bank (:func:`gpg.flight.adapt_bank`) whose weights forget over ``weight_tau`` s."""
    bank = [forgetting[n] for n in adapt_cfg["bank"] if n in forgetting]
    return adapt_bank(offline, bank, ahead=int(adapt_cfg["bank_ahead"]),
                      weight_tau=float(weight_tau), inducing=bank[0].inducing,
                      t0=t0)  # fmt: skip


def _hindsight(offline: Surrogate, stream: _Test, lab: Labels, drift, adapt_cfg) -> dict:
    """The tracked coefficients (``drift``'s spreads, no drift in time: one filter, ``τ`` and
    the bias's ``τ_b`` beyond the flight) and the inducing-point term (``adapt_cfg``'s
    inputs, no forgetting), each fitted on every sample of the test flight and then scored
    at its labels against the truth. At a steady wind, the least error each term reaches with
    coefficients that stay (a filter reading the flight forward pays its start on top); in a
    gust a filter that forgets can do better, following the gust in time."""
    s = stream.labels
    at = np.isin(s.t, lab.t)
    start = float(s.t[0])
    still = dataclasses.replace(drift, tau=1e12, bias_tau=1e12, fast=())
    models = {"tracked": track(offline, still, t0=start),
              "inducing": fc.adapt(offline, inducing=int(adapt_cfg["inducing"]), tau=1e12,
                                   t0=start)}  # fmt: skip
    out = {}
    for m, sur in models.items():
        final = prequential(sur, s).final
        p = final.predict_batch(s.rpm[at], s.euler[at], s.v_air[at], mean_only=True)
        out[f"stream_hindsight_{m}_mse"] = _mse(p.force, stream.force[at])
    return out


def _lag1(t: np.ndarray, e: np.ndarray) -> list[float]:
    """Each component's correlation between the errors of consecutive labels (one label period
    apart; pairs across a dropped stretch left out): how much of the next error the last one
    tells, what any online update can at best remove."""
    dt = np.diff(t)
    pair = np.abs(dt - np.median(dt)) < 1e-6
    return [float(np.corrcoef(e[:-1, c][pair], e[1:, c][pair])[0, 1]) for c in range(3)]


def _prequential_figure(where: Path, curves) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    where.mkdir(parents=True, exist_ok=True)
    tests = sorted({t for t, _ in curves})
    fig, axes = plt.subplots(len(tests), 1, figsize=(9, 3 * len(tests) + 1.5), sharex=True)
    styles = {"none": ("k--", "no adaptation"),
              "today": ("C5:", "today's adaptation (adapt on today's correct, best tau)"),
              "stream_today": ("C5", "today's adaptation, every sample of the log"),
              "inducing": ("C1", "inducing-point term (adapt)"),
              "tracked": ("C0", "tracked coefficients, fitted drift"),
              "tracked_default": ("C2:", "tracked coefficients, default drift"),
              "tracked_gusts": ("C3", "tracked coefficients and a wind state"),
              "stream_tracked_gusts": ("C4", "tracked coefficients and a wind state, "
                                              "every sample")}  # fmt: skip
    for ax, test in zip(np.atleast_1d(axes), tests, strict=True):
        for m, (style, label_) in styles.items():
            if (test, m) not in curves:
                continue
            t, err = curves[(test, m)]
            k = min(50, len(err))  # 5 s at 10 labels a second
            ax.semilogy(t[k - 1 :], np.convolve(err, np.ones(k) / k, "valid"), style, lw=1,
                        label=label_)  # fmt: skip
        ax.set_ylabel("force error² (N²), 5 s mean")
        ax.set_title(test, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    np.atleast_1d(axes)[-1].set_xlabel("time since the flight's first label (s)")
    # below the panels: over them it hid the curves
    handles, labels = np.atleast_1d(axes)[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=7)
    fig.tight_layout(rect=(0, 0.16, 1, 1))
    for ext in ("png", "pdf"):
        fig.savefig(where / f"prequential_along_flight.{ext}", dpi=150)
    plt.close(fig)


def _by_wind(train, labels: list[Labels]) -> list[Labels]:
    """The labels of the flights of each training wind as one part."""
    winds = sorted({w for w, _ in train})
    return [
        Labels.concatenate([lb for (w, _), lb in zip(train, labels, strict=True) if w == wind])
        for wind in winds
    ]


def _truth_parameters(real_cfg, base_cfg, h_real) -> dict[str, float]:
    """The real vehicle's values of :data:`gpg.flight.identify.PARAMETERS`."""
    out = {
        "rotor.radius": float(real_cfg["rotor"]["radius"]),
        "rotor.chord": float(np.mean(np.asarray(real_cfg["rotor"]["chord_in"])
                                     / np.asarray(base_cfg["rotor"]["chord_in"]))),
        "airfoil.lift_slope": float(real_cfg["airfoil"]["lift_slope"]),
        "airfoil.alpha_zero_lift_deg": float(real_cfg["airfoil"]["alpha_zero_lift_deg"]),
        "airfoil.cd0": float(real_cfg["airfoil"]["cd0"]),
        "generator.wake_gain": float(h_real["wake_gain"]),
    }  # fmt: skip
    for i, a in enumerate("xyz"):
        out[f"drag_area.{a}"] = float(real_cfg["drag_area"][i])
    return out


def _spread_text(drift: dict[str, Any]) -> str:
    """A drift's spread for the report: one number, or one per named column."""
    s = drift["spread"]
    if isinstance(s, (int, float)):
        return f"{s:.3g}"
    return "{" + ", ".join(f"{c} {v:.3g}" for c, v in zip(drift["columns"], s, strict=True)) + "}"


def _identification_lines(ident: dict[str, Any]) -> list[str]:
    """The report's lines of one identification: each parameter and ``M``'s coefficients
    against the truth, in standard errors."""
    lines = []
    for k, p in ident["parameters"].items():
        lines.append(
            f"  {k}: {p['value']:.4g} ± {p['se']:.2g} (labels alone ± {p['se_data']:.2g}; "
            f"truth {p['truth']}, "
            f"file {p['nominal']:.4g}){'' if p['identified'] else ' NOT IDENTIFIED'}"
        )
    for k in ("thrust_coefficient", "torque_coefficient"):
        c = ident[k]
        lines.append(
            f"  {k} identified {c['identified']:.4g} ± {c['se']:.2g} (labels alone "
            f"± {c['se_data']:.2g}), truth {c['truth']:.4g} "
            f"({100 * (c['identified'] / c['truth'] - 1):+.1f} %, "
            f"{(c['identified'] - c['truth']) / c['se']:+.1f} se)"
        )
    return lines


def _thrust_line(th: dict[str, list[float]]) -> str:
    """The report's line of :func:`_thrust_per_command`."""
    return "  thrust per rotor at the calm flight's 10/50/90 % commands " + " / ".join(
        f"{a:.3g} N against {b:.3g} ({100 * e:+.1f} %)"
        for a, b, e in zip(th["identified"], th["truth"], th["relative_error"], strict=True)
    )


def _report(res) -> str:
    cols = [("test", "test", "s")]
    for m in ("prior", "corrected_regression", "values_only", "flights_physical",
              "identified_prior", "identified", "identified_rho", "identified_estimated_wind",
              "oracle"):  # fmt: skip
        cols.append((f"{m}_mse", f"{m} MSE", ".3g"))
    cols += [("oracle_mean_air_mse", "oracle, wind's mean, MSE", ".3g"),
             ("identified_true_air_mse", "identified, wind known, MSE", ".3g"),
             ("ridge_mse", "ridge MSE", ".3g"), ("noise_floor", "noise", ".3g")]  # fmt: skip
    for m in ("corrected_regression", "identified", "identified_rho", "identified_estimated_wind"):
        cols.append((f"{m}_coverage95", f"{m} cov95", ".3f"))  # fmt: skip
    lines = ["hard scenario, force MSE (N²) against the truth:", table(res["tests"], cols)]
    ident = res["identification"]
    lines += _identification_lines(ident)
    lines.append(_thrust_line(ident["thrust_per_command"]))
    if res.get("identification_with_speeds") is not None:
        lines.append("  the same flights with the ESC telemetry's rotor speeds (hard.with_speeds):")
        lines += _identification_lines(res["identification_with_speeds"])
    if res.get("identification_with_bench_curve") is not None:
        b = res["identification_with_bench_curve"]
        lines.append("  the same commands through a bench's motor curve (hard.bench_curve):")
        lines += _identification_lines(b)
        lines.append(_thrust_line(b["thrust_per_command"]))
    for name, c in res["coefficients"].items():
        lines.append(f"  {name}: the physical terms' prior times "
                     f"{c['basis_prior']['factors']} per output (basis_prior)")  # fmt: skip
        if "held_out_coverage95" in c["basis_prior"]:
            lines.append(
                f"    calibration {np.round(c['calibration'], 2).tolist()}, the prior's share "
                f"{None if c['prior_share'] is None else np.round(c['prior_share'], 3).tolist()}"
                "; each wind "
                "held out, the share of its labels in the 95 % band, per output: "
                f"{np.round(c['basis_prior']['held_out_coverage95'], 3).tolist()}"
            )
    for r in res["tests"]:
        m = "identified"
        lines.append(
            f"  {r['test']}, {m} per force component: MSE "
            f"{np.round(r[f'{m}_mse_components'], 3).tolist()}, coverage "
            f"{np.round(r[f'{m}_coverage95_components'], 3).tolist()}, mean squared "
            f"standardised error {np.round(r[f'{m}_z2_components'], 3).tolist()}"
        )
        bp = r[f"{m}_band_parts"]
        for where in ("all", "in_domain"):
            lines.append(
                f"    its band's terms, {where.replace('_', ' ')} (per force component, N²; "
                f"{bp['share_in_domain']:.3f} of the labels in the prior's domain): "
                + "; ".join(f"{k} {np.round(v, 3).tolist()}" for k, v in bp.get(where, {}).items())
            )
    for w in res["wind"]:
        lines.append(f"  wind {w['flight']}: estimated {np.round(w['estimated_mean'], 2)}, "
                     f"RMS error {w['rms_error']:.3f} m/s")  # fmt: skip
    ad = res["adaptation"]
    d = ad["drift"]
    lines.append(f"prequential (each label predicted before it is used); drift fitted: tau "
                 f"{d['tau']:.3g} s, spread {_spread_text(d)}, bias tau {d['bias_tau']:.3g} s "
                 f"and sd {d['bias_sd']:.3g}, bank {d['fast']}:")  # fmt: skip
    if ad.get("one_spread"):
        o = ad["one_spread"]
        lines.append(
            f"  fitted with one spread for all columns (tracked_one_spread): spread "
            f"{_spread_text(o)}, bias tau {o['bias_tau']:.3g} s, bank {o['fast']}"
        )
    pcols = [("test", "test", "s")]
    for m in ("none", "inducing", "tracked", "tracked_default", "tracked_other",
              "tracked_one_spread", "tracked_gusts", "tracked_gusts_vertical"):  # fmt: skip
        if f"{m}_mse" in ad["tests"][0]:
            pcols += [(f"{m}_mse", f"{m} MSE", ".3g"), (f"{m}_coverage95", f"{m} cov95", ".3f")]
    pcols.append(("noise_floor", "noise", ".3g"))
    lines.append(table(ad["tests"], pcols))
    if "stream_none_mse" in ad["tests"][0]:
        st = res["config"]["hard"]["stream"]
        lines.append(f"the same read from every sample at {st['rate']:g} Hz (saturation "
                     f"{st['saturation']:g}), scored at the same labels:")  # fmt: skip
        scols = [("test", "test", "s"), ("stream_labels", "stream labels", "d"),
                 ("stream_scored", "scored", "d")]  # fmt: skip
        taus = [f"inducing_tau_{float(v):g}" for v in res["config"]["adapt"].get("stream_taus")
                or ()]  # fmt: skip
        fitted = [_fitted_key(name) for name in ad.get("forgetting") or {}]
        for m in ("none", "inducing", *taus, *fitted, "bank", "bank_fitted", "tracked",
                  "tracked_gusts",
                  "tracked_fit_stream", "tracked_gusts_fit_stream"):  # fmt: skip
            if f"stream_{m}_mse" in ad["tests"][0]:
                scols += [(f"stream_{m}_mse", f"{m} MSE", ".3g"),
                          (f"stream_{m}_coverage95", f"{m} cov95", ".3f")]  # fmt: skip
        scols.append(("noise_floor", "noise", ".3g"))
        lines.append(table(ad["tests"], scols))
        for name, fo in (ad.get("forgetting") or {}).items():
            tau, c = (" ".join(f"{v:.3g}" for v in np.atleast_1d(fo[k])) for k in ("tau", "factor"))
            lines.append(
                f"  inducing_fitted ({name.replace('_', ' ')} band): tau {tau} s and "
                f"{c} times each discrepancy's variance, fitted on the training "
                f"flights' streams ({fo['labels']} rows, {fo['log_likelihood']:.4g} nats a row)"
            )
    if ad.get("bank_fit"):
        bf = ad["bank_fit"]
        lines.append(
            f"  bank_fitted: weight forgetting time {bf['weight_tau']:.3g} s fitted on the "
            f"training flights' streams ({bf['labels']} rows, scored {bf['ahead']} ahead: "
            f"{bf['log_likelihood']:.4g} nats a row, the members alone "
            + " / ".join(f"{v:.4g}" for v in bf["members"])
            + "); its 95 % band held "
            + " / ".join(f"{v:.3f}" for v in bf.get("coverage95", ()))
            + " of those rows' labels (Fx Fy Fz Mx My Mz, the labels' noise in the band)"
        )
    if "stream_hindsight_tracked_mse" in ad["tests"][0]:
        lines.append(
            "in hindsight: each term fitted on the whole stream without forgetting, "
            "scored at the labels (at a steady wind, the least error it reaches):"
        )
        lines.append(
            table(
                ad["tests"],
                [("test", "test", "s")]
                + [
                    (f"stream_hindsight_{m}_mse", f"{m} MSE", ".3g")
                    for m in ("tracked", "inducing")
                ],
            )
        )
    if ad.get("spread_sweep"):
        lines.append(
            "the fitted drift with one spread for all columns swept, beside the fitted ones: "
            "the held-out log likelihood on "
            "the training winds (nats per label, what fit_drift maximises) and each "
            "test flight's prequential force MSE, coverage and labels' log density:"
        )
        srows, scols = [], [("spread", "spread", "s"), ("ll", "held-out ll", ".4g")]
        for t in ad["tests"]:
            scols += [(f"{t['test']}_{k}", f"{t['test']} {k}", f) for k, f in
                      (("mse", ".3g"), ("cov", ".3f"), ("lpd", ".4g"))]  # fmt: skip
        for sw in ad["spread_sweep"]:
            key = sw["model"]
            r = {"spread": f"{key}: {_spread_text(sw)}", "ll": sw["held_out_log_likelihood"]}
            for t in ad["tests"]:
                r.update({f"{t['test']}_mse": t[f"{key}_mse"],
                          f"{t['test']}_cov": t[f"{key}_coverage95"],
                          f"{t['test']}_lpd": t[f"{key}_lpd_labels"]})  # fmt: skip
            srows.append(r)
        lines.append(table(srows, scols))
    if ad.get("today"):
        lines.append(
            "today's adaptation (adapt on the correction before the physical basis), forgetting "
            f"times {ad['today']['taus']} s, the best of them, reading the labels and every sample:"
        )
        tcols = [("test", "test", "s")]
        for reading in ("labels", "stream"):
            tcols += [(f"{reading}_best_mse", f"{reading} MSE", ".3g"),
                      (f"{reading}_best_tau", "tau", "g"),
                      (f"{reading}_best_coverage95", "cov95", ".3f")]  # fmt: skip
        lines.append(table(ad["today"]["tests"], tcols))
    gcols = [("test", "test", "s"), ("after_gap_share", "share after a gap", ".2f")]
    for m in ("none", "inducing", "tracked", "tracked_gusts"):
        if f"{m}_mse" not in ad["tests"][0]:
            continue
        gcols += [(f"{m}_mse_after_gap", f"{m} after a gap", ".3g"),
                  (f"{m}_mse_no_gap", f"{m} otherwise", ".3g")]  # fmt: skip
    lines.append("prequential MSE on the labels after a stretch without labels, and on the rest:")
    lines.append(table(ad["tests"], gcols))
    ecols = [("test", "test", "s")]
    for m in ("none", "inducing", "tracked", "tracked_other", "tracked_one_spread", *(
            f"tracked_spread_{s:g}" for s in ad.get("spreads", ()))):  # fmt: skip
        if f"{m}_mse_first_10s" in ad["tests"][0]:
            ecols += [(f"{m}_mse_first_10s", f"{m} first 10 s", ".3g"),
                      (f"{m}_mse_after_10s", f"{m} after", ".3g")]  # fmt: skip
    lines.append("prequential MSE in the flight's first 10 s, and after:")
    lines.append(table(ad["tests"], ecols))
    u = ad["tracked_update"]
    lines.append(f"tracked update from Python: {u['median_ms']:.3f} ms median (p10 "
                 f"{u['p10_ms']:.3f}, p90 {u['p90_ms']:.3f}, {u['n']} updates)")  # fmt: skip
    if "tracked_gusts_update" in ad:
        u = ad["tracked_gusts_update"]
        lines.append(f"with the wind state {ad['gusts']}: {u['median_ms']:.3f} ms median (p10 "
                     f"{u['p10_ms']:.3f}, p90 {u['p90_ms']:.3f})")  # fmt: skip
    if "bank_update" in ad:
        u = ad["bank_update"]
        lines.append(f"bank update from Python: {u['median_ms']:.3f} ms median (p10 "
                     f"{u['p10_ms']:.3f}, p90 {u['p90_ms']:.3f}; "
                     f"{u['bytes_end']} bytes)")  # fmt: skip
    lines.append("stages (s): " + ", ".join(f"{k} {v:.0f}" for k, v in res["stages_s"].items()))
    return "\n".join(lines)
