"""``M_noise``: a simplified model of the three microphone levels, in the spirit of ``M``.

The paper attributes the poor noise predictions of every model to the absence of a simplified
noise model to take residuals against (its future work). ``M_noise`` is the generator's tonal
noise (:mod:`gpg.quadrotor.acoustics`, the same formulas) with the blade-element/momentum inflow
solution replaced by ``M`` and a prescribed inflow:

* **Mean loads** are ``M``'s: thrust ``T_i = P_F r_i²`` and drag torque ``Q_i = T_z r_i²``.
* **Their variation around the azimuth** (the unsteady loading that edgewise flight causes, and
  the only loading noise that reaches a microphone near the rotor axis) comes from a
  quasi-steady blade-element sum with a prescribed inflow: at ``n_strips`` stations the section
  lift per span ``∝ c U² (θ − α₀ − φ)`` with the local speed ``U_T = Ω r − v_t(ψ)``, the
  blade's pitch ``θ`` from the twist table, the airfoil's zero-lift angle ``α₀``, and Drees'
  linear inflow ``v_i(r, ψ)`` around a mean ``v₀`` from momentum theory with ``M``'s thrust
  (Glauert's closed form, no iteration). It only shapes the loads: ``T(ψ) = T_i s(ψ)/B`` with
  ``s`` normalised to mean one, and the torque follows the same shape.
* **Thickness** noise of the blades, as in the generator.

The in-plane air velocity at each hub follows from the attitude and airspeed inputs as in the
generator, or, for a body-frame input ``x_B = (r1..r4, u, v, w)`` (seven entries, the
``frame="body"`` datasets of :mod:`gpg.data`), is its ``(u, v)``: the same physics, with
``M_noise_B(r, R_WB(θ)ᵀ V e_x) = M_noise(r, θ, V)``. Left out after an exploratory check on
data=default (a script not kept in the repository): the axial flow through the disk, with
``v₀`` solved from momentum including it, made the training residual ``L − M_noise`` rougher,
most at L3 (``M``'s thrust, which sets ``v₀``, ignores the axial flow too); the generator's
nonlinear polar in place of the linear lift did not make it smoother; more span elements
changed it little. Body rates are not inputs. What ``M_noise`` misses (wake interference, the
real inflow solution, the polar, tip loss) is what the GP learns. Its Jacobian comes from
``jax.jacfwd``.

It needs the acoustic part of the vehicle (rotor geometry, airfoil, microphones, air
properties): a vehicle file for ``M`` and flight only has none, and
:meth:`SimpleNoise.from_vehicle` says so.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg._precision import highest
from gpg.quadrotor import acoustics
from gpg.quadrotor.bemt import AeroResult, RotorLoads, radial_elements
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.simple_model import SimpleModel, in_chunks
from gpg.quadrotor.vehicle import Vehicle

__all__ = ["SimpleNoise"]

RPM_TO_RAD_S = 2.0 * jnp.pi / 60.0
_EPS_V = 1e-6  # m/s, keeps speeds and their derivatives finite at rest


class SimpleNoise(eqx.Module):
    """``M_noise(x) -> (L1, L2, L3)`` dB at a dataset input ``x = (r1..r4, ψ, θ, φ, V)``, or at a
    body-frame one ``x_B = (r1..r4, u, v, w)`` (told apart by their length)."""

    vehicle: Vehicle
    P_F: Float[Array, ""]  # N/rpm², M's thrust coefficient
    T_z: Float[Array, ""]  # N·m/rpm², M's torque coefficient
    # The first four BPF harmonics and eight thickness stations: close to the ten and sixteen
    # of the generator's setting at hover, at a fraction of the cost (docs/measurements.md).
    n_harmonics: int = eqx.field(static=True, default=4)
    thickness_stations: int = eqx.field(static=True, default=8)
    # Twelve azimuthal stations resolve the load harmonics λ = 0..±5, enough for the on-axis
    # tones of the first two BPF harmonics (λ = mB = 2, 4).
    n_azimuth: int = eqx.field(static=True, default=12)
    n_strips: int = eqx.field(static=True, default=3)  # blade elements along the span

    @property
    def cfg(self) -> acoustics.AcousticsConfig:
        return acoustics.AcousticsConfig(
            n_harmonics=self.n_harmonics, thickness_stations=self.thickness_stations
        )

    @classmethod
    def from_vehicle(cls, vehicle: Vehicle, simple: SimpleModel) -> SimpleNoise:
        """``M_noise`` of ``vehicle`` with ``simple``'s coefficients.

        Args:
            vehicle: a vehicle with the acoustic data (rotor, airfoil, microphones, air
                density, speed of sound).
            simple: ``M``, whose ``P_F`` and ``T_z`` set the mean rotor loads.

        Returns:
            The noise model, with the default harmonics, stations and strips.

        Raises:
            ValueError: if the vehicle lacks any of the acoustic data, naming what.
        """
        missing = [
            k
            for k in ("rotor", "airfoil", "microphones", "air_density", "speed_of_sound")
            if k in vehicle.generator_missing
        ]
        if missing:
            raise ValueError(
                f"M_noise needs the vehicle's {', '.join(missing)} (vehicle {vehicle.name!r} "
                "has only what M needs); fit without it (noise_model=False)"
            )
        return cls(vehicle=vehicle, P_F=simple.P_F, T_z=simple.T_z)

    @highest
    def load_shape(self, x: Float[Array, " D"]) -> Float[Array, "4 P"]:
        """``s_i(ψ)``: each rotor's blade load at the azimuths ``2πk/P`` over its mean.

        From the quasi-steady blade elements with Drees' prescribed inflow around Glauert's
        ``v₀`` of ``M``'s thrust (module docstring).

        Args:
            x: one dataset input: (8,) ``(r1..r4, yaw, pitch, roll, V)`` in the airflow frame
                or (7,) ``(r1..r4, u, v, w)`` in the body frame.

        Returns:
            The (4, P) load shapes, each row of mean one, ``P = n_azimuth``.
        """
        veh, rot = self.vehicle, self.vehicle.rotor
        R = rot.radius
        omega = x[:4] * RPM_TO_RAD_S
        if x.shape[0] == 7:  # body frame: the air velocity is the input
            v_air_B = x[4:7]
        else:
            zero = jnp.zeros_like(x[7])
            v_air_B = R_WB(x[4:7]).T @ jnp.stack([x[7], zero, zero])
        v_in = -v_air_B[:2]  # air relative to the hubs, in the rotor plane (as the generator)
        psi = 2.0 * jnp.pi * jnp.arange(self.n_azimuth) / self.n_azimuth
        spin = veh.spin[:, None]
        v_t = -v_in[0] * jnp.sin(psi) + spin * v_in[1] * jnp.cos(psi)  # (4, P), along e_t
        v_r = v_in[0] * jnp.cos(psi) + spin * v_in[1] * jnp.sin(psi)
        speed2 = jnp.sum(v_in**2) + _EPS_V**2
        # Mean induced velocity from momentum theory with M's thrust: v₀⁴ + V²v₀² = v_h⁴
        # (Glauert's edgewise closed form; the axial flow is left out, see the module docstring).
        vh2 = self.P_F * x[:4] ** 2 / (2.0 * veh.air_density * rot.disk_area)
        v0 = jnp.sqrt(jnp.sqrt(0.25 * speed2**2 + vh2**2) - 0.5 * speed2 + _EPS_V**2)
        # Drees' linear inflow with the generator's bounded advance ratio (finite at zero rpm).
        ref = jnp.sqrt((omega * R) ** 2 + speed2)
        mu, lam = jnp.sqrt(speed2) / ref, v0 / ref
        hyp = jnp.sqrt(mu**2 + lam**2)
        kx = (4.0 / 3.0) * (mu / (hyp + lam) - 1.8 * mu * hyp)
        ky = -2.0 * mu
        speed = jnp.sqrt(speed2)
        cos_w, sin_w = v_r / speed, -v_t / speed
        x_s, dr, chord = radial_elements(rot, self.n_strips)  # (S,)
        twist = jnp.interp(x_s, rot.stations, rot.twist)
        v_i = v0[:, None, None] * (
            1.0
            + x_s[:, None]
            * (kx[:, None, None] * cos_w[:, None] + ky[:, None, None] * sin_w[:, None])
        )  # (4, S, P)
        u_t = (omega[:, None] * x_s * R)[..., None] - v_t[:, None, :]
        pitch = (twist - veh.airfoil.alpha_zero_lift)[:, None]
        # Linear lift above zero-lift, smoothly floored at 0 (a strip at negative incidence
        # carries no load rather than a negative one), with a 0.01 rad transition.
        aoa = 0.01 * jax.nn.softplus((pitch - jnp.arctan2(v_i, u_t)) / 0.01)
        lift = jnp.sum((chord * dr)[:, None] * (u_t**2 + v_i**2) * aoa, axis=1)  # (4, P)
        return lift / jnp.mean(lift, axis=1, keepdims=True)

    def _loads(self, x: Float[Array, " D"]) -> AeroResult:
        B = self.vehicle.rotor.n_blades
        rpm = x[:4]
        r2 = rpm**2
        thrust, torque = self.P_F * r2, self.T_z * r2
        shape = self.load_shape(x)
        zero3 = jnp.zeros((4, 3), dtype=r2.dtype)
        rotors = RotorLoads(
            thrust=thrust,
            torque=torque,
            force=zero3,
            moment=zero3,
            h_force=jnp.zeros_like(r2),
            side_force=jnp.zeros_like(r2),
            induced_velocity=jnp.zeros_like(r2),
            blade_thrust=(thrust / B)[:, None] * shape,
            blade_torque=(torque / B)[:, None] * shape,
        )
        z3 = jnp.zeros(3, dtype=r2.dtype)
        return AeroResult(z3, z3, z3, z3, rotors, rpm * RPM_TO_RAD_S)

    def __call__(self, x: Float[ArrayLike, " D"]) -> Float[Array, " 3"]:
        """Levels (dB re 20 µPa) at the microphones for the dataset input ``x``: (8,) in the
        airflow frame or (7,) in the body frame."""
        x = jnp.asarray(x)
        if x.shape not in ((8,), (7,)):
            raise ValueError(
                "x must be one dataset input, (r1..r4, yaw, pitch, roll, V) or body-frame "
                f"(r1..r4, u, v, w), got shape {x.shape}"
            )
        return acoustics.oaspl(self.vehicle, self._loads(x), self.cfg)

    def jacobian(self, x: Float[ArrayLike, " D"]) -> Float[Array, "3 D"]:
        """``∂M_noise/∂x``, by forward-mode autodiff.

        Args:
            x: one dataset input, (8,) airflow-frame or (7,) body-frame.

        Returns:
            The (3, D) Jacobian of the three levels (dB per input unit).
        """
        return jax.jacfwd(self.__call__)(jnp.asarray(x, dtype=float))

    def batch(
        self, X: Float[ArrayLike, "N D"]
    ) -> tuple[Float[Array, "N 3"], Float[Array, "N 3 D"]]:
        """Levels and Jacobians of many inputs, in padded chunks.

        One compiled program serves every N (:func:`gpg.quadrotor.simple_model.in_chunks`):
        its compilation, not the evaluation, is the cost.

        Args:
            X: (N, D) inputs, D = 8 airflow-frame or 7 body-frame entries.

        Returns:
            The levels (N, 3) (dB) and their Jacobians (N, 3, D).

        Raises:
            ValueError: if ``X`` is not (N, 8) or (N, 7).
        """
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or X.shape[1] not in (8, 7):
            raise ValueError(
                f"X must have shape (N, 8) (dataset inputs) or (N, 7) (body frame), got {X.shape}"
            )
        return in_chunks(_batch, self, X)


@eqx.filter_jit
def _batch(noise: SimpleNoise, X: Array) -> tuple[Array, Array]:
    return jax.vmap(noise.__call__)(X), jax.vmap(noise.jacobian)(X)
