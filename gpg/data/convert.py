"""Paper-style (airflow-frame) datasets in the body frame.

A case of the airflow frame, rotor speeds ``r``, attitude ``θ`` relative to the airflow and
airspeed ``V`` (the air ``V e_x`` of the dataset frame), is the body-frame case
``x_B = (r, R_WB(θ)ᵀ V e_x)`` with loads ``F_B = R_WB(θ)ᵀ F``, ``M_B = R_WB(θ)ᵀ M``: exact.
The rotor-speed gradients convert exactly too (``∂y_B/∂r = Rᵀ ∂y/∂r`` at fixed ``θ, V``,
which is fixed ``x_B``).

The angle gradients do not become coordinate gradients. A turn of the vehicle moves ``x_B``
on the sphere ``|v| = V``: the three angle derivatives are derivatives of ``y_B`` along two
tangent directions of ``(u, v, w)`` (the third combination is the turn about the airflow,
which moves nothing), and the datasets have none along the speed. A GP would take them as
directional-derivative rows (linear combinations of the coordinate blocks), which gpg's models
do not have yet; :func:`to_body` marks the ``u, v, w`` gradients as not run (NaN, the
dataset's convention for a perturbation not run), which ``gpg`` and ``gpgs_hybrid`` train on.
Levels are not converted: the airflow frame's microphones are fixed to the airflow, the body
frame's to the body. Raw 8X samples are not carried.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gpg.data.dataset import Dataset
from gpg.quadrotor.frames import R_WB


def body_inputs(x_air: np.ndarray) -> np.ndarray:
    """Airflow-frame cases ``(rpm, yaw, pitch, roll, V)`` (N, 8) as body-frame inputs
    ``(rpm, u, v, w)`` (N, 7): the air ``V e_x`` of the dataset frame seen from the body,
    ``R_WB(θ)ᵀ V e_x``."""
    R = np.asarray(jax.vmap(R_WB)(jnp.asarray(x_air[:, 4:7])))
    v_b = R[:, 0, :] * x_air[:, 7:8]  # R^T e_x is R's first row
    return np.concatenate([x_air[:, :4], v_b], axis=1)


def to_body(ds: Dataset) -> Dataset:
    """The airflow-frame dataset ``ds`` in the body frame (see the module docstring): values
    and rotor-speed gradients exactly, the ``u, v, w`` gradients not run (NaN), no levels and
    no raw samples. ``meta["bounds"]`` becomes the rotor speeds and the ball of the airspeed
    range; the cases cover only the directions of the airflow box within it (``meta["cases"]``
    says so), so a surrogate's ``in_domain`` claims more than the data hold."""
    if ds.frame != "airflow":
        raise ValueError(
            f"to_body converts airflow-frame data; this dataset is in the {ds.frame} frame"
        )
    R = np.asarray(jax.vmap(R_WB)(jnp.asarray(ds.x[:, 4:7])))
    Rt = np.swapaxes(R, 1, 2)
    y = np.concatenate(
        [
            np.einsum("nij,nj->ni", Rt, ds.y_aero[:, :3]),
            np.einsum("nij,nj->ni", Rt, ds.y_aero[:, 3:]),
        ],
        axis=1,
    )
    jac = None
    if ds.jac_aero is not None:
        jac = np.full((ds.n, 6, 7), np.nan)
        for sl in (slice(0, 3), slice(3, 6)):
            jac[:, sl, :4] = np.einsum("nij,njk->nik", Rt, ds.jac_aero[:, sl, :4])
    cases = "converted from the airflow frame: its directions only, no u, v, w gradients"
    return Dataset(x=body_inputs(ds.x), y_aero=y, jac_aero=jac, meta=body_meta(ds.meta, cases))


def body_meta(meta: dict, cases: str) -> dict:
    """The metadata of an airflow-frame dataset's cases in the body frame: its bounds as the
    rotor speeds and the ball of its airspeed range, without its finite-difference record
    (the caller adds the body frame's), and ``cases`` saying where they come from."""
    bounds = meta.get("bounds") or {}
    kept = {k: v for k, v in meta.items() if k not in ("bounds", "fd", "raw_layout", "frame")}
    return {
        **kept,
        "frame": "body",
        "bounds": {k: list(bounds[k]) for k in ("rpm", "airspeed") if k in bounds},
        "cases": cases,
    }
