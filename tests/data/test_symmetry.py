"""Mirror images of body-frame cases (gpg/data/symmetry.py): the generator's physics is
mirror-symmetric for the X layout, the mirrored gradients are the chain rule's, mirroring twice
is the identity, and what has no mirror symmetry is refused."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from gpg.data.symmetry import augment, mirror, reflection
from tests.helpers import smooth_body, synthetic_body_dataset


def test_the_generator_is_mirror_symmetric(y_body_of, vehicle):
    """``y(A x) = T y(x)`` for both mirrors of the X layout at three cases (forward flight
    with sideslip, descent, air from behind-left): force and moment to 1e-6 of their scale
    (the physics is symmetric; the blade-element grid's azimuth stations are placed per
    rotor, and agree to the solver's convergence), levels too for the fore-aft mirror."""
    f = y_body_of
    ds, _ = synthetic_body_dataset(3, seed=0)
    x = np.array(
        [[3500, 3700, 3300, 3600, 8.0, 2.0, -1.0], [4000, 3800, 3900, 4100, 0.5, -0.3, 3.0],
         [3000, 3200, 3400, 3100, -6.0, -4.0, 1.0]]
    )  # fmt: skip
    y = np.stack([np.asarray(f(jnp.asarray(r))) for r in x])
    base = dataclasses.replace(ds, x=x, y_aero=y[:, :6], y_noise=y[:, 6:], jac_aero=None,
                               jac_noise=None)  # fmt: skip
    for axis in ("x", "y"):
        m = mirror(base if axis == "x" else base.without("noise"), vehicle, axis)
        got = np.stack([np.asarray(f(jnp.asarray(r))) for r in m.x])
        scale = np.abs(y[:, :6]).max(0)
        np.testing.assert_allclose(got[:, :6], m.y_aero, atol=1e-6 * scale.max())
        if axis == "x":
            np.testing.assert_allclose(got[:, 6:], m.y_noise, atol=1e-6)


def test_mirrored_gradients_are_the_chain_rule_and_twice_is_identity(vehicle):
    ds, W = synthetic_body_dataset(5, seed=1)
    ds = ds.without("noise")
    m = mirror(ds, vehicle, "x")
    back = mirror(m, vehicle, "x")
    for k in ("x", "y_aero", "jac_aero"):
        np.testing.assert_allclose(getattr(back, k), getattr(ds, k), rtol=0, atol=1e-12)
    # the mirrored function y'(x') = T y(A^-1 x'): its gradient by central differences
    A = np.zeros((7, 7))
    A[np.arange(4), reflection(vehicle, "x", levels=False)] = 1.0
    A[4:, 4:] = np.diag([-1.0, 1.0, 1.0])
    T = np.diag([-1.0, 1, 1, 1, -1, -1])
    for i in range(m.n):
        for j in range(7):
            h = np.zeros(7)
            h[j] = 1e-3 if j < 4 else 1e-6
            yp = smooth_body((A.T @ (m.x[i] + h))[None], W)[0][0, :6] @ T.T
            ym = smooth_body((A.T @ (m.x[i] - h))[None], W)[0][0, :6] @ T.T
            np.testing.assert_allclose(
                (yp - ym) / (2 * h[j]), m.jac_aero[i, :, j], rtol=1e-6, atol=1e-9
            )


def test_augment_and_what_has_no_mirror_symmetry(vehicle):
    ds, _ = synthetic_body_dataset(6, seed=2)
    two = augment(ds, vehicle, ("x",))
    assert two.n == 12 and two.meta["runs"] == ds.runs and two.has_noise
    four = augment(ds.without("noise"), vehicle, ("x", "y"))
    assert four.n == 24 and len({tuple(r) for r in np.round(four.x, 9)}) == 24
    with pytest.raises(ValueError, match="microphones are not their own mirror images in y"):
        mirror(ds, vehicle, "y")
    import equinox as eqx

    lopsided = eqx.tree_at(lambda v: v.spin, vehicle, jnp.array([1, -1, -1, 1]))  # r1, r4 alike
    with pytest.raises(ValueError, match="spinning the same way"):
        mirror(ds.without("noise"), lopsided, "x")
    with pytest.raises(ValueError, match="axis must be one of"):
        mirror(ds, vehicle, "z")
    from tests.helpers import synthetic_dataset

    with pytest.raises(ValueError, match="body-frame data"):
        mirror(synthetic_dataset(4, raw=False)[0], vehicle, "x")


def test_mirrored_directional_gradients_turn_their_directions(vehicle):
    """Derivatives along per-case directions (converted data's ``grad_dirs``) mirror to
    derivatives along the mirrored directions: written back in coordinates they are the
    coordinate data's mirror."""
    ds, _ = synthetic_body_dataset(5, seed=2)
    ds = ds.without("noise")
    Q = np.linalg.qr(np.random.default_rng(0).normal(size=(ds.n, 7, 7)))[0]
    turned = dataclasses.replace(ds, jac_aero=np.einsum("nmh,ngh->nmg", ds.jac_aero, Q),
                                 grad_dirs=Q)  # fmt: skip
    for axis in ("x", "y"):
        a, b = mirror(ds, vehicle, axis), mirror(turned, vehicle, axis)
        coord = np.einsum("nmg,ngh->nmh", b.jac_aero, np.linalg.inv(np.swapaxes(b.grad_dirs, 1, 2)))
        np.testing.assert_allclose(coord, a.jac_aero, rtol=0, atol=1e-10)
