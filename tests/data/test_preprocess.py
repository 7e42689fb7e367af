"""Residuals against M, normalisation (paper Eqs. normalize_x/y/g), λ², and exact inverses."""

import numpy as np
import pytest

from gpg import models
from gpg.data.dataset import Dataset
from gpg.data.preprocess import Normalizer, prepare, residuals, restore, simple_model_for
from gpg.quadrotor.simple_model import SimpleModel


@pytest.fixture
def data(rng, vehicle):
    n = 40
    x = np.column_stack(
        [rng.uniform(0, 7000, (n, 4)), rng.uniform(-1.5, 1.5, (n, 3)), rng.uniform(0, 20, n)]
    )
    return Dataset(
        x=x,
        y_aero=rng.normal(size=(n, 6)) * [3, 3, 20, 0.5, 0.5, 0.1],
        jac_aero=rng.normal(size=(n, 6, 7)),
        y_noise=rng.normal(60, 8, (n, 3)),
        jac_noise=rng.normal(size=(n, 3, 7)),
        x_raw=np.repeat(x, 8, axis=0) + rng.normal(scale=1e-3, size=(8 * n, 8)),
        y_raw=rng.normal(size=(8 * n, 9)),
        meta={"simple_model": {"P_F": 5.3e-7, "T_z": 8.4e-9}},
    )


def test_normalizer_inverses_exact(rng):
    x, y = rng.uniform(-3, 9, (30, 8)), rng.normal(4, 2, (30, 9))
    J = rng.normal(size=(30, 9, 7))
    nz = Normalizer.fit(x, y)
    xn = np.asarray(nz.x(x))
    assert np.allclose(xn.min(0), -1) and np.allclose(xn.max(0), 1)
    np.testing.assert_allclose(nz.x_inv(xn), x, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(nz.y_inv(nz.y(y)), y, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(nz.grad_inv(nz.grad(J)), J, rtol=1e-14, atol=1e-14)
    # Eq. normalize_g: ∂_j ỹ_m = ∂_j y_m · (max−min)_j / 2 / std(y_m).
    want = J * ((x.max(0) - x.min(0))[:7] / 2)[None, None, :] / y.std(0)[None, :, None]
    np.testing.assert_allclose(nz.grad(J), want, rtol=1e-14)


def test_gradient_scaling_is_chain_rule(rng):
    """For y = A x the normalised gradients are the slopes of the normalised data."""
    A = rng.normal(size=(3, 8))
    x = rng.uniform(-2, 5, (50, 8))
    y = x @ A.T
    nz = Normalizer.fit(x, y)
    slopes = np.linalg.lstsq(
        np.column_stack([np.asarray(nz.x(x)), np.ones(50)]), np.asarray(nz.y(y)), rcond=None
    )[0]
    np.testing.assert_allclose(
        nz.grad(np.broadcast_to(A[:, :7], (1, 3, 7)))[0], slopes[:7].T, rtol=1e-10
    )


def test_constant_input_does_not_break(rng):
    x = rng.uniform(0, 1, (10, 8))
    x[:, 7] = 12.0
    nz = Normalizer.fit(x, rng.normal(size=(10, 2)))
    assert np.all(np.isfinite(nz.x(x)))
    np.testing.assert_allclose(nz.x_inv(nz.x(x)), x, rtol=1e-14)


def test_prepare_and_restore(data, vehicle):
    simple = simple_model_for(data, vehicle)
    tr = prepare(data, simple)
    assert tr.X.shape == (40, 8) and tr.Y.shape == (40, 9) and tr.dY.shape == (40, 9, 7)
    np.testing.assert_allclose(tr.Y.mean(0), 0, atol=1e-14)
    np.testing.assert_allclose(tr.Y.std(0), 1, rtol=1e-12)
    np.testing.assert_allclose(restore(tr, data.x, tr.Y), data.y, rtol=1e-12, atol=1e-12)
    # λ² = s · Var(∂_j Ỹ) over points and outputs, the models' initial gradient noise.
    want = 0.3 * np.array([np.var(tr.dY[:, :, j]) for j in range(7)])
    hyper = models.initial_hyper(models.resolve_config("gpg"), 8, tr.dY)
    np.testing.assert_allclose(hyper.grad_noise, want, rtol=1e-12)
    assert tr.X_raw.shape == (320, 8) and tr.Y_raw.shape == (320, 9)


def test_residuals_subtract_simple_model(data, vehicle):
    simple = SimpleModel.from_vehicle(vehicle, 5.3e-7, 8.4e-9)
    y, J, y_raw = residuals(data, simple)
    yM, JM = simple.batch(data.x[:, :7])
    np.testing.assert_allclose(y[:, :6], data.y_aero - np.asarray(yM), rtol=1e-12)
    np.testing.assert_allclose(J[:, :6], data.jac_aero - np.asarray(JM), rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(y[:, 6:], data.y_noise)  # M has no noise
    np.testing.assert_array_equal(J[:, 6:], data.jac_noise)
    yR = np.asarray(simple.batch(data.x_raw[:, :7])[0])
    np.testing.assert_allclose(y_raw[:, :6], data.y_raw[:, :6] - yR, rtol=1e-12)


def test_simple_model_fitted_from_data_when_metadata_lacks_it(vehicle, rng):
    """User data without generator metadata: P_F, T_z by least squares on the data itself."""
    true = SimpleModel.from_vehicle(vehicle, 4.1e-7, 6.0e-9)
    x = np.column_stack([rng.uniform(0, 7000, (30, 4)), rng.uniform(-1, 1, (30, 3)), np.zeros(30)])
    ds = Dataset(x=x, y_aero=np.asarray(true.batch(x[:, :7])[0]))
    fit = simple_model_for(ds, vehicle)
    np.testing.assert_allclose([float(fit.P_F), float(fit.T_z)], [4.1e-7, 6.0e-9], rtol=1e-10)


def test_prepare_partial_datasets(data, vehicle):
    simple = simple_model_for(data, vehicle)
    tr = prepare(data.without("gradients", "noise"), simple)
    assert tr.dY is None and tr.Y.shape == (40, 6)
    assert tr.output_names == ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
    tr = prepare(data.without("raw samples"), None)
    assert tr.X_raw is None and tr.simple is None


def test_noise_residuals_round_trip_with_m_noise(data, vehicle):
    """With M_noise the levels' targets are L − M_noise (gradients too); restore is exact."""
    from gpg.quadrotor.simple_noise import SimpleNoise

    simple = simple_model_for(data, vehicle)
    # A coarse M_noise (the round trip holds for any): a fraction of the default's compile time.
    noise = SimpleNoise(
        vehicle=vehicle,
        P_F=simple.P_F,
        T_z=simple.T_z,
        n_harmonics=2,
        thickness_stations=4,
        n_azimuth=8,
        n_strips=1,
    )
    plain, with_noise = prepare(data, simple), prepare(data, simple, noise)
    np.testing.assert_allclose(restore(with_noise, data.x, with_noise.Y), data.y, rtol=1e-12)
    y, J, _ = residuals(data, simple, noise)
    yN, JN = (np.asarray(a) for a in noise.batch(data.x))
    np.testing.assert_allclose(y[:, 6:], data.y[:, 6:] - yN, rtol=1e-12)
    np.testing.assert_allclose(J[:, 6:], data.jac[:, 6:] - JN[:, :, :7], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(with_noise.Y[:, :6], plain.Y[:, :6])  # forces untouched
    assert with_noise.noise_model is noise and plain.noise_model is None


def test_overflowing_data_is_refused_by_name(data, vehicle):
    """Finite data whose standardisation overflows (1e308 squared) never reach a model."""
    from dataclasses import replace

    y = data.y_aero.copy()
    y[3, 1] = 1e308
    with pytest.raises(ValueError, match="output 'Fy' cannot be standardised"):
        prepare(replace(data, y_aero=y), simple_model_for(data, vehicle))


def test_body_frame_residuals_round_trip_and_M_depends_on_rpm_alone():
    """Body-frame data: ``M`` in the body frame at the identity attitude, its Jacobian zero
    along ``u, v, w``; ``restore(prepare(ds))`` gives the data back (float64 rounding)."""
    from gpg.quadrotor.vehicle import load_vehicle
    from tests.helpers import synthetic_body_dataset

    ds, _ = synthetic_body_dataset(12, seed=4)
    simple = simple_model_for(ds, load_vehicle("sui_endurance"))
    y, J, _ = residuals(ds, simple)
    np.testing.assert_array_equal(J[:, :6, 4:], ds.jac_aero[:, :, 4:])
    f, t = (np.asarray(a) for a in simple.wrench_body(ds.x[0, :4]))
    np.testing.assert_allclose(ds.y_aero[0] - y[0, :6], np.r_[f, t], rtol=1e-12, atol=1e-12)
    tr = prepare(ds, simple)
    assert tr.frame == "body"
    np.testing.assert_allclose(restore(tr, ds.x, tr.Y), ds.y, rtol=1e-12, atol=1e-9)
