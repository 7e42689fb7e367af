"""Derivatives of every model's mean and variance: forward and reverse mode agree, match central
finite differences, and go through jit, vmap and lax.scan (the partitioned models' custom batch
rules included)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import models
from gpg.data.preprocess import prepare, simple_model_for
from gpg.quadrotor.vehicle import load_vehicle
from tests.helpers import synthetic_dataset

FAST = {
    "hyper": {"fit": False, "lengthscale": 1.0},
    "partition": {"bins": 3, "points_per_bin": None},
    "near": {"budget": 0.5, "points": None},
    "inducing": {"points": 8},
    "variance_dtype": "float64",  # finite differences need the variance in float64
}
pytestmark = pytest.mark.filterwarnings("ignore::gpg.gp.schur.SchurAssumptionWarning")


@pytest.fixture(scope="module")
def training():
    ds, _ = synthetic_dataset(40)
    return prepare(ds, simple_model_for(ds, load_vehicle()))


def _outputs(model):
    """Mean (M,) and latent variance (1,) at one normalised query, as one vector."""
    return lambda x: jnp.concatenate([model.mean_one(x), model.mean_var_one(x)[1][None]])


def _central(f, X, h=1e-6):
    E = jnp.eye(X.shape[1])
    return jax.vmap(lambda x: jax.vmap(lambda e: (f(x + h * e) - f(x - h * e)) / (2 * h))(E).T)(X)


@pytest.mark.parametrize("name", models.NAMES)
def test_jacobians_match_finite_differences_and_each_other(training, name):
    model = models.build(name, training, models.restrict(name, FAST)).model
    f = _outputs(model)
    X = jnp.asarray(training.X[:5] * 0.9)
    J_rev = jax.jit(jax.vmap(jax.jacrev(f)))(X)
    J_fwd = jax.jit(jax.vmap(jax.jacfwd(f)))(X)
    J_fd = jax.jit(lambda X: _central(f, X))(X)
    np.testing.assert_allclose(J_fwd, J_rev, rtol=1e-10, atol=1e-10)
    scale = np.max(np.abs(J_fd), axis=(1, 2), keepdims=True)
    assert np.max(np.abs(J_rev - J_fd) / scale) < 1e-6
    # Through lax.scan: the gradient of a sum over a sequence of queries.
    g = jax.jit(
        jax.grad(lambda X: jax.lax.scan(lambda c, x: (c + jnp.sum(f(x)), None), 0.0, X)[0])
    )(X)
    np.testing.assert_allclose(g, J_rev.sum(1), rtol=1e-9, atol=1e-9)
    # The batched predict differentiates too (its vmapped custom batch rules).
    gm = jax.jit(jax.grad(lambda X: sum(jnp.sum(o) for o in model.predict_unclipped(X))))(X)
    np.testing.assert_allclose(gm, J_rev.sum(1), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ["gpgs_hybrid", "gpg_pic"])
def test_float32_factors_differentiate_as_their_float64_copies(training, name):
    cfg = {**FAST, "variance_dtype": "float32"}
    model = models.build(name, training, models.restrict(name, cfg)).model
    wide = jax.tree.map(lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a, model)
    X = jnp.asarray(training.X[:4] * 0.9)
    J32 = eqx.filter_jit(lambda m, X: jax.vmap(jax.jacrev(_outputs(m)))(X))(model, X)
    J64 = eqx.filter_jit(lambda m, X: jax.vmap(jax.jacrev(_outputs(m)))(X))(wide, X)
    scale = np.max(np.abs(J64))
    assert np.max(np.abs(J32 - J64)) < 1e-4 * scale  # float32 rounding of the stored factors


def test_gradient_in_the_models_own_arrays(training):
    """Derivatives in the stored coefficients and factors (not only the query) are exact."""
    model = models.build("gpgs", training, models.restrict("gpgs", FAST)).model
    X = jnp.asarray(training.X[:3] * 0.9)

    @eqx.filter_jit
    def loss(m):
        return jnp.sum(jax.vmap(_outputs(m))(X))

    params, static = eqx.partition(model, eqx.is_inexact_array)
    # The direction and the moved arrays on the host (the compiled loss takes NumPy leaves
    # alike): op by op in JAX each leaf's shape compiled programs of its own.
    params = jax.tree.map(np.asarray, params)
    rng = np.random.default_rng(0)
    d = jax.tree.map(lambda a: rng.normal(size=a.shape), params)
    eps = 1e-6
    move = lambda s: eqx.combine(jax.tree.map(lambda p, q: p + s * q, params, d), static)  # noqa: E731
    fd = (loss(move(eps)) - loss(move(-eps))) / (2 * eps)
    g = eqx.filter_jit(eqx.filter_grad(loss))(model)
    ad = sum(
        np.sum(np.asarray(a) * b)
        for a, b in zip(
            jax.tree.leaves(eqx.filter(g, eqx.is_inexact_array)), jax.tree.leaves(d), strict=True
        )
    )
    np.testing.assert_allclose(ad, fd, rtol=1e-6)
