"""gpg.flight.wind: the wind of a flight estimated from its labels and a force model, against
labels made by that model in a known wind."""

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from gpg.flight import WindWarning, estimate_wind, with_wind
from gpg.flight.labels import Labels

WIND = np.array([4.0, -2.5, 0.0])  # m/s, the true steady wind
SIGMA = 0.05  # N, the labels' noise
DRAG = jnp.array([0.04, 0.05, 0.08])  # ½ ρ f per world axis, kg/m
ROTOR = 0.3  # N per m/s: the rotors' drag, horizontal


def drag_model(rpm, euler, v_air):
    """A quadrotor's force in closed form: thrust balancing 2.7 kg, quadratic airframe drag
    and linear rotor drag (world frame; the attitude enters nowhere, as for a level vehicle)."""
    speed = jnp.sqrt(jnp.sum(v_air**2) + 1e-12)
    rotor = ROTOR * v_air * jnp.array([1.0, 1.0, 0.0]) * jnp.sum(rpm) / 14400.0
    return jnp.array([0.0, 0.0, -26.5]) - DRAG * speed * v_air - rotor


def _labels(model, *, wind, manoeuvres=True, n=200, seed=0):
    """A flight of ``n`` labels at 10 Hz whose ground velocity sweeps ±3 m/s (a figure-eight's)
    or stays at rest, its force the model's at ``v − w`` plus noise; ``v_air`` is the ground
    velocity (a log without the wind)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    rpm = 3600 + 200 * rng.normal(size=(n, 4))
    euler = np.column_stack([np.full(n, 0.3), 0.1 * np.sin(0.7 * t), 0.1 * np.cos(0.5 * t)])
    a = 3.0 if manoeuvres else 0.0
    v = np.column_stack([a * np.sin(0.6 * t), a * np.sin(1.2 * t), 0.3 * a * np.cos(0.4 * t)])
    w = np.broadcast_to(wind, (n, 3))
    if callable(model):
        f = np.stack([np.asarray(model(*a)) for a in zip(rpm, euler, v - w, strict=True)])
    else:
        f = np.asarray(model.predict_batch(rpm, euler, v - w, mean_only=True).force)
    f = f + SIGMA * rng.normal(size=f.shape)
    z = np.zeros((n, 3))
    return Labels(t=t, rpm=rpm, euler=euler, v_air=v, force=f, torque=z, force_var=z + SIGMA**2,
                  torque_var=z + 1e-4, model_force=z, model_torque=z, name="flight")  # fmt: skip


def test_a_steady_wind_recovered_from_manoeuvres():
    """The wind within 0.2 m/s and its mean within 3 posterior sd, the vertical held
    at 0; with_wind turns the labels into those of the true air velocity (to the estimate's
    error) and adds the wind's uncertainty to the force noise."""
    lab = _labels(drag_model, wind=WIND)
    est = estimate_wind(lab, drag_model, knot_s=5.0, drift=0.05)
    assert est.informed[:2].all() and not est.informed[2]
    err = est.wind - WIND
    assert np.max(np.abs(err[:, :2])) < 0.2
    assert np.all(np.abs(err.mean(0)[:2]) <= 3 * np.median(est.sd[:, :2], 0))
    np.testing.assert_array_equal(est.wind[:, 2], 0.0)
    np.testing.assert_array_equal(est.sd[:, 2], 0.0)
    fixed = with_wind(lab, est)
    np.testing.assert_allclose(fixed.v_air, lab.v_air - est.wind)
    assert np.all(fixed.force_var >= lab.force_var) and np.any(fixed.force_var > lab.force_var)
    assert est.knots.shape == (est.knot_t.size, 3) and est.iterations >= 2


def test_what_a_flight_cannot_tell_is_named():
    """A flight at rest: a bias of the model would read as wind (no manoeuvres, named). A
    model whose force does not depend on the air's y component: the wind along y stays at
    its prior (not determined, named), the x one is found."""
    lab = _labels(drag_model, wind=WIND, manoeuvres=False, n=60)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", WindWarning)
        estimate_wind(lab, drag_model)
    msg = " ".join(str(w.message) for w in seen if w.category is WindWarning)
    assert "no manoeuvres along x, y" in msg and "does not determine" not in msg

    def along_x(rpm, euler, v_air):
        return drag_model(rpm, euler, v_air * jnp.array([1.0, 0.0, 1.0]))

    lab = _labels(along_x, wind=WIND)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", WindWarning)
        est = estimate_wind(lab, along_x)
    msg = " ".join(str(w.message) for w in seen if w.category is WindWarning)
    assert "does not determine the wind along y" in msg
    assert est.informed.tolist() == [True, False, False]
    assert abs(est.mean[0] - WIND[0]) < 0.2 and np.median(est.sd[:, 1]) > 5.0


def test_a_surrogate_as_the_force_model(synthetic_surrogate):
    """A fitted surrogate is read as its mean force: the same estimate as that function."""
    lab = _labels(synthetic_surrogate, wind=WIND, n=60)
    est = estimate_wind(lab, synthetic_surrogate, drift=0.05)
    same = estimate_wind(lab, lambda r, e, v: synthetic_surrogate.predict(r, e, v).force,
                         drift=0.05)  # fmt: skip
    np.testing.assert_allclose(est.wind, same.wind, atol=1e-9)
    np.testing.assert_allclose(est.sd, same.sd, rtol=1e-9)


def test_bad_input_refused():
    lab = _labels(drag_model, wind=WIND, n=30)
    two = Labels.concatenate([lab, lab])
    with pytest.raises(ValueError, match="one flight at a time"):
        estimate_wind(two, drag_model)
    with pytest.raises(ValueError, match="a gpg.Surrogate or a force"):
        estimate_wind(lab, "sui_endurance")
    with pytest.raises(ValueError, match="axes must be"):
        estimate_wind(lab, drag_model, axes="z")
    est = estimate_wind(lab, drag_model)
    other = dataclasses.replace(lab, t=lab.t + 1.0)
    with pytest.raises(ValueError, match="not of these labels"):
        with_wind(other, est)


def test_wind_variance_is_the_force_slope_squared():
    """``Σ_a (∂F_c/∂v_a)² σ_a²`` against central differences of the force model."""
    from gpg.flight.wind import wind_variance

    rng = np.random.default_rng(3)
    rpm, euler, v = 3600 + 100 * rng.normal(size=(4, 4)), np.zeros((4, 3)), rng.normal(size=(4, 3))
    sd = np.array([1.5, 0.5, 0.0])
    got = wind_variance(drag_model, rpm, euler, v, sd)
    h = 1e-6
    for n in range(4):
        J = np.stack([(np.asarray(drag_model(rpm[n], euler[n], v[n] + h * e))
                       - np.asarray(drag_model(rpm[n], euler[n], v[n] - h * e))) / (2 * h)
                      for e in np.eye(3)], 1)  # fmt: skip
        np.testing.assert_allclose(got[n], (J**2) @ sd**2, rtol=1e-6)
