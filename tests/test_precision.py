"""Every matrix product in gpg's numerics runs at ``Precision.HIGHEST`` (gpg._precision).

On NVIDIA GPUs a float32 product without a stated precision runs in TF32 (a 10-bit mantissa),
which made a float32 surrogate a hundred times less accurate there than on the CPU. Two
checks that a new product cannot slip in without it: the programs of the public predictions
(the default kind and those with other predictors, mean and variance, batched,
differentiated both ways, float32 and float64, the environment and the MPC's
linearisation) are walked equation by equation, nested programs
included; and every product bound while a surrogate is fitted (hyperparameters, factorisation,
CG) is recorded as it is traced.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax._src.lax import lax as lax_internal

from gpg.gp.binned import METHODS, by_bin
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset

HIGHEST = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)


def _subprograms(value):
    if hasattr(value, "eqns"):  # a Jaxpr
        yield value
    elif hasattr(value, "jaxpr") and hasattr(value.jaxpr, "eqns"):  # a ClosedJaxpr
        yield value.jaxpr
    elif isinstance(value, tuple | list):
        for v in value:
            yield from _subprograms(v)


def dot_precisions(jaxpr) -> list:
    """The precision of every ``dot_general`` in ``jaxpr`` and the programs nested in it."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            out.append(eqn.params["precision"])
        for v in eqn.params.values():
            for sub in _subprograms(v):
                out.extend(dot_precisions(sub))
    return out


def assert_highest(fn, *args, what: str):
    found = dot_precisions(jax.make_jaxpr(fn)(*args).jaxpr)
    assert found, f"{what}: no matrix product found (the walk is broken)"
    bad = [p for p in found if p != HIGHEST]
    assert not bad, f"{what}: {len(bad)} of {len(found)} products without HIGHEST: {bad[:3]}"


CFG = {"hyper": {"fit": False, "lengthscale": 0.8}, "variance_dtype": "float64"}
# The predictors besides the default's: the exact GP, and the binned mean and PIC's shared rows
# (gpgs and gpgs_schur predict with the same BinnedGP code as PIC, the hybrid's variance too).
KIND_CFG = {
    "gpg": {},
    "gpg_pic": {"partition": {"bins": 3, "points_per_bin": None}, "inducing": {"points": 8}},
}


@pytest.fixture(scope="module")
def data():
    return synthetic_dataset(40, seed=5, raw=False)[0]


def _states(n, dtype):
    rng = np.random.default_rng(0)
    rpm = rng.uniform(2500, 5000, (n, 4))
    euler = rng.uniform(-0.3, 0.3, (n, 3))
    v = rng.uniform(-4, 4, (n, 3))
    return tuple(jnp.asarray(a, dtype) for a in (rpm, euler, v))


def _check_surrogate(sur, dtype, what):
    rpm, euler, v = _states(40, dtype)  # more than a few per bin: the batch sorts by bin
    assert_highest(sur.predict, rpm[0], euler[0], v[0], what=f"{what} predict")
    assert_highest(sur.predict_mean, rpm[0], euler[0], v[0], what=f"{what} predict_mean")
    assert_highest(jax.vmap(sur.predict), rpm, euler, v, what=f"{what} vmap(predict)")
    for mean_only in (False, True):
        # Concrete states (the batch checks them on the host): the jitted call is traced inside.
        batch = lambda m=mean_only: sur.predict_batch(rpm, euler, v, mean_only=m, chunk=16)  # noqa: E731
        assert_highest(batch, what=f"{what} predict_batch(mean_only={mean_only})")

    def f(a):
        p = sur.predict(rpm[0], euler[0], a)
        return jnp.concatenate([p.force, p.variance[:3]])

    assert_highest(jax.jacrev(f), v[0], what=f"{what} jacrev(predict)")
    assert_highest(jax.jacfwd(f), v[0], what=f"{what} jacfwd(predict)")


def test_default_surrogate_products_are_highest(synthetic_surrogate):
    """float32, where TF32 would apply; a float64 program traces the same functions."""
    sur = synthetic_surrogate.astype(jnp.float32)
    _check_surrogate(sur, jnp.float32, "gpgs_hybrid")
    factor = sur.model.local.factor
    bins = jnp.arange(40) % len(factor)
    K = jnp.zeros((40, factor[0].n), jnp.float32)
    for method in METHODS:  # the GPU's execution too, which predict_batch takes there
        fn = lambda b, k, m=method: by_bin(factor, b, k, with_grad=True, method=m)  # noqa: E731
        assert_highest(fn, bins, K, what=f"by_bin({method})")


@pytest.mark.parametrize("name", sorted(KIND_CFG))
def test_every_kind_products_are_highest(data, name):
    sur = Surrogate.fit(data, name, {**CFG, **KIND_CFG[name]})
    _check_surrogate(sur.astype(jnp.float32), jnp.float32, name)
    model = sur.model
    Xq = jnp.zeros((3, model.n_inputs))
    assert_highest(model.predict, Xq, what=f"{name} model.predict")
    if hasattr(model, "predict_gradient"):
        assert_highest(model.predict_gradient, Xq, what=f"{name} predict_gradient")


def test_environment_and_mpc_products_are_highest(synthetic_surrogate, vehicle):
    from gpg.envs import EnvParams, QuadrotorEnv
    from gpg.mpc import Dynamics

    env = QuadrotorEnv.create(vehicle, synthetic_surrogate)
    params = EnvParams.create("hover")
    keys = jax.random.split(jax.random.key(0), 3)
    # Shapes only: the walk traces the step, nothing needs to run.
    obs, st = jax.eval_shape(jax.vmap(env.reset, in_axes=(0, None)), keys, params)
    a = jax.ShapeDtypeStruct((3, 4), obs.dtype)
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))
    assert_highest(step, keys, st, a, params, what="env.step")
    # The geometric controller, which a user's own loop may call outside the step.
    act = jax.vmap(env.geometric_action, in_axes=(0, None))
    assert_highest(act, st, params, what="env.geometric_action")

    dyn = Dynamics.create(vehicle, synthetic_surrogate, 0.01)
    x = jnp.zeros(17).at[3].set(1.0)
    u = jnp.full(4, 3600.0)
    assert_highest(lambda x, u: dyn.linearize(x, u, 0.0), x, u, what="Dynamics.linearize")


@pytest.mark.filterwarnings("ignore:hyperparameter fit did not converge")  # 3 steps, on purpose
def test_fit_products_are_highest(monkeypatch):
    """Every product bound while surrogates are fitted: the hyperparameter fit (optimistix),
    the dense factorisation, the hybrid's near sets and the matrix-free CG solve. Sizes no
    other test uses (33 points, a subset of 17), so that every program is traced here."""
    data = synthetic_dataset(33, seed=7, raw=False)[0]
    seen = []
    bind = lax_internal.dot_general_p.bind

    def recording(*args, **params):
        seen.append(params.get("precision"))
        return bind(*args, **params)

    monkeypatch.setattr(lax_internal.dot_general_p, "bind", recording)
    Surrogate.fit(data, "gpgs_hybrid", {"hyper": {"subset": 17, "max_steps": 3}})
    Surrogate.fit(data, "gpgs_hybrid", {**CFG, "solver": {"method": "cg", "points": 7}})
    monkeypatch.undo()
    assert len(seen) > 20, f"only {len(seen)} products recorded (the recorder is broken)"
    bad = [p for p in seen if p != HIGHEST]
    assert not bad, f"{len(bad)} of {len(seen)} products without HIGHEST: {bad[:3]}"
