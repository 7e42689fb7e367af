"""Tonal rotor noise at the microphones: a stand-in for PSU-WOPWOP's tones.

Per rotor and blade-passage harmonic ``m = 1..10`` (frequency ``mBΩ``), far field, compact
chord, sources at an effective radius ``R_e`` for loading:

* **Loading** (Gutin's steady result generalised to azimuthally varying blade loads, after
  Lowson): with one blade's thrust ``T(ψ) = Σ_λ T_λ e^{iλψ}`` and in-plane drag
  ``D(ψ) = Σ_λ D_λ e^{iλψ}`` at ``R_e``, observer distance ``S``, polar angle ``θ`` from the
  thrust axis and azimuth ``φ`` in the rotor's ψ convention, the harmonic's peak amplitude is

  ``p_L = (mB²Ω / 2πc₀S) |Σ_λ e^{-i(mB−λ)(φ−π/2)} J_{mB−λ}(mBΩR_e sin θ/c₀)
  [−T_λ cos θ + (mB−λ)/(mB) · c₀/(ΩR_e) · D_λ]|``.

  ``λ = 0`` is Gutin's formula (steady thrust and torque); ``λ ≠ 0`` is unsteady loading, the
  only loading term that reaches an observer on the rotor axis (``J_{mB−λ}(0) = 0`` unless
  ``λ = mB``), so the microphone below the vehicle hears tones only when the blade loads vary
  around the azimuth, as in edgewise flight.
* **Thickness** (compact monopole of the blade's cross-section area ``A(r)``, derived from the
  Ffowcs Williams–Hawkings thickness term; Hanson's compact-chord limit):
  ``p_V = (ρ₀ (mBΩ)² B / 2πS) |∫ A(r) J_{mB}(mBΩ r sin θ/c₀) dr|`` with the parabolic-arc
  area ``A = (2/3) c t``.

Thickness and steady loading harmonics are in quadrature, so their powers add; the rms of a
harmonic is its peak amplitude over √2. The four rotors (and the harmonics) are summed
incoherently into an OASPL in dB re 20 µPa. Forward-flight Doppler and convective
amplification (flight Mach ≤ 0.06 here) and broadband noise are left out.

Bessel functions of integer order come from their power series, evaluated by the term
recurrence: polynomial in ``z``, so value and gradient are finite everywhere (``z = 0``
included, where ``jax.scipy.special.bessel_jn`` returns NaN), and accurate to about 1e-14 for
the arguments that occur here (``z <= mB·ΩR/c₀ < 9``); the test checks it against SciPy.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from gpg._precision import highest
from gpg.quadrotor.bemt import AeroResult, radial_elements
from gpg.quadrotor.vehicle import Vehicle

__all__ = ["AcousticsConfig", "harmonic_msq", "oaspl"]

P_REF = 20e-6  # Pa, reference pressure for dB


class AcousticsConfig(eqx.Module):
    """Static settings of the tonal-noise model."""

    n_harmonics: int = eqx.field(static=True, default=10)
    effective_radius: float = eqx.field(static=True, default=0.8)  # R_e / R for loading
    thickness_stations: int = eqx.field(static=True, default=16)  # radial nodes, thickness


def bessel_j(
    n: Float[Array, "..."], z: Float[Array, "..."], max_order: int = 40, terms: int = 32
) -> Float[Array, "..."]:
    """``J_n(z)`` for integer-valued ``n`` (``|n| <= max_order``) and ``0 <= z < 12``.

    ``J_n(z) = Σ_k t_k`` with ``t_0 = (z/2)^|n| / |n|!`` and
    ``t_{k+1} = −t_k (z/2)² / ((k+1)(|n|+k+1))``; ``J_{−n} = (−1)^n J_n``.
    """
    n = jnp.asarray(n, dtype=float)
    z = jnp.asarray(z, dtype=float)
    n, z = jnp.broadcast_arrays(n, z)
    a = jnp.abs(n)
    h = 0.5 * z
    t = jnp.ones_like(z)
    for j in range(1, max_order + 1):  # (z/2)^|n|/|n|!, one factor per order below |n|
        t = jnp.where(a >= j, t * (h / j), t)
    total = t
    h2 = h * h
    for k in range(terms):
        t = -t * h2 / ((k + 1) * (a + k + 1))
        total = total + t
    sign = jnp.where((n < 0) & (jnp.mod(a, 2) == 1), -1.0, 1.0)
    return sign * total


DEFAULT = AcousticsConfig()


def _observer_geometry(vehicle: Vehicle):
    """Distance, cos θ, sin θ and azimuth φ of each microphone seen from each hub: (4, K)."""
    o = vehicle.mic_positions[None, :, :] - vehicle.positions[:, None, :]  # (4, K, 3)
    dist = jnp.sqrt(jnp.sum(o**2, -1))
    cos_t = -o[..., 2] / dist  # thrust axis is −z_B
    sin_t = jnp.sqrt(o[..., 0] ** 2 + o[..., 1] ** 2) / dist
    spin = vehicle.spin[:, None]
    phi = jnp.arctan2(spin * o[..., 1], o[..., 0])  # ψ convention e_r = (cos ψ, d sin ψ)
    return dist, cos_t, sin_t, phi


@highest
def harmonic_msq(
    vehicle: Vehicle, aero: AeroResult, cfg: AcousticsConfig = DEFAULT
) -> tuple[Float[Array, "4 K H"], Float[Array, "4 K H"]]:
    """Mean-square pressures (Pa²) of loading and thickness noise: (rotor, microphone, harmonic).

    Mean squares rather than amplitudes so that a silent rotor has a zero with a finite
    gradient (an amplitude ``|p|`` has none at zero). Loading follows the Gutin–Lowson series
    over the blade-load harmonics ``λ`` (module docstring), thickness the compact monopole of
    the section area; the rms of each harmonic is its peak over √2.

    Args:
        vehicle: the vehicle; its rotor geometry, microphone positions, air density and speed
            of sound enter (a full vehicle, as the generator needs).
        aero: the rotors' loads, of which ``omega`` (rad/s) and the per-blade azimuthal loads
            ``rotors.blade_thrust``/``rotors.blade_torque`` (4, P) are read.
        cfg: the number of BPF harmonics ``m = 1..H``, the loading radius ``R_e/R`` and the
            radial stations of the thickness integral.

    Returns:
        The loading and the thickness mean squares (Pa²), each (4, K, H): rotor, microphone,
        harmonic ``m``.
    """
    B = vehicle.rotor.n_blades
    c0, rho = vehicle.speed_of_sound, vehicle.air_density
    R = vehicle.rotor.radius
    Re = cfg.effective_radius * R
    omega = aero.omega  # (4,)
    dist, cos_t, sin_t, phi = _observer_geometry(vehicle)
    m = jnp.arange(1, cfg.n_harmonics + 1, dtype=float)  # (H,)
    mB = m * B

    # Blade-load harmonics, F(ψ) = Σ_λ F_λ e^{iλψ}, for λ = −L..L (L below Nyquist).
    n_psi = aero.rotors.blade_thrust.shape[-1]
    L = (n_psi - 1) // 2
    lam = jnp.arange(-L, L + 1, dtype=float)  # (Λ,)
    psi = 2.0 * jnp.pi * jnp.arange(n_psi) / n_psi
    basis = jnp.exp(-1j * lam[:, None] * psi[None, :]) / n_psi  # (Λ, P)
    T_l = aero.rotors.blade_thrust @ basis.T  # (4, Λ)
    D_l = (aero.rotors.blade_torque / Re) @ basis.T  # (4, Λ)

    order = mB[:, None] - lam[None, :]  # (H, Λ)
    mach_e = omega * Re / c0  # (4,)
    z = mB[None, None, :] * mach_e[:, None, None] * sin_t[:, :, None]  # (4, K, H)
    J = bessel_j(order[None, None], z[..., None])  # (4, K, H, Λ)
    phase = jnp.exp(-1j * order[None, None] * (phi[:, :, None, None] - jnp.pi / 2))
    # Drag term c₀/(ΩR_e)·(mB−λ)/mB·D_λ; D_λ ∝ Ω², so dividing by a floored Ω gives 0 at Ω = 0.
    drag = (order / mB[:, None])[None] * D_l[:, None, :] * (c0 / Re)  # (4, H, Λ)
    drag = drag / jnp.maximum(omega, 1e-9)[:, None, None]
    bracket = -T_l[:, None, None, :] * cos_t[:, :, None, None] + drag[:, None, :, :]
    series = jnp.sum(phase * J * bracket, axis=-1)  # (4, K, H)
    pref = m[None, :] * B**2 * omega[:, None] / (2 * jnp.pi * c0)  # (4, H)
    amp2 = (pref[:, None, :] / dist[:, :, None]) ** 2 * (series.real**2 + series.imag**2)

    # Thickness: compact monopole of the section area along the span.
    rot = vehicle.rotor
    x, dr, chord = radial_elements(rot, cfg.thickness_stations)
    area = (2.0 / 3.0) * chord**2 * rot.thickness_ratio  # (S,)
    kr = z / cfg.effective_radius  # (4, K, H): the loading argument per unit r/R
    Jt = bessel_j(mB[None, None, :, None], kr[..., None] * x)  # (4, K, H, S)
    integral = jnp.sum(area * dr * Jt, axis=-1)  # (4, K, H)
    thick = rho * (mB[None, None, :] * omega[:, None, None]) ** 2 * B / (2 * jnp.pi)
    thick2 = (thick * integral / dist[:, :, None]) ** 2
    return 0.5 * amp2, 0.5 * thick2  # rms² = peak²/2


def oaspl(vehicle: Vehicle, aero: AeroResult, cfg: AcousticsConfig = DEFAULT) -> Float[Array, " K"]:
    """Overall tonal sound pressure level (dB re 20 µPa) at each microphone.

    Sum of the mean squares of the first ``cfg.n_harmonics`` BPF harmonics of loading and
    thickness noise of the four rotors (:func:`harmonic_msq`), summed incoherently. A silent
    vehicle gives 0 dB: the reference pressure is added to the sum, so the level stays finite
    and differentiable at zero rpm.

    Args:
        vehicle: the (full) vehicle whose microphones hear the rotors.
        aero: the rotor speeds and blade loads of :func:`gpg.quadrotor.bemt.aero` (or of
            ``M_noise``'s prescribed loads).
        cfg: the tonal-noise settings (harmonics, effective radius, thickness stations).

    Returns:
        The (K,) OASPL in dB re 20 µPa, one per microphone.
    """
    load, thick = harmonic_msq(vehicle, aero, cfg)
    msq = jnp.sum(load + thick, axis=(0, 2))
    return 10.0 * jnp.log10(msq / P_REF**2 + 1.0)
