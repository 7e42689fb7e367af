"""Bins, anchors and near sets (paper, Section "Partitioning (Selection of Near and Far Sets)").

The input space is split into non-overlapping bins that cover all of it, with a jittable
lookup for one query or a batch:

* ``slab``: equal-count intervals along one input (airspeed by default);
* ``kdtree``: balanced median splits, each node cutting the input of largest spread among its
  points at the quantile that gives its two children bin counts in proportion.

A query ``x`` belongs to the bin whose box ``(lo, hi]`` holds it (a value on a split goes to
the lower side). The anchors of a bin are the training points inside it; its near set are the
points whose kernel correlation with some anchor exceeds ``ε`` (anchors included), or, with a
near-set budget, the ``⌈budget·N⌉`` most correlated points. The budget exists because with long
lengthscales a fixed ``ε`` makes nearly every point near.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from gpg import _host
from gpg.gp import kernels

__all__ = [
    "NearSets",
    "Partition",
    "SCHEMES",
    "adaptive",
    "boundary_pairs",
    "build",
    "far_correlation",
    "kdtree",
    "near_sets",
    "slab",
    "variation_weights",
]

SCHEMES = ("slab", "kdtree", "adaptive")


class Partition(eqx.Module):
    """Bins as a binary tree of axis-aligned splits (a slab partition is a chain).

    Internal node ``i`` sends ``x`` left when ``x[split_dim[i]] <= split_value[i]``; a child
    index ``c >= 0`` is another internal node, ``c < 0`` is bin ``−c − 1``.
    """

    split_dim: Int[Array, " I"]
    split_value: Float[Array, " I"]
    left: Int[Array, " I"]
    right: Int[Array, " I"]
    n_bins: int = eqx.field(static=True)
    depth: int = eqx.field(static=True)
    scheme: str = eqx.field(static=True)

    def lookup(self, x: Float[ArrayLike, " D"]) -> Int[Array, ""]:
        """Bin of one query (jittable, vmappable).

        A value on a split goes to the lower side (``x[d] <= split``).

        Args:
            x: (D,) one query in the normalised inputs the partition was built on.

        Returns:
            The bin index, an int32 scalar in ``[0, n_bins)``.
        """
        x = jnp.asarray(x)
        if self.n_bins == 1:
            return jnp.zeros((), dtype=jnp.int32)
        if self.scheme == "slab":  # increasing cuts on one input: count the cuts below x
            return jnp.sum(x[self.split_dim[0]] > self.split_value).astype(jnp.int32)
        node = jnp.zeros((), dtype=jnp.int32)
        for _ in range(self.depth):  # static unroll: depth is at most ceil(log2 n_bins) or n-1
            i = jnp.maximum(node, 0)
            go_left = x[self.split_dim[i]] <= self.split_value[i]
            child = jnp.where(go_left, self.left[i], self.right[i])
            node = jnp.where(node >= 0, child, node)
        return (-node - 1).astype(jnp.int32)

    @eqx.filter_jit  # one program, not one per operation of the walk (callers run it eagerly)
    def lookup_batch(self, X: Float[ArrayLike, "Q D"]) -> Int[Array, " Q"]:
        """Bins of a batch of queries.

        Args:
            X: (Q, D) queries in the normalised inputs.

        Returns:
            The (Q,) bin indices (int32), as :meth:`lookup` gives one by one.
        """
        return jax.vmap(self.lookup)(jnp.asarray(X))

    def boxes(self, n_inputs: int) -> tuple[np.ndarray, np.ndarray]:
        """Each bin's box ``(lo, hi]``, walking the tree of splits on the host.

        Args:
            n_inputs: D, the number of inputs (the tree records only the inputs it cuts).

        Returns:
            The lower and upper bounds ``lo``, ``hi``, each (n_bins, D), with ±inf where a bin
            is unbounded.
        """
        lo = np.full((self.n_bins, n_inputs), -np.inf)
        hi = np.full((self.n_bins, n_inputs), np.inf)
        if self.n_bins == 1:
            return lo, hi
        sd, sv = np.asarray(self.split_dim), np.asarray(self.split_value)
        left, right = np.asarray(self.left), np.asarray(self.right)

        def walk(node, a, b):
            for child, is_left in ((left[node], True), (right[node], False)):
                a2, b2 = a.copy(), b.copy()
                if is_left:
                    b2[sd[node]] = min(b2[sd[node]], sv[node])
                else:
                    a2[sd[node]] = max(a2[sd[node]], sv[node])
                if child >= 0:
                    walk(child, a2, b2)
                else:
                    lo[-child - 1], hi[-child - 1] = a2, b2

        walk(0, lo[0].copy(), hi[0].copy())
        return lo, hi


def _tree(nodes: list[tuple[int, float, int, int]], n_bins: int, depth: int, scheme: str):
    if not nodes:
        nodes = [(0, 0.0, -1, -1)]  # placeholder, never used with one bin
    sd, sv, le, ri = (np.array(c) for c in zip(*nodes, strict=True))
    return Partition(
        split_dim=jnp.asarray(sd, dtype=jnp.int32),
        split_value=jnp.asarray(sv, dtype=float),
        left=jnp.asarray(le, dtype=jnp.int32),
        right=jnp.asarray(ri, dtype=jnp.int32),
        n_bins=n_bins,
        depth=max(depth, 1),
        scheme=scheme,
    )


def _check(X: np.ndarray, n_bins: int) -> np.ndarray:
    X = np.asarray(X, dtype=float)
    if X.ndim != 2:
        raise ValueError(f"X must be (N, D), got shape {X.shape}")
    if not isinstance(n_bins, int | np.integer) or n_bins < 1:
        raise ValueError(f"n_bins must be a positive integer, got {n_bins!r}")
    if n_bins > X.shape[0]:
        raise ValueError(f"n_bins={n_bins} exceeds the {X.shape[0]} training points")
    return X


def slab(X: Float[ArrayLike, "N D"], n_bins: int, dim: int = 7) -> Partition:
    """Equal-count intervals along input ``dim`` (airspeed, the paper's dominant effect).

    Args:
        X: (N, D) training inputs.
        n_bins: the number of slabs, at most N.
        dim: the input cut (7, airspeed, in the airflow frame).

    Returns:
        A chain of ``n_bins − 1`` cuts, scheme ``slab``.

    Raises:
        ValueError: if ``X`` is not (N, D), ``n_bins`` is not in ``[1, N]``, ``dim`` is out
            of range, or input ``dim`` has too few distinct values for ``n_bins`` slabs.
    """
    return _slabs(X, n_bins, dim, None, "slab")


def adaptive(
    X: Float[ArrayLike, "N D"],
    n_bins: int,
    dim: int = 7,
    *,
    weights: Float[ArrayLike, " N"],
) -> Partition:
    """Intervals along input ``dim`` holding equal shares of ``weights`` instead of equal counts.

    More, narrower bins where the weights are large: the paper's proposal of finer partitions
    at high airspeed. Equal weights give exactly :func:`slab`. Every bin keeps at least a
    quarter of an equal share of the points, so that no bin is left without data to condition
    on.

    Args:
        X: (N, D) training inputs.
        n_bins: the number of intervals, at most N.
        dim: the input cut (7, airspeed, in the airflow frame).
        weights: (N,) finite, non-negative, not all zero: each point's weight, normally the
            outputs' local variation (:func:`variation_weights`).

    Returns:
        A chain of ``n_bins − 1`` cuts, scheme ``adaptive``.

    Raises:
        ValueError: if ``weights`` is not N finite values >= 0 with a positive sum, or for
            the reasons :func:`slab` gives.
    """
    w = np.asarray(weights, dtype=float)
    if w.shape != (np.shape(X)[0],) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"weights must be {np.shape(X)[0]} finite values >= 0, not all zero")
    return _slabs(X, n_bins, dim, w, "adaptive")


def _slabs(X, n_bins: int, dim: int, weights: np.ndarray | None, scheme: str) -> Partition:
    X = _check(X, n_bins)
    if not 0 <= dim < X.shape[1]:
        raise ValueError(f"slab dim {dim} out of range for {X.shape[1]} inputs")
    order = np.argsort(X[:, dim], kind="stable")
    v = X[order, dim]
    n = len(v)
    if weights is None:
        idx = [(k * n) // n_bins - 1 for k in range(1, n_bins)]
    else:
        # Cumulative weight in units of points (mean weight 1): equal weights give the
        # equal-count positions exactly (integer partial sums).
        s = np.cumsum(weights[order] / np.mean(weights))
        idx, least = [], max(1, n // (4 * n_bins))
        for k in range(1, n_bins):
            i = int(np.searchsorted(s, (k * n) // n_bins, side="left"))
            lo = (idx[-1] if idx else -1) + least
            idx.append(min(max(i, lo), n - 1 - (n_bins - k) * least))
    cuts = [v[i] for i in idx]
    if len(set(cuts)) != len(cuts):
        raise ValueError(f"input {dim} has too few distinct values for {n_bins} slabs")
    # A chain: node i sends x <= cut_i to bin i, the rest to node i + 1 (or the last bin).
    nodes = [
        (dim, float(c), -(i + 1), i + 1 if i + 1 < n_bins - 1 else -(n_bins))
        for i, c in enumerate(cuts)
    ]
    return _tree(nodes, n_bins, n_bins - 1, scheme)


def variation_weights(
    X: Float[ArrayLike, "N D"], Y: Float[ArrayLike, "N M"], k: int = 8
) -> np.ndarray:
    """How fast the outputs change around each training point.

    The mean over its ``k`` nearest neighbours (in the normalised inputs) of
    ``‖Y_i − Y_j‖ / ‖X_i − X_j‖``. Values only, so it serves the models with and without
    gradients alike; distances are computed a block of rows at a time.

    Args:
        X: (N, D) normalised training inputs.
        Y: (N, M) training outputs.
        k: neighbours per point (at most N − 1).

    Returns:
        The (N,) weights for :func:`adaptive` (ones when there are no neighbours).
    """
    X, Y = np.asarray(X, dtype=float), np.asarray(Y, dtype=float)
    k = min(k, X.shape[0] - 1)
    if k < 1:
        return np.ones(X.shape[0])
    out = np.empty(X.shape[0])
    sq = np.sum(X * X, axis=1)
    for start in range(0, X.shape[0], 1024):  # bounded memory: 1024 rows of distances at once
        Xb = X[start : start + 1024]
        d = np.sqrt(np.maximum(sq[start : start + 1024, None] + sq[None] - 2 * Xb @ X.T, 0.0))
        rows = np.arange(d.shape[0])
        d[rows, start + rows] = np.inf
        nn = np.argpartition(d, k, axis=1)[:, :k]
        dy = np.linalg.norm(Y[start : start + d.shape[0], None] - Y[nn], axis=-1)
        out[start : start + d.shape[0]] = np.mean(dy / d[rows[:, None], nn], axis=1)
    return out


def kdtree(X: Float[ArrayLike, "N D"], n_bins: int) -> Partition:
    """Balanced median splits into ``n_bins`` leaves (any count, not only powers of two).

    Each node cuts the input of largest spread among its points, at the quantile that gives
    its two children bin counts in proportion; ties at the cut go left, as :meth:`lookup` does.

    Args:
        X: (N, D) training inputs.
        n_bins: the number of leaves, at most N.

    Returns:
        The tree, scheme ``kdtree``.

    Raises:
        ValueError: if ``X`` is not (N, D), ``n_bins`` is not in ``[1, N]``, or repeated inputs
            leave a node that cannot be split.
    """
    X = _check(X, n_bins)
    nodes: list[list] = []

    def build(idx: np.ndarray, k: int, level: int, first: int) -> tuple[int, int]:
        """Split ``idx`` into ``k`` leaves numbered from ``first`` (left subtree first);
        returns the subtree's reference (node index, or ``-(bin + 1)`` for a leaf) and its
        deepest level."""
        if k == 1:
            return -(first + 1), level
        spread = X[idx].max(0) - X[idx].min(0)
        d = int(np.argmax(spread))
        order = idx[np.argsort(X[idx, d], kind="stable")]
        k_left = k // 2
        m = (len(order) * k_left) // k
        cut = float(X[order[m - 1], d])
        me = len(nodes)
        nodes.append([d, cut, 0, 0])
        # Ties at the cut all go left (x <= cut), keeping lookup and assignment identical.
        go_left = X[idx, d] <= cut
        if go_left.all() or not go_left.any():
            raise ValueError(f"cannot split {len(idx)} points into {k} bins: repeated inputs")
        nodes[me][2], deep_l = build(idx[go_left], k_left, level + 1, first)
        nodes[me][3], deep_r = build(idx[~go_left], k - k_left, level + 1, first + k_left)
        return me, max(deep_l, deep_r)

    _, depth = build(np.arange(X.shape[0]), n_bins, 0, 0)
    return _tree([tuple(n) for n in nodes], n_bins, depth, "kdtree")


def build(X: Float[ArrayLike, "N D"], scheme: str, n_bins: int, **kw: Any) -> Partition:
    """The partition of ``scheme``: :func:`slab`, :func:`kdtree` or :func:`adaptive`.

    Args:
        X: (N, D) training inputs.
        scheme: one of :data:`SCHEMES`.
        n_bins: the number of bins, at most N.
        **kw: the scheme's options: ``dim`` for ``slab`` and ``adaptive``, ``weights`` (needed)
            for ``adaptive``; none for ``kdtree``.

    Returns:
        The partition.

    Raises:
        ValueError: for an unknown scheme (listing the valid ones), options given to
            ``kdtree``, or what the scheme itself rejects.
    """
    if scheme == "slab":
        return slab(X, n_bins, **kw)
    if scheme == "adaptive":
        return adaptive(X, n_bins, **kw)
    if scheme == "kdtree":
        if kw:
            raise ValueError(f"kdtree takes no options, got {sorted(kw)}")
        return kdtree(X, n_bins)
    raise ValueError(f"unknown partition scheme {scheme!r}; valid: {list(SCHEMES)}")


@jax.jit
def _max_correlation(
    A: Float[Array, "N D"], B: Float[Array, "K D"], lengthscale: Float[Array, "*L"]
) -> Float[Array, " N"]:
    """Largest correlation of each row of ``A`` with any row of ``B``."""
    return jnp.max(kernels.correlation(A, B, lengthscale), axis=1)


@dataclass(frozen=True)
class NearSets:
    """Per bin: anchor and near point indices (sorted), the near fraction, and the smallest
    correlation admitted (the effective ``ε`` when a budget is used)."""

    anchors: tuple[np.ndarray, ...]
    near: tuple[np.ndarray, ...]
    fraction: np.ndarray
    epsilon: np.ndarray

    @property
    def n_bins(self) -> int:
        return len(self.near)


def near_sets(
    X: Float[ArrayLike, "N D"],
    partition: Partition,
    lengthscale: Float[ArrayLike, "*L"],
    *,
    epsilon: float | None = None,
    budget: float | None = None,
    points: int | None = None,
    chunk: int = 2048,
) -> NearSets:
    """Near set of every bin, by a correlation threshold, a fraction or a count of points.

    The correlation of a point with a bin is its largest ``k(x, a)/σ`` over the bin's anchors
    (its training points). Anchors are always near, even beyond a budget. Exactly one of
    ``epsilon``, ``budget`` and ``points`` must be given: with long lengthscales a fixed ``ε``
    makes nearly every point near, which a budget avoids.

    Args:
        X: (N, D) normalised training inputs.
        partition: the bins.
        lengthscale: the kernel lengthscale l (isotropic or per input).
        epsilon: correlation threshold ``ε`` in [0, 1): the points above it are near.
        budget: fraction in (0, 1]: the ``⌈budget·N⌉`` most correlated points are near.
        points: a positive count: that many most correlated points are near, whatever N.
        chunk: training points per block of the correlation computation.

    Returns:
        Per bin, its anchors, its near points (sorted), the near fraction and the smallest
        correlation admitted (the effective ``ε`` under a budget).

    Raises:
        ValueError: unless exactly one of ``epsilon``, ``budget`` and ``points`` is given
            and in range, or if a bin holds no training point.
    """
    if sum(v is not None for v in (epsilon, budget, points)) != 1:
        raise ValueError(
            "give exactly one of epsilon (a correlation threshold), budget (a fraction) "
            "and points (a count)"
        )
    if epsilon is not None and not 0 <= epsilon < 1:
        raise ValueError(f"epsilon must be in [0, 1), got {epsilon}")
    if budget is not None and not 0 < budget <= 1:
        raise ValueError(f"budget must be a fraction in (0, 1], got {budget}")
    if points is not None and (isinstance(points, bool) or int(points) != points or points < 1):
        raise ValueError(f"points must be a positive integer, got {points!r}")
    X = np.asarray(X, dtype=float)
    n = X.shape[0]
    bins = np.asarray(partition.lookup_batch(X))
    ls = jnp.asarray(lengthscale, dtype=float)
    anchors, near, frac, eps = [], [], [], []
    for b in range(partition.n_bins):
        a = np.flatnonzero(bins == b)
        if a.size == 0:
            raise ValueError(f"bin {b} holds no training point; use fewer bins")
        corr = np.empty(n)
        for s in range(0, n, chunk):
            corr[s : s + chunk] = np.asarray(
                _max_correlation(_host.asarray(X[s : s + chunk]), _host.asarray(X[a]), ls)
            )
        corr[a] = np.inf  # anchors first, whatever the rounding
        if epsilon is not None:
            idx = np.flatnonzero(corr > epsilon)
        else:
            want = math.ceil(budget * n) if budget is not None else min(int(points), n)
            k = max(want, a.size)
            idx = np.argsort(-corr, kind="stable")[:k]
        idx = np.sort(idx)
        finite = corr[idx][np.isfinite(corr[idx])]
        anchors.append(a)
        near.append(idx)
        frac.append(idx.size / n)
        eps.append(float(finite.min()) if finite.size else 1.0)
    return NearSets(tuple(anchors), tuple(near), np.array(frac), np.array(eps))


def far_correlation(
    X: Float[ArrayLike, "N D"],
    near: NearSets,
    lengthscale: Float[ArrayLike, "*L"],
    *,
    chunk: int = 2048,
) -> np.ndarray:
    """Each training input's largest kernel correlation ``k(x, x_f)/σ`` with its bin's far set.

    Each input is taken as a query in its own bin. The Schur forms (and any model that drops
    the far set) assume ``k_qf ≈ 0``; this is the size of what they drop, at the inputs the
    model was trained on.

    Args:
        X: (N, D) normalised training inputs.
        near: the near sets (:func:`near_sets`).
        lengthscale: the kernel lengthscale l.
        chunk: far points per block of the correlation computation.

    Returns:
        The (N,) correlations, 0 where the bin's far set is empty.
    """
    X = np.asarray(X, dtype=float)
    n = X.shape[0]
    ls = jnp.asarray(lengthscale, dtype=float)
    out = np.zeros(n)
    for a, nb in zip(near.anchors, near.near, strict=True):
        far = np.setdiff1d(np.arange(n), nb, assume_unique=True)
        if far.size == 0:
            continue
        best = np.zeros(a.size)
        for s in range(0, far.size, chunk):
            f = jnp.asarray(X[far[s : s + chunk]])
            best = np.maximum(best, np.asarray(_max_correlation(jnp.asarray(X[a]), f, ls)))
        out[a] = best
    return out


def boundary_pairs(
    partition: Partition,
    samples: Float[ArrayLike, "S D"],
    *,
    per_face: int = 50,
    delta: float = 1e-7,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of inputs straddling the bins' boundaries, to test continuity across bins.

    For every finite upper face ``x_d = hi`` of every bin box, a random subset of the
    ``samples`` is moved into the box and onto the face; the pair is ``x_d = hi − delta`` (in
    the bin) and ``x_d = hi + delta`` (in its neighbour). A model continuous across bins gives
    nearly equal predictions for the two members of a pair. Pairs whose members land in one
    bin are dropped.

    Args:
        partition: the bins.
        samples: (S, D) inputs to move onto the faces (normally the normalised test inputs).
        per_face: at most this many samples per face.
        delta: half the gap between a pair's members, along the face's input.
        seed: seed of the random choice of samples.

    Returns:
        ``(inside, outside)``, each (K, D): row ``k`` of each is one pair.

    Raises:
        ValueError: if ``samples`` is not a non-empty (S, D) array.
    """
    samples = np.asarray(samples, dtype=float)
    if samples.ndim != 2 or samples.shape[0] == 0:
        raise ValueError(f"samples must be a non-empty (S, D) array, got shape {samples.shape}")
    d = samples.shape[1]
    lo, hi = partition.boxes(d)
    rng = np.random.default_rng(seed)
    inside, outside = [], []
    for b in range(partition.n_bins):
        for dim in np.flatnonzero(np.isfinite(hi[b])):
            pick = rng.permutation(samples.shape[0])[:per_face]
            # Strictly inside the box along the other inputs (lower bounds are open).
            x = np.clip(samples[pick], np.nextafter(lo[b], np.inf), hi[b])
            a, c = x.copy(), x.copy()
            a[:, dim] = hi[b, dim] - delta
            c[:, dim] = hi[b, dim] + delta
            inside.append(a)
            outside.append(c)
    if not inside:
        return np.zeros((0, d)), np.zeros((0, d))
    A, C = np.concatenate(inside), np.concatenate(outside)
    ba = np.asarray(partition.lookup_batch(A))
    bc = np.asarray(partition.lookup_batch(C))
    keep = ba != bc  # both members in one bin would not test a boundary
    return A[keep], C[keep]
