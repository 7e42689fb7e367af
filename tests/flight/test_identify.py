"""gpg.flight.identify: the vehicle's physical parameters from labels, by maximum likelihood
through gpg's own physics; against labels made by that physics for a vehicle whose values
are known."""

import dataclasses
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.flight import IdentificationWarning, identify
from gpg.flight.identify import (
    ALL,
    PARAMETERS,
    _apply,
    _get,
    _long_run,
    hover_coefficients,
    loads_and_jacobian,
)
from gpg.flight.labels import Labels, MotorCurve
from gpg.flight.synthetic import perturbed
from gpg.quadrotor import bemt
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.vehicle import Vehicle, load_vehicle, vehicle_config

# A coarser blade grid for the truth and the fit alike: the identification is checked, not
# the physics' resolution (the inflow's iterations are the generator's: fewer do not converge).
PHYSICS = bemt.BEMTConfig(n_radial=6, n_azimuth=8)
TRUE = {"drag_area.x": 0.075, "drag_area.z": 0.12, "rotor.chord": 1.1}
SIGMA_F, SIGMA_T = 0.3, 0.05  # N, N·m: the labels' noise
N = 120  # labels: one shape, so that every test reuses the physics' compiled programs
BASE = load_vehicle("sui_endurance")


def _labels(theta, n, seed, speed=1.0):
    """Labels of the physics with the parameters ``theta`` (all of PARAMETERS, in order) at
    flight-like states in winds of 0-10 m/s (times ``speed``): the program identify compiles
    (its shapes, its context and the strong float64 reference speed), so that the tests
    compile it once."""
    rng = np.random.default_rng(seed)
    rpm = rng.uniform(3000, 5000, (n, 4))
    euler = np.column_stack(
        [rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n)]
    )
    v = speed * np.column_stack([rng.uniform(0, 10, n), rng.normal(0, 2, n), rng.normal(0, 1, n)])
    # body rates of a manoeuvring vehicle (their own stream: the draws above stay as they were)
    rates = np.random.default_rng(seed + 1000).normal(0.0, 0.5, (n, 3))
    states = (jnp.asarray(a) for a in (rpm, euler, v))
    # The reference speed identify takes: the labels' median (all N labels are used).
    ref = jnp.asarray(np.median(rpm))
    # identify's context (64 bits, matmul precision "highest": both in the compiled program's
    # key): identify runs the program compiled here
    with jax.enable_x64(True), jax.default_matmul_precision("highest"):
        y, _ = loads_and_jacobian(BASE, PHYSICS, jnp.asarray(theta), jnp.eye(len(ALL))[:, :3],
                                  *states, ref, jnp.asarray(rates))  # fmt: skip
    y = np.asarray(y)
    f = y[:, :3] + SIGMA_F * rng.normal(size=(n, 3))
    t = y[:, 3:] + SIGMA_T * rng.normal(size=(n, 3))
    return Labels(t=np.arange(n) * 0.1, rpm=rpm, euler=euler, v_air=v, force=f, torque=t,
                  force_var=np.full((n, 3), SIGMA_F**2), torque_var=np.full((n, 3), SIGMA_T**2),
                  model_force=0 * f, model_torque=0 * t, name="synthetic",
                  rates=rates)  # fmt: skip


def _theta(values):
    """θ of the vehicle file's values ``values`` (log-factors on sui_endurance's; the wake
    gain's on the physics' own)."""
    th = np.zeros(len(ALL))
    for name, v in values.items():
        th[ALL.index(name)] = math.log(v / _get(vehicle_config("sui_endurance"), name, PHYSICS))
    return th


@pytest.fixture(scope="module")
def real():
    """The "real" vehicle's file: sui_endurance with TRUE's values."""
    base = vehicle_config("sui_endurance")
    drag = list(base["drag_area"])
    drag[0], drag[2] = TRUE["drag_area.x"], TRUE["drag_area.z"]
    return perturbed(base, {"drag_area": drag, "rotor.chord_in": {"scale": TRUE["rotor.chord"]}})


CONSIDER_SD = 0.02  # the radius held at the file's value, as if measured to 2 %


@pytest.fixture(scope="module")
def identified_and_warnings():
    lab = _labels(_theta(TRUE), N, seed=0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", IdentificationWarning)
        out = identify(lab, "sui_endurance", free=tuple(TRUE), physics=PHYSICS, max_steps=30,
                       passes=2, consider={"rotor.radius": CONSIDER_SD})  # fmt: skip
    return out, [str(w.message) for w in seen if w.category is IdentificationWarning]


@pytest.fixture(scope="module")
def identified(identified_and_warnings):
    return identified_and_warnings[0]


def test_parameters_applied_as_the_vehicle_file_says(real):
    """θ of the real vehicle's values applied to the file's vehicle is that vehicle (so the
    labels made through θ are the real vehicle's)."""
    applied = _apply(BASE, ALL, jnp.asarray(_theta(TRUE)))
    np.testing.assert_allclose(applied.drag_area, real.drag_area, rtol=1e-12)
    np.testing.assert_allclose(applied.rotor.chord, real.rotor.chord, rtol=1e-12)
    np.testing.assert_allclose(applied.rotor.radius, real.rotor.radius, rtol=1e-12)


def test_physics_reads_the_body_rates():
    """The identification's physics (the program ``identify`` runs, at the labels' states)
    reads each label's body rates: row by row it is :func:`bemt.aero` with them (each hub
    moving at ω × p), and the rates change the loads. Two compiled programs (vmapped under
    ``jacfwd``, and one row) of the same float64 sums through the inflow's fixed Newton steps:
    their fusions round apart by some ulp, kept well inside 1e-10."""
    lab = _labels(_theta(TRUE), N, seed=0)
    theta = jnp.asarray(_theta(TRUE))
    states = [jnp.asarray(a) for a in (lab.rpm, lab.euler, lab.v_air)]
    ref = jnp.asarray(np.median(lab.rpm))

    def loads(w):
        with jax.enable_x64(True), jax.default_matmul_precision("highest"):
            y, _ = loads_and_jacobian(BASE, PHYSICS, theta, jnp.eye(len(ALL))[:, :3], *states,
                                      ref, jnp.asarray(w))  # fmt: skip
        return np.asarray(y)

    got, calm = loads(lab.rates), loads(np.zeros_like(lab.rates))
    veh = _apply(BASE, ALL, theta)
    one = jax.jit(lambda r, e, v, w: bemt.aero(veh, PHYSICS, r, R_WB(e), v, w))
    for i in range(2):
        r = one(*(jnp.asarray(a[i]) for a in (lab.rpm, lab.euler, lab.v_air, lab.rates)))
        want = np.concatenate([r.force_W, r.torque_W])
        np.testing.assert_allclose(got[i], want, rtol=1e-10, atol=1e-10 * np.abs(want).max())
    # rates of 0.5 rad/s: the rotors' damping moves the torques by more than the labels' noise
    assert np.sqrt(np.mean((got - calm)[:, 3:] ** 2)) > SIGMA_T


def test_parameters_recovered_within_their_standard_errors(identified):
    """Each parameter within 3 standard errors of the truth, the standard errors small against
    the prior (the labels inform them), and the fit's residual at the labels' noise."""
    assert identified.converged and not identified.unidentified
    for name, truth in TRUE.items():
        p = identified.parameters[name]
        assert p["identified"]
        # the labels are the file's radius's: the labels' own errors are the ones to hold
        assert abs(p["value"] - truth) <= 3 * p["se_data"], (name, p, truth)
        assert p["se_data"] < 0.05 * truth  # far inside the prior's factor
    assert identified.parameters["drag_area.x"]["nominal"] == pytest.approx(0.0251)
    np.testing.assert_allclose(identified.residual_rms[:3], SIGMA_F, rtol=0.3)


def test_vehicle_file_written_and_read(identified, tmp_path):
    """The identified vehicle as a file: load_vehicle reads it, the generator accepts it, its
    values are the identified ones and M's coefficients are its physics' hover fit."""
    path = identified.write(tmp_path / "mine.yaml")
    text = path.read_text()
    assert text.startswith("# Identified from flights") and "drag_area.x" in text
    veh = load_vehicle(path)
    veh.require_generator()
    assert veh.name == "sui_endurance_identified"
    assert float(veh.drag_area[0]) == pytest.approx(identified.parameters["drag_area.x"]["value"])
    chord0 = np.asarray(load_vehicle("sui_endurance").rotor.chord)
    np.testing.assert_allclose(
        np.asarray(veh.rotor.chord) / chord0, identified.parameters["rotor.chord"]["value"],
        rtol=1e-5)  # fmt: skip
    P_F, T_z = hover_coefficients(veh, PHYSICS)
    assert float(veh.thrust_coefficient) == pytest.approx(P_F, rel=1e-12)
    assert float(veh.torque_coefficient) == pytest.approx(T_z, rel=1e-12)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        identified.write(path)


def test_a_pair_the_flights_cannot_tell_apart_is_named():
    """Rotor speeds from a motor curve: in hover the curve's gain and the blade's chord trade
    (more thrust per rpm, fewer rpm per command), and without airspeed the airframe's drag
    does nothing. Force labels of hover alone: all three named in a warning, kept at the
    file's values, flagged in the summary the vehicle file's header carries."""
    hover = _labels(_theta(TRUE), N, seed=1, speed=0.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", IdentificationWarning)
        out = identify(hover, "sui_endurance", free=("rotor.chord", "motor.gain", "drag_area.x"),
                       loads="force", physics=PHYSICS, max_steps=10, passes=1)  # fmt: skip
    msg = " ".join(str(w.message) for w in seen if w.category is IdentificationWarning)
    assert all(n in msg for n in ("rotor.chord", "motor.gain", "drag_area.x")), msg
    assert set(out.unidentified) == {"rotor.chord", "motor.gain", "drag_area.x"}
    assert out.parameters["rotor.chord"]["value"] == 1.0 and out.motor_gain == 1.0
    assert out.parameters["motor.gain"]["se"] == pytest.approx(PARAMETERS["motor.gain"].prior)
    assert "not identified" in out.summary()


@pytest.mark.parametrize(
    "kw, message",
    [
        ({"free": ("drag_area.w",)}, "free must name distinct parameters"),
        ({"free": ("drag_area.x", "drag_area.x")}, "free must name distinct parameters"),
        ({"loads": "thrust"}, "loads must be"),
        ({"body_rates": "yes"}, "body_rates must be True or False"),
    ],
)
def test_bad_options_named(kw, message):
    lab = _labels(np.zeros(len(ALL)), N, seed=2)
    with pytest.raises(ValueError, match=message):
        identify(lab, "sui_endurance", physics=PHYSICS, **kw)


def test_needs_labels_and_a_generator_vehicle():
    with pytest.raises(ValueError, match="needs gpg.flight.Labels"):
        identify([], "sui_endurance")
    lab = _labels(np.zeros(len(ALL)), N, seed=2)
    with pytest.raises(ValueError, match="cannot drive the built-in generator"):
        identify(lab, "minimal_example", physics=PHYSICS)
    with pytest.raises(ValueError, match=r"rates must be \(N, 3\), got \(3, 3\)"):
        identify(dataclasses.replace(lab, rates=np.zeros((3, 3))), "sui_endurance")
    assert math.isfinite(PARAMETERS["drag_area.x"].prior)


def test_the_others_refitted_beside_an_unidentified_one():
    """Hover labels: the chord is identified by the thrust, the airframe's drag is not (no
    airspeed). The drag keeps the file's value and the chord is fitted again beside it: it
    comes out at the truth (the labels' drag is the truth's, but at rest drag is nothing).
    Three free parameters, as in the fixture: the first fit reuses its compiled program."""
    hover = _labels(_theta(TRUE), N, seed=3, speed=0.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always", IdentificationWarning)
        out = identify(hover, "sui_endurance", free=tuple(TRUE), physics=PHYSICS, max_steps=20,
                       passes=1)  # fmt: skip
    assert any("drag_area.x" in str(w.message) for w in seen)
    assert out.unidentified == ("drag_area.x", "drag_area.z")
    chord = out.parameters["rotor.chord"]
    assert chord["identified"] and abs(chord["value"] - TRUE["rotor.chord"]) <= 3 * chord["se"]
    assert out.parameters["drag_area.x"]["value"] == pytest.approx(0.0251)
    z0 = float(load_vehicle("sui_endurance").drag_area[2])
    assert out.parameters["drag_area.z"]["value"] == pytest.approx(z0)


def test_motor_curve_bend_and_wake_gain_recovered(identified):
    """Speeds from a curve whose bend is wrong (the labels' speeds are ``rpm_ref (r /
    rpm_ref)^(1/0.9)`` of the truth's ``r``) and a wake gain of 1.3: ``motor.exponent`` and
    ``generator.wake_gain`` come out within 3 standard errors of 0.9 and 1.3. The identified
    curve's speeds are :meth:`Identification.speeds` of the first curve's in closed form, and
    the prior's data config carries the wake gain. Three free parameters, as in the fixture:
    the same compiled program."""
    truth = {"rotor.chord": 1.1, "motor.exponent": 0.9, "generator.wake_gain": 1.3}
    lab = _labels(_theta(truth), N, seed=4)
    out = identify(lab, "sui_endurance", free=tuple(truth), physics=PHYSICS, max_steps=30,
                   passes=2)  # fmt: skip
    assert out.converged and not out.unidentified
    for name, value in truth.items():
        p = out.parameters[name]
        assert abs(p["value"] - value) <= 3 * p["se"], (name, p)
    assert out.motor_exponent == out.parameters["motor.exponent"]["value"]
    assert out.physics.wake_gain == out.parameters["generator.wake_gain"]["value"]
    assert out.rpm_ref == pytest.approx(np.median(lab.rpm), rel=1e-12)
    curve = MotorCurve(4500.0, 2600.0, 16.0, time_constant=0.05)
    u = np.random.default_rng(5).uniform(0.3, 0.9, (40, 4))
    volt, t = np.full(40, 15.8), np.arange(40) * 0.02
    np.testing.assert_allclose(out.curve(curve).rpm(u, volt, t),
                               out.speeds(curve.rpm(u, volt, t)), rtol=1e-12)  # fmt: skip
    data = out.data_config({"name": "x", "generator": {"n_radial": 6},
                            "bounds": {"rpm": [0.0, 7000.0], "airspeed": [0.0, 20.0]}})  # fmt: skip
    assert data["generator"] == {"n_radial": 6, "wake_gain": out.physics.wake_gain}
    assert "generator" not in identified.data_config({"name": "x"})  # not freed: as given
    # a half-turn prior: no levels (the file's side microphones are not their own images)
    assert identified.data_config({"name": "x", "noise": True}, half_turn=True)["noise"] is False
    assert identified.data_config({"name": "x", "noise": True})["noise"] is True
    # The prior's box and the vehicle's motor range in the identified speeds, in closed form.
    p, r = out.motor_exponent, out.rpm_ref
    top = r * (7000.0 / r) ** p  # motor.gain not freed: 1
    assert data["bounds"] == {"rpm": [0.0, pytest.approx(top, abs=1e-3)], "airspeed": [0.0, 20.0]}
    motor = out.config["motor"]
    assert (motor["rpm_min"], motor["rpm_max"]) == (0.0, pytest.approx(top, abs=1e-3))
    file_motor = vehicle_config("sui_endurance")["motor"]
    assert identified.config["motor"]["rpm_max"] == file_motor["rpm_max"]  # not freed: as given


RADIUS_STEP = 0.004  # log-factor: the radius of the fit that measures the estimate's sensitivity


@pytest.fixture(scope="module")
def shifted():
    """The fixture's fit again with the file's radius ``RADIUS_STEP`` (log) larger, nothing
    considered: the difference is the estimate's sensitivity to the radius."""
    lab = _labels(_theta(TRUE), N, seed=0)
    cfg = vehicle_config("sui_endurance")
    cfg["rotor"]["radius"] *= math.exp(RADIUS_STEP)
    return identify(lab, cfg, free=tuple(TRUE), physics=PHYSICS, max_steps=30, passes=2)


def test_considered_parameters_widen_the_errors_by_the_estimates_sensitivity(identified, shifted):
    """A parameter held at the file's value with a standard deviation (``consider``, the
    fixture's radius): each free parameter's variance grows by ``(s σ)²``, ``s`` the
    estimate's sensitivity to it, here checked against the difference of a fit whose file
    holds the radius 0.4 % larger; the summary names it."""
    h = RADIUS_STEP
    assert identified.considered == {"rotor.radius": CONSIDER_SD}
    assert "rotor.radius (sd 0.02" in identified.summary()
    moved = []
    for name in TRUE:
        p = identified.parameters[name]
        s = math.log(shifted.parameters[name]["value"] / p["value"]) / h
        extra = (p["se"] / p["value"]) ** 2 - (p["se_data"] / p["value"]) ** 2
        # One-sided: the curvature's O(h) share (6 % at h = 0.01, 2.5 % here: it halves with
        # h), the fits' 1e-4 convergence in θ (under 1 % of s h) and the refitted model-error
        # variances the linear sensitivity holds fixed: 10 %.
        assert math.sqrt(extra) == pytest.approx(abs(s) * CONSIDER_SD, rel=0.1), (name, s)
        moved.append(abs(s) * h)
    assert max(moved) > 0.01  # the radius matters here: the check can fail


def _hover_of(config, chord=0.0, radius=0.0):
    """``(P_F, T_z)`` of a vehicle file with its chord and radius scaled by ``e^chord`` and
    ``e^radius``, through the file and the public hover fit."""
    cfg = {**config, "rotor": dict(config["rotor"])}
    cfg["rotor"]["chord_in"] = [c * math.exp(chord) for c in cfg["rotor"]["chord_in"]]
    cfg["rotor"]["radius"] = cfg["rotor"]["radius"] * math.exp(radius)
    return np.array(hover_coefficients(Vehicle.from_config(cfg), PHYSICS))


def test_coefficients_carry_the_parameters_errors(identified, shifted):
    """``M``'s coefficients of the identified file with standard errors: the labels' part is
    the chord's error through the hover's slope in it (the drag areas do not enter a hover),
    and the considered radius's part goes through its direct effect and the chord's response
    to it, which cancel where the labels fix the thrust: ``P_F``'s error is then far under
    what the chord's error alone implies. References: central differences of the public
    hover fit of the written file and the refit's sensitivity."""
    e = 1e-3
    g_c = (_hover_of(identified.config, chord=e) - _hover_of(identified.config, chord=-e)) / (2 * e)
    g_r = (_hover_of(identified.config, radius=e) - _hover_of(identified.config, radius=-e)) / (
        2 * e
    )
    chord = identified.parameters["rotor.chord"]
    s = math.log(shifted.parameters["rotor.chord"]["value"] / chord["value"]) / RADIUS_STEP
    nominal = hover_coefficients(load_vehicle("sui_endurance"), PHYSICS)
    for i, key in enumerate(("thrust_coefficient", "torque_coefficient")):
        c = identified.coefficients[key]
        assert c["value"] == identified.config["simple_model"][key]
        assert c["value"] == pytest.approx(_hover_of(identified.config)[i], rel=1e-12)
        assert c["nominal"] == pytest.approx(nominal[i], rel=1e-12)
        # The difference's O(e²) truncation (1e-6 here) and the inflow's fixed iterations.
        assert c["se_data"] == pytest.approx(abs(g_c[i]) * chord["se_data"] / chord["value"],
                                             rel=1e-4)  # fmt: skip
        lever = math.sqrt(c["se"] ** 2 - c["se_data"] ** 2) / CONSIDER_SD
        # s is held to 10 % in the test above: that much of g_c s, in the difference
        assert abs(lever - abs(g_c[i] * s + g_r[i])) <= 0.1 * abs(g_c[i] * s), (key, lever)
        assert c["se"] < 0.25 * abs(g_c[i]) * chord["se"] / chord["value"]  # the cancellation
    assert "thrust_coefficient" in identified.summary()


def test_errors_owed_to_the_considered_parameters_named(identified_and_warnings):
    """The parameters whose standard error the considered radius widens over 3 times are
    named in one warning with the radius; the others are not."""
    out, said = identified_and_warnings
    widened = {n for n, p in out.parameters.items() if p["se"] > 3 * p["se_data"]}
    assert widened and widened != set(TRUE)  # both kinds here: the check can fail
    msg = [m for m in said if "owe their standard errors" in m]
    assert len(msg) == 1 and "rotor.radius" in msg[0], said
    assert {n for n in TRUE if n in msg[0]} == widened


@pytest.mark.parametrize(
    "consider, message",
    [
        ({"drag_area.x": 0.1}, "not free"),
        ({"rotor.span": 0.1}, "not free"),
        ({"rotor.radius": 0.0}, "positive finite"),
        ("drag_area.z", "not free, got 'drag_area.z'"),  # a name, not its letters
    ],
)
def test_bad_considered_parameters_named(consider, message):
    lab = _labels(np.zeros(len(ALL)), N, seed=2)
    with pytest.raises(ValueError, match=message):
        identify(lab, "sui_endurance", free=tuple(TRUE), physics=PHYSICS, consider=consider)


def _bartlett_reference(g, part, t, lags):
    """The Bartlett window's sum written out pair by pair within each flight in time."""
    B = np.zeros((g.shape[1], g.shape[1]))
    for f in np.unique(part):
        idx = np.flatnonzero(part == f)
        x = g[idx[np.argsort(t[idx])]]
        for i in range(len(x)):
            for j in range(len(x)):
                if abs(i - j) <= lags:
                    B += (1 - abs(i - j) / (lags + 1)) * np.outer(x[i], x[j])
    return B


def test_long_run_covariance_sums_each_flights_lags_in_time():
    """``_long_run`` against the window written out: three flights of unequal length, their
    labels shuffled (the lags follow each flight's time, never span two); the lags at least
    Newey and West's rule; positive semi-definite."""
    rng = np.random.default_rng(4)
    part = np.repeat([0, 1, 2], [40, 70, 25])
    t = np.concatenate([np.arange(40), np.arange(70), np.arange(25)]) * 0.1
    g = rng.normal(size=(len(part), 3))
    g += 0.8 * np.roll(g, 1, 0)  # correlated neighbours: Andrews' lags above the rule's
    shuffle = rng.permutation(len(part))
    B, lags = _long_run(g[shuffle], part[shuffle], t[shuffle])
    assert lags >= int(4 * (len(part) / 100) ** (2 / 9))
    # float64 sums of ~10⁴ products in another order: rounding relative to B's largest entry
    np.testing.assert_allclose(B, _bartlett_reference(g, part, t, lags), rtol=1e-12,
                               atol=1e-12 * np.abs(B).max())  # fmt: skip
    assert np.linalg.eigvalsh(B).min() > 0


def test_sandwich_holds_the_variance_of_a_regression_with_correlated_errors():
    """Least squares on four flights whose errors are AR(1) along each (ρ = 0.6): the estimate's
    variance is ``A Xᵀ Σ X A`` (``A = (XᵀX)⁻¹``, closed form). The sandwich of the residuals'
    scores, averaged over 200 draws, holds it: under by Bartlett's window at Andrews' lags
    (1 + 2 Σ_l≤15 (1 − l/16) ρˡ = 3.53 of (1 + ρ)/(1 − ρ) = 4 for the intercept: 0.88) and
    the residuals' own, over by at most the draws' error (a few %). The independent labels'
    ``A (Σ g gᵀ) A`` is a quarter to a half of it: the check can fail."""
    rho, m, flights = 0.6, 150, 4
    t = np.tile(np.arange(m) * 0.1, flights)
    part = np.repeat(np.arange(flights), m)
    X = np.column_stack([np.ones(m * flights), np.sin(2 * np.pi * t / 1.5)])
    C = rho ** np.abs(np.subtract.outer(np.arange(m), np.arange(m)))
    A = np.linalg.inv(X.T @ X)
    true = np.diag(A @ X.T @ np.kron(np.eye(flights), C) @ X @ A)
    chol = np.linalg.cholesky(C)
    rng = np.random.default_rng(0)
    sandwich, independent = [], []
    for _ in range(200):
        e = (chol @ rng.normal(size=(m, flights))).T.ravel()
        y = X @ np.array([1.0, 2.0]) + e
        g = X * (y - X @ (A @ X.T @ y))[:, None]
        sandwich.append(np.diag(A @ _long_run(g, part, t)[0] @ A))
        independent.append(np.diag(A @ (g.T @ g) @ A))
    ratio = np.mean(sandwich, 0) / true
    assert np.all((ratio > 0.75) & (ratio < 1.05)), ratio
    assert np.all(np.mean(independent, 0) / true < 0.5)
