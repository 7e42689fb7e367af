"""The C flight program (examples/c_flight/flight.c) with an exported surrogate flies the
round trip of ``experiments.simulate`` as gpg does (:func:`gpg.quadrotor.rollout.simulate`):
a whole closed-loop flight compiled and run, so the slow set."""

import subprocess
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import export
from gpg.export.flight import write_params
from gpg.quadrotor.control import GeometricController, WaypointPlan
from gpg.quadrotor.dynamics import Quadrotor, State, Wind
from gpg.quadrotor.rollout import simulate
from gpg.quadrotor.vehicle import Vehicle, vehicle_config
from gpg.surrogate import SurrogateAero
from tests.export.models import fitted

pytestmark = pytest.mark.slow
FLIGHT = Path(__file__).parents[2] / "examples" / "c_flight" / "flight.c"


def test_c_flight_matches_gpgs_own(tmp_path):
    """The same states step by step: positions within 1e-6 m, rotor speeds within 1e-4 rpm
    over 12 s at 100 Hz (a closed loop does not amplify the rounding differences of the two
    programs, libm against XLA), ``in_domain`` equal at every step."""
    sur = fitted("gpgs_hybrid")
    vehicle = Vehicle.from_config(vehicle_config("sui_endurance"))
    quad = Quadrotor.from_vehicle(vehicle, SurrogateAero(sur))
    ctrl = GeometricController.create(vehicle, sur.simple)
    plan = WaypointPlan.create([[0, 0, -10], [0, 20, -10], [0, 0, -10]], leg_time=5.0)
    wind = Wind(jnp.array([-2.0, 0.5, 0.0]), jnp.array([1.0, 1.0, 0.3]), jnp.asarray(3.0),
                jnp.asarray(0.4))  # fmt: skip
    s0 = State.hover([0.0, 0.0, -10.0], sur.simple.hover_rpm(float(vehicle.weight)))
    dt, n = 0.01, 1200
    _, tr = jax.jit(lambda s: simulate(quad, ctrl, plan, wind, s, dt, n))(s0)
    export.to_c(sur, tmp_path, name="model", variance=False)
    write_params(tmp_path / "flight_params.h", model="model", quad=quad, ctrl=ctrl, plan=plan,
                 wind=wind, s0=s0, dt=dt, n_steps=n)  # fmt: skip
    exe = tmp_path / "flight"
    build = subprocess.run(
        ["cc", "-O2", "-std=c99", "-Wall", "-Werror", "-I", str(tmp_path), "-o", str(exe),
         str(FLIGHT), str(tmp_path / "model.c"), "-lm"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert build.returncode == 0, build.stderr[-3000:]
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout
    c = np.array([[float(x) for x in line.split(",")] for line in out.strip().splitlines()])
    assert c.shape == (n, 12)
    np.testing.assert_allclose(c[:, 0], np.asarray(tr.t), rtol=0, atol=1e-12)
    np.testing.assert_allclose(c[:, 1:4], np.asarray(tr.p), rtol=0, atol=1e-6)
    np.testing.assert_allclose(c[:, 7:11], np.asarray(tr.rpm), rtol=0, atol=1e-4)
    assert np.array_equal(c[:, 11].astype(bool), np.asarray(tr.in_domain))
    travelled = np.abs(np.diff(np.asarray(tr.p)[:, 1])).sum()
    assert travelled > 30.0  # it flew the round trip (2 x 20 m), not a hover
