"""The batched variance by bins (gpg.gp.binned.by_bin): the queries sorted by bin, each bin's
run padded to whole tiles, one product per tile with its bin's factor. Checked against a NumPy
reference written here (``‖F_b k‖²`` and ``2 F_bᵀ F_b k`` query by query) for tiles of every
size, empty bins, one bin holding every query, float32 factors, and through ``vmap``,
``jacrev`` and ``jacfwd`` of the one-query function."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp.binned import binned_quadratic_form, by_bin, default_method, tile_rows
from gpg.linalg.tri import BlockTriangular

# compiled once per configuration: op by op each call compiled dozens of small programs
by_bin_jit = eqx.filter_jit(by_bin)

N_BINS, WIDTH = 5, 24
EPS64 = np.finfo(np.float64).eps
EPS32 = np.finfo(np.float32).eps


def _factors(rng, dtype="float64"):
    dense = [np.tril(rng.normal(size=(WIDTH, WIDTH))) / np.sqrt(WIDTH) for _ in range(N_BINS)]
    bands = tuple(
        BlockTriangular.from_dense(F.astype(dtype), lower=True, n_blocks=3) for F in dense
    )
    return dense, bands


def _reference(dense, bins, K):
    V = np.stack([dense[b] @ k for b, k in zip(bins, K, strict=True)])
    G = np.stack([2 * dense[b].T @ v for b, v in zip(bins, V, strict=True)])
    return np.sum(V * V, axis=1), G


def _bound(dense, K, eps):
    """Rounding bound of ``‖F k‖²`` and of its gradient: each entry sums ``WIDTH`` products
    twice over (``F k``, then its square or ``Fᵀ v``), so ``2·WIDTH·eps`` relative to the sum of
    the magnitudes, with a factor 4 of room."""
    mag = max(np.abs(F).max() for F in dense) * np.abs(K).max(axis=1)
    return 8 * WIDTH * eps * (WIDTH * mag) ** 2


@pytest.mark.parametrize(
    "method, bins_kind, tile",
    [
        ("loop", "mixed", None),
        ("loop", "mixed", 1),
        ("loop", "one_bin", 4),
        ("loop", "two_empty", 3),
        ("gather", "two_empty", 64),
        ("every", "mixed", None),
    ],
)
def test_by_bin_equals_per_query_reference(rng, bins_kind, tile, method):
    dense, bands = _factors(rng)
    q = 37
    bins = {
        "mixed": rng.integers(0, N_BINS, q),
        "one_bin": np.full(q, 3),
        "two_empty": rng.choice([0, 2, 4], q),
    }[bins_kind]
    K = rng.normal(size=(q, WIDTH))
    args = (bands, jnp.asarray(bins), jnp.asarray(K))
    quad, grad = by_bin_jit(*args, with_grad=True, tile=tile, method=method)
    ref_q, ref_g = _reference(dense, bins, K)
    bound = _bound(dense, K, EPS64)
    np.testing.assert_array_less(np.abs(np.asarray(quad) - ref_q), bound)
    np.testing.assert_array_less(np.abs(np.asarray(grad) - ref_g).max(axis=1), bound)
    if tile is None:  # the value alone: the same tiles without the gradient's products
        (quad_only,) = by_bin_jit(*args, with_grad=False, tile=tile, method=method)
        np.testing.assert_array_less(np.abs(np.asarray(quad_only) - ref_q), bound)


@pytest.mark.parametrize("method", ["loop", "gather"])
def test_float32_factors_within_their_rounding(rng, method):  # "every": the loop's products
    dense, bands = _factors(rng, "float32")
    bins = rng.integers(0, N_BINS, 50)
    K = rng.normal(size=(50, WIDTH)).astype(np.float32)
    (quad,) = by_bin_jit(bands, jnp.asarray(bins), jnp.asarray(K), with_grad=False, method=method)
    dense64 = [np.asarray(b.to_dense()) for b in bands]  # the stored float32 values, exactly
    ref, _ = _reference(dense64, bins, K.astype(np.float64))
    assert quad.dtype == jnp.float32
    err = np.abs(np.asarray(quad, np.float64) - ref)
    np.testing.assert_array_less(err, _bound(dense, K, EPS32))


def test_vmap_and_derivatives_of_the_one_query_form(rng):
    dense, bands = _factors(rng)
    bins = jnp.asarray(rng.integers(0, N_BINS, 9))
    K = jnp.asarray(rng.normal(size=(9, WIDTH)))
    one = lambda b, k: binned_quadratic_form(bands, b, k)  # noqa: E731
    batched = jax.vmap(one)(bins, K)
    looped = jnp.stack([one(b, k) for b, k in zip(bins, K, strict=True)])
    ref_q, ref_g = _reference(dense, np.asarray(bins), np.asarray(K))
    bound = _bound(dense, np.asarray(K), EPS64)
    np.testing.assert_array_less(np.abs(np.asarray(batched) - ref_q), bound)
    np.testing.assert_array_less(np.abs(np.asarray(looped) - ref_q), bound)
    for jac in (jax.jacrev, jax.jacfwd):
        G = jax.vmap(jac(one, argnums=1))(bins, K)
        np.testing.assert_array_less(np.abs(np.asarray(G) - ref_g).max(axis=1), bound)


def test_upper_factors_with_a_dense_block(rng):
    """PIC's factors: upper triangular below a dense block of inducing rows."""
    dense = [np.triu(rng.normal(size=(WIDTH, WIDTH))) for _ in range(N_BINS)]
    for F in dense:
        F[:6] = rng.normal(size=(6, WIDTH))
    bands = tuple(
        BlockTriangular.from_dense(F, lower=False, n_blocks=3, dense_rows=6) for F in dense
    )
    bins = rng.integers(0, N_BINS, 20)
    K = rng.normal(size=(20, WIDTH))
    ref_q, ref_g = _reference(dense, bins, K)
    for method in ("loop", "gather"):
        q, g = by_bin_jit(bands, jnp.asarray(bins), jnp.asarray(K), with_grad=True, method=method)
        bound = _bound(dense, K, EPS64)
        np.testing.assert_array_less(np.abs(np.asarray(q) - ref_q), bound)
        np.testing.assert_array_less(np.abs(np.asarray(g) - ref_g).max(axis=1), bound)
    with pytest.raises(ValueError, match="method"):
        by_bin(bands, jnp.asarray(bins), jnp.asarray(K), with_grad=False, method="scan")


def test_tile_rows_and_default_method():
    assert default_method(20, 5) == "every" and default_method(21, 5) == "loop"  # CPU backend
    assert tile_rows(1, 10) == 1
    assert tile_rows(1024, 8) == 64
    assert tile_rows(1024, 8, "gather") == 64
    assert tile_rows(10**6, 4) == 64 and tile_rows(10**6, 4, "gather") == 1024
