"""Mirror images of body-frame cases: free training data from an X-layout quadrotor's mirror
symmetries.

A vehicle whose rotor layout is symmetric under the reflection ``S`` of one body axis, with
the rotor permutation ``π`` that the reflection implies and each mirrored rotor spinning the
other way (a mirror-image propeller), has mirror-image loads: the case ``(rpm, v_B)`` gives
``(F, M)``, the case ``(rpm[π], S v_B)`` gives ``(S F, −S M)`` (the moment is an axial vector:
``det S = −1``). Gradients follow by the chain rule, ``J' = T J Aᵀ`` with the input map ``A``
(permutation and sign) and the output map ``T``. Levels carry over when every microphone is its
own mirror image (the fore-aft mirror of gpg's vehicles: microphones in the ``y-z`` plane);
otherwise the mirror is refused for data with levels.

``x`` (fore-aft: front and rear rotors swap) and ``y`` (left-right) are the mirrors of an X
layout; their product is the half turn about ``z``. Whether the extra cases pay is measured in
``experiments.envelope`` (README "The whole flight envelope"). Raw finite-difference samples
are not mirrored (a mirrored forward step is a backward one): the mirrored dataset has none.
"""

from __future__ import annotations

import itertools

import numpy as np

from gpg.data.dataset import Dataset
from gpg.quadrotor.vehicle import Vehicle

AXES = ("x", "y")


def reflection(vehicle: Vehicle, axis: str, *, levels: bool) -> np.ndarray:
    """The rotor permutation ``π`` (4,) of the mirror across the body plane normal to
    ``axis``, or ``ValueError`` naming what in ``vehicle`` is not symmetric (rotor positions,
    spins, drag areas are symmetric by construction; microphones when ``levels``)."""
    if axis not in AXES:
        raise ValueError(f"axis must be one of {list(AXES)}, got {axis!r}")
    S = _s(axis)
    pos = np.asarray(vehicle.positions, float)
    spin = np.asarray(vehicle.spin, float)
    mirrored = pos * S
    perm = np.array([int(np.argmin(np.linalg.norm(pos - p, axis=1))) for p in mirrored])
    tol = 1e-9 * max(1.0, float(np.abs(pos).max()))
    if sorted(perm.tolist()) != [0, 1, 2, 3] or np.abs(pos[perm] - mirrored).max() > tol:
        raise ValueError(
            f"vehicle {vehicle.name!r}: its rotor positions are not symmetric in {axis}"
        )
    if np.any(spin[perm] != -spin):
        raise ValueError(
            f"vehicle {vehicle.name!r}: the mirror in {axis} maps rotors onto rotors spinning the "
            "same way (a mirror image spins the other way): no mirror symmetry"
        )
    if levels and not keeps_levels(vehicle, axis):
        raise ValueError(
            f"vehicle {vehicle.name!r}: its microphones are not their own mirror images in "
            f"{axis}: mirror data without levels (Dataset.without('noise'))"
        )
    return perm


def keeps_levels(vehicle: Vehicle, axis: str) -> bool:
    """Whether every microphone of ``vehicle`` is its own mirror image across the plane normal
    to body ``axis``, so that the mirror keeps the levels."""
    mics = np.asarray(vehicle.mic_positions, float)
    tol = 1e-9 * max(1.0, float(np.abs(np.asarray(vehicle.positions)).max()))
    return bool(np.abs(mics * _s(axis) - mics).max() <= tol)


def mirror(ds: Dataset, vehicle: Vehicle, axis: str) -> Dataset:
    """The mirror image of every case of the body-frame ``ds`` across the plane normal to body
    ``axis`` (``"x"`` or ``"y"``): inputs, outputs and gradients (see the module docstring)."""
    if ds.frame != "body":
        raise ValueError("mirror images are of body-frame data (meta['frame'] == 'body')")
    perm = reflection(vehicle, axis, levels=ds.has_noise)
    S = np.diag(_s(axis))
    A = np.zeros((7, 7))  # x' = A x
    A[np.arange(4), perm] = 1.0
    A[4:, 4:] = S
    T_aero = np.zeros((6, 6))
    T_aero[:3, :3], T_aero[3:, 3:] = S, -S
    x = ds.x @ A.T
    y_aero = ds.y_aero @ T_aero.T
    dirs = ds.grad_dirs
    if dirs is None:
        jac = None if ds.jac_aero is None else np.einsum("ij,njk,lk->nil", T_aero, ds.jac_aero, A)
        jac_noise = None if ds.jac_noise is None else np.einsum("njk,lk->njl", ds.jac_noise, A)
    else:  # D_{A d} y'(A x) = T D_d y(x): the values keep their columns, the directions turn
        jac = np.einsum("ij,njk->nik", T_aero, ds.jac_aero)
        jac_noise = ds.jac_noise
        dirs = np.einsum("ngk,lk->ngl", dirs, A)
    meta = {**ds.meta, "mirrored": [*ds.meta.get("mirrored", []), axis]}
    return Dataset(
        x=x, y_aero=y_aero, jac_aero=jac, y_noise=ds.y_noise, jac_noise=jac_noise, meta=meta,
        grad_dirs=dirs,
    )  # fmt: skip


def augment(ds: Dataset, vehicle: Vehicle, axes: tuple[str, ...] = ("x",)) -> Dataset:
    """``ds`` and its mirror images across every product of ``axes`` (``("x",)``: 2x the
    cases; ``("x", "y")``: 4x), without raw samples. The simulator runs behind it are
    ``ds``'s: :attr:`Dataset.runs` of the result counts the mirrored cases as runs they are not,
    so the result records ``meta["runs"]``, the real count."""
    axes = tuple(dict.fromkeys(axes))
    for a in axes:
        if a not in AXES:
            raise ValueError(f"axes must be among {list(AXES)}, got {a!r}")
    base = ds.without("raw samples") if ds.has_raw else ds
    parts = [base]
    for k in range(1, len(axes) + 1):
        for combo in itertools.combinations(axes, k):
            m = base
            for a in combo:
                m = mirror(m, vehicle, a)
            parts.append(m)
    cat = {
        k: None if getattr(base, k) is None else np.concatenate([getattr(p, k) for p in parts])
        for k in ("x", "y_aero", "jac_aero", "y_noise", "jac_noise")
    }
    meta = {**ds.meta, "mirrored": list(axes), "runs": ds.runs}
    return Dataset(**cat, meta=meta)


def _s(axis: str) -> np.ndarray:
    return np.array([-1.0, 1.0, 1.0]) if axis == "x" else np.array([1.0, -1.0, 1.0])
