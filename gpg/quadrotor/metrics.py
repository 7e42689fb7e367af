"""Figures of merit of a closed-loop flight (:func:`gpg.quadrotor.rollout.simulate`): time
to reach each waypoint, overshoot, altitude loss, tracking error, rotor speeds, the share of
the flight in the surrogate's domain. NumPy on a finished trace, not part of any program."""

from __future__ import annotations

from typing import Any

import numpy as np

from gpg.quadrotor.control import WaypointPlan
from gpg.quadrotor.rollout import Trace

__all__ = ["flight_metrics"]


def flight_metrics(tr: Trace, plan: WaypointPlan, dt: float, radius: float) -> dict[str, Any]:
    """How a closed-loop flight went, leg by leg, as the paper's last section reports it.

    Args:
        tr: the flight (:func:`gpg.quadrotor.rollout.simulate`'s trace).
        plan: the waypoints it flew (its legs' start and duration).
        dt: the step the flight was simulated with, in s (recorded beside the metrics).
        radius: how close to a waypoint counts as reaching it, in m.

    Returns:
        ``legs`` (per leg: the waypoint, the time from the leg's start to the first entry
        within ``radius`` of it, None if never, and the overshoot past it along the leg, m),
        ``altitude_loss_m`` (the largest sink below the reference altitude; z is down), the
        largest and RMS tracking errors, the rotor speeds' mean and spread, the share of the
        flight inside the surrogate's training domain, the final position and ``dt``.
    """
    p, ref = np.asarray(tr.p), np.asarray(tr.ref_p)
    t = np.asarray(tr.t)
    w = np.asarray(plan.waypoints)
    legs = []
    for k in range(len(w) - 1):
        t0 = float(plan.start_time) + k * float(plan.leg_time)
        t1 = t0 + float(plan.leg_time) if k < len(w) - 2 else t[-1]
        sel = (t >= t0) & (t <= t1)
        d = w[k + 1] - w[k]
        u = d / (np.linalg.norm(d) + 1e-12)
        dist = np.linalg.norm(p[sel] - w[k + 1], axis=1)
        inside = np.flatnonzero(dist <= radius)
        past = (p[sel] - w[k + 1]) @ u
        legs.append(
            {
                "waypoint": w[k + 1].tolist(),
                "time_to_reach_s": float(t[sel][inside[0]] - t0) if inside.size else None,
                "overshoot_m": float(max(past.max(), 0.0)),
            }
        )
    rpm = np.asarray(tr.rpm)
    return {
        "legs": legs,
        "altitude_loss_m": float(max(np.max(p[:, 2] - ref[:, 2]), 0.0)),
        "max_tracking_error_m": float(np.max(np.linalg.norm(p - ref, axis=1))),
        "rms_tracking_error_m": float(np.sqrt(np.mean(np.sum((p - ref) ** 2, axis=1)))),
        "mean_rpm": float(rpm.mean()),
        "rpm_std": float(rpm.std()),
        "in_domain_fraction": float(np.mean(np.asarray(tr.in_domain))),
        "final_position": p[-1].tolist(),
        "dt": dt,
    }
