"""The parameters of a closed-loop flight for the C flight program of ``examples/c_flight``:
the vehicle's rigid body and motors, the geometric controller's gains, the waypoint plan,
the wind and the initial state, as a C header, from the same objects gpg flies
(:func:`gpg.quadrotor.rollout.simulate`), so that the C flight and gpg's match."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gpg._io import atomic_write


def write_params(
    path: str | Path, *, model: str, quad, ctrl, plan, wind, s0, dt: float, n_steps: int
) -> Path:
    """Write ``flight_params.h`` for a model exported as ``<model>.c`` by
    :func:`gpg.export.to_c` (its ``<model>_mean`` is the aerodynamics). ``quad`` a
    :class:`gpg.quadrotor.dynamics.Quadrotor` (its aerodynamics are not read), ``ctrl`` a
    :class:`gpg.quadrotor.control.GeometricController`, ``plan`` a ``WaypointPlan``, ``wind``
    a ``Wind``, ``s0`` the initial ``State``; ``dt`` s and ``n_steps`` the flight."""
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", model):
        raise ValueError(f"model must be a C identifier, got {model!r}")
    if quad.hold_aero is not True:
        raise ValueError("the C flight holds the aerodynamic wrench over each step (hold_aero)")
    scalars = {
        "MASS": quad.mass,
        "GRAVITY": quad.gravity,
        "MOTOR_TAU": quad.motor_time_constant,
        "RPM_MIN": quad.rpm_min,
        "RPM_MAX": quad.rpm_max,
        "MAX_TILT": ctrl.max_tilt,
        "START_TIME": plan.start_time,
        "LEG_TIME": plan.leg_time,
        "YAW0": plan.yaw0,
        "TURN_FRACTION": plan.turn_fraction,
        "GUST_PERIOD": wind.gust_period,
        "GUST_PHASE": wind.gust_phase,
        "DT": dt,
    }
    arrays = {
        "INERTIA": quad.inertia,
        "KP": ctrl.kp,
        "KV": ctrl.kv,
        "KR": ctrl.kR,
        "KW": ctrl.kw,
        "ALLOC_INV": ctrl.alloc_inv,
        "WAYPOINTS": plan.waypoints,
        "YAWS": plan.yaw,
        "WIND_MEAN": wind.mean,
        "WIND_GUST": wind.gust_amplitude,
        "P0": s0.p,
        "Q0": s0.q,
        "RPM0": s0.rpm,
    }
    if np.any(np.asarray(s0.v)) or np.any(np.asarray(s0.w)):
        raise ValueError("the C flight starts at rest (s0.v and s0.w zero)")
    lines = [
        "/* flight_params.h: written by gpg.export.flight.write_params */",
        f'#include "{model}.h"',
        f"#define AERO {model}_mean",
        f"#define N_STEPS {int(n_steps)}",
        f"#define N_WAYPOINTS {np.asarray(plan.waypoints).shape[0]}",
    ]
    lines += [f"#define {k} ({float(np.asarray(v)):.17g})" for k, v in scalars.items()]
    for k, v in arrays.items():
        a = np.asarray(v, dtype=float)
        dims = "".join(f"[{n}]" for n in a.shape)
        if a.ndim == 2:
            body = ", ".join("{" + ", ".join(f"{x:.17g}" for x in row) + "}" for row in a)
        else:
            body = ", ".join(f"{x:.17g}" for x in a)
        lines.append(f"static const double {k}{dims} = {{{body}}};")
    path = Path(path)
    atomic_write(path, ("\n".join(lines) + "\n").encode())
    return path
