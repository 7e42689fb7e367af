"""M_noise: Gutin's steady tone and the compact thickness tone, from M's loads alone."""

import numpy as np
import pytest
from scipy.special import jv

from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.simple_noise import SimpleNoise
from gpg.quadrotor.vehicle import load_vehicle


@pytest.fixture(scope="module")
def mnoise(vehicle):
    simple = SimpleModel.from_vehicle(vehicle, 5.3e-7, 8.4e-9)
    return SimpleNoise.from_vehicle(vehicle, simple)


def hand_level(vehicle, m_noise, rpm, mic):
    """One rotor (r1) alone at microphone ``mic``: Gutin's steady loading plus the compact
    thickness tone, summed over the harmonics, written out with SciPy's Bessel functions."""
    rot, B = vehicle.rotor, vehicle.rotor.n_blades
    c0, rho = float(vehicle.speed_of_sound), float(vehicle.air_density)
    R = float(rot.radius)
    Re = 0.8 * R
    omega = rpm * 2 * np.pi / 60
    T, Q = float(m_noise.P_F) * rpm**2, float(m_noise.T_z) * rpm**2
    o = np.asarray(vehicle.mic_positions[mic]) - np.asarray(vehicle.positions[0])
    S = np.linalg.norm(o)
    cos_t, sin_t = -o[2] / S, np.hypot(o[0], o[1]) / S
    # thickness stations as the model integrates them
    edges = np.linspace(float(rot.root_cutout), 1.0, m_noise.thickness_stations + 1)
    x = 0.5 * (edges[1:] + edges[:-1])
    dr = np.diff(edges) * R
    chord = np.interp(x, np.asarray(rot.stations), np.asarray(rot.chord))
    area = (2 / 3) * chord**2 * float(rot.thickness_ratio)
    msq = 0.0
    for m in range(1, m_noise.n_harmonics + 1):
        mB = m * B
        z = mB * omega * Re * sin_t / c0
        # Gutin: p = mB Ω/(2π c0 S) |−T cos θ + c0 Q/(Ω Re²)| J_mB(z), per-blade loads × B
        p_load = mB * omega / (2 * np.pi * c0 * S) * abs(-T * cos_t + c0 * Q / (omega * Re**2))
        p_load *= abs(jv(mB, z))
        Jt = jv(mB, z / 0.8 * x)
        p_thick = rho * (mB * omega) ** 2 * B / (2 * np.pi) * abs(np.sum(area * dr * Jt)) / S
        msq += 0.5 * (p_load**2 + p_thick**2)
    return msq


def test_one_rotor_at_one_microphone_matches_a_hand_computation(vehicle, mnoise):
    rpm = 4000.0
    # Rotor r1 alone: the others at zero rpm are silent (their mean square is exactly zero).
    x = np.array([[rpm, 0.0, 0.0, 0.0, 0.1, -0.2, 0.3, 12.0]])
    level = float(mnoise.batch(x)[0][0, 0])
    want = 10 * np.log10(hand_level(vehicle, mnoise, rpm, 0) / (20e-6) ** 2 + 1.0)
    np.testing.assert_allclose(level, want, rtol=1e-9)


def test_depends_on_rotor_speeds_only_and_grows_with_them(mnoise):
    X = np.array(
        [[3500.0] * 4 + [0.0, 0.0, 0.0, 0.0], [3500.0] * 4 + [0.5, -0.3, 0.2, 15.0]]
        + [[4500.0] * 4 + [0.0, 0.0, 0.0, 0.0]]
    )
    a, b, c = np.asarray(mnoise.batch(X)[0])
    np.testing.assert_array_equal(a, b)
    assert np.all(c > a)


def test_jacobian_matches_finite_differences(mnoise, rng):
    x = np.concatenate([rng.uniform(2500, 5500, 4), [0.1, -0.2, 0.3, 8.0]])
    h = 1e-3
    steps = np.concatenate([x + h * np.eye(8), x - h * np.eye(8), x[None]])
    y, jac = (np.asarray(a) for a in mnoise.batch(steps))  # one compiled call for all
    fd = ((y[:8] - y[8:16]) / (2 * h)).T
    J = jac[16]
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-9)
    assert np.all(J[:, 4:] == 0.0)


def test_a_vehicle_without_acoustics_is_refused():
    minimal = load_vehicle("minimal_example")
    simple = SimpleModel.from_vehicle(minimal, 5e-7, 8e-9)
    with pytest.raises(ValueError, match="M_noise needs the vehicle's rotor, microphones"):
        SimpleNoise.from_vehicle(minimal, simple)
