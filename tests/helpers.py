"""Test helpers: synthetic datasets with analytic gradients (no generator needed, fast to
build), configs composed as the entry points do, and a check of JSON results."""

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset
from gpg.data.sampling import FDSteps, latin_hypercube, raw_samples
from gpg.quadrotor.vehicle import vehicle_config

LO, HI = Bounds().arrays()


def smooth(x, W):
    """Outputs (N, 9) and exact Jacobians (N, 9, 7) of a smooth function of the scaled inputs."""
    u = 2 * (x - LO) / (HI - LO) - 1
    z = u @ W
    y = np.sin(z) + 0.3 * z
    dz = (np.cos(z) + 0.3)[:, :, None] * (W.T[None, :, :7] * (2 / (HI - LO))[None, None, :7])
    y = y * np.array([3, 3, 20, 0.5, 0.5, 0.2, 5, 5, 5]) + np.array(
        [0, 0, -26, 0, 0, 0, 60, 60, 50]
    )
    dz = dz * np.array([3, 3, 20, 0.5, 0.5, 0.2, 5, 5, 5])[None, :, None]
    return y, dz


def synthetic_dataset(n=60, seed=0, raw=True):
    rng = np.random.default_rng(seed)
    W = rng.normal(scale=0.5, size=(8, 9))
    x = latin_hypercube(n, Bounds(), seed)
    y, J = smooth(x, W)
    kw = {}
    if raw:
        xr, _ = raw_samples(x, FDSteps())
        kw = {"x_raw": xr, "y_raw": smooth(xr, W)[0]}
    return Dataset(
        x=x,
        y_aero=y[:, :6],
        jac_aero=J[:, :6],
        y_noise=y[:, 6:],
        jac_noise=J[:, 6:],
        meta={
            "simple_model": {"P_F": 5.3e-7, "T_z": 8.4e-9},
            "name": "synthetic",
            "vehicle": vehicle_config("sui_endurance"),  # whose layout M uses
        },
        **kw,
    ), W


def compose_plain(name: str, overrides: Sequence[str] = ()) -> dict[str, Any]:
    """``conf/<name>.yaml`` composed by Hydra with ``overrides``, as plain values (what the
    ``experiments`` entry points pass to ``gpg.runs``)."""
    from hydra import compose, initialize_config_dir

    from experiments._hydra import plain
    from gpg.runs.common import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return plain(compose(config_name=name, overrides=list(overrides)))


def finite_numbers(obj: Any) -> bool:
    """True when every number in a JSON-like structure is finite (None allowed)."""
    if isinstance(obj, dict):
        return all(finite_numbers(v) for v in obj.values())
    if isinstance(obj, list):
        return all(finite_numbers(v) for v in obj)
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return True
    if isinstance(obj, int | float):
        return math.isfinite(obj)
    return True
