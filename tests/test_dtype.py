"""The dtype policy: gpg leaves JAX's x64 flag to the caller, fits in float64 whatever it is,
and a float32 copy of a surrogate predicts in float32 close to float64."""

import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg._dtype import float64
from gpg.surrogate import Surrogate
from tests.helpers import compiles, synthetic_dataset

ROOT = Path(__file__).resolve().parents[1]
# A small likelihood fit (the part that must run in float64) and a cheap model to predict with.
FIT = {"hyper": {"subset": 30, "max_steps": 10}, "partition": {"bins": 2}, "near": {"budget": 0.5}}
FIXED = {"hyper": {"fit": False, "lengthscale": 0.8}, "partition": {"bins": 2}}

# Fits and predicts in a process where x64 is off (a float32 program), prints numbers.
SCRIPT = """
import json, sys, warnings
warnings.filterwarnings("error", message=".*truncated to dtype float32")  # none on the way
import jax, jax.numpy as jnp, numpy as np
assert not jax.config.read("jax_enable_x64")
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset
from tests.test_dtype import FIT, queries
data = synthetic_dataset(30, seed=3)[0]
sur = Surrogate.fit(data, "gps_1x", FIT)
sur32 = sur.astype(jnp.float32)
rpm, euler, v = queries(data)
p = sur32.predict_batch(rpm, euler, v)
one = sur32.realtime()(rpm[0], euler[0], v[0])
print(json.dumps({
    "leaf_dtypes": sorted({str(x.dtype) for x in jax.tree.leaves(sur) if hasattr(x, "dtype")}),
    "lengthscale": np.asarray(sur.model.lengthscale, dtype=np.float64).tolist(),
    "force_dtype": str(p.force.dtype), "one_dtype": str(one.force.dtype),
    "force": np.asarray(p.force, dtype=np.float64).tolist(),
    "var": np.asarray(p.variance, dtype=np.float64).tolist(),
}))
"""


def queries(data, n=20):
    """World-frame states of ``n`` training inputs, airflow along +x."""
    x = data.x[:n]
    v = np.stack([x[:, 7], np.zeros(n), np.zeros(n)], axis=1)
    return x[:, :4], x[:, [4, 5, 6]], v


def test_float64_wrapper_runs_in_x64_and_widens_arguments():
    @float64
    def probe(a):
        return jax.config.read("jax_enable_x64"), a.dtype, jnp.ones(2).dtype

    with jax.enable_x64(False):
        on, dt, default = probe(jnp.ones(3, dtype=jnp.float32))
        assert not jax.config.read("jax_enable_x64")  # restored afterwards
    assert on and dt == jnp.float64 and default == jnp.float64


def test_fit_in_a_float32_setting_is_the_float64_fit():
    """In-process: with x64 off around it, Surrogate.fit still fits in float64 (same result)."""
    data = synthetic_dataset(30, seed=3)[0]
    with jax.enable_x64(False):
        off = Surrogate.fit(data, "gps_1x", FIT)
    on = Surrogate.fit(data, "gps_1x", FIT)
    assert off.model.lengthscale.dtype == jnp.float64
    np.testing.assert_allclose(off.model.lengthscale, on.model.lengthscale, rtol=1e-12)


@pytest.mark.slow
def test_float32_program_fits_in_float64_and_predicts_in_float32():
    """The same in a fresh interpreter with x64 off (a float32 program), end to end."""
    import json
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    p = subprocess.run(
        [sys.executable, "-c", SCRIPT], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    # The fit ran in float64: same hyperparameters as in this float64 process.
    data = synthetic_dataset(30, seed=3)[0]
    sur = Surrogate.fit(data, "gps_1x", FIT)
    assert "float64" in out["leaf_dtypes"]
    np.testing.assert_allclose(out["lengthscale"], np.asarray(sur.model.lengthscale), rtol=1e-8)
    # The float32 copy predicts in float32, within float32 rounding of the float64 answer.
    assert out["force_dtype"] == out["one_dtype"] == "float32"
    ref = sur.predict_batch(*queries(data))
    scale = np.std(data.y_aero[:, :3], axis=0)
    err = np.abs(np.asarray(out["force"]) - np.asarray(ref.force)) / scale
    assert err.max() < 1e-3, err.max()
    # The variance σ − ‖F k‖² cancels near the data: float32 keeps it to a small fraction of
    # each output's spread, not to a relative tolerance (up to 9 % relative at training points).
    spread = np.var(np.concatenate([data.y_aero, data.y_noise], axis=1), axis=0)
    dv = np.abs(np.asarray(out["var"]) - np.asarray(ref.variance)) / spread
    assert dv.max() < 1e-3, dv.max()


def test_astype_in_a_float64_process_computes_in_float32():
    data = synthetic_dataset(50, seed=3)[0]
    sur = Surrogate.fit(data, "gps_1x", FIXED)
    rpm, euler, v = queries(data, 3)
    p32 = sur.astype(jnp.float32).predict(rpm[0], euler[0], v[0])
    p64 = sur.predict(rpm[0], euler[0], v[0])
    assert p32.force.dtype == jnp.float32 and p64.force.dtype == jnp.float64
    np.testing.assert_allclose(p32.force, p64.force, rtol=1e-3, atol=1e-3)


def test_astype_casts_every_float_leaf_in_one_program(caplog):
    """Every float array rounded once to float32 (bit for bit NumPy's rounding), every other
    leaf the same object, float32 already there kept as it is; the conversions compiled as one
    program for the model (op by op, one for each leaf's shape), none the second time."""
    data = synthetic_dataset(50, seed=3)[0]
    sur = Surrogate.fit(data, "gpgs_hybrid", FIXED)
    floats = sum(jnp.issubdtype(x.dtype, jnp.floating) for x in jax.tree.leaves(sur))
    assert floats > 10  # enough leaves of enough shapes that op by op would show

    sur32, n = compiles(caplog, lambda: sur.astype(jnp.float32))
    assert n <= 1
    for a, b in zip(jax.tree.leaves(sur), jax.tree.leaves(sur32), strict=True):
        if jnp.issubdtype(a.dtype, jnp.floating):
            assert b.dtype == jnp.float32
            np.testing.assert_array_equal(np.asarray(b), np.asarray(a).astype(np.float32))
        else:
            assert b is a
    again, n = compiles(caplog, lambda: sur.astype(jnp.float32))
    assert n == 0
    same = sur32.astype(jnp.float32)  # nothing to convert: the same arrays
    assert all(a is b for a, b in zip(jax.tree.leaves(sur32), jax.tree.leaves(same), strict=True))


def test_float64_wrapper_widens_a_module_in_one_program(caplog):
    """A module's float32 leaves widened exactly (float32 to float64 is exact), its float64
    and integer leaves the same objects (not copied); the casts compiled as one program for
    the module, where op by op each leaf's shape compiled one, and none the second time."""
    import equinox as eqx

    class Mixed(eqx.Module):
        narrow: tuple
        wide: jax.Array
        index: jax.Array

    rng = np.random.default_rng(1)
    narrow = tuple(jnp.asarray(rng.normal(size=(k + 2, k + 1)), jnp.float32) for k in range(12))
    m = Mixed(narrow, jnp.asarray(rng.normal(size=7)), jnp.arange(5))

    @float64
    def probe(module):
        return module

    out, n = compiles(caplog, lambda: probe(m))
    assert n <= 1
    for a, b in zip(m.narrow, out.narrow, strict=True):
        assert b.dtype == jnp.float64
        np.testing.assert_array_equal(np.asarray(b), np.asarray(a).astype(np.float64))
    assert out.wide is m.wide and out.index is m.index
    _, n = compiles(caplog, lambda: probe(m))
    assert n == 0
    wide = probe(out)  # nothing narrow: the module itself
    assert wide is out


def test_float64_wrapper_keeps_plain_containers_as_they_are():
    """Only arrays and modules are rebuilt: a config dict keeps its key order."""

    @float64
    def keys(cfg):
        return list(cfg)

    assert keys({"b": 1, "a": 2}) == ["b", "a"]


def test_a_float64_model_queried_from_a_float32_program_answers_in_float32():
    """``in_model_dtype``: a float64 model's eager ``predict``/``predict_mean``/
    ``predict_gradient`` under x64 off compute in float64 (no truncation warning) and hand
    back the float64 answer rounded once to float32."""
    import warnings

    from gpg.gp.exact import ExactGP

    data = synthetic_dataset(30, seed=3)[0]
    model = Surrogate.fit(data, "gpg", {"hyper": FIXED["hyper"]}).model
    assert isinstance(model, ExactGP)
    Xq = np.asarray(data.x[:5]) + 0.01
    mean64, var64 = model.predict(Xq)
    grad64 = model.predict_gradient(Xq)
    with jax.enable_x64(False), warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*truncated to dtype")
        mean, var = model.predict(Xq)
        only_mean = model.predict_mean(Xq)
        grad = model.predict_gradient(Xq)
    for got, ref in ((mean, mean64), (var, var64), (only_mean, mean64), (grad, grad64)):
        assert got.dtype == jnp.float32
        np.testing.assert_array_equal(np.asarray(got), np.asarray(ref).astype(np.float32))
