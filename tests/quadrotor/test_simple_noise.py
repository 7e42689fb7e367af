"""M_noise: Gutin's tones and the compact thickness tone from M's loads, shaped around the
azimuth by one quasi-steady blade strip."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
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
    # Rotor r1 alone: the others at zero rpm are silent (their mean square is exactly zero). At
    # zero airspeed the blade loads are uniform around the azimuth, whatever the attitude:
    # Gutin's steady tone.
    x = np.array([[rpm, 0.0, 0.0, 0.0, 0.1, -0.2, 0.3, 0.0]])
    level = float(mnoise.batch(x)[0][0, 0])
    want = 10 * np.log10(hand_level(vehicle, mnoise, rpm, 0) / (20e-6) ** 2 + 1.0)
    np.testing.assert_allclose(level, want, rtol=1e-9)


def hand_shape(vehicle, m_noise, x):
    """The blade load over its mean, (4, P), in NumPy: quasi-steady lift ``c U² (θ − α₀ − φ)``
    summed over equal span elements, Drees' inflow around Glauert's ``v₀`` from M's thrust."""
    rot = vehicle.rotor
    R, rho = float(rot.radius), float(vehicle.air_density)
    rpm = x[:4]
    omega = rpm * 2 * np.pi / 60
    # yaw-pitch-roll (z-y'-x''), body to world; the air moves at −(V, 0, 0) past the vehicle
    R_wb = Rotation.from_euler("ZYX", x[4:7]).as_matrix()
    v_in = -(R_wb.T @ np.array([x[7], 0.0, 0.0]))[:2]
    edges = np.linspace(float(rot.root_cutout), 1.0, m_noise.n_strips + 1)
    xs = 0.5 * (edges[1:] + edges[:-1])[:, None]  # (S, 1)
    stations, twist, chord = (np.asarray(a) for a in (rot.stations, rot.twist, rot.chord))
    c = np.interp(xs, stations, chord)
    pitch = np.interp(xs, stations, twist) - float(vehicle.airfoil.alpha_zero_lift)
    P = m_noise.n_azimuth
    psi = 2 * np.pi * np.arange(P) / P
    out = np.empty((4, P))
    for i in range(4):
        d = float(vehicle.spin[i])
        e_t = np.stack([-np.sin(psi), d * np.cos(psi)], -1)  # blade motion direction
        e_r = np.stack([np.cos(psi), d * np.sin(psi)], -1)
        v_t, v_r = e_t @ v_in, e_r @ v_in
        V = np.hypot(*v_in)
        T = float(m_noise.P_F) * rpm[i] ** 2
        vh4 = (T / (2 * rho * np.pi * R**2)) ** 2
        v0 = np.sqrt(np.sqrt(V**4 / 4 + vh4) - V**2 / 2)  # v0⁴ + V² v0² = vh⁴
        ref = np.hypot(omega[i] * R, V)
        mu, lam = V / ref, v0 / ref
        kx = 4 / 3 * (mu / (np.hypot(mu, lam) + lam) - 1.8 * mu * np.hypot(mu, lam))
        v_i = v0 * (1 + xs * (kx * v_r / V - 2 * mu * (-v_t / V)))  # (S, P)
        u_t = omega[i] * xs * R - v_t
        # incidence floored smoothly at zero (0.01 rad softplus): the retreating root stalls
        aoa = 0.01 * np.logaddexp(0.0, (pitch - np.arctan2(v_i, u_t)) / 0.01)
        lift = np.sum(c * (u_t**2 + v_i**2) * aoa, axis=0)  # equal element widths
        out[i] = lift / lift.mean()
    return out


def test_blade_load_shape_matches_a_numpy_strip(vehicle, mnoise):
    x = np.array([3800.0, 4100.0, 3600.0, 3900.0, 0.4, -0.25, 0.15, 14.0])
    got = np.asarray(mnoise.load_shape(x))
    want = hand_shape(vehicle, mnoise, x)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # The advancing blade carries more load, by more than the in-plane speed alone explains
    # at this advance ratio (the Drees inflow adds to it).
    assert got.max() > 1.1 and got.min() < 0.9


def test_levels_at_rest_depend_on_rotor_speeds_only_and_edgewise_flight_is_heard_below(mnoise):
    hover = [3500.0] * 4
    X = np.array(
        [
            hover + [0.0, 0.0, 0.0, 0.0],
            hover + [0.5, -0.3, 0.2, 0.0],
            [4500.0] * 4 + [0.0, 0.0, 0.0, 0.0],
            hover + [0.0, -0.1, 0.0, 15.0],
        ]
    )
    a, b, c, d = np.asarray(mnoise.batch(X)[0])
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert np.all(c > a)
    # The microphone below (L3) hears loading noise only when the loads vary around the
    # azimuth: at 15 m/s it is tens of dB louder than at rest.
    assert d[2] > a[2] + 10.0


def test_jacobian_matches_finite_differences(mnoise, rng):
    x = np.concatenate([rng.uniform(2500, 5500, 4), [0.1, -0.2, 0.3, 8.0]])
    h = np.array([1e-3] * 4 + [1e-6] * 3 + [1e-5])
    steps = np.concatenate([x + np.diag(h), x - np.diag(h), x[None]])
    y, jac = (np.asarray(a) for a in mnoise.batch(steps))  # one compiled call for all
    fd = ((y[:8] - y[8:16]) / (2 * h[:, None])).T
    J = jac[16]
    np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-6)
    assert np.all(np.abs(J[:, 4:]).max(0) > 1e-3)  # attitude and airspeed now enter


def test_body_frame_inputs_are_the_same_physics(mnoise, rng):
    """At ``x_B = (r, R_WB(θ)ᵀ V e_x)`` the body-frame M_noise equals the airflow-frame one at
    ``(r, θ, V)`` (the same float64 operations up to the rotation's rounding: 1e-12), and its
    Jacobian carried through ``∂x_B/∂(θ, V)`` (the chain rule, in NumPy) equals the airflow
    frame's (1e-9 of its largest entry: both are forward-mode derivatives of the same sums)."""
    n = 3
    rpm = rng.uniform(2500, 5500, (n, 4))
    ang = rng.uniform([-1.2, -0.8, -1.0], [1.2, 0.8, 1.0], (n, 3))
    V = rng.uniform(2.0, 15.0, n)
    y_a, J_a = (np.asarray(a) for a in mnoise.batch(np.c_[rpm, ang, V]))
    R = Rotation.from_euler("ZYX", ang).as_matrix()  # R_WB = Rz(yaw) Ry(pitch) Rx(roll)
    v_b = R[:, 0, :] * V[:, None]  # R_WBᵀ (V, 0, 0): the first row of R_WB, times V
    y_b, J_b = (np.asarray(a) for a in mnoise.batch(np.c_[rpm, v_b]))
    np.testing.assert_allclose(y_b, y_a, rtol=1e-12)
    # ∂v_B/∂(θ, V) by central differences of the closed form (exact to 1e-10 at h = 1e-6)
    h = 1e-6
    for i in range(n):
        cols = []
        for k in range(3):
            d = np.zeros(3)
            d[k] = h
            Rp = Rotation.from_euler("ZYX", ang[i] + d).as_matrix()
            Rm = Rotation.from_euler("ZYX", ang[i] - d).as_matrix()
            cols.append((Rp[0] - Rm[0]) * V[i] / (2 * h))
        dvb = np.c_[np.array(cols).T, R[i, 0]]  # (3, 4): yaw, pitch, roll, V
        want = np.c_[J_b[i, :, :4], J_b[i, :, 4:] @ dvb]
        np.testing.assert_allclose(want, J_a[i], atol=1e-9 * np.abs(J_a[i]).max())


def test_inputs_of_the_wrong_shape_are_refused(mnoise):
    with pytest.raises(ValueError, match=r"X must have shape \(N, 8\).*or \(N, 7\)"):
        mnoise.batch(np.zeros((3, 6)))
    with pytest.raises(ValueError, match="x must be one dataset input"):
        mnoise(np.zeros(6))


def test_a_vehicle_without_acoustics_is_refused():
    minimal = load_vehicle("minimal_example")
    simple = SimpleModel.from_vehicle(minimal, 5e-7, 8e-9)
    with pytest.raises(ValueError, match="M_noise needs the vehicle's rotor, airfoil, microphones"):
        SimpleNoise.from_vehicle(minimal, simple)
