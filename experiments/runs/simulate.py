"""Closed-loop flights (``python -m experiments.simulate``), as the paper's last section.

The same geometric controller (designed on the simplified model ``M``) flies a two-waypoint
round trip twice: with ``M`` as the dynamics, and with a GP surrogate of the mid-fidelity data.
Recorded: time to reach each waypoint, overshoot, altitude loss, rotor speeds, the surrogate's
microphone levels along both flights, and the share of the flight inside the surrogate's
training domain. Then the throughput of the surrogate dynamics: one environment against real
time, and a batch of environments with randomised targets and wind.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from experiments.runs.common import flight_setup
from experiments.runs.output import report
from experiments.runs.timing import machine
from gpg.quadrotor.control import GeometricController, WaypointPlan
from gpg.quadrotor.dynamics import Quadrotor, SimpleAero, State, Wind
from gpg.quadrotor.metrics import flight_metrics
from gpg.quadrotor.rollout import batched_rollouts, simulate
from gpg.runtime import float64, write_json
from gpg.surrogate import SurrogateAero


def _wind(w: dict[str, Any]) -> Wind:
    return Wind(
        jnp.asarray(w["mean"], dtype=float),
        jnp.asarray(w["gust_amplitude"], dtype=float),
        jnp.asarray(float(w["gust_period"])),
        jnp.asarray(0.0),
    )


def _single_env_speed(fly, quad, s0, n_steps: int, dt: float) -> dict[str, Any]:
    """Wall time of one compiled closed-loop episode against the time it simulates."""
    t0 = time.perf_counter()
    jax.block_until_ready(fly(quad, s0))
    wall = time.perf_counter() - t0
    return {
        "single_env_steps": n_steps,
        "single_env_wall_s": wall,
        "single_env_realtime_factor": n_steps * dt / wall,
    }


def _batch_speed(quad, ctrl, s0, dt: float, ro: dict[str, Any]) -> dict[str, Any]:
    """Environment-steps per second of vmapped random episodes (compiled first, then timed
    on a fresh key), and how many of their steps stayed in the training domain."""
    key = jax.random.key(int(ro["seed"]))
    batch = jax.jit(
        lambda q, k: batched_rollouts(
            q,
            ctrl,
            k,
            s0,
            n_envs=int(ro["n_envs"]),
            n_steps=int(ro["n_steps"]),
            dt=dt,
            target_range=float(ro["target_range"]),
            wind_max=float(ro["wind_max"]),
            gust_max=float(ro["gust_max"]),
        )
    )
    jax.block_until_ready(batch(quad, key))  # compile
    t0 = time.perf_counter()
    _, btr = jax.block_until_ready(batch(quad, jax.random.fold_in(key, 1)))
    wall = time.perf_counter() - t0
    return {
        "batch_envs": int(ro["n_envs"]),
        "batch_steps": int(ro["n_steps"]),
        "batch_wall_s": wall,
        "batch_env_steps_per_s": ro["n_envs"] * ro["n_steps"] / wall,
        "batch_in_domain_fraction": float(np.mean(np.asarray(btr.in_domain))),
        "batch_finite": bool(np.all(np.isfinite(np.asarray(btr.p)))),
    }


def _report(flights: dict[str, Any], speed: dict[str, Any]) -> None:
    for name, f in flights.items():
        reach = ", ".join(
            "never" if leg["time_to_reach_s"] is None else f"{leg['time_to_reach_s']:.2f} s"
            for leg in f["legs"]
        )
        report(
            f"{name:11s} reach {reach}; overshoot "
            + ", ".join(f"{leg['overshoot_m']:.2f} m" for leg in f["legs"])
            + f"; altitude loss {f['altitude_loss_m']:.2f} m; mean rpm {f['mean_rpm']:.0f} "
            f"(std {f['rpm_std']:.0f}); in domain {100 * f['in_domain_fraction']:.0f} %"
        )
    report(
        f"one env: {speed['single_env_realtime_factor']:.0f}x real time; "
        f"{speed['batch_envs']} envs: {speed['batch_env_steps_per_s']:,.0f} env-steps/s"
    )


OPTIONS = {
    "figures": "bool",
    "sync_dispatch": "bool",
    "cache_dir": "path",
    "surrogate_checkpoint": "path?",
}  # the run's own keys besides its config groups (runs.common.check_options)


# Long by design: the experiment's steps in order (config, fit, two flights, batched
# throughput, write).
@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Fit the surrogate, fly the round trip on M and on the surrogate, time the batched
    environments, and write ``results.json`` and the figures into ``outdir``."""
    outdir = Path(outdir)
    vehicle, sur = flight_setup(cfg, OPTIONS)
    simple = sur.simple
    ctrl = GeometricController.create(vehicle, simple, cfg["controller"])
    fl = cfg["flight"]
    plan = WaypointPlan.create(
        fl["waypoints"], start_time=fl["start_time"], leg_time=fl["leg_time"]
    )
    dt = float(fl["dt"])
    n_steps = int(round((float(plan.end_time) + fl["settle_time"]) / dt))
    wind = _wind(cfg["wind"])
    s0 = State.hover(fl["waypoints"][0], simple.hover_rpm(float(vehicle.weight)))
    hold = bool(fl.get("hold_aero", True))
    quads = {
        "simplified": Quadrotor.from_vehicle(vehicle, SimpleAero(simple), hold_aero=hold),
        "surrogate": Quadrotor.from_vehicle(vehicle, SurrogateAero(sur), hold_aero=hold),
    }
    fly = jax.jit(lambda q, s: simulate(q, ctrl, plan, wind, s, dt, n_steps))
    traces, flights = {}, {}
    for name, quad in quads.items():
        _, tr = fly(quad, s0)
        traces[name] = jax.block_until_ready(tr)
        flights[name] = flight_metrics(tr, plan, dt, fl["reach_radius"])

    # The surrogate's microphone levels along the simplified flight (M has no noise model).
    tr = traces["simplified"]
    wind_t = jax.vmap(wind)(tr.t)
    noise_simple = np.asarray(
        sur.predict_batch(tr.rpm, tr.euler, tr.v - wind_t, mean_only=True).levels
    )
    speed = {
        **_single_env_speed(fly, quads["surrogate"], s0, n_steps, dt),
        **_batch_speed(quads["surrogate"], ctrl, s0, dt, cfg["rollouts"]),
    }
    figures = []
    if cfg.get("figures", True):
        from experiments.runs import plots

        figures = plots.flight_figures(traces, noise_simple, plan, outdir / "figures")
    out = {
        "machine": machine(),
        "surrogate": {"model": sur.model_name, "bytes": sur.nbytes()},
        "flights": flights,
        "speed": speed,
        "figures": [str(p.relative_to(outdir)) for p in figures],
        "config": cfg,
    }
    write_json(outdir / "results.json", out)
    _report(flights, speed)
    return out
