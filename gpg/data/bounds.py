"""The input box of a dataset: the sampling domain, and where a surrogate is ``in_domain``."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


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
    def from_config(cls, cfg: Mapping[str, Any]) -> Bounds:
        unknown = sorted(set(cfg) - set(cls.__dataclass_fields__))
        if unknown:
            raise ValueError(
                f"unknown bounds keys {unknown}; valid: {list(cls.__dataclass_fields__)}"
            )
        kw = {}
        for k, v in cfg.items():
            if not isinstance(v, list | tuple) or len(v) != 2:
                raise ValueError(f"bounds.{k} must be [lower, upper], got {v!r}")
            kw[k] = (float(v[0]), float(v[1]))
        return cls(**kw)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of ``x`` (8,) in file units (rpm, rad, m/s)."""
        rad = math.pi / 180.0
        lo = [self.rpm[0]] * 4 + [a[0] * rad for a in (self.yaw_deg, self.pitch_deg, self.roll_deg)]
        hi = [self.rpm[1]] * 4 + [a[1] * rad for a in (self.yaw_deg, self.pitch_deg, self.roll_deg)]
        return np.array(lo + [self.airspeed[0]]), np.array(hi + [self.airspeed[1]])
