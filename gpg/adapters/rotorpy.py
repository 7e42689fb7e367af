"""gpg's aerodynamics inside RotorPy (``pip install 'gpg[rotorpy]'``).

RotorPy's :class:`rotorpy.vehicles.multirotor.Multirotor` computes its body wrench in
``compute_body_wrench(body_rates, rotor_speeds, body_airspeed)``, which is not given the
attitude; gpg's surrogate needs it (its inputs are the attitude in the airflow frame), so
:class:`GpgMultirotor` keeps the attitude of the state being differentiated and replaces the
wrench with gpg's: a :class:`gpg.Surrogate` (any model) or gpg's simplified model ``M``
(``SimpleAero``). Everything else — rigid body, motors, RotorPy's controllers, trajectories,
wind and its ``simulate`` — is RotorPy's own. :func:`quad_params` turns a gpg vehicle into
RotorPy's parameter dictionary (frames, rotor order and units by
:mod:`gpg.adapters.conventions`), so that RotorPy's controller is designed for the same
vehicle.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

try:
    from rotorpy.vehicles.multirotor import Multirotor
except ImportError as exc:  # an optional extra
    raise ImportError(
        "gpg.adapters.rotorpy needs RotorPy: pip install 'gpg[rotorpy]' (or rotorpy)"
    ) from exc

from gpg.adapters.conventions import RAD_S_PER_RPM, ZUp, flip
from gpg.quadrotor.dynamics import AeroModel, SimpleAero
from gpg.quadrotor.simple_model import SimpleModel
from gpg.quadrotor.vehicle import Vehicle
from gpg.surrogate import Surrogate

__all__ = ["GpgMultirotor", "quad_params"]


def quad_params(
    vehicle: Vehicle,
    simple: SimpleModel,
    *,
    tau_m: float | None = None,
    **overrides: Any,
) -> dict[str, Any]:
    """RotorPy's ``quad_params`` for a gpg vehicle whose rotors follow ``M``.

    Mass and principal inertia, hub positions converted from FRD to FLU in gpg's rotor order,
    spin directions (gpg's ``spin`` is RotorPy's ``rotor_directions``), ``k_eta = P_F`` and
    ``k_m = T_z`` converted from rpm² to (rad/s)², the motor range in rad/s and its time
    constant. RotorPy's own aerodynamic terms are zero: with :class:`GpgMultirotor` gpg
    provides them.

    Args:
        vehicle: the gpg vehicle.
        simple: ``M``, whose ``P_F`` and ``T_z`` give RotorPy's thrust and drag-torque
            coefficients.
        tau_m: the motor time constant (s); default the vehicle's. RotorPy needs one > 0.
        **overrides: entries of the dictionary replaced, or RotorPy's controller gains
            ``kp_att``, ``kd_att``, ``k_w``, ``k_v`` added.

    Returns:
        RotorPy's parameter dictionary.

    Raises:
        ValueError: if the motor time constant is not > 0, or ``overrides`` names another
            key.
    """
    lag = float(vehicle.motor_time_constant) if tau_m is None else float(tau_m)
    if not lag > 0:
        raise ValueError(
            f"RotorPy integrates the motors with a time constant > 0 s; vehicle "
            f"{vehicle.name!r} has {lag}: pass tau_m="
        )
    J = np.asarray(vehicle.inertia, dtype=float)
    pos = np.asarray(flip(vehicle.positions), dtype=float)
    c2 = RAD_S_PER_RPM**2
    params = {
        "mass": float(vehicle.mass),
        "Ixx": J[0],
        "Iyy": J[1],
        "Izz": J[2],
        "Ixy": 0.0,
        "Ixz": 0.0,
        "Iyz": 0.0,
        "num_rotors": 4,
        "rotor_pos": {f"r{i + 1}": pos[i] for i in range(4)},
        "rotor_directions": np.asarray(vehicle.spin, dtype=float),
        "rI": np.zeros(3),
        "c_Dx": 0.0,
        "c_Dy": 0.0,
        "c_Dz": 0.0,
        "k_eta": float(simple.P_F) / c2,
        "k_m": float(simple.T_z) / c2,
        "k_d": 0.0,
        "k_z": 0.0,
        "k_h": 0.0,
        "k_flap": 0.0,
        "tau_m": lag,
        "rotor_speed_min": float(vehicle.rpm_min) * RAD_S_PER_RPM,
        "rotor_speed_max": float(vehicle.rpm_max) * RAD_S_PER_RPM,
        "motor_noise_std": 0.0,
    }
    unknown = sorted(set(overrides) - set(params) - {"k_w", "k_v", "kp_att", "kd_att"})
    if unknown:
        raise ValueError(f"unknown RotorPy parameters {unknown}")
    return {**params, **overrides}


class GpgMultirotor(Multirotor):
    """RotorPy's ``Multirotor`` with gpg's aerodynamic wrench.

    ``aero``: a :class:`gpg.Surrogate` (its mean wrench; ``last_in_domain`` keeps the flag of
    the latest evaluation), a :class:`gpg.quadrotor.SimpleModel` (``M``) or any
    :class:`gpg.quadrotor.dynamics.AeroModel`. The other arguments are RotorPy's; its own
    aerodynamics (``aero=``) are switched off, since gpg's wrench replaces them. Wind comes from
    RotorPy's wind profiles as usual (the wrench sees the airspeed ``v − wind``).

    Args:
        quad_params: RotorPy's parameters (:func:`quad_params`).
        aero: the aerodynamics: a :class:`gpg.Surrogate`, ``M`` or an ``AeroModel``.
        **kwargs: RotorPy's other ``Multirotor`` arguments (initial state, control
            abstraction, ...), without ``aero``.

    Raises:
        ValueError: if ``aero=`` is passed among ``kwargs``, or ``aero`` is of another type.
    """

    def __init__(
        self,
        quad_params: dict[str, Any],
        aero: Surrogate | SimpleModel | AeroModel,
        **kwargs: Any,
    ):
        if kwargs.pop("aero", False):
            raise ValueError("GpgMultirotor replaces RotorPy's aerodynamics: leave aero= unset")
        super().__init__(quad_params, aero=False, **kwargs)
        if isinstance(aero, SimpleModel):
            aero = SimpleAero(aero)
        if not isinstance(aero, Surrogate | AeroModel):
            raise ValueError(
                f"aero must be a gpg.Surrogate, SimpleModel or AeroModel, got {type(aero).__name__}"
            )
        self.gpg_aero = ZUp(aero, rad_s=True, with_var=False)
        self._wrench = jax.jit(lambda m, *args: m.wrench(*args))
        self._q = np.array([0.0, 0.0, 0.0, 1.0])
        self.last_in_domain = True

    def _s_dot_fn(self, t, s, cmd_rotor_speeds):
        self._q = np.asarray(s[6:10], dtype=float)  # attitude [x, y, z, w] of this evaluation
        return super()._s_dot_fn(t, s, cmd_rotor_speeds)

    def compute_body_wrench(
        self,
        body_rates: np.ndarray,
        rotor_speeds: np.ndarray,
        body_airspeed_vector: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """gpg's force and moment in RotorPy's body frame (FLU), replacing RotorPy's own.

        RotorPy does not pass the attitude here; the one of the state being differentiated,
        stored by ``_s_dot_fn``, turns the body airspeed into the world frame gpg reads.
        ``last_in_domain`` keeps the evaluation's ``in_domain``.

        Args:
            body_rates: (3,) body rates (FLU, rad/s).
            rotor_speeds: (4,) rotor speeds (rad/s), gpg's rotor order.
            body_airspeed_vector: (3,) the airspeed ``v − wind`` in the body frame (FLU, m/s).

        Returns:
            The force (N) and moment (N·m), (3,) each, body frame (FLU).
        """
        from scipy.spatial.transform import Rotation

        R = Rotation.from_quat(self._q).as_matrix()  # FLU body to RotorPy's world
        w = self._wrench(
            self.gpg_aero,
            np.asarray(rotor_speeds, dtype=float),
            self._q,
            R @ np.asarray(body_airspeed_vector, dtype=float),  # airspeed, z-up world
            None,
            np.asarray(body_rates, dtype=float),
        )
        self.last_in_domain = bool(w.in_domain)
        return np.asarray(w.force_body, dtype=float), np.asarray(w.torque_body, dtype=float)
