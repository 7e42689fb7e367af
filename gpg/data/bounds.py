"""The input box of a dataset: the sampling domain, and where a surrogate is ``in_domain``."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["Bounds"]


@dataclass(frozen=True)
class Bounds:
    """Sampling box; angles in degrees (config keys end in ``_deg``), rpm, m/s."""

    rpm: tuple[float, float] = (0.0, 7000.0)
    yaw_deg: tuple[float, float] = (-90.0, 90.0)
    pitch_deg: tuple[float, float] = (-60.0, 60.0)
    roll_deg: tuple[float, float] = (-90.0, 90.0)
    airspeed: tuple[float, float] = (0.0, 20.0)

    def __post_init__(self):
        for name, (lo, hi) in asdict(self).items():
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"bounds.{name} must be finite, got ({lo}, {hi})")
            if not lo < hi:
                raise ValueError(f"bounds.{name} is inverted or empty: lower {lo} >= upper {hi}")
        if self.rpm[0] < 0 or self.airspeed[0] < 0:
            raise ValueError("bounds.rpm and bounds.airspeed must start at >= 0")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], where: str = "bounds") -> Bounds:
        """The bounds of a ``data.bounds`` config (``{"yaw_deg": [-90, 90], ...}``).

        Missing keys keep their defaults; each value is a pair ``[lower, upper]`` of numbers.

        Args:
            cfg: the mapping of field names (``rpm``, ``yaw_deg``, ``pitch_deg``, ``roll_deg``,
                ``airspeed``) to ``[lower, upper]``.
            where: what ``cfg`` is, named in every error (e.g. a dataset's metadata,
                ``"meta['bounds']"``).

        Returns:
            The :class:`Bounds`.

        Raises:
            ValueError: if ``cfg`` is not a mapping, names an unknown key, or holds a value
                that is not two numbers or a range that is empty, inverted, infinite or
                negative (rpm, airspeed); naming ``where`` and the key.
        """
        fields = list(cls.__dataclass_fields__)
        if not isinstance(cfg, Mapping):
            raise ValueError(
                f"{where} must be a mapping of {fields} to [lower, upper], such as "
                f"{{'yaw_deg': [-90, 90]}}; got a {type(cfg).__name__}: {cfg!r:.80}"
            )
        unknown = sorted(str(k) for k in set(cfg) - set(fields))
        if unknown:
            raise ValueError(f"unknown {where} keys {unknown}; valid: {fields}")
        kw = {}
        for k, v in cfg.items():
            if not isinstance(v, list | tuple) or len(v) != 2:
                raise ValueError(f"{where}.{k} must be [lower, upper], got {v!r}")
            try:
                kw[k] = (float(v[0]), float(v[1]))
            except (TypeError, ValueError):
                raise ValueError(f"{where}.{k} must be two numbers, got {v!r}") from None
        try:
            return cls(**kw)
        except ValueError as exc:
            if where == "bounds":
                raise
            raise ValueError(str(exc).replace("bounds.", f"{where}.")) from None

    def arrays(self, frame: str = "airflow") -> tuple[np.ndarray, np.ndarray]:
        """The box as lower and upper corners of the inputs ``x``, in file units.

        In the airflow frame the corners are (8,) in rpm, rad and m/s. In the body frame they
        are (7,): the rotor speeds' box and the box ``[-V, V]³`` around the ball of air
        velocities of radius ``V = airspeed[1]`` (the angles do not bound body-frame data).

        Args:
            frame: ``"airflow"`` or ``"body"``.

        Returns:
            The lower and the upper corner.

        Raises:
            ValueError: if ``frame`` is neither.
        """
        if frame == "body":
            v = self.airspeed[1]
            return (np.array([self.rpm[0]] * 4 + [-v] * 3), np.array([self.rpm[1]] * 4 + [v] * 3))
        if frame != "airflow":
            raise ValueError(f"frame must be 'airflow' or 'body', got {frame!r}")
        rad = math.pi / 180.0
        lo = [self.rpm[0]] * 4 + [a[0] * rad for a in (self.yaw_deg, self.pitch_deg, self.roll_deg)]
        hi = [self.rpm[1]] * 4 + [a[1] * rad for a in (self.yaw_deg, self.pitch_deg, self.roll_deg)]
        return np.array(lo + [self.airspeed[0]]), np.array(hi + [self.airspeed[1]])
