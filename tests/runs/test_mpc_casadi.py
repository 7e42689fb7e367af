"""The CasADi MPC (gpg/runs/mpc_casadi.py) on a small surrogate: one IPOPT solve from hover
behind a moving reference returns offsets inside their bounds that push toward the reference,
and a second solve warm-starts from the first."""

import numpy as np
import pytest

from gpg.mpc import pack
from gpg.quadrotor.control import GeometricController, WaypointPlan
from gpg.quadrotor.dynamics import State
from gpg.quadrotor.vehicle import Vehicle, vehicle_config
from tests.export.models import fitted

pytest.importorskip("casadi")

C = {
    **{"dt": 0.1, "horizon": 5, "knots": 2, "caution_points": 2, "max_offset": 4.0},
    **{"w_position": 10.0, "w_velocity": 1.0, "w_control": 0.05, "w_rate": 0.5, "max_iter": 30},
}


@pytest.mark.parametrize("beta", [0.0, 2.0])
def test_one_solve_pushes_toward_the_reference(beta):
    from gpg.runs.mpc_casadi import make_casadi_solver

    sur = fitted("gpgs_hybrid")
    vehicle = Vehicle.from_config(vehicle_config("sui_endurance"))
    ctrl = GeometricController.create(vehicle, sur.simple)
    plan = WaypointPlan.create([[0, 0, -10], [0, 20, -10]], start_time=0.0, leg_time=4.0, yaw=0.0)
    solve = make_casadi_solver(sur, vehicle, ctrl, plan, C, beta)
    # 1 m behind the reference along y, at rest: the plan wants +y, so should the offset.
    x0 = pack(State.hover([0.0, -1.0, -10.0], sur.simple.hover_rpm(float(vehicle.weight))))
    u, info = solve(None, x0, np.zeros((5, 3)), 1.0, np.zeros(3))
    assert u.shape == (5, 3) and np.all(np.abs(u) <= C["max_offset"] + 1e-6)
    assert info["converged"] and u[0, 1] > 0.1
    u2, info2 = solve(None, x0, np.zeros((5, 3)), 1.0, np.zeros(3))  # warm: the same problem
    assert info2["converged"]
    np.testing.assert_allclose(u2, u, atol=1e-3 * np.abs(u).max())  # IPOPT's tolerance
