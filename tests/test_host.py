"""gpg._host.asarray: jnp.asarray's array, put on the device without a compiled program;
gpg._host.each_row: a module at every row in one compiled program."""

import logging

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg import _host
from tests.helpers import compiles


def _same(a, b):
    assert type(a) is type(b)
    assert (a.dtype, a.shape, a.weak_type) == (b.dtype, b.shape, b.weak_type)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("x64", [True, False])
def test_the_array_jnp_asarray_gives(rng, x64):
    """Floats, integers and booleans of several shapes, a view with strides, in a float64 and
    a float32 program (where float64 host data becomes float32, as jnp.asarray makes it)."""
    host = [rng.normal(size=(7, 3)), rng.normal(size=5).astype(np.float32),
            rng.integers(0, 9, (2, 2, 2)), rng.normal(size=4) > 0, rng.normal(size=(9, 9))[::2, 1:],
            np.float64(2.5) * np.ones(())]  # fmt: skip
    with jax.enable_x64(x64):
        for x in host:
            _same(_host.asarray(x), jnp.asarray(x))
        # anything but a NumPy array is jnp.asarray's: Python scalars stay weakly typed
        for x in (2.5, [1.0, 2.0], jnp.arange(3)):
            _same(_host.asarray(x), jnp.asarray(x))
        y = jnp.ones(3)
        assert _host.asarray(y) is y


def test_no_program_compiled_and_the_host_bytes_copied(rng, caplog):
    """A new shape compiles nothing (jnp.asarray compiles a staged identity for each in this
    JAX); the device array does not share the host's memory; inside a trace the values are
    jnp.asarray's."""
    shapes = [(11, 13), (17,), (3, 19, 2)]
    with jax.log_compiles(True), caplog.at_level(logging.WARNING, logger="jax"):
        for s in shapes:
            _host.asarray(rng.normal(size=s)).block_until_ready()
    assert not [r for r in caplog.records if "ompil" in r.getMessage()]
    x = np.zeros((64, 64))
    a = _host.asarray(x).block_until_ready()
    x[0, 0] = 7.0
    assert float(np.asarray(a)[0, 0]) == 0.0
    for _ in range(20):  # the device buffer is not the host's, whatever its alignment
        x = rng.normal(size=(int(rng.integers(1, 300)), 8))
        a, want = _host.asarray(x).block_until_ready(), x.copy()
        x[:] = 0.0
        np.testing.assert_array_equal(np.asarray(a), want)
    c = rng.normal(size=(4, 2))
    got = jax.jit(lambda t: t + _host.asarray(c))(1.0)
    np.testing.assert_array_equal(got, jax.jit(lambda t: t + jnp.asarray(c))(1.0))
    # the check itself can fail: a program of a new shape is seen compiling
    caplog.clear()
    with jax.log_compiles(True), caplog.at_level(logging.WARNING, logger="jax"):
        jax.jit(lambda v: v + 1.0)(rng.normal(size=(23, 29))).block_until_ready()
    assert [r for r in caplog.records if "ompil" in r.getMessage()]


def test_as_stored_keeps_the_dtype(rng):
    """A float64 array stays float64 in a float32 program (asarray would make it float32), and
    a float32 one float32 in a float64 program; the values are the host's, bit for bit."""
    x, y = rng.normal(size=(5, 3)), rng.normal(size=4).astype(np.float32)
    for x64 in (False, True):
        with jax.enable_x64(x64):
            for a in (x, y):
                got = _host.as_stored(a)
                assert got.dtype == a.dtype
                np.testing.assert_array_equal(np.asarray(got), a)
    with jax.enable_x64(False):
        assert _host.asarray(x).dtype == np.float32  # what as_stored is for


class _Affine(eqx.Module):
    """A module with arrays and a static field, as the flight bases are."""

    A: jax.Array
    b: jax.Array
    square: bool = eqx.field(static=True, default=False)

    def __call__(self, x):
        y = self.A @ x + self.b
        return (y * y if self.square else y), jnp.sum(x)


def test_each_row_is_vmap_in_one_program(rng, caplog):
    """The eager vmap's values (to the rounding of one fused program against op by op), as
    NumPy arrays, tuples kept; one compilation for a module's structure and the rows' shape,
    none for new arrays of the same shapes, one for a new static field; the count itself can
    fail: eager vmap compiles its operations one by one."""
    X = rng.normal(size=(9, 3))
    f = _Affine(jnp.asarray(rng.normal(size=(4, 3))), jnp.asarray(rng.normal(size=4)))
    got = _host.each_row(f, X)
    want = jax.vmap(f)(jnp.asarray(X))
    assert isinstance(got, tuple) and all(type(g) is np.ndarray for g in got)
    for g, w in zip(got, want, strict=True):
        # a sum of three products of O(1) terms, rounded in another order
        np.testing.assert_allclose(g, w, rtol=0, atol=8 * np.finfo(float).eps * 10)

    X2 = rng.normal(size=(13, 3))
    assert compiles(caplog, lambda: _host.each_row(f, X2))[1] == 1
    g = _Affine(jnp.asarray(rng.normal(size=(4, 3))), jnp.asarray(rng.normal(size=4)))
    assert compiles(caplog, lambda: _host.each_row(g, X2))[1] == 0
    assert compiles(caplog, lambda: _host.each_row(_Affine(g.A, g.b, square=True), X2))[1] == 1
    X3 = jnp.asarray(rng.normal(size=(17, 3)))
    assert compiles(caplog, lambda: jax.vmap(g)(X3))[1] > 1
