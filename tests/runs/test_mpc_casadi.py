"""The CasADi MPC (experiments/runs/mpc_casadi.py) on a small surrogate: one IPOPT solve from hover
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


def setup():
    sur = fitted("gpgs_hybrid")
    vehicle = Vehicle.from_config(vehicle_config("sui_endurance"))
    ctrl = GeometricController.create(vehicle, sur.simple)
    plan = WaypointPlan.create([[0, 0, -10], [0, 20, -10]], start_time=0.0, leg_time=4.0, yaw=0.0)
    # 1 m behind the reference along y, at rest: the plan wants +y, so should the offset.
    x0 = pack(State.hover([0.0, -1.0, -10.0], sur.simple.hover_rpm(float(vehicle.weight))))
    return sur, vehicle, ctrl, plan, x0


@pytest.mark.parametrize("beta, linear", [(0.0, True), (2.0, False)])
def test_one_solve_pushes_toward_the_reference(beta, linear):
    from experiments.runs.mpc_casadi import make_casadi_solver

    sur, vehicle, ctrl, plan, x0 = setup()
    solve = make_casadi_solver(sur, vehicle, ctrl, plan, {**C, "caution_linearised": linear}, beta)
    u, info = solve(None, x0, np.zeros((5, 3)), 1.0, np.zeros(3))
    assert u.shape == (5, 3) and np.all(np.abs(u) <= C["max_offset"] + 1e-6)
    assert info["converged"] and u[0, 1] > 0.1
    u2, info2 = solve(None, x0, np.zeros((5, 3)), 1.0, np.zeros(3))  # warm: the same problem
    assert info2["converged"]
    np.testing.assert_allclose(u2, u, atol=1e-3 * np.abs(u).max())  # IPOPT's tolerance


def test_linearised_caution_converges_to_the_exact_one():
    """The linearised caution matches the exact term's value and gradient at its point, so a
    KKT point of the exact NLP is one of the linearised NLP about it: re-solving the same
    problem, each time about the last plan, reaches the exact term's solution (to IPOPT's
    tolerance of the scaled optimality error, 1e-8 here; it contracts by about 7x a solve on
    this problem, so six reach 1e-4 of the offsets with margin)."""
    from experiments.runs.mpc_casadi import make_casadi_solver

    sur, vehicle, ctrl, plan, x0 = setup()
    c = {**C, "tol": 1e-8}
    exact = make_casadi_solver(sur, vehicle, ctrl, plan, {**c, "caution_linearised": False}, 2.0)
    linear = make_casadi_solver(sur, vehicle, ctrl, plan, {**c, "caution_linearised": True}, 2.0)
    want, info = exact(None, x0, np.zeros((5, 3)), 1.0, np.array([2.0, 0.0, 0.0]))
    assert info["converged"]
    steps = []
    for _ in range(6):
        got, info = linear(None, x0, np.zeros((5, 3)), 1.0, np.array([2.0, 0.0, 0.0]))
        assert info["converged"]
        steps.append(np.abs(got - want).max())
    assert steps[-1] <= 1e-4 * np.abs(want).max() < steps[0], steps
