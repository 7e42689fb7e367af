"""The vehicle identified from its flights: the physical parameters of gpg's own physics that
explain the labels (the calibration step of Kennedy and O'Hagan: fit the simulator's
parameters ``θ`` first, so that the discrepancy learns only what the physics cannot).

The model of a label is the blade-element-momentum physics that the generator runs
(:func:`gpg.quadrotor.bemt.aero`: the four rotors' thrust, torque, H-force and hub moments, the
wake interference, the airframe drag) for the vehicle with ``θ`` applied, at the label's rotor
speeds, attitude and air velocity. The parameters are named by the vehicle file's keys
(:data:`PARAMETERS`): ``rotor.radius`` and ``rotor.chord`` (the blade's size and solidity, which
set the thrust and torque coefficients and the rotor drag), the airfoil's ``lift_slope``,
``alpha_zero_lift_deg`` and ``cd0``, the airframe's ``drag_area`` per body axis, and
``motor.gain`` and ``motor.exponent``, a factor and a power on the rotor speeds where they come
from commands through a motor curve (``gain · r_ref (rpm / r_ref)^exponent`` about the labels'
median speed ``r_ref``: the curve's scale and its bend, :meth:`MotorCurve.scaled`).

The estimate is the maximum of the labels' likelihood times a weak prior on ``θ`` around the
vehicle file's values (a factor of :data:`PARAMETERS`' ``prior`` on scales, degrees on
shifts): each label's own noise variance plus a model-error variance per component, itself
estimated from the residuals (so that the standard errors carry what the physics misses).
The maximum is found by Levenberg-Marquardt on the whitened residuals, with the Jacobian of
the physics by ``jax.jacfwd`` (one compiled program for every choice of free parameters: the
loop itself is a handful of NumPy solves of the parameters' size). The standard errors come from
the sandwich ``H⁻¹ (B + P) H⁻¹``: ``H = JᵀJ + P`` the Gauss-Newton curvature, ``B`` the
long-run covariance of the labels' scores ``Jₜᵀ rₜ`` along each flight (Newey and West's
Bartlett window; what the physics misses varies along a flight and differs between labels,
and such residuals inform less than as many independent ones of the stated variance). With
independent labels of the stated variances ``B → JᵀJ``, and the errors are the curvature's.
Those errors hold the parameters that are not free at the file's values as if they were
exact; ``consider`` names the ones that are not (a measured rotor radius, a wake gain no
flight separates from the drag), each with a standard deviation, and adds
``S Σ Sᵀ`` to the covariance, ``S`` the estimate's linear sensitivity to them (the "consider"
covariance of orbit determination): errors that say what holding them fixed costs. A
parameter whose direction the flights do not determine (an eigenvalue of the data's
effective information ``H (B + P)⁻¹ H − P``, in units of the prior's, under
:data:`IDENTIFIABLE`) is named in :attr:`Identification.unidentified`: it keeps its prior
value, the others are fitted again beside it, and the vehicle file says so. With commands
only, ``motor.gain`` and the rotor's size are such a pair: a rotor that gives more thrust per
rpm and a curve that gives fewer rpm per command explain the same flights (measure the
radius, free the gain).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import yaml
from jaxtyping import Array, Float

if TYPE_CHECKING:
    from gpg.surrogate import Surrogate

from gpg._dtype import float64
from gpg._io import atomic_write
from gpg._precision import highest
from gpg.flight.labels import Labels, MotorCurve
from gpg.quadrotor import bemt
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.simple_model import HOVER_RPM, fit_coefficients
from gpg.quadrotor.vehicle import Vehicle, vehicle_config

__all__ = [
    "DEFAULT_FREE",
    "PARAMETERS",
    "Identification",
    "IdentificationWarning",
    "identify",
]


@dataclass(frozen=True)
class ParameterSpec:
    """How one parameter enters: ``scale`` multiplies the file's value by ``e^θ``, ``shift``
    adds ``θ``; the prior is ``θ ~ N(0, prior²)`` (``prior`` a log-factor or the shift's
    units)."""

    kind: str
    prior: float
    unit: str


PARAMETERS: dict[str, ParameterSpec] = {
    "rotor.radius": ParameterSpec("scale", math.log(1.5), "m"),
    "rotor.chord": ParameterSpec("scale", math.log(2.0), "x the file's chord"),
    "airfoil.lift_slope": ParameterSpec("scale", math.log(1.5), "1/rad"),
    "airfoil.alpha_zero_lift_deg": ParameterSpec("shift", 3.0, "deg"),
    "airfoil.cd0": ParameterSpec("scale", math.log(3.0), ""),
    "drag_area.x": ParameterSpec("scale", math.log(5.0), "m²"),
    "drag_area.y": ParameterSpec("scale", math.log(5.0), "m²"),
    "drag_area.z": ParameterSpec("scale", math.log(5.0), "m²"),
    "motor.gain": ParameterSpec("scale", math.log(1.5), "x the curve's rpm"),
    "motor.exponent": ParameterSpec("scale", math.log(1.5), "power on the curve's rpm"),
    "generator.wake_gain": ParameterSpec("scale", math.log(2.0), "x ingested induced velocity"),
}
"""The parameters :func:`identify` can free, by vehicle-file key, with their priors."""

DEFAULT_FREE = (
    "rotor.chord",
    "airfoil.cd0",
    "drag_area.x",
    "drag_area.y",
    "drag_area.z",
)
"""What :func:`identify` frees by default: the blade's chord (the thrust and torque
coefficients), its profile drag, the airframe's drag areas. The radius trades with the chord
on most flights (both scale the thrust); free it where the flights span the inflow's range."""

# A direction of θ whose data information is under this many times the prior's is not
# identified by the flights: there the posterior is mostly the prior.
IDENTIFIABLE = 4.0
_DRAG_AXES = {"x": 0, "y": 1, "z": 2}


class IdentificationWarning(UserWarning):
    """A parameter the flights cannot identify, or a fit that did not converge."""


@dataclass(frozen=True)
class Identification:
    """A vehicle identified from its flights (:func:`identify`).

    Attributes:
        vehicle: the identified vehicle (generator part included).
        config: its vehicle file's mapping (:meth:`write` writes it).
        parameters: per freed parameter: ``value``, ``se`` (standard error, the value's
            units, the considered parameters' uncertainty included), ``se_data`` (the labels'
            alone), ``nominal`` (the file's), ``unit`` and ``identified`` (False: the flights
            do not determine it; it keeps the prior's value).
        unidentified: the names of the parameters the flights cannot identify.
        model_noise: (6,) the model-error variance per load component (N², N²m²), world.
        residual_rms: (6,) the labels' RMS residual per component after the fit.
        n_labels: labels the fit used.
        steps: Levenberg-Marquardt steps taken (all passes).
        converged: whether the last pass converged.
        motor_gain: the rotor speeds' factor (1 unless ``motor.gain`` was freed).
        physics: the blade-element-momentum settings the parameters hold for.
        motor_exponent: the power on the rotor speeds (1 unless ``motor.exponent`` was freed).
        rpm_ref: rpm, the labels' median rotor speed, which the power leaves unchanged.
        considered: the parameters held at the file's values whose uncertainty ``se``
            carries, with their standard deviations in the prior's units (``identify``'s
            ``consider``).
        coefficients: ``M``'s ``thrust_coefficient`` (``P_F``, N/rpm²) and
            ``torque_coefficient`` (``T_z``, N·m/rpm²) of the identified vehicle's hover, as
            its file holds them, each with ``value``, ``se`` and ``se_data`` (through the
            parameters' covariance and the considered ones' uncertainty, to first order),
            ``nominal`` (the starting file's physics') and ``unit``. Per rotor speed of the
            identified curve (:meth:`speeds`): with commands only the flights fix the thrust
            per command, and ``se`` says how well that pins ``P_F``.
    """

    vehicle: Vehicle
    config: dict[str, Any]
    parameters: dict[str, dict[str, Any]]
    unidentified: tuple[str, ...]
    model_noise: np.ndarray
    residual_rms: np.ndarray
    n_labels: int
    steps: int
    converged: bool
    motor_gain: float = 1.0
    physics: bemt.BEMTConfig = field(default_factory=bemt.BEMTConfig)
    motor_exponent: float = 1.0
    rpm_ref: float = 1.0
    considered: dict[str, float] = field(default_factory=dict)
    coefficients: dict[str, dict[str, Any]] = field(default_factory=dict)

    def curve(self, curve: MotorCurve) -> MotorCurve:
        """A motor curve with the identified gain and exponent applied (``motor.gain``,
        ``motor.exponent``): label the flights again with it before correcting a prior of
        the identified vehicle, whose rotor speeds these are.

        Args:
            curve: the curve the labels' rotor speeds came from.

        Returns:
            The curve whose speeds are :meth:`speeds` of ``curve``'s.
        """
        return curve.scaled(self.motor_gain, self.motor_exponent, self.rpm_ref)

    def speeds(self, rpm: Float[Array, "*N 4"]) -> Float[Array, "*N 4"]:
        """The identified rotor speeds of the labels' ones (the curve's gain and power).

        Args:
            rpm: rotor speeds as the labels the identification saw hold them, rpm.

        Returns:
            ``motor_gain · rpm_ref (rpm / rpm_ref)^motor_exponent``, rpm.
        """
        return motor_speeds(jnp.asarray(rpm), jnp.log(self.motor_gain),
                            jnp.log(self.motor_exponent), self.rpm_ref)  # fmt: skip

    def prior(
        self,
        data: str | Mapping[str, Any] = "default",
        model: str = "gpgs_hybrid",
        config: Mapping[str, Any] | None = None,
        *,
        cache_dir: str | Path = "data/cache",
        progress: bool = True,
        half_turn: bool = False,
    ) -> Surrogate:
        """The simulator's prior of the identified vehicle: its data generated (cached by the
        vehicle file's hash, as every dataset: :func:`gpg.data.cache.ensure`) and the
        surrogate fitted on them, so that the prior carries this vehicle's physics (an
        identified ``generator.wake_gain`` goes into the data config's ``generator``). Its
        rotor speeds are the identified curve's (:meth:`curve`): label the flights with it.

        Args:
            data: a ``data`` config of the package (``"default"``, ``"smoke"``) or its mapping.
            model: the surrogate's model name (:data:`gpg.models.NAMES`).
            config: overrides of the model's options.
            cache_dir: the dataset cache.
            progress: progress bars while generating.
            half_turn: the prior reads airflow from behind at the state's half-turn image
                (:meth:`gpg.Surrogate.fit`): the identified vehicle must be its own image; its
                data carry no levels unless every microphone is its own image
                (:meth:`data_config`).

        Returns:
            The fitted :class:`~gpg.Surrogate` (its ``M`` is the identified vehicle's).

        Raises:
            ValueError: as :meth:`gpg.Surrogate.fit` raises it (a vehicle that is not its own
                image under ``half_turn``, naming what differs).
        """
        from gpg.data.cache import ensure
        from gpg.surrogate import Surrogate

        _, train, _, _, _ = ensure(self.data_config(data, half_turn=half_turn), self.config,
                                   cache_dir, progress=progress)  # fmt: skip
        return Surrogate.fit(train, model, config, vehicle=self.vehicle, half_turn=half_turn)

    def data_config(
        self, data: str | Mapping[str, Any] = "default", *, half_turn: bool = False
    ) -> dict[str, Any]:
        """The ``data`` config the identified vehicle's prior is generated with: ``data`` with
        an identified ``generator.wake_gain`` in its ``generator`` mapping, and its rotor
        speeds' box in the identified curve's speeds (:meth:`speeds`) where ``motor.gain`` or
        ``motor.exponent`` was identified, as the identified file's motor range.

        Args:
            data: a ``data`` config of the package (``"default"``, ``"smoke"``) or its mapping.
            half_turn: for a prior that reads airflow from behind at the half-turn image:
                ``noise: false`` unless every microphone is its own image (a level elsewhere
                has no microphone at its image, and the flights read no levels).

        Returns:
            The mapping (a copy).
        """
        from gpg import conf

        cfg = conf.load(data, "data") if isinstance(data, str) else copy.deepcopy(dict(data))
        if "generator.wake_gain" in self.parameters:  # the physics' own identified setting
            cfg["generator"] = {**cfg.get("generator", {}),
                                "wake_gain": float(self.physics.wake_gain)}  # fmt: skip
        if (self.motor_gain, self.motor_exponent) != (1.0, 1.0) and "bounds" in cfg:
            # the box in the identified speeds, as the vehicle file's motor range
            lo, hi = np.asarray(self.speeds(jnp.asarray(cfg["bounds"]["rpm"], float)))
            cfg["bounds"] = {**cfg["bounds"], "rpm": [round(float(lo), 3), round(float(hi), 3)]}
        veh = self.vehicle  # more asymmetries with the levels: microphones off the axis
        if half_turn and veh.half_turn_asymmetries(levels=True) != veh.half_turn_asymmetries():
            cfg["noise"] = False
        return cfg

    def summary(self) -> str:
        """The parameter table as text: value ± standard error, the file's value.

        Returns:
            One line per parameter, then the unidentified ones named.
        """
        lines = [f"{'parameter':30s} {'value':>12s} {'± se':>10s} {'file':>12s}"]
        for k, p in self.parameters.items():
            flag = "" if p["identified"] else "  (not identified: prior)"
            lines.append(
                f"{k:30s} {p['value']:12.5g} {p['se']:10.2g} {p['nominal']:12.5g} {p['unit']}"
                + flag
            )
        for k, p in self.coefficients.items():
            lines.append(f"{k:30s} {p['value']:12.5g} {p['se']:10.2g} {p['nominal']:12.5g} "
                         f"{p['unit']} (M's, of the identified hover)")  # fmt: skip
        if self.unidentified:
            lines.append("not identified by these flights: " + ", ".join(self.unidentified))
        if self.considered:
            lines.append("± se with the uncertainty of " + ", ".join(
                f"{k} (sd {v:.3g} {'log-factor' if PARAMETERS[k].kind == 'scale' else 'shift'})"
                for k, v in self.considered.items()))  # fmt: skip
        return "\n".join(lines)

    def write(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """The identified vehicle as a vehicle file that :func:`~gpg.quadrotor.load_vehicle`
        and the generator read; its header lists the parameters with their standard errors
        and names the unidentified ones.

        Args:
            path: the YAML file to write (atomically).
            overwrite: replace an existing file.

        Returns:
            The path written.

        Raises:
            FileExistsError: the file exists and ``overwrite`` is False.
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists: pass overwrite=True to replace it")
        head = ["# Identified from flights by gpg.flight.identify (value ± standard error)."]
        head += ["# " + line for line in self.summary().splitlines()]
        if any(n.startswith("motor.") for n in self.parameters):
            head.append("# motor.*: the motor curve's, not this file's: label the flights with "
                        "Identification.curve(curve)")  # fmt: skip
        if "generator.wake_gain" in self.parameters:
            head.append("# generator.wake_gain: the generator's, not this file's: "
                        "data.generator.wake_gain (Identification.data_config)")  # fmt: skip
        text = "\n".join(head) + "\n" + yaml.safe_dump(self.config, sort_keys=False)
        atomic_write(path, text.encode())
        return path


def _get(cfg: dict[str, Any], name: str, physics: bemt.BEMTConfig) -> float:
    """A parameter's value in the vehicle file ``cfg`` (or, for the generator's, ``physics``)."""
    if name == "generator.wake_gain":
        return float(physics.wake_gain)
    if name.startswith("drag_area."):
        return float(cfg["drag_area"][_DRAG_AXES[name.split(".")[1]]])
    if name == "rotor.chord":
        return 1.0
    if name in ("motor.gain", "motor.exponent"):
        return 1.0
    section, _, leaf = name.partition(".")
    return float(cfg[section][leaf])


def _set(cfg: dict[str, Any], name: str, value: float) -> None:
    if name.startswith("drag_area."):
        cfg["drag_area"] = [float(v) for v in cfg["drag_area"]]
        cfg["drag_area"][_DRAG_AXES[name.split(".")[1]]] = float(value)
    elif name == "rotor.chord":
        cfg["rotor"]["chord_in"] = [round(float(c) * value, 6) for c in cfg["rotor"]["chord_in"]]
    elif not name.startswith("motor."):
        section, _, leaf = name.partition(".")
        cfg[section][leaf] = float(value)


def _apply(vehicle: Vehicle, names: tuple[str, ...], theta: Float[Array, " P"]) -> Vehicle:
    """The vehicle with ``θ`` applied (traceable: a differentiable function of ``θ``)."""
    for i, name in enumerate(names):
        s, d = jnp.exp(theta[i]), theta[i]
        if name == "rotor.radius":
            vehicle = eqx.tree_at(lambda v: v.rotor.radius, vehicle, vehicle.rotor.radius * s)
        elif name == "rotor.chord":
            vehicle = eqx.tree_at(lambda v: v.rotor.chord, vehicle, vehicle.rotor.chord * s)
        elif name == "airfoil.lift_slope":
            vehicle = eqx.tree_at(
                lambda v: v.airfoil.lift_slope, vehicle, vehicle.airfoil.lift_slope * s
            )
        elif name == "airfoil.alpha_zero_lift_deg":
            vehicle = eqx.tree_at(
                lambda v: v.airfoil.alpha_zero_lift,
                vehicle,
                vehicle.airfoil.alpha_zero_lift + jnp.deg2rad(d),
            )
        elif name == "airfoil.cd0":
            vehicle = eqx.tree_at(lambda v: v.airfoil.cd0, vehicle, vehicle.airfoil.cd0 * s)
        elif name.startswith("drag_area."):
            k = _DRAG_AXES[name.split(".")[1]]
            vehicle = eqx.tree_at(
                lambda v: v.drag_area, vehicle, vehicle.drag_area.at[k].multiply(s)
            )
    return vehicle


@eqx.filter_jit
@highest
def physics_loads(
    vehicle: Vehicle,
    cfg: bemt.BEMTConfig,
    rpm: Float[Array, "N 4"],
    euler: Float[Array, "N 3"],
    v_air: Float[Array, "N 3"],
    wake_gain: Float[Array, ""] | None = None,
    rates: Float[Array, "N 3"] | None = None,
) -> Float[Array, "N 6"]:
    """The physics' world-frame force and torque at many states (what a label measures).

    Args:
        vehicle: a full vehicle (generator part included).
        cfg: the physics' settings.
        rpm: (N, 4) rotor speeds, rpm.
        euler: (N, 3) (yaw, pitch, roll), rad.
        v_air: (N, 3) air velocity, world, m/s.
        wake_gain: the ingested wake's gain in place of ``cfg.wake_gain`` (traceable).
        rates: (N, 3) body rates, body frame, rad/s: each hub moves at ``ω × p`` through the
            air (the rotors' rate damping). None: a vehicle that does not rotate.

    Returns:
        (N, 6) the force (N) and torque (N·m), world frame.
    """
    w = jnp.zeros_like(v_air) if rates is None else rates

    def one(r, e, v, om):
        res = bemt.aero(vehicle, cfg, r, R_WB(e), v, om, wake_gain=wake_gain)
        return jnp.concatenate([res.force_W, res.torque_W])

    return jax.vmap(one)(rpm, euler, v_air, w)


ALL = tuple(PARAMETERS)  # θ's order inside: one compiled program serves any choice of free


def motor_speeds(
    rpm: Float[Array, "*N 4"], log_gain, log_exponent, rpm_ref
) -> Float[Array, "*N 4"]:
    """``e^{log_gain} r_ref (rpm / r_ref)^{e^{log_exponent}}`` (0 stays 0; differentiable in
    both logs at every speed)."""
    x = jnp.maximum(rpm, 1e-9 * rpm_ref) / rpm_ref
    return jnp.where(rpm > 0, jnp.exp(log_gain) * rpm_ref * x ** jnp.exp(log_exponent), 0.0)


@eqx.filter_jit
@highest
def loads_and_jacobian(
    vehicle: Vehicle,
    cfg: bemt.BEMTConfig,
    theta: Float[Array, " P"],
    directions: Float[Array, "P F"],
    rpm: Float[Array, "N 4"],
    euler: Float[Array, "N 3"],
    v_air: Float[Array, "N 3"],
    rpm_ref: Float[Array, ""] | float = 4000.0,
    rates: Float[Array, "N 3"] | None = None,
) -> tuple[Float[Array, "N 6"], Float[Array, "N 6 F"]]:
    """The physics' loads with ``θ`` applied, and their derivatives along ``directions``.

    ``θ`` holds every parameter of :data:`PARAMETERS`, in its order (a log-factor on a
    scale, a shift's own units); the rotor speeds go through :func:`motor_speeds` with
    ``motor.gain`` and ``motor.exponent``. The derivatives are taken along the columns of
    ``directions`` only (the free parameters' unit vectors): forward mode costs one pass per
    column.

    Args:
        vehicle: the vehicle file's vehicle (θ = 0).
        cfg: the physics' settings.
        theta: (P,) the parameters (``P = len(PARAMETERS)``).
        directions: (P, F) the directions of the derivatives.
        rpm: (N, 4) rotor speeds, rpm.
        euler: (N, 3) attitudes, rad.
        v_air: (N, 3) air velocities, world, m/s.
        rpm_ref: rpm, the speed ``motor.exponent`` leaves unchanged.
        rates: (N, 3) body rates, rad/s (:func:`physics_loads`); None: zero.

    Returns:
        The (N, 6) world-frame force and torque and their (N, 6, F) derivatives.
    """

    def f(phi):
        th = theta + directions @ phi
        veh = _apply(vehicle, ALL, th)
        speeds = motor_speeds(rpm, th[ALL.index("motor.gain")], th[ALL.index("motor.exponent")],
                              rpm_ref)  # fmt: skip
        wake = cfg.wake_gain * jnp.exp(th[ALL.index("generator.wake_gain")])
        out = physics_loads(veh, cfg, speeds, euler, v_air, wake, rates)
        return out, out

    phi = jnp.zeros(directions.shape[1], theta.dtype)
    J, out = jax.jacfwd(f, has_aux=True)(phi)
    return out, J


def _levenberg_marquardt(fun, theta, prior_sd, free, max_steps: int):
    """Damped Gauss-Newton on ``½‖r(θ)‖² + ½‖θ/sd‖²`` over the free entries of ``θ``, from
    ``fun(θ) -> (r, ∂r/∂θ)``: the step ``(JᵀJ + P + μ diag(JᵀJ + P)) δ = −(Jᵀr + Pθ)``,
    ``μ`` shrunk after a step that lowers the cost and grown after one that does not.
    Converged when no free entry moves by more than 1e-4 (log-factors and degrees: far
    below any standard error)."""
    P = np.diag(1.0 / prior_sd[free] ** 2)
    r, J = fun(theta)
    cost = 0.5 * (r @ r + theta[free] @ P @ theta[free])
    mu, steps, converged = 1e-3, 0, False
    while steps < max_steps:
        steps += 1
        Jf = J[:, free]
        H = Jf.T @ Jf + P
        g = Jf.T @ r + P @ theta[free]
        delta = -np.linalg.solve(H + mu * np.diag(np.diag(H)), g)
        trial = theta.copy()
        trial[free] += delta
        r2, J2 = fun(trial)
        cost2 = 0.5 * (r2 @ r2 + trial[free] @ P @ trial[free])
        if np.isfinite(cost2) and cost2 <= cost:
            theta, r, J, cost, mu = trial, r2, J2, cost2, max(mu / 10, 1e-9)
            if np.max(np.abs(delta)) < 1e-4:
                converged = True
                break
        else:
            mu *= 10
            if mu > 1e8:
                converged = np.max(np.abs(delta)) < 1e-4
                break
    return theta, J, steps, converged


def _pick(labels: Labels, n: int) -> np.ndarray:
    """At most ``n`` labels, spread evenly over each flight's labels (every flight kept)."""
    if len(labels) <= n:
        return np.arange(len(labels))
    return np.unique(np.linspace(0, len(labels) - 1, n).round().astype(int))


@float64
def identify(
    labels: Labels | Sequence[Labels],
    vehicle: str | Path | Mapping[str, Any],
    *,
    free: Sequence[str] = DEFAULT_FREE,
    loads: str = "both",
    physics: bemt.BEMTConfig | None = None,
    max_labels: int = 400,
    max_steps: int = 40,
    passes: int = 3,
    consider: Mapping[str, float | None] | Sequence[str] = (),
    body_rates: bool = True,
) -> Identification:
    """The vehicle's physical parameters from flight labels, by maximum likelihood (module
    docstring).

    Args:
        labels: :func:`gpg.flight.label` of one or more flights (their air velocity must be
            known: the log's wind, or :func:`gpg.flight.with_wind`).
        vehicle: the vehicle file (name, path or mapping) whose values are the starting point
            and the prior's centre: the measured mass, inertia and layout, and the generator's
            part (rotor, airfoil, drag areas), from the nearest known vehicle where the
            vehicle's own are unknown.
        free: the parameters to fit, by key of :data:`PARAMETERS`.
        loads: ``"force"``, ``"torque"`` or ``"both"``: which labels enter the likelihood.
        physics: the blade-element-momentum settings (default: the generator's).
        max_labels: at most this many labels (spread over the flights in time; every step
            evaluates the physics and its derivatives at each).
        max_steps: Levenberg-Marquardt steps per pass.
        passes: fits alternated with the model-error variances' estimate.
        consider: parameters of :data:`PARAMETERS` held at the vehicle file's values but not
            known exactly (a measured rotor radius, a wake gain taken from another vehicle),
            each with its standard deviation in the prior's units (a log-factor on a scale,
            the shift's own units; ``None`` or a bare name: :data:`PARAMETERS`' prior). Their
            uncertainty goes into the free parameters' standard errors: ``se`` is the
            Schmidt "consider" covariance's, ``se_data`` the labels' alone.
        body_rates: read each label's body rates (:attr:`Labels.rates`): the hubs move at
            ``ω × p`` through the air, as in flight. False: the physics of a vehicle that does
            not rotate (as labels without rates are read), whose rotors' rate damping the
            torque coefficient and profile drag then take up.

    Returns:
        The :class:`Identification`: the vehicle, its file, the parameters with standard
        errors, the unidentified ones named.

    Raises:
        ValueError: no labels, an unknown parameter or ``loads``, a vehicle without the
            generator's part, labels with NaN, or a considered parameter that is free, unknown
            or without a positive finite standard deviation.
    """
    names = tuple(free)
    if not isinstance(body_rates, bool):
        raise ValueError(f"body_rates must be True or False, got {body_rates!r}")
    data = _data(labels, names, loads, max_labels)
    if not body_rates:
        data["rates"] = np.zeros_like(data["rates"])
    considered = _considered(consider, names)
    cfg0 = copy.deepcopy(dict(vehicle) if isinstance(vehicle, Mapping) else vehicle_config(vehicle))
    veh0 = Vehicle.from_config(cfg0).require_generator()
    physics0 = physics = bemt.BEMTConfig() if physics is None else physics
    fit, theta, model_var, steps, converged, info, weak = _fit_and_flag(
        veh0, physics, names, data, passes, max_steps
    )
    cov, S = fit.covariances(theta, model_var, info, names, weak, considered)
    se_theta, se_data = _errors(cov, S, considered)
    _warn(converged, max_steps, weak, names, se_theta / se_data, considered)
    theta[fit.free[_weak_mask(names, weak)]] = 0.0
    params, cfg, motor, physics = _identified_file(
        cfg0, names, theta[fit.free], (se_theta, se_data), weak, physics, data["rpm_ref"]
    )
    resid = data["y"] - fit.loads(theta)[0]
    return Identification(
        vehicle=Vehicle.from_config(cfg),
        config=cfg,
        parameters=params,
        unidentified=tuple(weak),
        model_noise=model_var,
        residual_rms=np.sqrt(np.mean(resid**2, 0)),
        n_labels=int(data["y"].shape[0]),
        steps=steps,
        converged=bool(converged),
        motor_gain=motor["motor.gain"],
        physics=physics,
        motor_exponent=motor["motor.exponent"],
        rpm_ref=float(data["rpm_ref"]),
        considered=considered,
        coefficients=_coefficients(veh0, physics0, theta, fit.free, (cov, S), considered, cfg),
    )


# A free parameter whose standard error is over this many times the labels' own owes it mostly
# to the considered parameters: the flights do not tell it apart from them.
CONSIDER_DOMINATES = 3.0


def _warn(converged, max_steps, weak, names, widening, considered) -> None:
    """The identification's warnings: no convergence, parameters the flights do not
    determine, parameters whose error is mostly the considered ones'."""
    said = []
    if not converged:
        said.append(f"Levenberg-Marquardt did not converge in {max_steps} steps a pass; the "
                    "parameters are the last iterate")  # fmt: skip
    if weak:
        said.append("the flights do not determine " + ", ".join(weak) + " (a near-singular "
                    "information matrix): they keep the vehicle file's values within their "
                    "prior; fly manoeuvres that excite them, or fix them (free=)")  # fmt: skip
    dominated = [n for n, r in zip(names, widening, strict=True)
                 if n not in weak and r > CONSIDER_DOMINATES]  # fmt: skip
    if dominated:
        said.append(", ".join(dominated) + " owe their standard errors mostly to the "
                    "uncertainty of " + ", ".join(considered) + " (consider=): know those "
                    "better, or free them on flights that tell them apart")  # fmt: skip
    for text in said:
        warnings.warn("identify: " + text, IdentificationWarning, stacklevel=3)


def _considered(consider, names: tuple[str, ...]) -> dict[str, float]:
    """``consider`` as {name: standard deviation in the prior's units}, checked."""
    if isinstance(consider, str):  # one name, not its characters
        consider = (consider,)
    items = consider.items() if isinstance(consider, Mapping) else ((n, None) for n in consider)
    out: dict[str, float] = {}
    for n, sd in items:
        if n not in PARAMETERS or n in names:
            raise ValueError(
                f"consider must name parameters of {sorted(PARAMETERS)} that are not free, "
                f"got {n!r}"
            )
        sd = PARAMETERS[n].prior if sd is None else float(sd)
        if not (math.isfinite(sd) and sd > 0):
            raise ValueError(f"consider[{n!r}] must be a positive finite standard deviation")
        out[n] = sd
    return out


def _fit_and_flag(veh0, physics, names, data, passes: int, max_steps: int):
    """The fit, the parameters the flights do not determine, and the others fitted again
    beside them held at the file's values (a vehicle consistent with what it keeps, not the
    joint fit's values beside reset ones). Returns the fit (its ``free`` all of ``names``),
    θ, the model-error variances, the steps, convergence, the information and the weak."""
    fit = _Fit(veh0, physics, names, data)
    theta, model_var, steps, converged = fit.run(passes, max_steps)
    info = fit.information(theta, model_var)
    weak = _weak_parameters(info, fit.sd_all[fit.free], names)
    if weak and len(weak) < len(names):
        fit = _Fit(veh0, physics, tuple(n for n in names if n not in weak), data, columns=names)
        theta, model_var, n, converged = fit.run(passes, max_steps)
        steps += n
        kept = fit.information(theta, model_var)
        keep = np.array([n not in weak for n in names])
        info = np.zeros((len(names), len(names)))
        info[np.ix_(keep, keep)] = kept
        fit.free = np.array([ALL.index(n) for n in names])
    return fit, theta, model_var, steps, converged, info, weak


def _data(labels, names: tuple[str, ...], loads: str, max_labels: int) -> dict[str, Any]:
    """The labels' arrays the likelihood reads (at most ``max_labels``), checked, and which
    load components enter it."""
    parts = [labels] if isinstance(labels, Labels) else list(labels)
    if not parts or not all(isinstance(p, Labels) for p in parts):
        raise ValueError("identify needs gpg.flight.Labels (label your logs first)")
    lab = Labels.concatenate(parts)
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown or not names or len(set(names)) != len(names):
        raise ValueError(f"free must name distinct parameters of {sorted(PARAMETERS)}, got {names}")
    if loads not in ("force", "torque", "both"):
        raise ValueError(f"loads must be 'force', 'torque' or 'both', got {loads!r}")
    if len(lab) < 2 * len(names):
        raise ValueError(f"identify needs at least {2 * len(names)} labels, got {len(lab)}")
    rows = _pick(lab, max_labels)
    part = np.repeat(np.arange(len(parts)), [len(p) for p in parts])
    out = {
        # each label's flight and instant: the scores' correlation is summed along a flight
        "part": part[rows],
        "t": np.asarray(lab.t, float)[rows],
        "rpm": np.asarray(lab.rpm, float)[rows],
        "euler": np.asarray(lab.euler, float)[rows],
        "v_air": np.asarray(lab.v_air, float)[rows],
        # a label without its body rates is read as a vehicle that does not rotate
        "rates": np.zeros((len(lab), 3)) if lab.rates is None else np.asarray(lab.rates, float),
        "y": np.concatenate([lab.force, lab.torque], 1)[rows],
        "var": np.concatenate([lab.force_var, lab.torque_var], 1)[rows],
    }
    if out["rates"].shape != (len(lab), 3):
        raise ValueError(f"labels' rates must be (N, 3), got {out['rates'].shape}")
    out["rates"] = out["rates"][rows]
    for nm, a in out.items():
        if not np.isfinite(a).all():
            raise ValueError(f"labels hold NaN or inf in {nm}")
    use = np.zeros(6, bool)
    use[:3] = loads in ("force", "both")
    use[3:] = loads in ("torque", "both")
    out["use"] = use
    turning = out["rpm"][out["rpm"] > 0]
    out["rpm_ref"] = float(np.median(turning)) if turning.size else 1.0
    return out


class _Fit:
    """The likelihood of :func:`identify`: the physics at the labels, whitened residuals, the
    Levenberg-Marquardt passes alternated with the model-error variances' estimate."""

    def __init__(self, veh0: Vehicle, physics: bemt.BEMTConfig, names, data, columns=None):
        self.veh0, self.physics, self.data = veh0, physics, data
        self.free = np.array([ALL.index(n) for n in names])
        self.sd_all = np.array([PARAMETERS[n].prior for n in ALL])
        # The parameters E differentiates along: the free ones, or (a refit beside fixed ones)
        # the first fit's, so that the refit runs the program the first fit compiled.
        self.columns = np.array([ALL.index(n) for n in (names if columns is None else columns)])
        self.E = jnp.asarray(np.eye(len(ALL))[:, self.columns])
        self.states = tuple(jnp.asarray(data[k]) for k in ("rpm", "euler", "v_air"))
        self.rates = jnp.asarray(data["rates"])
        # a strong float64, as an array's median is: a weak-typed Python float would compile
        # the physics' program a second time for the same shapes
        self.rpm_ref = jnp.asarray(np.float64(data["rpm_ref"]))
        self._last: tuple[np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None

    def loads(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The physics' loads (N, 6) and their Jacobian (N, 6, 9), zero off the free columns.

        The last θ's are kept: the model-error variances, the information and the residuals
        after a pass all read the physics at the θ the pass ended on."""
        if self._last is not None and np.array_equal(self._last[0], theta):
            return self._last[1]
        out, Jf = loads_and_jacobian(self.veh0, self.physics, jnp.asarray(theta), self.E,
                                     *self.states, self.rpm_ref, self.rates)  # fmt: skip
        J = np.zeros((*out.shape, len(ALL)))
        J[:, :, self.columns] = np.asarray(Jf)
        self._last = (np.array(theta), (np.asarray(out), J))
        return self._last[1]

    def model_var(self, theta: np.ndarray) -> np.ndarray:
        """Each component's variance left beyond the labels' noise (a floor keeps it > 0)."""
        y, var = self.data["y"], self.data["var"]
        r = y - self.loads(theta)[0]
        return np.maximum(np.mean(r**2 - var, 0), 1e-6 * np.mean(y**2, 0) + 1e-12)

    def residuals(self, theta: np.ndarray, model_var: np.ndarray):
        """The whitened residuals and their Jacobian in θ."""
        d = self.data
        w = np.where(d["use"], 1.0 / np.sqrt(d["var"] + model_var), 0.0)
        out, J = self.loads(theta)
        return ((d["y"] - out) * w).ravel(), -(J * w[:, :, None]).reshape(-1, len(ALL))

    def run(self, passes: int, max_steps: int):
        theta = np.zeros(len(ALL))
        model_var = self.model_var(theta)
        steps, converged = 0, False
        for _ in range(max(1, passes)):
            theta, _, n, converged = _levenberg_marquardt(
                lambda th, mv=model_var: self.residuals(th, mv),
                theta, self.sd_all, self.free, max_steps,
            )  # fmt: skip
            steps += n
            model_var = self.model_var(theta)
        return theta, model_var, steps, converged

    def information(self, theta: np.ndarray, model_var: np.ndarray) -> np.ndarray:
        """The data's effective information over the free parameters: ``H (B + P)⁻¹ H − P``
        (its negative eigenvalues cut to zero), so that ``(info + P)⁻¹`` is the sandwich
        ``H⁻¹ (B + P) H⁻¹`` of the estimate, ``H = JᵀJ + P`` the objective's curvature and
        ``B`` the scores' long-run covariance (:func:`_long_run`). With independent labels
        whose variances the model states, ``B → JᵀJ`` and ``info → JᵀJ``."""
        r, J = self.residuals(theta, model_var)
        n = self.data["y"].shape[0]
        J = J[:, self.free]
        scores = np.einsum("tcp,tc->tp", J.reshape(n, 6, -1), r.reshape(n, 6))
        B, _ = _long_run(scores, self.data["part"], self.data["t"])
        P = np.diag(1.0 / self.sd_all[self.free] ** 2)
        H = J.T @ J + P
        eff = H @ np.linalg.solve(B + P, H) - P
        lam, vec = np.linalg.eigh(0.5 * (eff + eff.T))
        return (vec * np.maximum(lam, 0.0)) @ vec.T

    def covariances(self, theta, model_var, info, names, weak, considered):
        """The free parameters' covariance from the labels alone and their estimate's linear
        sensitivity to the considered parameters (θ's units): the covariance with the
        considered ones' uncertainty is ``C + S Σ_c Sᵀ``."""
        cov = np.linalg.inv(info + np.diag(1.0 / self.sd_all[self.free] ** 2))
        S = np.zeros((len(names), len(considered)))
        if considered:
            S = self.consider_sensitivity(theta, model_var, names, weak, considered)
        return cov, S

    def consider_sensitivity(self, theta, model_var, names, weak, considered):
        """``S = −H⁻¹ I_c``: the estimate's linear sensitivity to the considered parameters
        (``H = JᵀJ + P`` the objective's curvature, ``I_c`` the whitened Jacobians'
        cross-information; Tapley, Schutz and Born, chapter 6: how far the optimum moves,
        whatever the labels' correlation). The weak parameters, held at the file's values,
        get none.

        The derivatives along the considered parameters come from the fit's own compiled
        program: its directions hold as many columns as the fit frees, so the considered
        parameters' unit vectors go in that many at a time, padded with zeros."""
        d, width = self.data, len(self.columns)
        w = np.where(d["use"], 1.0 / np.sqrt(d["var"] + model_var), 0.0)
        idx = [ALL.index(n) for n in considered]
        cols = []
        for start in range(0, len(idx), width):
            chunk = idx[start : start + width]
            E = np.zeros((len(ALL), width))
            E[chunk, np.arange(len(chunk))] = 1.0
            _, Jc = loads_and_jacobian(self.veh0, self.physics, jnp.asarray(theta),
                                       jnp.asarray(E), *self.states, self.rpm_ref,
                                       self.rates)  # fmt: skip
            cols.append(np.asarray(Jc)[:, :, : len(chunk)])
        Jc = (np.concatenate(cols, 2) * w[:, :, None]).reshape(-1, len(idx))
        keep = ~_weak_mask(names, weak)
        Jt = self.residuals(theta, model_var)[1][:, self.free[keep]]
        H = Jt.T @ Jt + np.diag(1.0 / self.sd_all[self.free[keep]] ** 2)
        out = np.zeros((len(names), len(idx)))
        # Jt is the residuals' Jacobian (minus the loads'), Jc the loads': Jtᵀ Jc = −I_c.
        out[keep] = np.linalg.solve(H, Jt.T @ Jc)
        return out


def _errors(cov: np.ndarray, S: np.ndarray, considered: Mapping[str, float]):
    """The standard errors with the considered parameters' uncertainty, and the labels'
    alone (θ's units)."""
    sd_c = np.array(list(considered.values()), float)
    return np.sqrt(np.diag(cov + (S * sd_c**2) @ S.T)), np.sqrt(np.diag(cov))


def _identified_file(cfg0, names, theta, errors, weak, physics, rpm_ref):
    """The parameters' table, the identified vehicle file (``M``'s coefficients fitted to its
    hover; its motor's speed range in the identified curve's speeds), the motor curve's gain
    and exponent, and the physics' settings (the wake gain). ``errors``: the free parameters'
    standard errors with the considered ones' uncertainty, and the labels' alone (θ's units)."""
    params: dict[str, dict[str, Any]] = {}
    cfg = copy.deepcopy(cfg0)
    motor = {"motor.gain": 1.0, "motor.exponent": 1.0}
    physics0 = physics
    for i, n in enumerate(names):
        spec = PARAMETERS[n]
        nominal = _get(cfg0, n, physics0)
        if n in weak:
            th, se, se_data = 0.0, float(spec.prior), float(spec.prior)
        else:
            th, se, se_data = float(theta[i]), float(errors[0][i]), float(errors[1][i])
        scaled = nominal * math.exp(th)
        factor = scaled if spec.kind == "scale" else 1.0  # θ's units to the value's
        value = scaled if spec.kind == "scale" else nominal + th
        params[n] = {"value": value, "se": factor * se, "se_data": factor * se_data,
                     "nominal": nominal, "unit": spec.unit,
                     "identified": n not in weak}  # fmt: skip
        if n in motor:
            motor[n] = value
        elif n == "generator.wake_gain":
            physics = dataclasses.replace(physics, wake_gain=value)
        else:
            _set(cfg, n, value)
    cfg["name"] = f"{cfg0.get('name', 'vehicle')}_identified"
    if motor != {"motor.gain": 1.0, "motor.exponent": 1.0} and "motor" in cfg:
        # The file's range was in the speeds the labels held: the identified rotor's is the
        # identified curve's image of it (the saturation and the flight's limits follow).
        cfg["motor"] = dict(cfg["motor"])
        for key in ("rpm_min", "rpm_max"):
            cfg["motor"][key] = round(float(motor_speeds(
                jnp.asarray(float(cfg["motor"][key])), math.log(motor["motor.gain"]),
                math.log(motor["motor.exponent"]), float(rpm_ref))), 3)  # fmt: skip
    P_F, T_z = hover_coefficients(Vehicle.from_config(cfg), physics)
    cfg["simple_model"] = {"thrust_coefficient": P_F, "torque_coefficient": T_z}
    return params, cfg, motor, physics


# θ's units: a central difference errs by O(step²) of the hover's curvature (1e-8 relative),
# its rounding by float64's 1e-16 over the step (1e-12)
HOVER_STEP = 1e-4


def _hover_fit(vehicle: Vehicle, cfg: bemt.BEMTConfig, theta) -> tuple[float, float]:
    """``(P_F, T_z)`` of the hover sweep with ``θ`` applied (the wake gain's included)."""
    T, Q = _hover(vehicle, cfg, jnp.asarray(HOVER_RPM), theta)
    return fit_coefficients(np.repeat(HOVER_RPM, 4), np.asarray(T).ravel(), np.asarray(Q).ravel())


def _hover_gradient(vehicle: Vehicle, cfg: bemt.BEMTConfig, theta: np.ndarray, columns):
    """(2, C) derivatives of ``(P_F, T_z)`` in θ's ``columns``, by central differences of the
    compiled hover sweep: ``jax.jacfwd`` through it compiles a program of its own, a large
    share of an identification's time (the design notes), for a first-order error that a
    difference gives to 1e-8."""
    out = np.zeros((2, len(columns)))
    for k, j in enumerate(columns):
        step = np.zeros(len(ALL))
        step[j] = HOVER_STEP
        up, down = (np.array(_hover_fit(vehicle, cfg, jnp.asarray(theta + s)))
                    for s in (step, -step))  # fmt: skip
        out[:, k] = (up - down) / (2 * HOVER_STEP)
    return out


def _coefficients(veh0, physics, theta, free, covariances, considered, cfg):
    """``M``'s coefficients of the identified file with standard errors, to first order:
    ``g C gᵀ`` from the labels (``g`` their gradient in the free θ), plus ``(g S + g_c) Σ_c
    (g S + g_c)ᵀ`` from the considered parameters, which move them directly (``g_c``: a
    radius held fixed) and through the free ones' estimates (``S``): where the flights fix the
    thrust, a chord that makes up for the radius leaves ``P_F`` where it was."""
    cov, S = covariances
    g = _hover_gradient(veh0, physics, theta, free)
    g_c = _hover_gradient(veh0, physics, theta, [ALL.index(n) for n in considered])
    sd_c = np.array(list(considered.values()), float)
    lever = g @ S + g_c
    var_data = np.einsum("ip,pq,iq->i", g, cov, g)
    var = var_data + np.einsum("ic,c,ic->i", lever, sd_c**2, lever)
    nominal = hover_coefficients(veh0, physics)
    out = {}
    for i, (key, unit) in enumerate((("thrust_coefficient", "N/rpm²"),
                                     ("torque_coefficient", "N·m/rpm²"))):  # fmt: skip
        out[key] = {"value": float(cfg["simple_model"][key]), "se": float(np.sqrt(var[i])),
                    "se_data": float(np.sqrt(var_data[i])), "nominal": float(nominal[i]),
                    "unit": unit}  # fmt: skip
    return out


def _weak_mask(names: tuple[str, ...], weak: Sequence[str]) -> np.ndarray:
    """(P,) True for the parameters in ``weak``."""
    return np.array([n in weak for n in names])


def _long_run(
    scores: Float[np.ndarray, "N P"], part: np.ndarray, t: np.ndarray
) -> tuple[Float[np.ndarray, "P P"], int]:
    """The long-run covariance ``B = Σ_|l|≤L (1 − |l|/(L+1)) Γ_l`` of the labels' scores
    (Newey and West's Bartlett window: positive semi-definite), ``Γ_l`` the lag-``l``
    cross-products of each flight's scores in time (no lag spans two flights).

    The lags ``L`` are the larger of Newey and West's (1994) rule ``⌊4 (N/100)^{2/9}⌋`` and
    Andrews' (1991) AR(1) plug-in ``⌈1.1447 (α N)^{1/3}⌉``, at most a flight's labels: the
    rule sums the weak correlation spread over many lags that a misfit varying along the
    flights gives (the hard benchmark's, whose lag-one correlation is near zero), the plug-in
    follows a strong one.

    Returns:
        ``B`` and ``L``.
    """
    order = np.lexsort((t, part))
    g, part = scores[order], part[order]
    n = len(g)
    longest = int(np.max(np.unique(part, return_counts=True)[1]))
    lags = min(max(int(4 * (n / 100) ** (2 / 9)), _andrews(g, part, n)), longest - 1)
    B = g.T @ g
    for lag in range(1, lags + 1):
        same = part[lag:] == part[:-lag]
        G = g[lag:][same].T @ g[:-lag][same]
        B += (1 - lag / (lags + 1)) * (G + G.T)
    return B, lags


def _andrews(g: np.ndarray, part: np.ndarray, n: int) -> int:
    """Andrews' AR(1) plug-in lags for the Bartlett window: each score's lag-one
    coefficient ``ρ_p`` and innovation variance ``σ_p²`` within the flights, ``α = Σ 4ρ²σ⁴ /
    ((1−ρ)⁶(1+ρ)²) / Σ σ⁴/(1−ρ)⁴`` (``ρ`` clipped to ±0.97: a score that does not vary
    along a flight is not a random walk)."""
    same = part[1:] == part[:-1]
    if not same.any():
        return 0
    a, b = g[1:][same], g[:-1][same]
    rho = np.clip(np.sum(a * b, 0) / np.maximum(np.sum(b * b, 0), 1e-300), -0.97, 0.97)
    s2 = np.mean((a - rho * b) ** 2, 0)
    den = np.sum(s2**2 / (1 - rho) ** 4)
    if den <= 0:
        return 0
    alpha = np.sum(4 * rho**2 * s2**2 / ((1 - rho) ** 6 * (1 + rho) ** 2)) / den
    return int(math.ceil(1.1447 * (alpha * n) ** (1 / 3)))


def _weak_parameters(info: np.ndarray, sd: np.ndarray, names: tuple[str, ...]) -> list[str]:
    """The parameters that load on a direction the data barely inform: eigenvectors of the
    data's information in prior units, ``S I S`` (``S = diag(sd)``), with an eigenvalue under
    :data:`IDENTIFIABLE`; a parameter is named where its share of such a vector is over a
    fifth."""
    scaled = info * sd[:, None] * sd[None, :]
    lam, vec = np.linalg.eigh(0.5 * (scaled + scaled.T))
    weak: set[int] = set()
    for k in np.flatnonzero(lam < IDENTIFIABLE):
        share = vec[:, k] ** 2
        weak.update(int(i) for i in np.flatnonzero(share > 0.2))
    return [names[i] for i in sorted(weak)]


@eqx.filter_jit  # one compiled program: op by op, the sweep took seconds every call
@highest
def _hover(vehicle: Vehicle, cfg: bemt.BEMTConfig, rpm: Float[Array, " S"], theta):
    """Each rotor's thrust and torque at hover at each speed, ``θ`` applied (zeros: none)."""
    vehicle = _apply(vehicle, ALL, theta)
    wake = cfg.wake_gain * jnp.exp(theta[ALL.index("generator.wake_gain")])

    def one(r):
        res = bemt.aero(vehicle, cfg, jnp.full(4, r), jnp.eye(3), jnp.zeros(3), wake_gain=wake)
        return res.rotors.thrust, res.rotors.torque

    return jax.vmap(one)(rpm)


def hover_coefficients(vehicle: Vehicle, cfg: bemt.BEMTConfig | None = None) -> tuple[float, float]:
    """``M``'s ``P_F`` and ``T_z`` of a vehicle, fitted to its physics' hover sweep (2000 to
    6000 rpm, as :func:`gpg.quadrotor.simple_model.fit_to_generator`).

    Args:
        vehicle: a full vehicle.
        cfg: the physics' settings (default: the generator's).

    Returns:
        ``P_F`` (N/rpm²) and ``T_z`` (N·m/rpm²).
    """
    # θ = 0 traced, as where the coefficients' derivatives are taken: one compiled sweep
    return _hover_fit(vehicle, bemt.BEMTConfig() if cfg is None else cfg, jnp.zeros(len(ALL)))
