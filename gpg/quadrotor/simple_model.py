"""The paper's simplified model ``M`` (Section "Simple Quadrotor Aerodynamic Model").

Body-frame thrust ``P_F r_i²`` along ``−z_B`` at each hub and reaction torque ``T_z r_i²``
opposing each rotor's spin; world-frame wrench ``y_M = (R_WB F_B, R_WB τ_B)`` and its
Jacobian ``J_M`` with respect to ``x_M = (r1..r4, yaw, pitch, roll)`` by ``jax.jacfwd``.

The allocation matrix ``A`` (``(ΣT, τx, τy, τz) = A r²``) is derived from the hub positions
and spin directions rather than typed in. The paper prints identical sign patterns for ``τx``
and ``τz``, which makes ``A`` singular (docs/design.md, pitfall 3); with the diagonal pairs (r1, r3)
and (r2, r4) spinning alike, ``τz ∝ (−r1² + r2² − r3² + r4²)`` and ``A`` is invertible.

``P_F`` (N/rpm²) and ``T_z`` (N·m/rpm²) are least-squares fits to the generator's own hover
sweep (:func:`fit_to_generator`), so the residual the GP learns is what ``M`` misses.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg import _host
from gpg._dtype import float64, in_model_dtype
from gpg.quadrotor import bemt
from gpg.quadrotor.frames import R_WB, matvec
from gpg.quadrotor.vehicle import Vehicle

if TYPE_CHECKING:
    from gpg.quadrotor.generator import Generator

__all__ = ["SimpleModel", "fit_to_generator", "hover_sweep"]

# fit_to_generator's default sweep, rpm: the paper's hover condition and its margins (also
# the sweep gpg.flight.identify fits an identified vehicle's coefficients to)
HOVER_RPM = np.arange(2000.0, 6001.0, 500.0)
HOVER_RPM.setflags(write=False)  # shared by every default fit: no caller may change it


class SimpleModel(eqx.Module):
    """``M``: thrust and drag-torque coefficients plus the rotor layout (body FRD)."""

    P_F: Float[Array, ""]  # N/rpm²
    T_z: Float[Array, ""]  # N·m/rpm²
    positions: Float[Array, "4 3"]  # m
    spin: Float[Array, " 4"]  # +1: rotation about +z_B

    @classmethod
    def from_vehicle(cls, vehicle: Vehicle, P_F: float, T_z: float) -> SimpleModel:
        """``M`` with the rotor layout of ``vehicle`` and the given coefficients.

        Args:
            vehicle: the vehicle whose hub positions and spins set the allocation.
            P_F: the thrust coefficient (N/rpm²), ``T = P_F r²`` per rotor.
            T_z: the torque coefficient (N·m/rpm²), ``Q = T_z r²`` per rotor.

        Returns:
            The model, its coefficients as float arrays.
        """
        return cls(
            P_F=jnp.asarray(P_F, dtype=float),
            T_z=jnp.asarray(T_z, dtype=float),
            positions=vehicle.positions,
            spin=vehicle.spin,
        )

    @property
    def allocation(self) -> Float[Array, "4 4"]:
        """``A`` with ``(ΣT, τx, τy, τz) = A r²``; thrust ``T_i`` acts along ``−z_B`` at ``p_i``."""
        p = self.positions
        # p × (0, 0, −T) = (−p_y T, p_x T, 0); reaction torque −d T_z r² about z_B.
        # broadcast_to, not ones(dtype=P_F.dtype): a model fitted in float64 and read in a
        # float32 program must not request float64 (JAX warns and truncates).
        return jnp.stack(
            [
                jnp.broadcast_to(self.P_F, (4,)),
                -self.P_F * p[:, 1],
                self.P_F * p[:, 0],
                -self.T_z * self.spin,
            ]
        )

    def wrench_body(
        self, rpm: Float[ArrayLike, " 4"]
    ) -> tuple[Float[Array, " 3"], Float[Array, " 3"]]:
        """Body-frame force and torque at rotor speeds ``rpm``.

        ``(ΣT, τ) = A r²`` with ``A`` from :attr:`allocation`, the matrix the controller
        inverts; the thrust acts along ``−z_B``.

        Args:
            rpm: (4,) rotor speeds r1..r4 (rpm).

        Returns:
            The body-frame force (3,) (N), ``(0, 0, −ΣT)``, and torque (3,) (N·m).
        """
        u = matvec(self.allocation, jnp.asarray(rpm) ** 2)  # (ΣT, τx, τy, τz)
        zero = jnp.zeros_like(u[0])
        return jnp.stack([zero, zero, -u[0]]), u[1:]

    def __call__(self, x_M: Float[ArrayLike, " 7"]) -> Float[Array, " 6"]:
        """``y_M = (F_W, τ_W)`` at ``x_M = (r1..r4, yaw, pitch, roll)``."""
        x_M = jnp.asarray(x_M)
        F, tau = self.wrench_body(x_M[:4])
        R = R_WB(x_M[4:7])
        return jnp.concatenate([matvec(R, F), matvec(R, tau)])

    def jacobian(self, x_M: Float[ArrayLike, " 7"]) -> Float[Array, "6 7"]:
        """``J_M = ∂y_M/∂x_M``, by forward-mode autodiff.

        Args:
            x_M: (7,) state ``(r1..r4, yaw, pitch, roll)`` (rpm, rad).

        Returns:
            The (6, 7) Jacobian of the world-frame wrench ``y_M = (F_W, τ_W)``.
        """
        return jax.jacfwd(self.__call__)(jnp.asarray(x_M))

    def batch(
        self, X_M: Float[ArrayLike, "N 7"]
    ) -> tuple[Float[Array, "N 6"], Float[Array, "N 6 7"]]:
        """``y_M`` and ``J_M`` for many states, in padded chunks.

        One compiled program serves every ``N`` (:func:`in_chunks`); a traced ``X_M`` (inside
        a user's ``jit``) is vmapped directly.

        Args:
            X_M: (N, 7) states ``(r1..r4, yaw, pitch, roll)``.

        Returns:
            The wrenches ``y_M`` (N, 6) and the Jacobians ``J_M`` (N, 6, 7).
        """
        return in_chunks(_batch, self, X_M)

    def values(self, X_M: Float[ArrayLike, "N 7"]) -> Float[Array, "N 6"]:
        """``y_M`` for many states, as :meth:`batch` without the Jacobians.

        Args:
            X_M: (N, 7) states ``(r1..r4, yaw, pitch, roll)``.

        Returns:
            The world-frame wrenches ``y_M`` (N, 6).
        """
        return in_chunks(_values, self, X_M)

    def hover_rpm(self, weight: float) -> Float[Array, ""]:
        """Equal rotor speed at which ``M``'s thrust balances ``weight``: ``√(W / 4P_F)``.

        Args:
            weight: the weight to carry (N).

        Returns:
            The rotor speed (rpm), a scalar (computed in the model's dtype).
        """
        return in_model_dtype(self, lambda: jnp.sqrt(weight / (4.0 * self.P_F)))


CHUNK = 256  # rows per compiled call of in_chunks


def in_chunks(fn, model, X: ArrayLike):
    """``fn(model, X)`` over ``X``'s rows in blocks of ``CHUNK`` (the last one padded with its
    last row), the outputs' rows concatenated; a traced ``X`` (inside a user's ``jit``) is
    passed to ``fn`` whole. One compiled program serves every ``N``: run op
    by op, the vmapped model and its Jacobian compiled some 80 small programs for every new
    ``N`` (a compile at each fit or conditioning, see docs/measurements.md), and a program
    per ``N`` rounds a row's
    Jacobian differently, by an ulp, from one ``N`` to another, so that a case's targets would
    depend on the batch it came in (conditioning then differs from a rebuild by far more on
    ill-conditioned data). Here a row's result is the same in any batch."""
    if isinstance(X, jax.core.Tracer):
        return fn(model, X)
    X = np.asarray(X)
    if X.shape[0] == 0:
        return fn(model, jnp.asarray(X))
    outs = []
    for start in range(0, X.shape[0], CHUNK):
        block = X[start : start + CHUNK]
        n = block.shape[0]
        if n < CHUNK:
            block = np.concatenate([block, np.repeat(block[-1:], CHUNK - n, axis=0)])
        # the padding cut and the chunks joined on the host: op by op on the device, each new
        # ``n`` and each new total compiled a slice and a concatenation of its own
        outs.append(jax.tree.map(lambda a, n=n: np.asarray(a)[:n], fn(model, _host.asarray(block))))
    # in the chunks' own dtype: float64 stays float64 in a float32 program, as the device's
    # concatenation kept it
    return jax.tree.map(lambda *a: _host.as_stored(np.concatenate(a)), *outs)


@eqx.filter_jit
def _batch(model: SimpleModel, X_M):
    return jax.vmap(model)(X_M), jax.vmap(model.jacobian)(X_M)


@eqx.filter_jit
def _values(model: SimpleModel, X_M):
    return jax.vmap(model)(X_M)


def fit_coefficients(
    rpm: Float[ArrayLike, " S"], thrust: Float[ArrayLike, " S"], torque: Float[ArrayLike, " S"]
) -> tuple[float, float]:
    """Least-squares ``P_F``, ``T_z`` for per-rotor ``T ≈ P_F r²`` and ``Q ≈ T_z r²``."""
    r2 = np.asarray(rpm, dtype=float) ** 2
    if not np.any(r2 > 0):
        raise ValueError("the hover sweep needs at least one non-zero rpm")
    den = float(np.sum(r2 * r2))
    return float(np.sum(r2 * np.asarray(thrust)) / den), float(
        np.sum(r2 * np.asarray(torque)) / den
    )


def hover_sweep(generator: Generator, rpm: Float[ArrayLike, " S"]) -> tuple[np.ndarray, np.ndarray]:
    """Per-rotor thrust and torque of the generator at hover, all four rotors at each rpm.

    Hover here is level, at zero airspeed, without body rates (:func:`gpg.quadrotor.bemt.aero`
    with the generator's settings).

    Args:
        generator: the generator (:class:`gpg.quadrotor.generator.Generator`).
        rpm: (S,) rotor speeds (rpm), the same on all four rotors.

    Returns:
        The thrust (N) and torque (N·m) of each rotor, each (S, 4), as NumPy.
    """

    @jax.jit
    def one(r):
        res = bemt.aero(generator.vehicle, generator.bemt, jnp.full(4, r), jnp.eye(3), jnp.zeros(3))
        return res.rotors.thrust, res.rotors.torque

    T, Q = jax.vmap(one)(jnp.asarray(rpm, dtype=float))
    return np.asarray(T), np.asarray(Q)


@float64
def fit_to_generator(
    generator: Generator, rpm: Float[ArrayLike, " S"] | None = None
) -> SimpleModel:
    """Fit ``P_F`` and ``T_z`` on the generator's :func:`hover_sweep`.

    The sweep defaults to 2000–6000 rpm in 500 rpm steps, the range of the paper's hover
    condition and its margins; the fit runs in float64.

    Args:
        generator: the generator (:class:`gpg.quadrotor.generator.Generator`) whose vehicle
            ``M`` describes.
        rpm: (S,) the rotor speeds of the sweep (rpm); None: the default sweep.

    Returns:
        ``M`` of the generator's vehicle with the fitted ``P_F`` and ``T_z``.
    """
    rpm = HOVER_RPM if rpm is None else np.asarray(rpm, dtype=float)
    T, Q = hover_sweep(generator, rpm)
    P_F, T_z = fit_coefficients(np.repeat(rpm, 4), T.ravel(), Q.ravel())
    return SimpleModel.from_vehicle(generator.vehicle, P_F, T_z)
