"""Triangular matrices stored as bands of rows, for the variance term ``‖F k‖²``.

A dense ``n x n`` triangular factor wastes half its bytes on zeros, and a matrix-vector
product with it reads all of them: at the sizes of a bin (1000 rows, 1000² doubles) or of an
exact GP-G (8000 rows, 8000² doubles) that product is bound by memory. Cut into ``n_blocks``
bands of rows, each band keeps only the columns that can be non-zero (from its first row on for
an upper factor, up to its last row for a lower one), so a product reads
``(1 + 1/n_blocks)/2`` of the dense bytes. Each band is its own array: the product never
slices a larger buffer, which on the CPU would copy it first.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from gpg import _host
from gpg._precision import highest
from gpg.linalg.memory import SquareBuffer

__all__ = ["BlockTriangular", "BorderedTriangular"]


class BlockTriangular(eqx.Module):
    """Row bands of a triangular ``n x n`` matrix (``lower`` or upper).

    Build one with :meth:`from_dense`, :meth:`from_buffer` or :meth:`from_device`; the
    products read only the bands, never the zeros across the diagonal.
    """

    blocks: tuple[Float[Array, "b c"], ...]
    n: int = eqx.field(static=True)
    lower: bool = eqx.field(static=True)

    @classmethod
    def from_dense(
        cls, F: Float[ArrayLike, "n n"], *, lower: bool, n_blocks: int = 4, dense_rows: int = 0
    ) -> BlockTriangular:
        """Bands of the triangular ``F``; entries on the other side of the diagonal are dropped.

        Args:
            F: (n, n) triangular matrix, NumPy or JAX.
            lower: whether ``F`` is lower triangular (else upper).
            n_blocks: bands to cut the rows into (fewer when ``F`` has fewer rows).
            dense_rows: upper factors only: the first that many rows are one band of their
                own, kept whole, for a factor that is triangular only below them
                (:mod:`gpg.gp.pic`).

        Returns:
            The banded ``F``, each band a JAX array of its own.

        Raises:
            ValueError: if ``F`` is not square, if ``dense_rows`` is given for a lower factor,
                or if it is outside ``[0, n]``.
        """
        F = np.asarray(F)
        n = F.shape[0]
        if F.shape != (n, n):
            raise ValueError(f"F must be square, got {F.shape}")
        if dense_rows and lower:
            raise ValueError("dense_rows applies to upper factors only")
        if not 0 <= dense_rows <= n:
            raise ValueError(f"dense_rows must be in [0, {n}], got {dense_rows}")
        rest = np.linspace(dense_rows, n, min(n_blocks, max(n - dense_rows, 1)) + 1).astype(int)
        edges = np.unique(np.concatenate([[0], rest]))
        blocks = []
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            band = F[a:b, :b] if lower else F[a:b, a:]
            blocks.append(_host.asarray(band))
        return cls(blocks=tuple(blocks), n=n, lower=lower)

    @classmethod
    def from_buffer(cls, buf: SquareBuffer, *, lower: bool, n_blocks: int = 4) -> BlockTriangular:
        """Bands of the lower-triangular matrix in ``buf``, its rows given back as they are copied.

        Each band's rows are released (:meth:`gpg.linalg.memory.SquareBuffer.release_rows`)
        once JAX holds their copy, so that the dense matrix and its bands are never both held
        in full; ``buf`` is not readable afterwards.

        Args:
            buf: the (n, n) buffer holding the lower-triangular factor.
            lower: must be True (kept for the signature of :meth:`from_dense`).
            n_blocks: bands to cut the rows into.

        Returns:
            The banded factor, its bands owned by JAX.

        Raises:
            ValueError: if ``lower`` is False.
        """
        if not lower:
            raise ValueError("from_buffer handles lower-triangular matrices (rows end at the band)")
        F = buf.array
        n = F.shape[0]
        edges = np.linspace(0, n, min(n_blocks, max(n, 1)) + 1).astype(int)
        blocks = []
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            # A copy owned by JAX, made before the rows are given back (``_host.asarray``
            # copies on the host before the transfer): rows released under a pending copy
            # read as zeros (seen in practice: the last band came back partly zeroed under
            # load, and every band when the device buffer was the buffer's own rows).
            blocks.append(_host.asarray(F[a:b, :b]))
            buf.release_rows(a, b)
        return cls(blocks=tuple(blocks), n=n, lower=True)

    @classmethod
    def from_device(cls, F: Float[Array, "n n"], *, n_blocks: int = 4) -> BlockTriangular:
        """Bands of the lower-triangular JAX array ``F``, cut on the device where it lives.

        An accelerator's factor never visits the host; the caller drops ``F`` itself afterwards,
        so that only the bands stay on the device.

        Args:
            F: (n, n) lower-triangular JAX array (``L⁻¹`` from
                :func:`gpg.linalg.device.factor_solve`).
            n_blocks: bands to cut the rows into.

        Returns:
            The banded ``F``, on ``F``'s device.
        """
        n = F.shape[0]
        edges = np.linspace(0, n, min(n_blocks, max(n, 1)) + 1).astype(int)
        return cls(blocks=_bands(F, tuple(int(e) for e in edges)), n=n, lower=True)

    def _starts(self) -> list[int]:
        out, a = [], 0
        for blk in self.blocks:
            out.append(a)
            a += blk.shape[0]
        return out

    @property
    def dtype(self):
        """The storage dtype of the bands (the products' dtype)."""
        return self.blocks[0].dtype

    @eqx.filter_jit
    @highest
    def matvec(self, k: Float[Array, " n"]) -> Float[Array, " n"]:
        """``F k`` for one vector, band by band.

        Computed in the factor's storage dtype: a float32 factor reads half the bytes.

        Args:
            k: (n,) vector, e.g. the covariances ``k̄`` of a query with the training rows.

        Returns:
            The (n,) product ``F k``.
        """
        k = k.astype(self.dtype)
        parts = []
        for blk in self.blocks:
            # A lower band ends its columns at its last row, an upper one starts them at its first.
            parts.append(blk @ (k[: blk.shape[1]] if self.lower else k[self.n - blk.shape[1] :]))
        return jnp.concatenate(parts)

    @eqx.filter_jit
    @highest
    def rmatmul(self, K: Float[Array, "q n"]) -> Float[Array, "q n"]:
        """``K Fᵀ`` for a batch of rows ``K``: each row's ``F k``.

        Args:
            K: (q, n) rows, one per query.

        Returns:
            The (q, n) product, in the factor's storage dtype.
        """
        K = K.astype(self.dtype)
        parts = []
        for blk in self.blocks:
            Kp = K[:, : blk.shape[1]] if self.lower else K[:, self.n - blk.shape[1] :]
            # (B Kᵀ)ᵀ, not K Bᵀ: XLA's CPU dot transposes the big operand for the latter, far
            # slower for one row against a band.
            parts.append((blk @ Kp.T).T)
        return jnp.concatenate(parts, axis=1)

    def rmatvec(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """``Fᵀ v`` for one vector (:meth:`lmatmul` on a batch of one).

        Args:
            v: (n,) vector.

        Returns:
            The (n,) product ``Fᵀ v``, in the factor's storage dtype.
        """
        return self.lmatmul(v[None])[0]

    @eqx.filter_jit
    @highest
    def lmatmul(self, V: Float[Array, "q n"]) -> Float[Array, "q n"]:
        """``V F`` for a batch of rows ``V``: each row's ``Fᵀ v``.

        Each band's product is padded back to ``n`` columns and summed.

        Args:
            V: (q, n) rows.

        Returns:
            The (q, n) product, in the factor's storage dtype.
        """
        V = V.astype(self.dtype)
        out = jnp.zeros(V.shape, dtype=self.dtype)
        for a, blk in zip(self._starts(), self.blocks, strict=True):
            part = V[:, a : a + blk.shape[0]] @ blk  # (q, columns of the band)
            cols = blk.shape[1]
            pad = (0, self.n - cols) if self.lower else (self.n - cols, 0)
            out = out + jnp.pad(part, ((0, 0), pad))
        return out

    def host_matmul(self, B: np.ndarray) -> np.ndarray:
        """``F B`` with NumPy's BLAS on the host, for lower factors.

        The same product as :meth:`rmatmul` transposed, without a JAX compilation for every
        new shape (a model conditioned again and again has new shapes each time).

        Args:
            B: (n, m) host matrix.

        Returns:
            The (n, m) float64 product ``F B``.

        Raises:
            ValueError: if the factor is upper triangular.
        """
        if not self.lower:
            raise ValueError("host_matmul handles lower-triangular factors")
        out = np.empty((self.n, B.shape[1]))
        for a, blk in zip(self._starts(), self.blocks, strict=True):
            band = np.asarray(blk)  # a view of JAX's CPU buffer
            out[a : a + band.shape[0]] = band @ B[: band.shape[1]]
        return out

    def host_lmatmul(self, V: np.ndarray) -> np.ndarray:
        """``V F`` on the host, for lower factors: :meth:`lmatmul` without compilation.

        Args:
            V: (q, n) host rows.

        Returns:
            The (q, n) float64 product ``V F``.

        Raises:
            ValueError: for an upper-triangular factor (only lower ones are banded by rows
                here).
        """
        if not self.lower:
            raise ValueError("host_lmatmul handles lower-triangular factors")
        out = np.zeros((V.shape[0], self.n))
        for a, blk in zip(self._starts(), self.blocks, strict=True):
            band = np.asarray(blk)
            out[:, : band.shape[1]] += V[:, a : a + band.shape[0]] @ band
        return out

    def to_dense(self) -> np.ndarray:
        """The full matrix, zeros across the diagonal filled in.

        Returns:
            The (n, n) float64 NumPy array.
        """
        out = np.zeros((self.n, self.n))
        for a, blk in zip(self._starts(), self.blocks, strict=True):
            b = a + blk.shape[0]
            if self.lower:
                out[a:b, : blk.shape[1]] = np.asarray(blk)
            else:
                out[a:b, a:] = np.asarray(blk)
        return out


@functools.partial(jax.jit, static_argnums=1)
def _bands(F: Float[Array, "n n"], edges: tuple[int, ...]) -> tuple[Array, ...]:
    """The lower bands ``F[a:b, :b]`` between consecutive ``edges``: one compiled program,
    where each slice outside a trace compiled on its own for its shape."""
    return tuple(F[a:b, :b] for a, b in zip(edges[:-1], edges[1:], strict=True))


class BorderedTriangular(eqx.Module):
    """``L'⁻¹`` of a bordered lower Cholesky factor ``L' = [[L, 0], [S, L₂]]`` kept factored:

        L'⁻¹ = [[L⁻¹, 0], [−L₂⁻¹ S L⁻¹, L₂⁻¹]],   so   L'⁻¹ k = [v; L₂⁻¹ k₂ − M v],  v = L⁻¹ k₁,

    with ``base`` = ``L⁻¹`` (a :class:`BlockTriangular`, or a bordered factor itself after
    several updates), ``coupling`` = ``M = L₂⁻¹ S`` (r, n − r) and ``corner`` = ``L₂⁻¹``
    (r, r). Storing ``M`` instead of the explicit band ``−L₂⁻¹ S L⁻¹`` makes the same products
    and saves forming ``S L⁻¹``, the update's largest product (:mod:`gpg.gp.update`)."""

    base: BlockTriangular | BorderedTriangular
    coupling: Float[Array, "r m"]
    corner: Float[Array, "r r"]
    n: int = eqx.field(static=True)

    lower = True

    @property
    def dtype(self):
        """The storage dtype of the border (the products' dtype)."""
        return self.corner.dtype

    def _split(self, A, axis: int):
        m = self.base.n
        return (A[:m], A[m:]) if axis == 0 else (A[:, :m], A[:, m:])

    @eqx.filter_jit
    @highest
    def matvec(self, k: Float[Array, " n"]) -> Float[Array, " n"]:
        """``F k`` for one vector: ``[v; L₂⁻¹ k₂ − M v]`` with ``v = L⁻¹ k₁``.

        Args:
            k: (n,) vector, split after the base's rows into ``k₁`` and ``k₂``.

        Returns:
            The (n,) product, in the factor's storage dtype.
        """
        k1, k2 = self._split(k.astype(self.dtype), 0)
        v = self.base.matvec(k1)
        return jnp.concatenate([v, self.corner @ k2 - self.coupling @ v])

    @eqx.filter_jit
    @highest
    def rmatmul(self, K: Float[Array, "q n"]) -> Float[Array, "q n"]:
        """``K Fᵀ`` for a batch of rows, the base's part first, then the border's.

        Args:
            K: (q, n) rows, one per query.

        Returns:
            The (q, n) product (each row's ``F k``), in the factor's storage dtype.
        """
        K1, K2 = self._split(K.astype(self.dtype), 1)
        V = self.base.rmatmul(K1)
        # (A Bᵀ)ᵀ as in BlockTriangular.rmatmul: XLA's CPU dot is fast that way round.
        return jnp.concatenate([V, (self.corner @ K2.T).T - (self.coupling @ V.T).T], axis=1)

    def rmatvec(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """``Fᵀ v`` for one vector, through :meth:`lmatmul`.

        Args:
            v: (n,) vector.

        Returns:
            The (n,) product ``Fᵀ v``.
        """
        return self.lmatmul(v[None])[0]

    @eqx.filter_jit
    @highest
    def lmatmul(self, V: Float[Array, "q n"]) -> Float[Array, "q n"]:
        """``V F`` for a batch of rows: ``[(V₁ − V₂ M) L⁻¹, V₂ L₂⁻¹]``.

        Args:
            V: (q, n) rows, split after the base's columns into ``V₁`` and ``V₂``.

        Returns:
            The (q, n) product (each row's ``Fᵀ v``), in the factor's storage dtype.
        """
        V1, V2 = self._split(V.astype(self.dtype), 1)
        return jnp.concatenate([self.base.lmatmul(V1 - V2 @ self.coupling), V2 @ self.corner], 1)

    def host_matmul(self, B: np.ndarray) -> np.ndarray:
        """``F B`` with NumPy on the host, the base's product reused for the border's rows.

        Args:
            B: (n, m) host matrix.

        Returns:
            The (n, m) float64 product ``F B``.
        """
        B1, B2 = self._split(B, 0)
        top = self.base.host_matmul(B1)
        return np.concatenate([top, np.asarray(self.corner) @ B2 - np.asarray(self.coupling) @ top])

    def host_lmatmul(self, V: np.ndarray) -> np.ndarray:
        """``V F`` with NumPy on the host: :meth:`lmatmul` without compilation.

        Args:
            V: (q, n) host rows.

        Returns:
            The (q, n) product ``V F``.
        """
        V1, V2 = self._split(V, 1)
        left = self.base.host_lmatmul(V1 - V2 @ np.asarray(self.coupling))
        return np.concatenate([left, V2 @ np.asarray(self.corner)], axis=1)

    def to_dense(self) -> np.ndarray:
        """The full ``L'⁻¹``, its lower-left block ``−M L⁻¹`` formed explicitly.

        Returns:
            The (n, n) float64 NumPy array.
        """
        top = self.base.to_dense()
        m = self.base.n
        out = np.zeros((self.n, self.n))
        out[:m, :m] = top
        out[m:, :m] = -np.asarray(self.coupling) @ top
        out[m:, m:] = np.asarray(self.corner)
        return out
