"""Paper-style datasets in the body frame (gpg/data/convert.py): against the generator's own
body frame at the converted inputs, values and rotor-speed gradients to rounding; the
velocity gradients marked not run; and a surrogate trains on the result."""

import numpy as np
import pytest

from gpg import Surrogate
from gpg.data.bounds import Bounds
from gpg.data.convert import to_body
from gpg.data.sampling import generate
from gpg.quadrotor.generator import jacobian_body
from tests.helpers import synthetic_body_dataset, synthetic_dataset


@pytest.mark.slow  # a generator compile; to_body keeps the fast test below
def test_converted_values_are_the_generators_body_frame(gen, y_body_of):
    """Values to 1e-10 of the load's scale at the converted inputs."""
    air = generate(gen, 3, bounds=Bounds(), seed=5, chunk=32, gradients="none", keep_raw=False,
                   meta={"simple_model": {"P_F": 1.0, "T_z": 1.0}})  # fmt: skip
    body = to_body(air)
    assert body.frame == "body" and body.x.shape == (3, 7) and not body.has_noise
    for i in range(3):
        y = np.asarray(y_body_of(body.x[i]))
        np.testing.assert_allclose(body.y_aero[i], y[:6], atol=1e-10 * np.abs(y[:6]).max())
    assert body.meta["bounds"] == {"rpm": [0.0, 7000.0], "airspeed": [0.0, 20.0]}


@pytest.mark.slow  # the generator's exact Jacobian in both frames (long compiles)
def test_converted_rpm_gradients_are_the_generators_body_frame(gen):
    """Rotor-speed gradients (exact in both frames) to 1e-8 relative: ``∂y_B/∂r = Rᵀ ∂y/∂r``
    at fixed body-frame air; the velocity gradients not run."""
    import jax

    air = generate(gen, 3, bounds=Bounds(), seed=5, chunk=32, gradients="exact", keep_raw=False,
                   meta={"simple_model": {"P_F": 1.0, "T_z": 1.0}})  # fmt: skip
    body = to_body(air)
    jac = jax.jit(lambda x: jacobian_body(gen, x))
    for i in range(3):
        J = np.asarray(jac(body.x[i]))[:6, :4]
        np.testing.assert_allclose(
            body.jac_aero[i, :, :4], J, rtol=1e-8, atol=1e-10 * np.abs(J).max()
        )
    assert np.isnan(body.jac_aero[:, :, 4:]).all() and body.gradient_mask[:, :4].all()


def test_a_surrogate_trains_on_converted_data_and_body_data_are_refused():
    air, _ = synthetic_dataset(30, seed=2, raw=False)
    body = to_body(air)
    sur = Surrogate.fit(body, "gpg", {"hyper": {"fit": False, "lengthscale": 0.8}})
    assert sur.frame == "body"
    p = sur.predict(np.full(4, 3600.0), np.zeros(3), np.array([5.0, 0.0, 0.0]))
    assert np.all(np.isfinite(np.asarray(p.force)))
    with pytest.raises(ValueError, match="converts airflow-frame data"):
        to_body(synthetic_body_dataset(4)[0])
