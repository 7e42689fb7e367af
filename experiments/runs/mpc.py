"""Cautious MPC on the surrogate against the geometric controller in gusts
(``python -m experiments.mpc``).

The plant is the vehicle flown on the surrogate (its mean, float64, 100 Hz), in a wind made of
a constant mean, a sinusoidal gust and Dryden turbulence (:mod:`gpg.envs.wind`), the same wind
for every controller. The mission is the paper's round trip (``simulate``'s flight).

* **geometric**: gpg's SE(3) controller designed on ``M`` (no aerodynamic model, no wind).
* **mpc**: MPPI (:class:`gpg.mpc.MPPI`) over an acceleration offset ``u`` (3,) added to the
  reference the same geometric controller tracks (a reference governor: the inner loop keeps
  attitude and motors, the MPC anticipates what the inner loop's model lacks). Its prediction
  model is the closed loop on the surrogate's mean (float32), with the wind measured at the
  solve held over the horizon. Cost: squared position and velocity errors, ``u`` and its rate.
* **mpc_cautious**: the same, plus ``β`` times the surrogate's predicted standard deviation of
  the aerodynamic force along each sampled path, linearised about the nominal path with its
  gradient (:meth:`gpg.mpc.Dynamics.linearize`'s ingredients: the variance and its Jacobian):
  it steers away from states where the model is unsure (outside or at the edge of its data).

* **casadi** (``casadi.enabled``): a gradient-based MPC of the same offsets through CasADi's
  ``Opti`` and IPOPT on the exported surrogate (:mod:`experiments.runs.mpc_casadi`), its variance as
  the cautious term (linearised about the previous plan, or exact), at its own rate
  (``casadi.dt``).

Measured: tracking error (RMS, max), in-domain share, the force standard deviation met along
the flight, and the wall time of every MPC solve (median, p95) on this machine.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from experiments.runs.common import flight_setup
from experiments.runs.output import report
from experiments.runs.timing import machine
from gpg.envs.wind import Dryden
from gpg.mpc import MPPI, pack, unpack
from gpg.quadrotor.control import GeometricController, Reference, WaypointPlan
from gpg.quadrotor.dynamics import Quadrotor, State, Wind
from gpg.quadrotor.frames import euler_from_R
from gpg.quadrotor.vehicle import Vehicle
from gpg.runtime import float64, write_json
from gpg.surrogate import Surrogate, SurrogateAero, predict_state


def force_std(sur: Surrogate, x: jax.Array, wind: jax.Array) -> jax.Array:
    """The surrogate's predictive standard deviation of the aerodynamic force (N, the root of
    the summed component variances) at flat state ``x`` in ``wind``."""
    s = unpack(x)
    p = predict_state(sur, s.rpm, euler_from_R(s.R), s.v - wind, True)
    return jnp.sqrt(jnp.sum(p.variance[:3]) + 1e-12)


class Governor(eqx.Module):
    """The MPC's prediction model: the geometric controller tracking ``plan`` shifted by the
    acceleration offset ``u``, flying the surrogate's mean in a constant wind."""

    quad: Quadrotor
    ctrl: GeometricController
    plan: WaypointPlan
    wind: jax.Array
    dt: float = eqx.field(static=True)

    def __call__(self, x, u, t):
        s = unpack(x)
        ref = self.plan(t)
        ref = Reference(ref.p, ref.v, ref.a + u, ref.yaw)
        new, _ = self.quad.step(s, self.ctrl(s, ref), t, self.dt, Wind.constant(self.wind))
        return pack(new)


def make_solver(sur32: Surrogate, vehicle: Vehicle, ctrl, plan, c: dict[str, Any], beta: float):
    """A jitted ``solve(key, x0, u_nom, t0, wind0) -> (u_new, info)`` for one MPC step."""
    H, dt = int(c["horizon"]), float(c["dt"])
    dtype = jnp.float32
    quad = Quadrotor.from_vehicle(vehicle, SurrogateAero(sur32))
    quad = jax.tree.map(lambda a: jnp.asarray(a, dtype) if eqx.is_inexact_array(a) else a, quad)
    ctrl32 = jax.tree.map(lambda a: jnp.asarray(a, dtype) if eqx.is_inexact_array(a) else a, ctrl)
    plan32 = jax.tree.map(lambda a: jnp.asarray(a, dtype) if eqx.is_inexact_array(a) else a, plan)
    w = {k: float(c[k]) for k in ("w_position", "w_velocity", "w_control", "w_rate")}
    limit = float(c["max_offset"])

    @jax.jit
    def solve(key, x0, u_nom, t0, wind0):
        x0, u_nom, t0, wind0 = (jnp.asarray(a, dtype) for a in (x0, u_nom, t0, wind0))
        model = Governor(quad, ctrl32, plan32, wind0, dt)
        mppi = MPPI(
            dynamics=model,
            cost=lambda xs, us, ts: 0.0,
            noise_std=jnp.full(3, float(c["noise_std"]), dtype),
            u_min=jnp.full(3, -limit, dtype),
            u_max=jnp.full(3, limit, dtype),
            temperature=float(c["temperature"]),
            dt=dt,
            horizon=H,
            samples=int(c["samples"]),
            knots=int(c["knots"]),
        )
        if beta > 0:
            # Caution: σ_F along the nominal path and its gradient (one reverse pass per knot),
            # then first order about it for every sample (the variance's Jacobian at work).
            # At `caution_points` evenly spaced steps of the horizon, each standing for its share.
            xs_nom, _ = mppi.rollout(x0, u_nom, t0)
            at = np.linspace(0, H - 1, int(c["caution_points"])).round().astype(int)
            sig, grad = jax.lax.map(
                jax.value_and_grad(lambda x: force_std(sur32, x, wind0)), xs_nom[at]
            )
            xs_nom = xs_nom[at]
            share = H / at.size
        else:
            xs_nom = sig = grad = None

        def cost(xs, us, ts):
            ref = jax.vmap(plan32)(ts)
            e_p = xs[:, :3] - ref.p
            e_v = xs[:, 3:6] - ref.v
            du = jnp.diff(jnp.concatenate([u_nom[:1], us]), axis=0)
            total = (
                w["w_position"] * jnp.sum(e_p * e_p)
                + w["w_velocity"] * jnp.sum(e_v * e_v)
                + w["w_control"] * jnp.sum(us * us)
                + w["w_rate"] * jnp.sum(du * du)
            )
            if beta > 0:
                s = sig + jnp.sum(grad * (xs[at] - xs_nom), axis=1)
                total = total + beta * share * jnp.sum(jnp.maximum(s, 0.0))
            return total

        mppi = eqx.tree_at(lambda m: m.cost, mppi, cost)
        return mppi.solve(key, x0, u_nom, t0)

    return solve


def _wind_sequence(key, c: dict[str, Any], n: int, dt: float) -> np.ndarray:
    """The wind (n, 3) every controller flies in: mean + sinusoidal gust + Dryden."""
    mean = jnp.asarray(c["mean"], float)
    gust = jnp.asarray(c["gust_amplitude"], float)
    turb = Dryden.create(key, jnp.asarray(float(c["turbulence"])), jnp.asarray(10.0), mean, dt)
    t = dt * jnp.arange(n)

    def step(d, k):
        d = d.step(k)
        return d, d.velocity()

    _, turb_v = jax.lax.scan(step, turb, jax.random.split(jax.random.fold_in(key, 1), n))
    g = gust[None] * jnp.sin(2 * jnp.pi * t[:, None] / float(c["gust_period"]))
    return np.asarray(mean[None] + g + turb_v)


OPTIONS = {
    "figures": "bool",
    "sync_dispatch": "bool",
    "seed": "index",
    "cache_dir": "path",
    "surrogate_checkpoint": "path?",
}  # the run's own keys besides its config groups (runs.common.check_options)


@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Fly the three controllers through the same gusts; write ``results.json`` (and a figure)
    into ``outdir``."""
    outdir = Path(outdir)
    vehicle, sur = flight_setup(cfg, OPTIONS)
    c = cfg["mpc"]
    _check_mpc(c)
    ctrl = GeometricController.create(vehicle, sur.simple, cfg["controller"])
    fl = cfg["flight"]
    plan = WaypointPlan.create(
        fl["waypoints"], start_time=fl["start_time"], leg_time=fl["leg_time"], yaw=fl["yaw"]
    )
    dt = float(fl["dt"])
    every = int(round(float(c["dt"]) / dt))
    if every < 1 or abs(every * dt - float(c["dt"])) > 1e-9:
        raise ValueError(f"mpc.dt ({c['dt']}) must be a whole number of flight.dt ({dt})")
    n = int(round((float(plan.end_time) + float(fl["settle_time"])) / dt))
    key = jax.random.key(int(cfg["seed"]))
    winds = _wind_sequence(key, cfg["wind"], n, dt)
    plant = Quadrotor.from_vehicle(vehicle, SurrogateAero(sur))
    s0 = State.hover(fl["waypoints"][0], sur.simple.hover_rpm(float(vehicle.weight)))
    sur32 = sur.astype(jnp.float32)

    @jax.jit
    def plant_step(s, offset, t, wind):
        ref = plan(t)
        ref = Reference(ref.p, ref.v, ref.a + offset, ref.yaw)
        new, wr = plant.step(s, ctrl(s, ref), t, dt, Wind.constant(wind))
        return new, wr.in_domain, force_std(sur, pack(s), wind)

    runs = {"geometric": None, "mpc": 0.0, "mpc_cautious": float(c["caution"])}
    flights, traces = {}, {}
    for name, beta in runs.items():
        solve = None if beta is None else make_solver(sur32, vehicle, ctrl, plan, c, beta)
        flights[name], traces[name] = _fly(
            solve, plant_step, s0, plan, winds, key, dt, every, int(c["horizon"])
        )
    cas = {**c, **cfg.get("casadi", {})}
    if cas.get("enabled", False):  # IPOPT on the exported surrogate (experiments.runs.mpc_casadi)
        from experiments.runs.mpc_casadi import make_casadi_solver

        every_c = int(round(float(cas["dt"]) / dt))
        if every_c < 1 or abs(every_c * dt - float(cas["dt"])) > 1e-9:
            raise ValueError(f"casadi.dt ({cas['dt']}) must be a whole number of flight.dt")
        solve = make_casadi_solver(sur, vehicle, ctrl, plan, cas, float(cas["caution"]))
        flights["casadi"], traces["casadi"] = _fly(
            solve, plant_step, s0, plan, winds, key, dt, every_c, int(cas["horizon"])
        )
    figures = []
    if cfg.get("figures", True):
        figures = [_figure(traces, dt, outdir / "figures")]
    out = {
        "machine": machine(),
        "surrogate": {"model": sur.model_name},
        "flights": flights,
        "figures": [str(f.relative_to(outdir)) for f in figures],
        "config": cfg,
    }
    write_json(outdir / "results.json", out)
    _report(flights)
    return out


def _fly(solve, plant_step, s0, plan, winds, key, dt: float, every: int, horizon: int):
    """One flight of ``len(winds)`` steps: MPPI's offsets every ``every`` steps when ``solve``
    is given (the geometric controller alone otherwise). Its record and tracking errors."""
    s, u_nom = s0, np.zeros((horizon, 3))
    offset = np.zeros(3)
    p, ref_p, ok, sig, solve_s = [], [], [], [], []
    for k in range(len(winds)):
        t = k * dt
        if solve is not None and k % every == 0:
            args = (jax.random.fold_in(key, 1000 + k), pack(s), u_nom, t, winds[k])
            if k == 0:
                jax.block_until_ready(solve(*args))  # compile outside the timing
            t0 = time.perf_counter()
            u_new, _ = jax.block_until_ready(solve(*args))
            solve_s.append(time.perf_counter() - t0)
            offset = np.asarray(u_new[0], float)
            u_nom = np.asarray(MPPI.shift(u_new))
        p.append(np.asarray(s.p))
        ref_p.append(np.asarray(plan(t).p))
        s, in_dom, sd = plant_step(s, jnp.asarray(offset), t, jnp.asarray(winds[k]))
        ok.append(bool(in_dom))
        sig.append(float(sd))
    p, ref_p = np.array(p), np.array(ref_p)
    err = np.linalg.norm(p - ref_p, axis=1)
    record = {
        "rms_tracking_error_m": float(np.sqrt(np.mean(err**2))),
        "max_tracking_error_m": float(err.max()),
        "in_domain_fraction": float(np.mean(ok)),
        "mean_force_std_N": float(np.mean(sig)),
        "finite": bool(np.all(np.isfinite(p))),
    }
    if solve_s:
        record.update(
            solve_ms_median=1e3 * float(np.median(solve_s)),
            solve_ms_p95=1e3 * float(np.percentile(solve_s, 95)),
            solves=len(solve_s),
        )
    return record, err


def _report(flights: dict[str, dict[str, Any]]) -> None:
    for name, f in flights.items():
        solve = (
            f" solve {f['solve_ms_median']:.1f} ms (p95 {f['solve_ms_p95']:.1f})"
            if "solves" in f
            else ""
        )
        report(
            f"{name:13s} RMS error {f['rms_tracking_error_m']:.3f} m, "
            f"max {f['max_tracking_error_m']:.3f} m, "
            f"in domain {100 * f['in_domain_fraction']:.0f} %, "
            f"mean σ_F {f['mean_force_std_N']:.3f} N{solve}"
        )


def _check_mpc(c: dict[str, Any]) -> None:
    """Every MPC option present and in range, before any work."""
    need = {
        "dt": float,
        "horizon": int,
        "samples": int,
        "knots": int,
        "caution_points": int,
        "noise_std": float,
        "temperature": float,
        "max_offset": float,
        "caution": float,
        "w_position": float,
        "w_velocity": float,
        "w_control": float,
        "w_rate": float,
    }
    for k, kind in need.items():
        v = c.get(k)
        if isinstance(v, bool) or not isinstance(v, int | float) or (kind is int and int(v) != v):
            raise ValueError(
                f"mpc.{k} must be a{'n integer' if kind is int else ' number'}, got {v!r}"
            )
        if v < 0 or (k not in ("caution", "w_control", "w_rate", "w_velocity") and v <= 0):
            raise ValueError(f"mpc.{k} must be > 0, got {v!r}")
    if c["horizon"] < 2 or c["samples"] < 2:
        raise ValueError("mpc.horizon and mpc.samples must be >= 2")
    if not 2 <= c["knots"] <= c["horizon"] or not 1 <= c["caution_points"] <= c["horizon"]:
        raise ValueError("mpc.knots must be in [2, horizon] and mpc.caution_points in [1, horizon]")


def _figure(traces: dict[str, np.ndarray], dt: float, folder: Path) -> Path:
    from matplotlib.figure import Figure

    folder.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(7, 3.2))
    ax = fig.add_subplot()
    for name, e in traces.items():
        ax.plot(dt * np.arange(e.size), e, label=name)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tracking error (m)")
    ax.legend()
    fig.tight_layout()
    path = folder / "tracking_error.png"
    fig.savefig(path, dpi=120)
    return path
