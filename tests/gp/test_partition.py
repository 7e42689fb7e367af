"""Bins: lookup against brute-force box membership (edges included), near sets, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.gp import partition


def brute_force(part, X):
    lo, hi = part.boxes(X.shape[1])
    inside = np.all((X[:, None, :] > lo[None]) & (X[:, None, :] <= hi[None]), axis=-1)
    assert np.all(inside.sum(1) == 1), "bins must not overlap and must cover every point"
    return np.argmax(inside, axis=1)


@pytest.mark.parametrize("scheme", ["slab", "kdtree"])
@pytest.mark.parametrize("n_bins", [1, 2, 3, 7, 10])
def test_lookup_matches_brute_force(rng, scheme, n_bins):
    X = rng.uniform(-1, 1, (300, 8))
    part = partition.build(X, scheme, n_bins)
    assert part.n_bins == n_bins
    # Training points, fresh points, points outside the box, and points exactly on every split.
    Q = [X, rng.uniform(-1.5, 1.5, (300, 8))]
    for d, v in zip(np.asarray(part.split_dim), np.asarray(part.split_value), strict=True):
        edge = rng.uniform(-1, 1, (20, 8))
        edge[:, d] = v
        Q.append(edge)
    Q = np.concatenate(Q)
    got = np.asarray(part.lookup_batch(jnp.asarray(Q)))
    np.testing.assert_array_equal(got, brute_force(part, Q))
    counts = np.bincount(got[:300], minlength=n_bins)
    assert counts.max() - counts.min() <= (1 if scheme == "slab" else 2)


def test_slab_splits_airspeed_by_default(rng):
    X = rng.uniform(-1, 1, (100, 8))
    part = partition.slab(X, 4)
    assert set(np.asarray(part.split_dim).tolist()) == {7}


def test_near_sets_budget_and_epsilon(rng):
    X = rng.uniform(-1, 1, (200, 3))
    part = partition.kdtree(X, 4)
    ns = partition.near_sets(X, part, 0.4, budget=0.4)
    bins = np.asarray(part.lookup_batch(jnp.asarray(X)))
    for b in range(4):
        assert set(ns.anchors[b]) == set(np.flatnonzero(bins == b))
        assert set(ns.anchors[b]) <= set(ns.near[b])
        assert ns.near[b].size == 80
        np.testing.assert_array_equal(ns.near[b], np.sort(ns.near[b]))
    np.testing.assert_allclose(ns.fraction, 0.4)
    # Threshold: near = correlation with some anchor above ε, anchors always in.
    eps = partition.near_sets(X, part, 0.4, epsilon=0.3)
    for b in range(4):
        a = X[eps.anchors[b]]
        corr = np.exp(-0.5 * np.sum((X[:, None] - a[None]) ** 2, -1) / 0.16).max(1)
        want = np.flatnonzero(corr > 0.3)
        np.testing.assert_array_equal(eps.near[b], np.union1d(want, eps.anchors[b]))
    assert np.all(eps.epsilon > 0.3)
    # A budget smaller than a bin still keeps its anchors.
    small = partition.near_sets(X, part, 0.4, budget=0.01)
    assert all(s.size == a.size for s, a in zip(small.near, small.anchors, strict=True))


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda X: partition.build(X, "voronoi", 4),
            r"unknown partition scheme 'voronoi'; valid: \['slab', 'kdtree', 'adaptive'\]",
        ),
        (lambda X: partition.build(X, "slab", 0), r"n_bins must be a positive integer"),
        (lambda X: partition.build(X, "slab", 500), r"exceeds the 100 training points"),
        (lambda X: partition.slab(X, 3, dim=9), r"slab dim 9 out of range"),
        (lambda X: partition.kdtree(X[:, :, None], 3), r"X must be \(N, D\)"),
        (lambda X: partition.slab(np.zeros((100, 8)), 3), r"too few distinct values"),
    ],
)
def test_bad_partitions(rng, call, match):
    with pytest.raises(ValueError, match=match):
        call(rng.uniform(-1, 1, (100, 8)))


@pytest.mark.parametrize(
    "kw, match",
    [
        ({}, "exactly one"),
        ({"epsilon": 0.1, "budget": 0.2}, "exactly one"),
        ({"budget": 1.5}, r"budget must be a fraction"),
        ({"epsilon": 1.0}, r"epsilon must be in \[0, 1\)"),
    ],
)
def test_bad_near_options(rng, kw, match):
    X = rng.uniform(-1, 1, (50, 2))
    with pytest.raises(ValueError, match=match):
        partition.near_sets(X, partition.slab(X, 2, dim=0), 0.5, **kw)


def test_far_correlation_matches_numpy(rng):
    X = rng.uniform(-1, 1, (30, 2))
    part = partition.slab(X, 3, dim=0)
    ls = np.array([0.4, 0.7])
    ns = partition.near_sets(X, part, ls, budget=0.5)
    got = partition.far_correlation(X, ns, ls)
    bins = np.asarray(part.lookup_batch(X))
    for i in range(30):
        far = np.setdiff1d(np.arange(30), ns.near[bins[i]])
        d = (X[i] - X[far]) / ls
        assert got[i] == pytest.approx(np.exp(-0.5 * np.sum(d * d, 1)).max(), rel=1e-12)


@pytest.mark.parametrize("scheme", ["slab", "kdtree"])
def test_boundary_pairs_straddle_every_boundary(rng, scheme):
    X = rng.uniform(-1, 1, (80, 3))
    part = partition.build(X, scheme, 5, **({"dim": 2} if scheme == "slab" else {}))
    A, C = partition.boundary_pairs(part, X, per_face=10, delta=1e-6)
    ba, bc = np.asarray(part.lookup_batch(A)), np.asarray(part.lookup_batch(C))
    assert A.shape == C.shape and A.shape[0] >= 4 * 5 and np.all(ba != bc)
    diff = np.abs(A - C)
    assert np.all(np.isclose(diff.max(1), 2e-6)) and np.all((diff > 0).sum(1) == 1)
    # Every internal boundary is crossed by some pair.
    crossed = {tuple(sorted(p)) for p in zip(ba.tolist(), bc.tolist(), strict=True)}
    assert len(crossed) >= part.n_bins - 1


def test_near_sets_by_points(rng):
    X = rng.uniform(-1, 1, (50, 2))
    part = partition.slab(X, 5, dim=0)
    ns = partition.near_sets(X, part, 0.5, points=17)
    assert all(nb.size == 17 for nb in ns.near)
    with pytest.raises(ValueError, match="exactly one of"):
        partition.near_sets(X, part, 0.5, points=3, budget=0.1)
    with pytest.raises(ValueError, match="points must be a positive integer"):
        partition.near_sets(X, part, 0.5, points=0)


def test_adaptive_equal_weights_is_the_equal_count_slab(rng):
    X = rng.uniform(-1, 1, (103, 8))
    a = partition.adaptive(X, 7, weights=np.full(103, 2.5))
    b = partition.slab(X, 7)
    np.testing.assert_array_equal(a.split_value, b.split_value)
    np.testing.assert_array_equal(a.split_dim, b.split_dim)


def test_adaptive_bins_are_narrow_where_the_outputs_vary_fast(rng):
    """Outputs that wiggle only at high airspeed: the adaptive slabs crowd there, cover the
    whole box without overlap (one bin per point, bins ordered along airspeed), and the jitted
    lookup agrees with the NumPy assignment."""
    X = rng.uniform(-1, 1, (400, 8))
    Y = np.where(X[:, 7:] > 0.5, np.sin(25 * X[:, 7:]), 0.1 * X[:, 7:])
    w = partition.variation_weights(X, Y)
    part = partition.adaptive(X, 8, weights=w)
    cuts = np.asarray(part.split_value)
    assert np.all(np.diff(cuts) > 0) and np.sum(cuts > 0.5) >= 4  # half the bins in a quarter
    Q = rng.uniform(-1.2, 1.2, (500, 8))
    bins = np.asarray(jax.jit(lambda p, q: p.lookup_batch(q))(part, jnp.asarray(Q)))
    want = np.searchsorted(cuts, Q[:, 7], side="left")  # x <= cut_i goes to bin i
    np.testing.assert_array_equal(bins, want)
    counts = np.bincount(np.asarray(part.lookup_batch(jnp.asarray(X))), minlength=8)
    assert counts.sum() == 400 and counts.min() >= 400 // (4 * 8)


def test_adaptive_needs_valid_weights(rng):
    X = rng.uniform(-1, 1, (20, 8))
    with pytest.raises(ValueError, match="weights must be 20 finite values"):
        partition.adaptive(X, 2, weights=np.full(20, np.nan))
    with pytest.raises(ValueError, match="weights must be"):
        partition.build(X, "adaptive", 2, weights=np.ones(3))
