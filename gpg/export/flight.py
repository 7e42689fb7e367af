"""The parameters of a closed-loop flight for the C flight program of ``examples/c_flight``:
the vehicle's rigid body and motors, the geometric controller's gains, the waypoint plan,
the wind and the initial state, as a C header, from the same objects gpg flies
(:func:`gpg.quadrotor.rollout.simulate`), so that the C flight and gpg's match."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gpg._io import atomic_write

if TYPE_CHECKING:
    from gpg.quadrotor.control import GeometricController, WaypointPlan
    from gpg.quadrotor.dynamics import Quadrotor, State, Wind

__all__ = ["write_params"]


def write_params(
    path: str | Path,
    *,
    model: str,
    quad: Quadrotor,
    ctrl: GeometricController,
    plan: WaypointPlan,
    wind: Wind,
    s0: State,
    dt: float,
    n_steps: int,
) -> Path:
    """Write ``flight_params.h``, the flight's parameters as C constants (full precision).

    The C flight holds the aerodynamic wrench over each step and starts at rest, so the
    flight given must too, for gpg's and the C flight to match.

    Args:
        path: the header to write.
        model: the exported model's name (a C identifier): ``<model>.c`` as written by
            :func:`gpg.export.to_c`, whose ``<model>_mean`` is the aerodynamics.
        quad: the rigid body and motors (:class:`gpg.quadrotor.dynamics.Quadrotor`; its
            aerodynamics are not read), with ``hold_aero``.
        ctrl: the geometric controller (:class:`gpg.quadrotor.control.GeometricController`).
        plan: the waypoint plan (``WaypointPlan``).
        wind: the wind (``Wind``): its mean and sinusoidal gust.
        s0: the initial ``State``, at rest (``v`` and ``w`` zero).
        dt: the step (s).
        n_steps: steps flown.

    Returns:
        ``path``, written.

    Raises:
        ValueError: if ``model`` is not a C identifier, ``quad`` does not hold the
            aerodynamics over a step, or ``s0`` is not at rest.
    """
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
    lines += [_c_array(k, v) for k, v in arrays.items()]
    path = Path(path)
    atomic_write(path, ("\n".join(lines) + "\n").encode())
    return path


def _c_array(key: str, value: object) -> str:
    """``static const double KEY[n]... = {...};`` of a vector or matrix, values exact."""
    a = np.asarray(value, dtype=float)
    dims = "".join(f"[{n}]" for n in a.shape)
    if a.ndim == 2:
        body = ", ".join("{" + ", ".join(f"{x:.17g}" for x in row) + "}" for row in a)
    else:
        body = ", ".join(f"{x:.17g}" for x in a)
    return f"static const double {key}{dims} = {{{body}}};"
