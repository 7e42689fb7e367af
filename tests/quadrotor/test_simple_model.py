"""Simplified model M against hand-derived closed forms; allocation from geometry."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.quadrotor.simple_model import CHUNK, SimpleModel, fit_coefficients

P_F, T_Z = 5.3e-7, 8.4e-9


@pytest.fixture(scope="module")
def model(vehicle):
    return SimpleModel.from_vehicle(vehicle, P_F, T_Z)


def rot(yaw, pitch, roll):
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    dRz = np.array([[-sy, -cy, 0], [cy, -sy, 0], [0, 0, 0]])
    dRy = np.array([[-sp, 0, cp], [0, 0, 0], [-cp, 0, -sp]])
    dRx = np.array([[0, 0, 0], [0, -sr, -cr], [0, cr, -sr]])
    return Rz @ Ry @ Rx, (dRz @ Ry @ Rx, Rz @ dRy @ Rx, Rz @ Ry @ dRx)


ARM = 0.36 / np.sqrt(2)  # l_x = l_y


def closed_form(x, arm=ARM):
    r = x[:4]
    F_B = np.array([0, 0, -P_F * np.sum(r**2)])
    # Paper's τx, τy patterns; τz with diagonal pairs (r1, r3) and (r2, r4) spinning alike.
    tau_B = np.array(
        [
            arm * P_F * (-(r[0] ** 2) + r[1] ** 2 + r[2] ** 2 - r[3] ** 2),
            arm * P_F * (-(r[0] ** 2) - r[1] ** 2 + r[2] ** 2 + r[3] ** 2),
            T_Z * (-(r[0] ** 2) + r[1] ** 2 - r[2] ** 2 + r[3] ** 2),
        ]
    )
    R, dR = rot(*x[4:7])
    y = np.concatenate([R @ F_B, R @ tau_B])
    J = np.zeros((6, 7))
    dF = np.zeros((3, 4))
    dF[2] = -2 * P_F * r
    dtau = np.array(
        [
            arm * P_F * 2 * r * [-1, 1, 1, -1],
            arm * P_F * 2 * r * [-1, -1, 1, 1],
            T_Z * 2 * r * [-1, 1, -1, 1],
        ]
    )
    J[:3, :4] = R @ dF
    J[3:, :4] = R @ dtau
    for k in range(3):
        J[:3, 4 + k] = dR[k] @ F_B
        J[3:, 4 + k] = dR[k] @ tau_B
    return y, J


def test_matches_closed_form(model, rng):
    X = np.column_stack([rng.uniform(0, 7000, (10, 4)), rng.uniform(-1.5, 1.5, (10, 3))])
    Y, J = eqx.filter_jit(SimpleModel.batch)(model, X)
    for i, x in enumerate(X):
        y, j = closed_form(x)
        np.testing.assert_allclose(Y[i], y, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(J[i], j, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(model(X[0]), Y[0], rtol=1e-12, atol=1e-12)


def test_host_batches_give_a_row_the_same_bits_in_any_batch(model, rng):
    """Outside jit, ``batch`` runs padded chunks of one compiled program: a state's ``y_M`` and
    ``J_M`` are the same bits whichever batch (and chunk position) it comes in, so a case's
    targets do not depend on whether it was preprocessed alone or with the training set (a
    program per N differed by an ulp, which an ill-conditioned GP turns into 5e-7); the values
    also match the closed form and the traced path."""
    n = CHUNK + 44
    X = np.column_stack([rng.uniform(0, 7000, (n, 4)), rng.uniform(-1.5, 1.5, (n, 3))])
    Y, J = model.batch(X)
    assert Y.shape == (n, 6) and J.shape == (n, 6, 7)
    for k, m in ((0, 1), (5, 7), (CHUNK - 3, 7), (n - 10, 10)):  # one straddles the chunks
        y, j = model.batch(X[k : k + m])
        assert np.array_equal(y, Y[k : k + m]) and np.array_equal(j, J[k : k + m])
    assert np.array_equal(model.values(X), Y)
    for i in (0, CHUNK, n - 1):
        y, j = closed_form(X[i])
        np.testing.assert_allclose(Y[i], y, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(J[i], j, rtol=1e-10, atol=1e-12)
    traced = eqx.filter_jit(SimpleModel.values)(model, X)
    np.testing.assert_allclose(traced, Y, rtol=1e-13, atol=1e-12)
    Y0, J0 = model.batch(X[:0])
    assert Y0.shape == (0, 6) and J0.shape == (0, 6, 7)


def test_allocation_invertible(model):
    A = np.asarray(model.allocation)
    assert abs(np.linalg.det(A)) > 0
    assert np.linalg.cond(A) < 1e3
    # Pitfall 3: the paper prints the τz row with the τx row's sign pattern, T_z (−1, 1, 1, −1),
    # which makes its matrix singular; A's τz row follows the spin directions instead.
    np.testing.assert_allclose(A[3], -T_Z * np.asarray(model.spin), rtol=1e-15)


def test_hover_rpm_and_fit():
    rpm = np.array([1000.0, 2000.0, 3000.0])
    P, T = fit_coefficients(
        np.repeat(rpm, 2), 2e-7 * np.repeat(rpm, 2) ** 2, 3e-9 * np.repeat(rpm, 2) ** 2
    )
    np.testing.assert_allclose([P, T], [2e-7, 3e-9], rtol=1e-12)
    with pytest.raises(ValueError, match="non-zero rpm"):
        fit_coefficients([0.0], [0.0], [0.0])


def test_fit_to_generator_hovers_in_range(gen, simple):
    m = simple
    hover = float(m.hover_rpm(float(gen.vehicle.weight)))
    assert 3300 < hover < 3900
    assert float(m.T_z) > 0 and float(m.P_F) > 0
    np.testing.assert_allclose(
        m(jnp.array([hover] * 4 + [0, 0, 0]))[2], -float(gen.vehicle.weight), rtol=1e-12
    )
