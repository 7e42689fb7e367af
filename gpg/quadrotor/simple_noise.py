"""``M_noise``: a simplified model of the three microphone levels, in the spirit of ``M``.

The paper attributes the poor noise predictions of every model to the absence of a simplified
noise model to take residuals against (its future work). ``M_noise`` is the steady part of the
generator's tonal noise (:mod:`gpg.quadrotor.acoustics`) with the inflow solution replaced by
``M``: each rotor carries ``M``'s
thrust ``T_i = P_F r_i²`` and drag torque ``Q_i = T_z r_i²``, uniformly around the azimuth
(Gutin's steady loading, no unsteady harmonics), plus the compact thickness tone of its blades;
the tones of the first BPF harmonics of the four rotors reach each microphone with spherical
spreading and add incoherently (:func:`gpg.quadrotor.acoustics.harmonic_msq`, the same
formulas with one azimuthal station). It depends on the rotor speeds only: what it misses
(unsteady loading in edgewise flight, the attitude and airspeed dependence of the loads) is what
the GP learns. A query costs a few microseconds; its Jacobian comes from ``jax.jacfwd``.

It needs the acoustic part of the vehicle (rotor geometry, microphones, air properties): a
vehicle file for ``M`` and flight only has none, and :meth:`SimpleNoise.from_vehicle` says so.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg.quadrotor import acoustics
from gpg.quadrotor.bemt import AeroResult, RotorLoads
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle

RPM_TO_RAD_S = 2.0 * jnp.pi / 60.0
CHUNK = 256  # rows per compiled batch call


class SimpleNoise(eqx.Module):
    """``M_noise(x) -> (L1, L2, L3)`` dB from the rotor speeds ``x[:4]`` (rpm)."""

    vehicle: Vehicle
    P_F: Float[Array, ""]  # N/rpm², M's thrust coefficient
    T_z: Float[Array, ""]  # N·m/rpm², M's torque coefficient
    # The first four BPF harmonics and eight thickness stations: within 0.03 dB of the ten and
    # sixteen of the generator's setting at hover, at a quarter of the cost.
    n_harmonics: int = eqx.field(static=True, default=4)
    thickness_stations: int = eqx.field(static=True, default=8)

    @property
    def cfg(self) -> acoustics.AcousticsConfig:
        return acoustics.AcousticsConfig(
            n_harmonics=self.n_harmonics, thickness_stations=self.thickness_stations
        )

    @classmethod
    def from_vehicle(cls, vehicle: Vehicle, simple: SimpleModel) -> SimpleNoise:
        """``M_noise`` of ``vehicle`` with ``simple``'s coefficients; ``ValueError`` naming what
        a vehicle without the acoustic data lacks."""
        missing = [
            k
            for k in ("rotor", "microphones", "air_density", "speed_of_sound")
            if k in vehicle.generator_missing
        ]
        if missing:
            raise ValueError(
                f"M_noise needs the vehicle's {', '.join(missing)} (vehicle {vehicle.name!r} "
                "has only what M needs); fit without it (noise_model=False)"
            )
        return cls(vehicle=vehicle, P_F=simple.P_F, T_z=simple.T_z)

    def _loads(self, rpm: Float[Array, " 4"]) -> AeroResult:
        B = self.vehicle.rotor.n_blades
        r2 = rpm**2
        thrust, torque = self.P_F * r2, self.T_z * r2
        zero3 = jnp.zeros((4, 3), dtype=r2.dtype)
        rotors = RotorLoads(
            thrust=thrust,
            torque=torque,
            force=zero3,
            moment=zero3,
            h_force=jnp.zeros_like(r2),
            side_force=jnp.zeros_like(r2),
            induced_velocity=jnp.zeros_like(r2),
            blade_thrust=(thrust / B)[:, None],  # one azimuthal station: steady loading only
            blade_torque=(torque / B)[:, None],
        )
        z3 = jnp.zeros(3, dtype=r2.dtype)
        return AeroResult(z3, z3, z3, z3, rotors, rpm * RPM_TO_RAD_S)

    def __call__(self, x: Float[ArrayLike, " D"]) -> Float[Array, " 3"]:
        """Levels (dB re 20 µPa) at the microphones for the input ``x`` (rotor speeds first;
        any further inputs, attitude and airspeed, do not enter)."""
        rpm = jnp.asarray(x)[:4]
        return acoustics.oaspl(self.vehicle, self._loads(rpm), self.cfg)

    def jacobian(self, x: Float[ArrayLike, " D"]) -> Float[Array, "3 D"]:
        """``∂M_noise/∂x`` (zero along every input but the rotor speeds)."""
        return jax.jacfwd(self.__call__)(jnp.asarray(x, dtype=float))

    def batch(
        self, X: Float[ArrayLike, "N D"]
    ) -> tuple[Float[Array, "N 3"], Float[Array, "N 3 D"]]:
        """Levels and Jacobians of many inputs, in padded chunks of ``CHUNK`` rows: one compiled
        program serves every N (its compilation, not the evaluation, is the cost)."""
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or X.shape[1] < 4:
            raise ValueError(f"X must have shape (N, D >= 4), got {X.shape}")
        ys, js = [], []
        for start in range(0, X.shape[0], CHUNK):
            block = X[start : start + CHUNK]
            n = block.shape[0]
            if n < CHUNK:
                block = np.concatenate([block, np.repeat(block[-1:], CHUNK - n, axis=0)])
            y, j = _batch(self, jnp.asarray(block))
            ys.append(y[:n])
            js.append(j[:n])
        if not ys:
            return jnp.zeros((0, 3)), jnp.zeros((0, 3, X.shape[1]))
        return jnp.concatenate(ys), jnp.concatenate(js)


@eqx.filter_jit
def _batch(noise: SimpleNoise, X: Array) -> tuple[Array, Array]:
    return jax.vmap(noise.__call__)(X), jax.vmap(noise.jacobian)(X)
