"""The partitioned predictor: every query answered from its own bin's near set.

One class serves GP-S, GP-G-S, GP-G-S-Schur, the hybrid's variance and GP-G-PIC: what
differs between them is only how each bin's mean coefficients and variance factor were
computed (:mod:`gpg.gp.local`, :mod:`gpg.gp.schur`, :mod:`gpg.gp.pic`), each handing over one
:class:`BinFactors` per bin; :func:`pack_points` stores them padded and stacked so that one
jitted query reads one bin. This module owns that per-bin format, the row order of a bin
(:func:`near_rows`) and the padding of bins to one width (:func:`pad_units`) that both device
precomputes use.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Float, Int

from gpg import _host
from gpg._precision import highest
from gpg.gp import kernels, partition
from gpg.gp.gram import to_bases
from gpg.gp.hyper import Hyper
from gpg.gp.mean import output_scale
from gpg.gp.predictor import Predictor, plain
from gpg.linalg.tri import BlockTriangular

__all__ = [
    "BinFactors",
    "BinnedGP",
    "METHODS",
    "by_bin",
    "near_rows",
    "pack",
    "pack_points",
]

FAR = 1e3  # padding position: its kernel with any query in [-1, 1]^D underflows to 0
FACTOR_BANDS = 8  # row bands per variance factor (gpg.linalg.tri): (1 + 1/8)/2 of the dense bytes


@dataclass(frozen=True)
class BinFactors:
    """One bin, over its near rows (:func:`near_rows`, bin-local dimension-major order): mean
    coefficients ``coef`` (r, M) and variance factor ``factor`` (r, r), triangular (``lower`` or
    upper). An upper factor may be dense in its first ``dense_rows`` rows (PIC's inducing
    block, :mod:`gpg.gp.pic`); below them it is triangular."""

    coef: np.ndarray
    factor: np.ndarray
    lower: bool
    dense_rows: int = 0
    # ``Ȳ_bᵀ K_b⁻¹ Ȳ_b`` (M,) over the bin's own rows and their number: pooled over bins they
    # give the per-output signal scale (:func:`gpg.gp.mean.output_scale`).
    yty: np.ndarray | None = None
    n_rows: int = 0


def near_rows(near: np.ndarray, n_points: int, n_grad: int) -> np.ndarray:
    """Rows of ``K̄`` for near points ``near``: value rows, then each gradient dimension's rows.

    ``K̄`` is dimension-major (:mod:`gpg.gp.kernels`): point ``i``'s value row is ``i`` and its
    gradient row along the ``k``-th gradient dimension is ``k·N + i``.

    Args:
        near: (p,) indices of the points, in the order their rows are wanted.
        n_points: N, the number of training points behind ``K̄``.
        n_grad: G, the number of gradient dimensions (rows per point beyond its value).

    Returns:
        The (p(1+G),) row indices: the value rows of ``near``, then its rows of each gradient
        dimension in turn.
    """
    return np.concatenate([near + k * n_points for k in range(1 + n_grad)])


def bin_yty(Ybar_n: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """``Ȳ_nᵀ c`` per output: a bin's share of the output scale (:class:`BinFactors`)."""
    return np.sum(Ybar_n * coef, axis=0)


def pad_units(
    X: np.ndarray, Ybar: np.ndarray, sets: Sequence[np.ndarray], n_grad: int
) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """Every point set ``X[s]`` and its target rows padded to the largest set with points at
    :data:`FAR`, whose kernel with every real point underflows to zero: a padded ``K̄`` is block
    diagonal, so any factorisation restricted to the real rows is the real one, and every bin
    runs the same compiled program (bit-identical for any device count, :mod:`gpg.parallel`).
    Returns the units ``(X_b, Ȳ_b)`` and, per set, its real rows in the padded order."""
    n, d = X.shape
    width = max(s.size for s in sets)
    units, pos = [], []
    for s in sets:
        Xp = np.full((width, d), FAR)
        Xp[: s.size] = X[s]
        pos.append(near_rows(np.arange(s.size), width, n_grad))
        Yp = np.zeros((width * (1 + n_grad), Ybar.shape[1]))
        Yp[pos[-1]] = Ybar[near_rows(s, n, n_grad)]
        units.append((Xp, Yp))
    return units, pos


class BinnedGP(Predictor):
    """Partitioned predictor: each query is answered from its bin's near set only.

    ``Xn`` (B, P, D) near points per bin, padded to P with far-away points; ``coef`` (B, M, Rp)
    mean coefficients and ``factor`` one triangular variance factor per bin (row bands, see
    :mod:`gpg.linalg.tri`) over the bin's rows (``Rp = P(1+G)``, value rows then gradient rows),
    zero on padding; ``noise`` the value-noise variance ``ν²`` of an observation. The mean
    computes the query's kernel row against its own bin only, then multiplies it by every bin's
    small coefficient block and keeps its own: under ``vmap`` that is one dense product instead
    of a per-query gather of coefficients, which the CPU serves several times faster.

    The "near set" of a bin is whatever the bin's predictor conditions on: the near training
    points (``gps_*``, ``gpgs``, ``gpgs_schur``, the hybrid's variance), or, for ``gpg_pic``,
    the ``shared`` inducing inputs (U, D), whose rows come first in every bin, followed by the
    bin's own points.
    """

    partition: partition.Partition
    shared: Float[Array, "U D"] | None
    Xn: Float[Array, "B P D"]
    coef: Float[Array, "B M Rp"]
    factor: tuple[BlockTriangular, ...]
    variance: Float[Array, ""]
    lengthscale: Float[Array, "*L"]
    noise: Float[Array, ""]
    output_scale: Float[Array, " M"]
    n_near: Int[Array, " B"]
    grad_dims: tuple[int, ...] = eqx.field(static=True)
    # (B, P, G, G): the directions of the near points' gradient rows
    # (gpg.gp.gram.row_directions; zero on padding), None for derivatives along the inputs
    bases: Float[Array, "B P G G"] | None = None

    @property
    def n_inputs(self) -> int:
        return self.Xn.shape[2]

    @property
    def n_outputs(self) -> int:
        return self.coef.shape[1]

    def with_output_scale(self, scale: Float[ArrayLike, " M"]) -> BinnedGP:
        """This model with the per-output variance scale replaced.

        Args:
            scale: (M,) the new per-output scale of the predictive variance.

        Returns:
            A copy sharing every other array with this one.
        """
        return eqx.tree_at(lambda m: m.output_scale, self, jnp.asarray(scale))

    def describe(self) -> dict[str, Any]:
        """The hyperparameters and the partition, as plain values for a checkpoint's metadata.

        Returns:
            ``hyperparameters`` (σ ``variance``, ``lengthscale`` l, ``noise`` ν²) and
            ``partition`` (``scheme``, ``n_bins`` and each bin's number of ``near_points``).
        """
        return {
            "hyperparameters": {
                "variance": plain(self.variance),
                "lengthscale": plain(self.lengthscale),
                "noise": plain(self.noise),
            },
            "partition": {
                "scheme": self.partition.scheme,
                "n_bins": self.partition.n_bins,
                "near_points": plain(self.n_near),
            },
        }

    def kernel_row(self, x: Float[Array, " D"], b: Int[Array, ""]) -> Float[Array, " Rp"]:
        """``k̄(x, X_n)`` against bin ``b``'s near set: values, then gradient rows.

        The padding points sit at :data:`FAR`, so their entries underflow to zero; with
        ``bases`` the gradient rows are turned to the stored directions, and with ``shared``
        (PIC) the inducing rows come first.

        Args:
            x: (D,) one normalised query.
            b: the bin whose near set the row is taken against (the query's own, normally).

        Returns:
            The (Rp,) kernel row in the bin's row order (zeros on padding).
        """
        Xb = jax.lax.dynamic_index_in_dim(self.Xn, b, keepdims=False)
        row = kernels.query_rows(x[None], Xb, self.variance, self.lengthscale, self.grad_dims)[0]
        if self.bases is not None:
            Bb = jax.lax.dynamic_index_in_dim(self.bases, b, keepdims=False)
            row = to_bases(row, Bb, Xb.shape[0])
        if self.shared is None:
            return row
        k_u = kernels.query_rows(
            x[None], self.shared, self.variance, self.lengthscale, self.grad_dims
        )[0]
        return jnp.concatenate([k_u, row])

    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """Posterior mean at one query, from its own bin's coefficients: ``k̄_qnᵀ c_b``.

        Args:
            x: (D,) one normalised query.

        Returns:
            The (M,) posterior mean.
        """
        b = self.partition.lookup(x)
        return binned_contract(self.coef, b, self.kernel_row(x, b))

    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        """Posterior mean and latent variance at one query, both from its own bin.

        One kernel row serves both: the mean ``k̄_qnᵀ c_b`` and the variance
        ``σ − ‖F_b k̄_qn‖²``.

        Args:
            x: (D,) one normalised query.

        Returns:
            The (M,) posterior mean and the scalar latent variance (unclamped).
        """
        b = self.partition.lookup(x)
        k = self.kernel_row(x, b)
        quad = binned_quadratic_form(self.factor, b, k)
        return binned_contract(self.coef, b, k), self.variance - quad

    def mean_view(self) -> BinnedGP:
        """This model without the variance factors (the mean reads the coefficients only).

        Returns:
            A copy whose ``factor`` is empty: its mean equals this one's, its variance is not
            to be used.
        """
        return eqx.tree_at(lambda m: m.factor, self, ())

    def variance_one(self, x: Float[Array, " D"]) -> Float[Array, ""]:
        """Latent variance alone (unclamped): ``σ − ‖F_b k̄_qn‖²``.

        Args:
            x: (D,) one normalised query.

        Returns:
            The scalar latent variance from the query's own bin (the hybrid's variance).
        """
        b = self.partition.lookup(x)
        return self.variance - binned_quadratic_form(self.factor, b, self.kernel_row(x, b))


# One query reads one bin's arrays; a batch reads every bin's arrays once. JAX would turn the
# one-query code into a per-query gather (coefficients) or a select with every bin's factor
# broadcast to the batch (variance), so both get a batch rule of their own (custom_vmap):
# one dense product per bin for all queries, each query keeping its own bin's result.
# custom_vmap has no reverse mode and its forward mode breaks on batched tangents, so each
# function is wrapped in a custom_jvp whose tangent is written in plain, linear JAX (every
# bin's product, then the query's own): JAX transposes that for reverse mode and batches it
# for jacfwd/vmap, while an undifferentiated call keeps the custom batch rule and its speed.


def _batched_args(axis_size, in_batched, b, k):
    bins = b if in_batched[1] else jnp.broadcast_to(b, (axis_size,))
    K = k if in_batched[2] else jnp.broadcast_to(k, (axis_size,) + k.shape)
    return bins, K


@jax.custom_batching.custom_vmap
@highest
def _contract(coef: Float[Array, "B M R"], b: Int[Array, ""], k: Float[Array, " R"]):
    return jax.lax.dynamic_index_in_dim(coef, b, keepdims=False) @ k


@_contract.def_vmap
@highest
def _contract_batched(axis_size, in_batched, coef, b, k):
    bins, K = _batched_args(axis_size, in_batched, b, k)
    if in_batched[0]:  # a batch of models: one pair at a time
        return jax.lax.map(lambda a: _contract(*a), (coef, bins, K)), True
    every = jnp.einsum("qr,bmr->qbm", K, coef)  # all bins for all queries: one product
    return jnp.take_along_axis(every, bins[:, None, None], axis=1)[:, 0], True


@jax.custom_jvp
def binned_contract(
    coef: Float[Array, "B M R"], b: Int[Array, ""], k: Float[Array, " R"]
) -> Float[Array, " M"]:
    """``C_b k``: one bin's mean coefficients applied to a kernel row."""
    return _contract(coef, b, k)


@highest
def _every_bin(coef, k):
    """``C_i k`` for every bin ``i`` (B, M): linear in both, batches into one product."""
    return jnp.einsum("bmr,r->bm", coef, k)


@highest
def _binned_contract_jvp(primals, tangents):
    coef, b, k = primals
    dcoef, _, dk = tangents
    out = binned_contract(coef, b, k)
    tangent = jnp.zeros_like(out)
    if not isinstance(dk, SymbolicZero):
        tangent = tangent + _every_bin(coef, dk)[b]
    if not isinstance(dcoef, SymbolicZero):
        tangent = tangent + _every_bin(dcoef, k)[b]
    return out, tangent


binned_contract.defjvp(_binned_contract_jvp, symbolic_zeros=True)


@jax.custom_batching.custom_vmap
@highest
def _quadratic_form(factor: tuple[BlockTriangular, ...], b: Int[Array, ""], k: Float[Array, " R"]):
    return jnp.sum(jnp.square(_apply(factor, b, k))).astype(k.dtype)


@_quadratic_form.def_vmap
@highest
def _quadratic_form_batched(axis_size, in_batched, factor, b, k):
    bins, K = _batched_args(axis_size, in_batched, b, k)
    if any(jax.tree.leaves(in_batched[0])):
        return jax.lax.map(lambda a: _quadratic_form(*a), (factor, bins, K)), True
    (q,) = by_bin(factor, bins, K, with_grad=False)
    return q, True


@jax.custom_batching.custom_vmap
@highest
def _quadratic_form_grad(factor: tuple[BlockTriangular, ...], b: Int[Array, ""], k):
    """``‖F_b k‖²`` and its gradient in ``k``, ``2 F_bᵀ F_b k``."""
    branches = [lambda kk, f=f: f.rmatvec(f.matvec(kk)) for f in factor]
    v = _apply(factor, b, k)
    g = jax.lax.switch(b, branches, k)
    return jnp.sum(jnp.square(v)).astype(k.dtype), (2.0 * g).astype(k.dtype)


@_quadratic_form_grad.def_vmap
@highest
def _quadratic_form_grad_batched(axis_size, in_batched, factor, b, k):
    bins, K = _batched_args(axis_size, in_batched, b, k)
    if any(jax.tree.leaves(in_batched[0])):
        out = jax.lax.map(lambda a: _quadratic_form_grad(*a), (factor, bins, K))
        return out, (True, True)
    return by_bin(factor, bins, K, with_grad=True), (True, True)


# The executions of by_bin and their largest tile. On a CPU a loop over the tiles, each
# multiplied by its own bin's bands (lax.switch), keeps one tile's product in cache, and tiles
# of 64 rows were fastest (experiments.bench). On a GPU a loop launches a dozen kernels per
# tile; there every tile's bands are gathered instead and one batched product per band runs
# over all tiles (the gathered copies cost memory traffic, not arithmetic). A batch of a few
# queries per bin (a Jacobian's columns, a handful of states) is cheaper still as every bin's
# product for every query: no sort, no loop, B times a small product.
METHODS = ("every", "loop", "gather")
MAX_TILE = {"loop": 64, "gather": 1024}  # queries per tile, at most
FEW_PER_BIN = 4  # at most this many queries per bin on average: "every"


def default_method(n_queries: int, n_bins: int) -> str:
    """``every`` for a batch of at most :data:`FEW_PER_BIN` queries per bin, else ``loop`` on
    the CPU backend and ``gather`` on an accelerator (:data:`METHODS`)."""
    if n_queries <= FEW_PER_BIN * n_bins:
        return "every"
    return "loop" if jax.default_backend() == "cpu" else "gather"


def tile_rows(n_queries: int, n_bins: int, method: str = "loop") -> int:
    """Queries per tile of :func:`by_bin`: half a bin's share of the batch, so that the tiles
    padded at the end of each bin's run add at most a half (a quarter on average) to the
    work, and at most ``MAX_TILE[method]``."""
    return int(min(MAX_TILE[method], max(1, n_queries // (2 * n_bins))))


@highest
def by_bin(
    factor: tuple[BlockTriangular, ...],
    bins: Int[Array, " Q"],
    K: Float[Array, "Q R"],
    *,
    with_grad: bool,
    tile: int | None = None,
    method: str | None = None,
) -> tuple[Float[Array, " Q"]] | tuple[Float[Array, " Q"], Float[Array, "Q R"]]:
    """``‖F_b k_q‖²`` for a batch of kernel rows, each with its own bin, by one product per bin.

    The queries are sorted by bin and each bin's run is padded to whole tiles, so every tile
    belongs to one bin and is multiplied by its own bin's factor. At most ``Q/tile + B`` tiles,
    so the work is that of the queries' own products plus at most one padded tile per bin,
    where reading every bin's factor for every query costs ``B`` times the work (what a plain
    ``vmap`` of the one-query code does).

    Args:
        factor: one triangular variance factor ``F_b`` per bin (row bands), all of one width.
        bins: (Q,) the bin of each query.
        K: (Q, R) the queries' kernel rows against their own bins' rows.
        with_grad: also return the gradients ``2 F_bᵀ F_b k_q`` of the forms in ``k_q``.
        tile: queries per tile; default :func:`tile_rows`.
        method: ``loop`` (a ``lax.map`` over the tiles, a ``lax.switch`` reading only that
            bin's bands), ``gather`` (the bands of every tile's bin gathered, one batched
            product per band) or ``every`` (every query times every bin's factor, each keeping
            its own: for a few queries per bin); default :func:`default_method`.

    Returns:
        ``(q,)`` with the (Q,) forms ``‖F_b k_q‖²``, or with ``with_grad`` ``(q, G)`` with the
        (Q, R) gradients as well.

    Raises:
        ValueError: if ``method`` is not one of :data:`METHODS`.
    """
    q_count, width = K.shape
    n_bins = len(factor)
    method = default_method(q_count, n_bins) if method is None else method
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "every":
        return _every_bin_terms(factor, bins, K, with_grad)
    tile = tile_rows(q_count, n_bins, method) if tile is None else int(tile)
    n_tiles = (q_count + n_bins * (tile - 1)) // tile  # Σ_b ⌈c_b / tile⌉ for any counts c_b
    order = jnp.argsort(bins, stable=True)
    sorted_bins = bins[order]
    counts = jnp.bincount(bins, length=n_bins)
    bin_tiles = (counts + tile - 1) // tile
    tile_end = jnp.cumsum(bin_tiles)
    first_tile = tile_end - bin_tiles
    first_query = jnp.cumsum(counts) - counts
    # Sorted query j of bin b sits at row (first tile of b)·tile + (its rank within b).
    slot = first_tile[sorted_bins] * tile + jnp.arange(q_count) - first_query[sorted_bins]
    padded = jnp.zeros((n_tiles * tile, width), K.dtype).at[slot].set(K[order])
    tiles = padded.reshape(n_tiles, tile, width)
    # Tiles past the last bin's (empty) take the last bin: zero rows, never read back.
    tile_bin = jnp.minimum(
        jnp.searchsorted(tile_end, jnp.arange(n_tiles), side="right"), n_bins - 1
    )
    if method == "loop":

        def one_tile(args):
            Kt, b = args
            branches = [lambda kt, f=f: _tile_terms(f, kt, with_grad) for f in factor]
            return jax.lax.switch(b, branches, Kt)

        out = jax.lax.map(one_tile, (tiles, tile_bin))
    else:
        out = _gathered_terms(factor, tiles, tile_bin, with_grad)
    back = slot[jnp.argsort(order)]  # each query's row in the padded order
    return tuple(o.reshape(n_tiles * tile, *o.shape[2:])[back] for o in out)


def _every_bin_terms(factor: tuple[BlockTriangular, ...], bins, K, with_grad: bool):
    q = jnp.zeros(K.shape[0], dtype=K.dtype)
    G = jnp.zeros(K.shape, dtype=K.dtype) if with_grad else None
    for i, f in enumerate(factor):
        here = bins == i
        terms = _tile_terms(f, K, with_grad)
        q = jnp.where(here, terms[0], q)
        if with_grad:
            G = jnp.where(here[:, None], terms[1], G)
    return (q,) if not with_grad else (q, G)


def _tile_terms(f: BlockTriangular, Kt, with_grad: bool):
    V = f.rmatmul(Kt)
    q = jnp.sum(V * V, axis=1).astype(Kt.dtype)
    if not with_grad:
        return (q,)
    return q, (2.0 * f.lmatmul(V)).astype(Kt.dtype)


def _gathered_terms(factor: tuple[BlockTriangular, ...], tiles, tile_bin, with_grad: bool):
    """:func:`_tile_terms` of every tile at once: band ``j`` of each tile's bin gathered
    (tiles, rows_j, cols_j), one batched product per band. Every bin's bands have the same
    shapes (the bins are padded to one width, :func:`pack_points`)."""
    first = factor[0]
    dt = first.dtype
    Kt = tiles.astype(dt)
    n = first.n
    # Band j of every tile's bin (tiles, rows_j, cols_j), gathered once for both products.
    bands = [jnp.stack([f.blocks[j] for f in factor])[tile_bin] for j in range(len(first.blocks))]
    Vs = []
    for band in bands:
        cols = band.shape[2]
        part = Kt[:, :, :cols] if first.lower else Kt[:, :, n - cols :]
        Vs.append(jnp.einsum("tqc,trc->tqr", part, band))
    V = jnp.concatenate(Vs, axis=2)
    q = jnp.sum(V * V, axis=2).astype(tiles.dtype)
    if not with_grad:
        return (q,)
    G = jnp.zeros(Kt.shape, dt)
    a = 0
    for band in bands:
        rows, cols = band.shape[1], band.shape[2]
        part = jnp.einsum("tqr,trc->tqc", V[:, :, a : a + rows], band)
        pad = (0, n - cols) if first.lower else (n - cols, 0)
        G = G + jnp.pad(part, ((0, 0), (0, 0), pad))
        a += rows
    return q, (2.0 * G).astype(tiles.dtype)


def _apply(factor: tuple[BlockTriangular, ...], b, k):
    """``F_b k`` (in the factor's dtype): a ``lax.switch`` reads bin ``b``'s bands only."""
    branches = [lambda kk, f=f: f.matvec(kk) for f in factor]
    return jax.lax.switch(b, branches, k)


@jax.custom_jvp
def binned_quadratic_form(
    factor: tuple[BlockTriangular, ...], b: Int[Array, ""], k: Float[Array, " R"]
) -> Float[Array, ""]:
    """``‖F_b k‖²`` with bin ``b``'s factor."""
    return _quadratic_form(factor, b, k)


@highest
def _binned_quadratic_form_jvp(primals, tangents):
    # The tangent in k is g·dk with the gradient g = 2 F_bᵀ F_b k computed beside the value
    # (batched per bin like the value): a dot product, which JAX transposes and batches at the
    # cost of one product, where a tangent through the per-bin switch batched into every bin.
    factor, b, k = primals
    dfactor, _, dk = tangents
    leaves = jax.tree.leaves(dfactor, is_leaf=lambda t: isinstance(t, SymbolicZero))
    factor_moves = not all(isinstance(t, SymbolicZero) for t in leaves)
    if isinstance(dk, SymbolicZero) and not factor_moves:
        out = binned_quadratic_form(factor, b, k)
        return out, jnp.zeros_like(out)
    out, g = _quadratic_form_grad(factor, b, k)
    tangent = jnp.zeros_like(out) if isinstance(dk, SymbolicZero) else jnp.dot(g, dk)
    if factor_moves:  # derivatives in the stored factor itself (rare): plain JAX
        dense = jax.tree.map(
            lambda t, p: jnp.zeros_like(p) if isinstance(t, SymbolicZero) else t,
            dfactor,
            factor,
            is_leaf=lambda t: isinstance(t, SymbolicZero),
        )
        v = _apply(factor, b, k)
        tangent = tangent + (2.0 * jnp.sum(v * _apply(dense, b, k))).astype(k.dtype)
    return out, tangent


binned_quadratic_form.defjvp(_binned_quadratic_form_jvp, symbolic_zeros=True)


def pack_points(
    points: Sequence[np.ndarray],
    factors: Iterable[BinFactors],
    part: partition.Partition,
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    dtype: str = "float64",
    shared: np.ndarray | None = None,
    scale: np.ndarray | None = None,
    bases: Sequence[np.ndarray] | None = None,
) -> BinnedGP:
    """A :class:`BinnedGP` from each bin's points and factors, padded and stacked.

    Each bin is padded to the widest with points at :data:`FAR`; the local-to-padded row map
    is increasing, so a triangular factor stays triangular. Each bin's factor is stored in
    bands before the next one is drawn, so with a generator of ``factors`` the dense factors
    are never all held at once.

    Args:
        points: per bin ``b``, the (p_b, D) points it conditions on.
        factors: per bin, its :class:`BinFactors` (rows dimension-major over its points, after
            the ``shared`` rows); a generator is consumed one bin at a time.
        part: the partition that assigns queries to the bins.
        hyper: the hyperparameters (σ, l, ν²) the factors were computed with.
        grad_dims: the input dimensions that carry gradient rows.
        dtype: storage type of the variance factors.
        shared: (U, D) points whose rows come first in every bin (PIC's inducing inputs).
        scale: (M,) per-output variance scale; by default pooled from the bins' own fits
            (ones where a route does not report them).
        bases: per bin, the (p_b, G, G) directions of its points' gradient rows
            (:func:`gpg.gp.gram.row_directions`); None for derivatives along the inputs.

    Returns:
        The partitioned predictor.
    """
    B, D = len(points), points[0].shape[1]
    g = len(grad_dims)
    P = max(p.shape[0] for p in points)
    up = 0 if shared is None else shared.shape[0] * (1 + g)
    Rp = up + P * (1 + g)
    Xn = np.full((B, P, D), FAR)
    coefs, bands, ytys, n_rows = [], [], [], 0
    for b, (pts, f) in enumerate(zip(points, factors, strict=True)):
        p = pts.shape[0]
        Xn[b, :p] = pts
        # Local row -> padded row is increasing, so a triangular factor stays triangular.
        pos = np.concatenate([np.arange(up), up + near_rows(np.arange(p), P, g)])
        coef = np.zeros((f.coef.shape[1], Rp))
        coef[:, pos] = f.coef.T
        coefs.append(coef)
        if p == P:  # no padding: the factor as it is
            dense = np.asarray(f.factor, dtype=dtype)
        else:
            dense = np.zeros((Rp, Rp), dtype=dtype)
            dense[np.ix_(pos, pos)] = f.factor
        bands.append(
            BlockTriangular.from_dense(
                dense, lower=f.lower, n_blocks=FACTOR_BANDS, dense_rows=f.dense_rows
            )
        )
        ytys.append(f.yty)
        n_rows += f.n_rows
        del dense, f
    if scale is None:
        if all(y is not None for y in ytys):
            scale = output_scale(np.sum(ytys, axis=0), n_rows)
        else:
            scale = np.ones(coefs[0].shape[0])
    return BinnedGP(
        partition=part,
        shared=None if shared is None else jnp.asarray(shared),
        Xn=_host.asarray(Xn),
        coef=_host.asarray(np.stack(coefs)),
        factor=tuple(bands),
        variance=hyper.variance,
        lengthscale=hyper.lengthscale,
        noise=hyper.noise,
        output_scale=jnp.asarray(scale, dtype=float),
        n_near=jnp.asarray([p.shape[0] for p in points]),
        grad_dims=grad_dims,
        bases=None if bases is None else jnp.asarray(_pad_bases(bases, P, g)),
    )


def _pad_bases(bases: Sequence[np.ndarray], P: int, g: int) -> np.ndarray:
    out = np.zeros((len(bases), P, g, g))
    for b, B in enumerate(bases):
        out[b, : B.shape[0]] = B
    return out


def pack(
    X: np.ndarray,
    factors: list[BinFactors],
    near: partition.NearSets,
    part: partition.Partition,
    hyper: Hyper,
    grad_dims: tuple[int, ...],
    *,
    dtype: str = "float64",
    scale: np.ndarray | None = None,
    bases: np.ndarray | None = None,
) -> BinnedGP:
    """:func:`pack_points` for near sets of training points ``X[near.near[b]]``.

    Args:
        X: (N, D) normalised training inputs.
        factors: per bin, its :class:`BinFactors` over the rows of its near set.
        near: the near sets (:func:`gpg.gp.partition.near_sets`).
        part: the partition that assigns queries to the bins.
        hyper: the hyperparameters (σ, l, ν²) the factors were computed with.
        grad_dims: the input dimensions that carry gradient rows.
        dtype: storage type of the variance factors.
        scale: (M,) per-output variance scale; by default pooled from the bins' own fits.
        bases: (N, G, G) the directions of the training points' gradient rows, if not the
            inputs'.

    Returns:
        The partitioned predictor.
    """
    points = [X[nb] for nb in near.near]
    per_bin = None if bases is None else [bases[nb] for nb in near.near]
    return pack_points(
        points, factors, part, hyper, grad_dims, dtype=dtype, scale=scale, bases=per_bin
    )
