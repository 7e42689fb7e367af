"""Vehicle parameters, loaded by name from the vehicle files shipped with gpg
(``gpg/conf/vehicle/<name>.yaml``, package data) or from any YAML file (units in the YAML
comments).

A vehicle file has two parts. What the simplified model ``M``, the rigid body and the
controller need is required: ``name``, ``mass``, ``inertia``, the ``layout`` (an X layout by
``arm`` or explicit hub ``positions``, ``spin``, ``hub_height``) and the ``motor`` range
(``rpm_min``, ``rpm_max``, optionally its ``time_constant``; without one, rotor speeds follow
their commands at once), plus optionally ``gravity`` (default 9.81 m/s²) and ``simple_model``
(``thrust_coefficient`` ``P_F`` in N/rpm² and ``torque_coefficient`` ``T_z`` in N·m/rpm²;
without them they are fitted from the data). What only the built-in generator needs is
optional as a whole: ``rotor`` (blade tables), ``airfoil``, ``microphones``, ``drag_area``,
``air_density`` and ``speed_of_sound``; the generator refuses a vehicle that lacks any of them
and names what is missing.

Everything numeric is a JAX array leaf, so a :class:`Vehicle` can be passed through ``jit`` and
differentiated; only the blade count and the name are static.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import yaml
from jaxtyping import Array, Float

from gpg import conf

__all__ = ["Airfoil", "Rotor", "Vehicle", "known_vehicles", "load_vehicle", "vehicle_config"]

INCH = 0.0254  # m


class Airfoil(eqx.Module):
    """Smooth lift/drag polar: attached flow blended into flat-plate post-stall behaviour."""

    lift_slope: Float[Array, ""]  # 1/rad
    alpha_zero_lift: Float[Array, ""]  # rad
    stall: Float[Array, ""]  # rad, centre of the blend
    stall_sharpness: Float[Array, ""]  # 1/rad
    cd0: Float[Array, ""]
    cd2: Float[Array, ""]  # 1/rad²
    alpha_min_drag: Float[Array, ""]  # rad


class Rotor(eqx.Module):
    """Blade geometry shared by the four rotors."""

    radius: Float[Array, ""]  # m
    root_cutout: Float[Array, ""]  # r/R
    stations: Float[Array, " S"]  # r/R of the blade tables
    twist: Float[Array, " S"]  # rad
    chord: Float[Array, " S"]  # m
    thickness_ratio: Float[Array, ""]  # t/c
    n_blades: int = eqx.field(static=True)

    @property
    def disk_area(self) -> Float[Array, ""]:
        return jnp.pi * self.radius**2


# The generator's part of a vehicle file, by YAML key.
GENERATOR_KEYS = ("rotor", "airfoil", "microphones", "drag_area", "air_density", "speed_of_sound")


class Vehicle(eqx.Module):
    """A quadrotor: layout, mass properties and motors (what ``M``, the rigid body and the
    controller need), plus, for the built-in generator only, rotor geometry, airfoil, airframe
    drag, air properties and the microphones of the noise outputs (None on a minimal vehicle).

    ``positions`` are hub positions in the body frame (FRD, m) in rotor order r1..r4 (rear-right,
    rear-left, front-left, front-right); ``spin`` is +1 for rotation about +z_B (clockwise seen
    from above) and −1 otherwise. ``mic_positions`` are body-frame microphone positions (m).
    ``thrust_coefficient``/``torque_coefficient`` are ``M``'s ``P_F``/``T_z`` when the file gives
    them. ``motor_time_constant`` 0 means rotor speeds follow their commands at once.
    """

    positions: Float[Array, "4 3"]
    spin: Float[Array, " 4"]
    mass: Float[Array, ""]  # kg
    gravity: Float[Array, ""]  # m/s²
    inertia: Float[Array, " 3"]  # kg·m², principal moments about body x, y, z
    motor_time_constant: Float[Array, ""]  # s, first-order rotor-speed lag (0: none)
    rpm_min: Float[Array, ""]  # rpm
    rpm_max: Float[Array, ""]  # rpm
    thrust_coefficient: Float[Array, ""] | None  # P_F, N/rpm²
    torque_coefficient: Float[Array, ""] | None  # T_z, N·m/rpm²
    rotor: Rotor | None
    airfoil: Airfoil | None
    drag_area: Float[Array, " 3"] | None  # m², airframe D/q along body x, y, z
    air_density: Float[Array, ""] | None  # kg/m³
    speed_of_sound: Float[Array, ""] | None  # m/s
    mic_positions: Float[Array, "K 3"] | None
    name: str = eqx.field(static=True)

    @property
    def weight(self) -> Float[Array, ""]:
        return self.mass * self.gravity

    @property
    def generator_missing(self) -> tuple[str, ...]:
        """The generator-only parts this vehicle lacks (empty for a full vehicle)."""
        have = {
            "rotor": self.rotor,
            "airfoil": self.airfoil,
            "microphones": self.mic_positions,
            "drag_area": self.drag_area,
            "air_density": self.air_density,
            "speed_of_sound": self.speed_of_sound,
        }
        return tuple(k for k in GENERATOR_KEYS if have[k] is None)

    def require_generator(self) -> Vehicle:
        """This vehicle, checked to carry everything the built-in generator needs.

        Returns:
            The vehicle itself, unchanged.

        Raises:
            ValueError: if it lacks any generator-only part (:attr:`generator_missing`), naming
                them.
        """
        missing = self.generator_missing
        if missing:
            raise ValueError(
                f"vehicle {self.name!r} cannot drive the built-in generator: it lacks "
                f"{', '.join(missing)} (a vehicle file for the simplified model and flight "
                "only may omit them; see conf/vehicle/sui_endurance.yaml for the full form)"
            )
        return self

    def half_turn_asymmetries(self, *, levels: bool = False) -> list[str]:
        """What keeps this vehicle from being its own image under a half turn about the body
        z axis with the rotors relabelled (:func:`gpg.quadrotor.frames.half_turn`): empty when
        a surrogate may use that symmetry.

        The hubs ``r1, r2`` must be the images of ``r3, r4`` (to a micrometre per metre of the
        layout), each diagonal pair spin the same way, and, where the noise levels are
        predicted, each microphone lie on the body z axis (its own image: a microphone off the
        axis has no microphone at its image, so its level there is unknown).

        Args:
            levels: also require the microphones to be their own images.

        Returns:
            One sentence per mismatch, naming the rotors or microphones.
        """
        pos, spin = np.asarray(self.positions, float), np.asarray(self.spin)
        tol = 1e-6 * max(float(np.abs(pos).max()), 1e-3)
        image = pos * np.array([-1.0, -1.0, 1.0])
        out = []
        for i, j in ((0, 2), (1, 3)):
            if np.abs(image[i] - pos[j]).max() > tol:
                out.append(f"hub r{j + 1} {pos[j].tolist()} is not the image of r{i + 1}'s "
                           f"{pos[i].tolist()} under the half turn")  # fmt: skip
            if spin[i] != spin[j]:
                out.append(f"rotors r{i + 1} and r{j + 1} spin opposite ways")
        if levels and self.mic_positions is not None:
            mics = np.asarray(self.mic_positions, float)
            for k, m in enumerate(mics):
                if np.hypot(m[0], m[1]) > 1e-6 * max(float(np.abs(m).max()), 1e-3):
                    out.append(f"microphone {k} at {m.round(4).tolist()} m is off the body z "
                               "axis: its level has no microphone at its image")  # fmt: skip
        return out

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> Vehicle:
        """Build from the mapping of a vehicle YAML file (plain dict).

        The module docstring says what is required and what is optional. Every key is read
        once: a missing required key, a value out of range and an unknown key are errors,
        each naming the full key (``vehicle.motor.rpm_max``).

        Args:
            cfg: the vehicle file's mapping (as :func:`vehicle_config` returns it).

        Returns:
            The vehicle; the generator-only fields are None where the file omits them.

        Raises:
            ValueError: if a key is missing, malformed, out of range or unknown, or the spins,
                inertia or motor range are inconsistent, naming the key.
        """
        c = _Reader(cfg, "vehicle")
        lay = _Reader(c.get("layout"), "vehicle.layout")
        motor = _Reader(c.get("motor"), "vehicle.motor")
        spin = lay.array("spin", ndim=1)
        if spin.shape != (4,) or not np.all(np.abs(spin) == 1):
            raise ValueError(f"vehicle.layout.spin must be four entries of +1 or -1, got {spin}")
        positions = _positions(lay)
        inertia = c.array("inertia", ndim=1)
        if inertia.shape != (3,) or np.any(inertia <= 0):
            raise ValueError(f"vehicle.inertia must be three values > 0 (kg·m²), got {inertia}")
        rpm_min, rpm_max = motor.number("rpm_min"), motor.positive("rpm_max")
        if not 0 <= rpm_min < rpm_max:
            raise ValueError(
                f"vehicle.motor needs 0 <= rpm_min < rpm_max, got {rpm_min}, {rpm_max}"
            )
        lag = motor.number("time_constant") if motor.has("time_constant") else 0.0
        if lag < 0:
            raise ValueError(f"vehicle.motor.time_constant must be >= 0 s, got {lag}")
        P_F = T_z = None
        if c.has("simple_model"):
            sm = _Reader(c.get("simple_model"), "vehicle.simple_model")
            P_F = jnp.asarray(sm.positive("thrust_coefficient"))
            T_z = jnp.asarray(sm.positive("torque_coefficient"))
            sm.done()
        gen = _generator_part(c)
        out = cls(
            positions=jnp.asarray(positions),
            spin=jnp.asarray(spin),
            mass=jnp.asarray(c.positive("mass")),
            gravity=jnp.asarray(c.positive("gravity") if c.has("gravity") else 9.81),
            inertia=jnp.asarray(inertia),
            motor_time_constant=jnp.asarray(lag),
            rpm_min=jnp.asarray(rpm_min),
            rpm_max=jnp.asarray(rpm_max),
            thrust_coefficient=P_F,
            torque_coefficient=T_z,
            name=str(c.get("name")),
            **gen,
        )
        for r in (lay, motor, c):
            r.done()
        return out


def _positions(lay: _Reader) -> np.ndarray:
    """Hub positions (4, 3) in rotor order: an X layout from ``arm``, or explicit ones."""
    h = lay.number("hub_height") if lay.has("hub_height") else 0.0
    if lay.has("positions"):
        if lay.has("arm"):
            raise ValueError("vehicle.layout: give either arm (X layout) or positions, not both")
        p = lay.array("positions", ndim=2)
        if p.shape != (4, 3):
            raise ValueError(f"vehicle.layout.positions must be 4 x 3 (m, FRD), got {p.shape}")
        return p
    arm = lay.positive("arm")
    ell = arm / math.sqrt(2.0)
    # r1 rear-right, r2 rear-left, r3 front-left, r4 front-right; rotor plane above the CoM.
    return np.array(
        [[-ell, ell, -h], [-ell, -ell, -h], [ell, -ell, -h], [ell, ell, -h]], dtype=float
    )


# Long by design: one flat check per key of the generator's part of a vehicle file.
def _generator_part(c: _Reader) -> dict[str, Any]:
    """The generator-only fields (None each where the file omits its key)."""
    out: dict[str, Any] = {
        "rotor": None,
        "airfoil": None,
        "mic_positions": None,
        "drag_area": None,
        "air_density": None,
        "speed_of_sound": None,
    }
    radius = None
    if c.has("rotor"):
        rot = _Reader(c.get("rotor"), "vehicle.rotor")
        twist = np.deg2rad(rot.array("twist_deg", ndim=1))
        chord = rot.array("chord_in", ndim=1) * INCH
        if twist.shape != chord.shape or twist.size < 2:
            raise ValueError(
                "vehicle.rotor.twist_deg and chord_in must be tables of equal length >= 2, "
                f"got {twist.size} and {chord.size}"
            )
        radius = rot.positive("radius")
        cutout = rot.number("root_cutout")
        if not 0 <= cutout < 1:
            raise ValueError(f"vehicle.rotor.root_cutout must be in [0, 1), got {cutout}")
        n_blades = rot.get("n_blades")
        if not isinstance(n_blades, int) or n_blades < 1:
            raise ValueError(f"vehicle.rotor.n_blades must be a positive integer, got {n_blades}")
        out["rotor"] = Rotor(
            radius=jnp.asarray(radius),
            root_cutout=jnp.asarray(cutout),
            stations=jnp.asarray(np.linspace(cutout, 1.0, twist.size)),
            twist=jnp.asarray(twist),
            chord=jnp.asarray(chord),
            thickness_ratio=jnp.asarray(rot.positive("thickness_ratio")),
            n_blades=n_blades,
        )
        rot.done()
    if c.has("airfoil"):
        foil = _Reader(c.get("airfoil"), "vehicle.airfoil")
        out["airfoil"] = Airfoil(
            lift_slope=jnp.asarray(foil.positive("lift_slope")),
            alpha_zero_lift=jnp.asarray(math.radians(foil.number("alpha_zero_lift_deg"))),
            stall=jnp.asarray(math.radians(foil.positive("stall_deg"))),
            stall_sharpness=jnp.asarray(foil.positive("stall_sharpness")),
            cd0=jnp.asarray(foil.positive("cd0")),
            cd2=jnp.asarray(foil.number("cd2")),
            alpha_min_drag=jnp.asarray(math.radians(foil.number("alpha_min_drag_deg"))),
        )
        foil.done()
    if c.has("microphones"):
        mics = _Reader(c.get("microphones"), "vehicle.microphones")
        if radius is None:
            raise ValueError("vehicle.microphones are placed in rotor radii: give vehicle.rotor")
        r_mic = mics.positive("radius_in_rotor_radii") * radius
        elev = np.deg2rad(mics.array("elevation_deg", ndim=1))
        out["mic_positions"] = jnp.asarray(
            np.stack([np.zeros_like(elev), np.cos(elev), np.sin(elev)], -1) * r_mic
        )
        mics.done()
    if c.has("drag_area"):
        drag = c.array("drag_area", ndim=1)
        if drag.shape != (3,) or np.any(drag < 0):
            raise ValueError(f"vehicle.drag_area must be three values >= 0 (m²), got {drag}")
        out["drag_area"] = jnp.asarray(drag)
    for key in ("air_density", "speed_of_sound"):
        if c.has(key):
            out[key] = jnp.asarray(c.positive(key))
    return out


def load_vehicle(name_or_path: str | Path = "sui_endurance") -> Vehicle:
    """A vehicle by name or from a YAML file at any path.

    An existing file (any suffix) is read as it is; anything else is looked up by name among
    the vehicle files shipped with gpg (:func:`known_vehicles`).

    Args:
        name_or_path: a shipped vehicle's name (``"sui_endurance"``, the default) or a path.

    Returns:
        The vehicle (:meth:`Vehicle.from_config` of :func:`vehicle_config`).
    """
    return Vehicle.from_config(vehicle_config(name_or_path))


def known_vehicles() -> list[str]:
    """The names of the vehicle files shipped with gpg (``gpg/conf/vehicle``).

    Returns:
        The names, each accepted by :func:`load_vehicle`.
    """
    return conf.names("vehicle")


def vehicle_config(name_or_path: str | Path = "sui_endurance") -> dict[str, Any]:
    """The plain mapping of a vehicle file, unchecked beyond being a mapping.

    Used e.g. to record in a dataset's metadata, so that the dataset names its own vehicle;
    the lookup is :func:`load_vehicle`'s.

    Args:
        name_or_path: a shipped vehicle's name or the path of a YAML file.

    Returns:
        The file's mapping as a plain dict.

    Raises:
        ValueError: if there is no such file or shipped vehicle, or the file is not valid
            YAML (or UTF-8) or does not hold a mapping.
    """
    path = Path(name_or_path)
    where: Any = path
    if path.is_file():
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as exc:
            raise ValueError(f"vehicle file {path} is not valid YAML: {exc}") from exc
    else:
        # A bare name only: a path that is not a file is not looked up among the vehicles.
        plain = path.name == str(name_or_path) and not path.name.startswith(".")
        text = conf.read_text("vehicle", path.name) if plain else None
        where = f"gpg/conf/vehicle/{name_or_path}.yaml"
        if text is None:
            raise ValueError(
                f"no vehicle file {name_or_path!r}; known vehicles: {known_vehicles()}"
            )
    try:
        cfg = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"vehicle file {where} is not valid YAML: {exc}") from exc
    if not isinstance(cfg, Mapping):
        raise ValueError(f"vehicle file {where} must hold a mapping, got {type(cfg).__name__}")
    return dict(cfg)


class _Reader:
    """Reads keys of one config mapping, naming the full key in every error."""

    def __init__(self, cfg: Any, where: str):
        if not isinstance(cfg, Mapping):
            raise ValueError(f"{where} must be a mapping, got {type(cfg).__name__}")
        self.cfg, self.where, self.used = cfg, where, set()

    def has(self, key: str) -> bool:
        return key in self.cfg

    def get(self, key: str) -> Any:
        if key not in self.cfg:
            raise ValueError(f"{self.where}.{key} is missing")
        self.used.add(key)
        return self.cfg[key]

    def number(self, key: str) -> float:
        v = self.get(key)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ValueError(f"{self.where}.{key} must be a finite number, got {v!r}")
        return float(v)

    def positive(self, key: str) -> float:
        v = self.number(key)
        if v <= 0:
            raise ValueError(f"{self.where}.{key} must be > 0, got {v}")
        return v

    def array(self, key: str, ndim: int) -> np.ndarray:
        v = self.get(key)
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self.where}.{key} must be numeric, got {v!r}") from exc
        if a.ndim != ndim or not np.all(np.isfinite(a)):
            raise ValueError(f"{self.where}.{key} must be a finite {ndim}-d list, got {v!r}")
        return a

    def done(self) -> None:
        extra = sorted(set(self.cfg) - self.used)
        if extra:
            raise ValueError(f"{self.where} has unknown keys {extra}")
