"""Synthetic datasets with analytic gradients (no generator needed, fast to build)."""

import numpy as np

from gpg.data.dataset import Dataset
from gpg.data.sampling import Bounds, FDSteps, latin_hypercube, raw_samples

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
        meta={"simple_model": {"P_F": 5.3e-7, "T_z": 8.4e-9}, "name": "synthetic"},
        **kw,
    ), W
