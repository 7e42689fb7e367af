"""A flight whose signals agree with each other exactly (written out, not simulated): the
kinematics that gpg.flight.kinematics checks hold by construction."""

import numpy as np

from gpg.flight.log import FlightLog, matrix_to_quat

GRAVITY = 9.81
TILT = (0.15, -0.1)  # rad, a fixed roll and pitch under the turning yaw


def _Rz(a):
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    rows = [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)]
    return np.stack(rows, -2)


def _R0():
    r, p = TILT
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    return Ry @ Rx


def _rocking(t):
    """``R = Ry(θ) Rx(φ)`` (yaw held, as a figure-eight's controller holds it), rolling and
    pitching at up to 6 and 5 rad/s: body rates ``(φ', θ' cos φ, −θ' sin φ)`` (``Rᵀ Ṙ =
    [φ' e_x]× + [θ' Rxᵀ e_y]×``), the yaw rate small beside the others."""
    phi, dphi = 0.6 * np.sin(10.0 * t), 6.0 * np.cos(10.0 * t)
    th, dth = 0.6 * np.sin(8.0 * t + 0.3), 4.8 * np.cos(8.0 * t + 0.3)
    c, s, z, o = np.cos(phi), np.sin(phi), np.zeros_like(t), np.ones_like(t)
    Rx = np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)
    c, s = np.cos(th), np.sin(th)
    Ry = np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)
    return Ry @ Rx, np.stack([dphi, dth * np.cos(phi), -dth * np.sin(phi)], 1)


def consistent_flight(n=400, rate=100.0, seed=0, rocking=False, **over) -> FlightLog:
    """A smooth flight, NED/FRD: position and its derivative, an attitude ``Rz(ψ(t)) R0`` with
    the body rates ``ψ' R0ᵀ e_z`` it implies (``rocking``: rolling and pitching hard instead,
    :func:`_rocking`), the specific force ``Rᵀ(a − g e_z)``; rotor speeds, commands, wind and
    voltage drawn at random (nothing ties them). ``over`` replaces any field (the checks run
    on what is given)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    p = np.stack([2 * np.sin(0.8 * t), 1.5 * np.cos(0.6 * t) - 1.5, -3 - 0.5 * np.sin(0.4 * t)], 1)
    v = np.stack([1.6 * np.cos(0.8 * t), -0.9 * np.sin(0.6 * t), -0.2 * np.cos(0.4 * t)], 1)
    a = np.stack([-1.28 * np.sin(0.8 * t), -0.54 * np.cos(0.6 * t), 0.08 * np.sin(0.4 * t)], 1)
    psi = 0.7 * np.sin(0.9 * t) + 0.3 * t
    dpsi = 0.63 * np.cos(0.9 * t) + 0.3
    R0 = _R0()
    R = _Rz(psi) @ R0
    rates = dpsi[:, None] * (R0.T @ [0.0, 0.0, 1.0])[None, :]
    if rocking:
        R, rates = _rocking(t)
    f_B = np.einsum("nji,nj->ni", R, a - [0.0, 0.0, GRAVITY])
    kw = dict(
        t=t,
        position=p,
        velocity=v,
        quaternion=matrix_to_quat(R),
        rates=rates,
        rpm=rng.uniform(2000, 5000, (n, 4)),
        command=rng.uniform(0.2, 0.8, (n, 4)),
        specific_force=f_B,
        wind=rng.normal(size=(n, 3)),
        voltage=rng.uniform(14, 16, n),
        name="log",
    )
    kw.update(over)
    return FlightLog(**kw)
