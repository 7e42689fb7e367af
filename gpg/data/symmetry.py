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

__all__ = ["augment", "keeps_levels", "mirror", "reflection"]

AXES = ("x", "y")


def reflection(vehicle: Vehicle, axis: str, *, levels: bool) -> np.ndarray:
    """The rotor permutation of the mirror across a body plane, after checking the symmetry.

    Rotor positions must map onto rotor positions and each rotor onto one spinning the other
    way (a mirror-image propeller); drag areas are symmetric by construction.

    Args:
        vehicle: the vehicle.
        axis: the body axis normal to the mirror plane, ``"x"`` or ``"y"``.
        levels: whether the data have levels, which then need every microphone to be its own
            mirror image (:func:`keeps_levels`).

    Returns:
        The (4,) permutation ``π``: rotor ``i``'s mirror image is rotor ``π[i]``.

    Raises:
        ValueError: if ``axis`` is unknown, or naming what in ``vehicle`` is not symmetric
            (rotor positions, spins, microphones when ``levels``).
    """
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
    """Whether the mirror across a body plane keeps a vehicle's levels.

    It does when every microphone is its own mirror image across the plane.

    Args:
        vehicle: the vehicle.
        axis: the body axis normal to the mirror plane, ``"x"`` or ``"y"``.

    Returns:
        True when every microphone lies in the plane (to rounding).
    """
    mics = np.asarray(vehicle.mic_positions, float)
    tol = 1e-9 * max(1.0, float(np.abs(np.asarray(vehicle.positions)).max()))
    return bool(np.abs(mics * _s(axis) - mics).max() <= tol)


def mirror(ds: Dataset, vehicle: Vehicle, axis: str) -> Dataset:
    """The mirror image of every case of a body-frame dataset across a body plane.

    Inputs, outputs and gradients are mirrored (see the module docstring); directional
    gradient columns keep their values and turn their directions. ``meta["mirrored"]``
    records the axis.

    Args:
        ds: the body-frame dataset.
        vehicle: its vehicle, which must be symmetric in ``axis`` (:func:`reflection`).
        axis: the body axis normal to the mirror plane, ``"x"`` or ``"y"``.

    Returns:
        The mirrored :class:`~gpg.data.Dataset`, as many cases as ``ds``.

    Raises:
        ValueError: if ``ds`` is not in the body frame, or the vehicle is not symmetric in
            ``axis`` (:func:`reflection`).
    """
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
    """A dataset and its mirror images across every product of some body axes.

    The result has ``ds``'s cases and their mirror images (``("x",)``: 2x the cases;
    ``("x", "y")``: 4x), without raw samples. The simulator runs behind it are ``ds``'s:
    :attr:`Dataset.runs` of the result counts the mirrored cases as runs they are not, so the
    result records ``meta["runs"]``, the real count.

    Args:
        ds: the body-frame dataset.
        vehicle: its vehicle, symmetric in every axis of ``axes``.
        axes: the mirrors, among ``"x"`` and ``"y"`` (repeats ignored).

    Returns:
        The :class:`~gpg.data.Dataset`: ``ds``'s cases, then each mirror's.

    Raises:
        ValueError: if an axis is unknown, or as :func:`mirror`.
    """
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
