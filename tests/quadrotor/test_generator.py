"""The generator in the body frame (gpg.quadrotor.generator.evaluate_body): the same physics
as the airflow frame's, read in the body frame, and its exact Jacobian."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.data.bounds import Bounds
from gpg.data.sampling import generate
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.generator import evaluate_body, jacobian_body


def test_body_frame_is_the_airflow_frame_rotated(y_of, y_body_of):
    """``y_W(θ, V) = R_WB(θ) y_B(R_WB(θ)ᵀ V e_x)`` for force and moment: a change of frame,
    so equal to rounding (1e-10 of the load's scale, float64)."""
    f_air, f_body = y_of, y_body_of
    for x in (
        [3500, 3600, 3400, 3550, 0.4, -0.3, 0.6, 8.0],
        [5000, 2000, 4000, 3000, -1.2, 0.9, -1.4, 15.0],
    ):
        x = jnp.asarray(x, float)
        R = R_WB(x[4:7])
        xb = jnp.concatenate([x[:4], R.T @ jnp.array([x[7], 0.0, 0.0])])
        y, yb = np.asarray(f_air(x)), np.asarray(f_body(xb))
        R = np.asarray(R)
        for sl in (slice(0, 3), slice(3, 6)):
            np.testing.assert_allclose(y[sl], R @ yb[sl], atol=1e-10 * np.abs(y[sl]).max())


@pytest.mark.slow  # the generator's exact Jacobian, as the airflow frame's (a long compile)
def test_body_jacobian_equals_finite_differences(gen):
    """Near hover, climbing and with air from behind: the forward-mode Jacobian against central
    differences (steps 1e-2 rpm and 1e-5 m/s; 1e-6 of each output's largest derivative).
    Away from exactly axial air: there the wake-interference model's downstream direction
    ``v_xy/|v_xy|`` is regularised at 1e-6 m/s, and its autodiff derivative is not the
    function's (the next test)."""
    f = jax.jit(lambda x: evaluate_body(gen, x))
    jac = jax.jit(lambda x: jacobian_body(gen, x))
    for v in ([0.3, 0.2, 0.1], [0.5, -0.4, -4.0], [-6.0, 1.0, -1.0]):
        x = np.array([3600.0, 3500.0, 3700.0, 3650.0, *v])
        J = np.asarray(jac(jnp.asarray(x)))
        for k in range(7):
            h = 1e-2 if k < 4 else 1e-5
            e = np.zeros(7)
            e[k] = h
            fd = (np.asarray(f(jnp.asarray(x + e))) - np.asarray(f(jnp.asarray(x - e)))) / (2 * h)
            np.testing.assert_allclose(fd[:6], J[:6, k], atol=1e-6 * np.abs(J[:6]).max() + 1e-9)


@pytest.mark.slow  # likewise
def test_axial_air_is_continuous_but_not_smooth_in_the_generator(gen):
    """A finding, kept as a test: at exactly axial air (hover, vertical climb or descent) the
    wake-interference model switches which rotor is downstream of which within 1e-6 m/s of
    sideways air. The loads stay continuous (sideways air of ±1e-4 m/s moves the force by
    under 1e-2 N), but the autodiff Jacobian there is not their derivative (thousands), which
    is why the envelope's data take forward differences (steps of 0.1 m/s average over it)."""
    f = jax.jit(lambda x: evaluate_body(gen, x))
    jac = jax.jit(lambda x: jacobian_body(gen, x))
    for w in (0.0, -3.0, 3.0):
        a, b = (np.asarray(f(jnp.array([3600.0] * 4 + [s, 0.0, w]))) for s in (1e-4, -1e-4))
        assert np.abs(a[:3] - b[:3]).max() < 1e-2
        assert np.abs(np.asarray(jac(jnp.array([3600.0] * 4 + [0.0, 0.0, w])))[:6, 4:]).max() > 1e2


@pytest.mark.slow  # a compile of the batched body-frame generator (the pieces are fast tests)
def test_body_frame_dataset_records_its_frame_and_round_trips(gen, tmp_path):
    from gpg.data.dataset import Dataset

    ds = generate(gen, 3, bounds=Bounds(), seed=0, chunk=32, frame="body",
                  meta={"simple_model": {"P_F": 1.0, "T_z": 1.0}})  # fmt: skip
    assert ds.frame == "body" and ds.x.shape == (3, 7) and ds.x_raw.shape == (24, 7)
    assert ds.meta["bounds"] == {"rpm": (0.0, 7000.0), "airspeed": (0.0, 20.0)}
    assert "velocity" in ds.meta["fd"] and "angle_deg" not in ds.meta["fd"]
    ds.save(tmp_path / "b")
    back = Dataset.load(tmp_path / "b")
    assert back.frame == "body" and back.inputs[4:] == ("u", "v", "w")
    np.testing.assert_array_equal(back.jac_aero, ds.jac_aero)
