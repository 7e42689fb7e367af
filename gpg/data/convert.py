"""Paper-style (airflow-frame) datasets in the body frame.

A case of the airflow frame, rotor speeds ``r``, attitude ``θ`` relative to the airflow and
airspeed ``V`` (the air ``V e_x`` of the dataset frame), is the body-frame case
``x_B = (r, v(θ))`` with ``v(θ) = R_WB(θ)ᵀ V e_x`` and loads ``F_B = R_WB(θ)ᵀ F``,
``M_B = R_WB(θ)ᵀ M``: exact. The rotor-speed gradients convert exactly too
(``∂y_B/∂r = Rᵀ ∂y/∂r`` at fixed ``θ, V``, which is fixed ``x_B``).

The angle gradients become **directional derivatives** (the paper's remark on derivatives in
arbitrary directions). The body-frame loads depend on ``(r, v)`` alone, so by the chain rule
``∂y_B/∂θ_k = D_{d_k} y_B`` with the direction ``d_k = ∂v/∂θ_k`` and
``∂y_B/∂θ_k = (∂Rᵀ/∂θ_k) y + Rᵀ ∂y/∂θ_k`` from the dataset's own ``y`` and ``∂y/∂θ_k``. The
three ``d_k`` are tangent to the sphere ``|v| = V`` and span its tangent plane (one of their
combinations is the turn about the airflow, which moves nothing): :func:`to_body` keeps two
rows, the derivatives along an orthonormal basis ``t_1, t_2`` of that plane, fitted to the
three by least squares (exact when the three are consistent, as the exact derivatives of a
body-frame function are; forward differences agree to their own truncation). The third row,
along the radial direction ``v/|v|`` (the airspeed, which the paper's data did not perturb),
is not run (NaN). At ``V = 0`` the angles move nothing and the velocity rows are all not
run. The directions go to :attr:`gpg.data.Dataset.grad_dirs`; ``gpg`` and ``gpgs_hybrid``
train on them as directional-derivative rows (:func:`gpg.gp.gram.row_directions`).

Levels are not converted: the airflow frame's microphones are fixed to the airflow, the body
frame's to the body. Raw 8X samples are not carried.
"""

from __future__ import annotations

import jax
import numpy as np
from jaxtyping import Float

from gpg._dtype import float64
from gpg.data.dataset import Dataset
from gpg.quadrotor.frames import R_WB

__all__ = ["body_inputs", "body_meta", "to_body"]

RANK_TOL = 1e-9  # a direction shorter than this times the airspeed moves nothing


# One compiled program for every batch of angles: vmapped op by op, each new batch size
# compiled a program for every operation of the rotation.
_R_batch = jax.jit(jax.vmap(R_WB))
_dR_batch = jax.jit(jax.vmap(jax.jacfwd(R_WB)))  # likewise its derivatives


@float64
def body_inputs(x_air: np.ndarray) -> np.ndarray:
    """Airflow-frame cases as body-frame inputs.

    The air ``V e_x`` of the dataset frame seen from the body is ``R_WB(θ)ᵀ V e_x``, the
    first row of ``R_WB(θ)`` scaled by the airspeed; the rotor speeds are unchanged.

    Args:
        x_air: (N, 8) cases ``(r1..r4, yaw, pitch, roll, V)`` in rpm, rad and m/s.

    Returns:
        The (N, 7) body-frame inputs ``(r1..r4, u, v, w)``.
    """
    R = np.asarray(_R_batch(x_air[:, 4:7]))
    v_b = R[:, 0, :] * x_air[:, 7:8]  # R^T e_x is R's first row
    return np.concatenate([x_air[:, :4], v_b], axis=1)


def _angle_rows(
    x_air: Float[np.ndarray, "N 8"],
    jac_air: Float[np.ndarray, "N 6 7"],
    y_air: Float[np.ndarray, "N 6"],
    R: Float[np.ndarray, "N 3 3"],
) -> tuple[np.ndarray, np.ndarray]:
    """The airflow-frame angle gradients as body-frame rows along ``u, v, w``: values
    (N, 6, 3) and directions (N, 3, 3) (rows ``t_1, t_2``, then the radial ``v/|v|``), with
    NaN values where there is no derivative (the radial row; every row at ``V = 0``; the
    plane's rows when the angle gradients were not run). ``R`` is ``R_WB(θ)`` of the cases.
    See the module docstring."""
    n = x_air.shape[0]
    dR = np.asarray(_dR_batch(x_air[:, 4:7]))  # k last
    V = x_air[:, 7]
    Rt, dRt = np.swapaxes(R, 1, 2), np.swapaxes(dR, 1, 2)  # dRt[n, i, j, k] = ∂R[j, i]/∂θ_k
    d = dR[:, 0, :, :] * V[:, None, None]  # d[n, :, k] = ∂(Rᵀ V e_x)/∂θ_k: R's first row
    # ∂y_B/∂θ_k = ∂Rᵀ/∂θ_k y + Rᵀ ∂y/∂θ_k for force and torque alike: (N, 6, 3)
    G = np.empty((n, 6, 3))
    for sl in (slice(0, 3), slice(3, 6)):
        G[:, sl] = np.einsum("nijk,nj->nik", dRt, y_air[:, sl]) + np.einsum(
            "nij,njk->nik", Rt, jac_air[:, sl, 4:7]
        )
    values = np.full((n, 6, 3), np.nan)
    dirs = np.zeros((n, 3, 3))
    run = ~np.isnan(jac_air[:, 0, 4:7])  # (N, 3) which angle perturbations were run
    for i in range(n):
        ks = np.flatnonzero(run[i])
        U, s, _ = np.linalg.svd(d[i][:, ks])  # U (3, 3) even with no column
        rank = int(np.sum(s > RANK_TOL * max(V[i], 1e-300)))
        # Rows t_1, t_2 of the tangent plane (or of the span of the run directions) first, then
        # their complement: the radial direction R[0] (V >= 0) when the plane is full.
        basis = _complete(U[:, :rank], R[i, 0])
        dirs[i] = basis.T
        if rank:
            A = basis[:, :rank].T @ d[i][:, ks]  # (rank, m): d_k in the basis
            # Least squares J_T A = G over the run k: the derivatives along the basis.
            J_T = np.linalg.lstsq(A.T, G[i][:, ks].T, rcond=None)[0].T
            values[i, :, :rank] = J_T
    return values, dirs


def _complete(T: np.ndarray, radial: np.ndarray) -> np.ndarray:
    """An orthonormal basis (3, 3) whose first columns are ``T``'s (orthonormal), the next the
    radial direction's part outside them when there is one."""
    cols = [T[:, j] for j in range(T.shape[1])]
    for cand in (radial, np.eye(3)[0], np.eye(3)[1], np.eye(3)[2]):
        if len(cols) == 3:
            break
        w = cand - sum((c @ cand) * c for c in cols)
        if np.linalg.norm(w) > 1e-6:
            cols.append(w / np.linalg.norm(w))
    return np.stack(cols, axis=1)


@float64
def to_body(ds: Dataset, *, angle_gradients: bool = True) -> Dataset:
    """An airflow-frame dataset in the body frame (see the module docstring).

    Values and rotor-speed gradients convert exactly, the angle gradients as derivatives along
    two directions of ``(u, v, w)`` (:attr:`Dataset.grad_dirs`), the airspeed's not run (NaN);
    no levels and no raw samples. ``meta["bounds"]`` becomes the rotor speeds and the ball of
    the airspeed range; the cases cover only the directions of the airflow box within it
    (``meta["cases"]`` says so), so a surrogate's ``in_domain`` claims more than the data hold.

    Args:
        ds: the airflow-frame dataset.
        angle_gradients: keep the angle gradients as directional derivatives; False drops
            them (the ``u, v, w`` columns all not run, no ``grad_dirs``): what they add is
            measured by ``experiments.envelope``.

    Returns:
        The body-frame :class:`~gpg.data.Dataset`.

    Raises:
        ValueError: if ``ds`` is not in the airflow frame.
    """
    if ds.frame != "airflow":
        raise ValueError(
            f"to_body converts airflow-frame data; this dataset is in the {ds.frame} frame"
        )
    R = np.asarray(_R_batch(ds.x[:, 4:7]))
    Rt = np.swapaxes(R, 1, 2)
    y = np.concatenate(
        [
            np.einsum("nij,nj->ni", Rt, ds.y_aero[:, :3]),
            np.einsum("nij,nj->ni", Rt, ds.y_aero[:, 3:]),
        ],
        axis=1,
    )
    jac, dirs = None, None
    if ds.jac_aero is not None:
        jac = np.full((ds.n, 6, 7), np.nan)
        for sl in (slice(0, 3), slice(3, 6)):
            jac[:, sl, :4] = np.einsum("nij,njk->nik", Rt, ds.jac_aero[:, sl, :4])
        if angle_gradients:
            jac[:, :, 4:], turned = _angle_rows(ds.x, ds.jac_aero, ds.y_aero, R)
            dirs = np.zeros((ds.n, 7, 7))
            dirs[:, np.arange(4), np.arange(4)] = 1.0
            dirs[:, 4:, 4:] = turned
    cases = "converted from the airflow frame: its directions only; " + (
        "the angle gradients as derivatives along two directions of (u, v, w), none along "
        "the airspeed"
        if angle_gradients
        else "no u, v, w gradients"
    )
    return Dataset(
        x=body_inputs(ds.x), y_aero=y, jac_aero=jac, meta=body_meta(ds.meta, cases),
        grad_dirs=dirs,
    )  # fmt: skip


def body_meta(meta: dict, cases: str) -> dict:
    """The metadata of an airflow-frame dataset's cases in the body frame.

    The bounds become the rotor speeds and the ball of the airspeed range; the
    finite-difference record, raw-sample layout and frame are dropped (the caller adds the
    body frame's record).

    Args:
        meta: the airflow-frame dataset's metadata.
        cases: where the body-frame cases come from, recorded as ``meta["cases"]``.

    Returns:
        The body-frame metadata (``frame`` ``"body"``).
    """
    bounds = meta.get("bounds") or {}
    kept = {k: v for k, v in meta.items() if k not in ("bounds", "fd", "raw_layout", "frame")}
    return {
        **kept,
        "frame": "body",
        "bounds": {k: list(bounds[k]) for k in ("rpm", "airspeed") if k in bounds},
        "cases": cases,
    }
