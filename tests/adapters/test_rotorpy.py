"""The RotorPy plug-in against RotorPy itself: with gpg's M as the aerodynamics, RotorPy's own
Multirotor, controller, trajectories and simulate give the same flight (hover from an offset,
and a circular manoeuvre in wind), which checks every frame, order and unit conversion."""

import numpy as np
import pytest

pytest.importorskip("rotorpy")
from rotorpy.controllers.quadrotor_control import SE3Control  # noqa: E402
from rotorpy.estimators.nullestimator import NullEstimator  # noqa: E402
from rotorpy.sensors.external_mocap import MotionCapture  # noqa: E402
from rotorpy.sensors.imu import Imu  # noqa: E402
from rotorpy.simulate import simulate  # noqa: E402
from rotorpy.trajectories.circular_traj import ThreeDCircularTraj  # noqa: E402
from rotorpy.trajectories.hover_traj import HoverTraj  # noqa: E402
from rotorpy.vehicles.multirotor import Multirotor  # noqa: E402
from rotorpy.wind.default_winds import ConstantWind  # noqa: E402
from rotorpy.world import World  # noqa: E402

from gpg.adapters.rotorpy import GpgMultirotor, quad_params  # noqa: E402
from gpg.quadrotor.simple_model import SimpleModel  # noqa: E402

NO_NOISE = {
    "pos_noise_density": np.zeros(3),
    "vel_noise_density": np.zeros(3),
    "att_noise_density": np.zeros(3),
    "rate_noise_density": np.zeros(3),
    "vel_artifact_max": 0,
    "vel_artifact_prob": 0,
    "rate_artifact_max": 0,
    "rate_artifact_prob": 0,
}


def _fly(vehicle, qp, traj, seconds):
    x0 = np.asarray(traj.update(0.0)["x"], float) + np.array([0.3, -0.2, 0.1])
    hover = float(np.sqrt(qp["mass"] * 9.81 / 4 / qp["k_eta"]))
    state = {
        "x": x0,
        "v": np.zeros(3),
        "q": np.array([0, 0, 0, 1.0]),
        "w": np.zeros(3),
        "wind": np.zeros(3),
        "rotor_speeds": np.full(4, hover),
    }
    out = simulate(
        World.empty((-30, 30, -30, 30, -30, 30)),
        state,
        vehicle,
        SE3Control(qp),
        traj,
        ConstantWind(1.0, -0.5, 0.0),
        Imu(sampling_rate=100),
        MotionCapture(sampling_rate=100, mocap_params=NO_NOISE, with_artifacts=False),
        NullEstimator(),
        seconds,
        0.01,
        0.25,
        use_mocap=False,
        terminate=False,
    )
    return out[1], out[3]


@pytest.mark.parametrize(
    "traj",
    [
        HoverTraj(np.zeros(3)),
        ThreeDCircularTraj(radius=np.array([1.0, 1.0, 0.3]), freq=np.array([0.15, 0.15, 0.15])),
    ],
    ids=["hover", "circle"],
)
def test_plugin_with_M_reproduces_rotorpy(vehicle, traj):
    M = SimpleModel.from_vehicle(vehicle, 5.278e-07, 7.095e-09)
    qp = quad_params(vehicle, M, kp_att=100.0, kd_att=20.0)
    native, flat = _fly(Multirotor(qp, aero=False), qp, traj, 3.0)
    plugin, _ = _fly(GpgMultirotor(qp, M), qp, traj, 3.0)
    moved = np.max(np.linalg.norm(native["x"] - native["x"][0], axis=1))
    assert moved > 0.2  # a real flight, not a vehicle at rest
    for k in ("x", "v", "q", "w", "rotor_speeds"):
        scale = max(np.max(np.abs(native[k])), 1.0)
        np.testing.assert_allclose(plugin[k], native[k], atol=1e-7 * scale, err_msg=k)
    assert np.max(np.linalg.norm(native["x"] - flat["x"], axis=1)[-50:]) < 0.5  # it tracks


def test_quad_params_checks(vehicle):
    M = SimpleModel.from_vehicle(vehicle, 5.278e-07, 7.095e-09)
    with pytest.raises(ValueError, match="unknown RotorPy parameters"):
        quad_params(vehicle, M, k_eta2=1.0)
    with pytest.raises(ValueError, match="time constant > 0"):
        quad_params(vehicle, M, tau_m=0.0)
    with pytest.raises(ValueError, match="aero must be"):
        GpgMultirotor(quad_params(vehicle, M), "M")


@pytest.mark.slow  # a body-frame dataset generated and a surrogate fitted
def test_body_frame_surrogate_flies_take_off_hover_and_descent_in_domain(vehicle, tmp_path):
    """RotorPy's own simulate, SE3 controller and hover trajectories fly gpg's body-frame
    surrogate (data=envelope_smoke) from the ground up 3 m (a vertical climb), hold, and down
    2.5 m (a vertical descent: air from below, where the paper's airflow frame has a gimbal
    lock): every wrench RotorPy asks for is in the surrogate's domain, and it tracks."""
    from experiments.runs.config import conf
    from gpg import Surrogate
    from gpg.data.cache import ensure_datasets
    from gpg.quadrotor.vehicle import vehicle_config

    train = ensure_datasets(
        conf("envelope_smoke", "data"), vehicle_config("sui_endurance"), tmp_path, progress=False
    )[0]
    sur = Surrogate.fit(
        train, "gpgs_hybrid", {"partition": {"points_per_bin": 20}, "near": {"points": 30}}
    )
    assert sur.frame == "body"
    qp = quad_params(vehicle, sur.simple, kp_att=100.0, kd_att=20.0)
    flags = []

    class Watched(GpgMultirotor):
        def compute_body_wrench(self, *args):
            out = super().compute_body_wrench(*args)
            flags.append(self.last_in_domain)
            return out

    for start, target in (([0.0, 0.0, 0.0], [0.0, 0.0, 3.0]), ([0.0, 0.0, 3.0], [0.0, 0.0, 0.5])):
        traj = HoverTraj(np.array(target))
        x0 = np.array(start)
        hover = float(np.sqrt(qp["mass"] * 9.81 / 4 / qp["k_eta"]))
        state = {"x": x0, "v": np.zeros(3), "q": np.array([0, 0, 0, 1.0]), "w": np.zeros(3),
                 "wind": np.zeros(3), "rotor_speeds": np.full(4, hover)}  # fmt: skip
        out = simulate(
            World.empty((-30, 30, -30, 30, -30, 30)), state, Watched(qp, sur), SE3Control(qp),
            traj, ConstantWind(1.0, -0.5, 0.0), Imu(sampling_rate=100),
            MotionCapture(sampling_rate=100, mocap_params=NO_NOISE, with_artifacts=False),
            NullEstimator(), 6.0, 0.01, 0.25, use_mocap=False, terminate=False,
        )  # fmt: skip
        x = out[1]["x"]
        climb = np.max(np.abs(x[:, 2] - start[2]))
        assert climb > 2.0  # it flew the whole way
        assert np.linalg.norm(x[-1] - np.array(target)) < 0.3
    assert len(flags) > 1000 and all(flags)
