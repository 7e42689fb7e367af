"""Vehicle parameters, loaded from ``conf/vehicle/<name>.yaml`` (units in the YAML comments).

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

INCH = 0.0254  # m

VEHICLE_DIR = Path(__file__).resolve().parents[2] / "conf" / "vehicle"


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


class Vehicle(eqx.Module):
    """A quadrotor: rotor geometry, layout, airframe and the microphones of the noise outputs.

    ``positions`` are hub positions in the body frame (FRD, m) in rotor order r1..r4 (rear-right,
    rear-left, front-left, front-right); ``spin`` is +1 for rotation about +z_B (clockwise seen
    from above) and −1 otherwise. ``mic_positions`` are body-frame microphone positions (m).
    """

    rotor: Rotor
    airfoil: Airfoil
    positions: Float[Array, "4 3"]
    spin: Float[Array, " 4"]
    mass: Float[Array, ""]  # kg
    drag_area: Float[Array, " 3"]  # m², airframe D/q along body x, y, z
    air_density: Float[Array, ""]  # kg/m³
    speed_of_sound: Float[Array, ""]  # m/s
    gravity: Float[Array, ""]  # m/s²
    mic_positions: Float[Array, "K 3"]
    inertia: Float[Array, " 3"]  # kg·m², principal moments about body x, y, z
    motor_time_constant: Float[Array, ""]  # s, first-order rotor-speed lag
    rpm_min: Float[Array, ""]  # rpm
    rpm_max: Float[Array, ""]  # rpm
    name: str = eqx.field(static=True)

    @property
    def weight(self) -> Float[Array, ""]:
        return self.mass * self.gravity

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> Vehicle:
        """Build from the mapping of a ``conf/vehicle/*.yaml`` file (plain dict)."""
        c = _Reader(cfg, "vehicle")
        rot = _Reader(c.get("rotor"), "vehicle.rotor")
        foil = _Reader(c.get("airfoil"), "vehicle.airfoil")
        lay = _Reader(c.get("layout"), "vehicle.layout")
        mics = _Reader(c.get("microphones"), "vehicle.microphones")
        motor = _Reader(c.get("motor"), "vehicle.motor")

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
        rotor = Rotor(
            radius=jnp.asarray(radius),
            root_cutout=jnp.asarray(cutout),
            stations=jnp.asarray(np.linspace(cutout, 1.0, twist.size)),
            twist=jnp.asarray(twist),
            chord=jnp.asarray(chord),
            thickness_ratio=jnp.asarray(rot.positive("thickness_ratio")),
            n_blades=n_blades,
        )
        airfoil = Airfoil(
            lift_slope=jnp.asarray(foil.positive("lift_slope")),
            alpha_zero_lift=jnp.asarray(math.radians(foil.number("alpha_zero_lift_deg"))),
            stall=jnp.asarray(math.radians(foil.positive("stall_deg"))),
            stall_sharpness=jnp.asarray(foil.positive("stall_sharpness")),
            cd0=jnp.asarray(foil.positive("cd0")),
            cd2=jnp.asarray(foil.number("cd2")),
            alpha_min_drag=jnp.asarray(math.radians(foil.number("alpha_min_drag_deg"))),
        )
        arm = lay.positive("arm")
        spin = lay.array("spin", ndim=1)
        if spin.shape != (4,) or not np.all(np.abs(spin) == 1):
            raise ValueError(f"vehicle.layout.spin must be four entries of +1 or -1, got {spin}")
        h = rot.number("hub_height")
        ell = arm / math.sqrt(2.0)
        # r1 rear-right, r2 rear-left, r3 front-left, r4 front-right; rotor plane above the CoM.
        positions = np.array(
            [[-ell, ell, -h], [-ell, -ell, -h], [ell, -ell, -h], [ell, ell, -h]], dtype=float
        )
        r_mic = mics.positive("radius_in_rotor_radii") * radius
        elev = np.deg2rad(mics.array("elevation_deg", ndim=1))
        mic_positions = np.stack([np.zeros_like(elev), np.cos(elev), np.sin(elev)], -1) * r_mic
        inertia = c.array("inertia", ndim=1)
        if inertia.shape != (3,) or np.any(inertia <= 0):
            raise ValueError(f"vehicle.inertia must be three values > 0 (kg·m²), got {inertia}")
        rpm_min, rpm_max = motor.number("rpm_min"), motor.positive("rpm_max")
        if not 0 <= rpm_min < rpm_max:
            raise ValueError(
                f"vehicle.motor needs 0 <= rpm_min < rpm_max, got {rpm_min}, {rpm_max}"
            )
        drag = c.array("drag_area", ndim=1)
        if drag.shape != (3,) or np.any(drag < 0):
            raise ValueError(f"vehicle.drag_area must be three values >= 0 (m²), got {drag}")
        out = cls(
            rotor=rotor,
            airfoil=airfoil,
            positions=jnp.asarray(positions),
            spin=jnp.asarray(spin),
            mass=jnp.asarray(c.positive("mass")),
            drag_area=jnp.asarray(drag),
            air_density=jnp.asarray(c.positive("air_density")),
            speed_of_sound=jnp.asarray(c.positive("speed_of_sound")),
            gravity=jnp.asarray(c.positive("gravity")),
            mic_positions=jnp.asarray(mic_positions),
            inertia=jnp.asarray(inertia),
            motor_time_constant=jnp.asarray(motor.positive("time_constant")),
            rpm_min=jnp.asarray(rpm_min),
            rpm_max=jnp.asarray(rpm_max),
            name=str(c.get("name")),
        )
        for r in (rot, foil, lay, mics, motor, c):
            r.done()
        return out


def load_vehicle(name_or_path: str | Path = "sui_endurance") -> Vehicle:
    """A vehicle by name (``conf/vehicle/<name>.yaml``) or from a YAML file path."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = VEHICLE_DIR / f"{name_or_path}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in VEHICLE_DIR.glob("*.yaml"))
        raise ValueError(f"no vehicle file {path}; known vehicles: {known}")
    with open(path) as f:
        return Vehicle.from_config(yaml.safe_load(f))


class _Reader:
    """Reads keys of one config mapping, naming the full key in every error."""

    def __init__(self, cfg: Any, where: str):
        if not isinstance(cfg, Mapping):
            raise ValueError(f"{where} must be a mapping, got {type(cfg).__name__}")
        self.cfg, self.where, self.used = cfg, where, set()

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
