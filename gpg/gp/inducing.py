"""A values-only GP on many cases through ``m`` inducing inputs (the projected-process, or DTC,
approximation: Seeger, Williams and Lawrence 2003; Quiñonero-Candela and Rasmussen 2005).

With inducing inputs ``Z`` (m, D), ``K_mm = k(Z, Z) = L Lᵀ``, the cases' cross-covariance
``K_mn`` and each case's noise ``Λ = diag(ν² + row noise)``, the covariance of the targets is
taken as ``K̃ = K_nm K_mm⁻¹ K_mn + Λ``. With ``A = L⁻¹ K_mn Λ^{-1/2}`` (m, N) and
``B = I + A Aᵀ = L_B L_Bᵀ``:

* mean ``μ(x) = k_m(x)ᵀ w``, ``w = L⁻ᵀ B⁻¹ A Λ^{-1/2} y`` (m weights per output);
* latent variance ``σ − ‖L⁻¹ k_m‖² + ‖L_B⁻¹ L⁻¹ k_m‖²``;
* ``Vᵀ K̃⁻¹ V = uᵀu − (A u)ᵀ B⁻¹ (A u)``, ``u = Λ^{-1/2} V``, for any columns ``V`` (what
  the flight correction's integrated basis needs, :mod:`gpg.flight.correction`).

The fit costs ``O(N m²)`` time and ``O(m² + m c)`` memory (the cases are read ``chunk`` at a
time), one jitted program on the host or an accelerator. The hyperparameters can be fitted on
every case the same way: :func:`collapsed_bound` is Titsias's (2009) lower bound on the log
marginal likelihood, ``log N(y | 0, K̃) − ½ Σ_i (σ − q_ii)/λ_i``, and :func:`fit_collapsed`
maximises it. With ``Z`` every case the model is the
exact GP (Woodbury: ``K⁻¹ − K⁻¹ (K⁻¹ + Λ⁻¹)⁻¹ K⁻¹ = (K + Λ)⁻¹``), the test of the module.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float

from gpg import _host
from gpg._dtype import float64
from gpg._precision import highest
from gpg.gp.hyper import Hyper
from gpg.gp.kernels import rbf_matrix
from gpg.gp.predictor import Predictor, plain

__all__ = [
    "InducingGP",
    "Projection",
    "StackedInducing",
    "collapsed_bound",
    "fit_collapsed",
    "inducing_inputs",
    "project",
    "variance_factor",
]

# Relative jitter on K_mm's diagonal: k-means centres can lie close enough together for K_mm to
# be singular in floating point; 1e-8 σ moves the model by about that much relative.
JITTER = 1e-8
# Row bands of a stacked variance triangle (StackedInducing): a query reads (1 + 1/4)/2 of
# the dense bytes in four products; eight read less but cost more per product (the design
# notes, "The wind state's step and its triangles").
TRI_BANDS = 4


class Projection(eqx.Module):
    """The projected-process quantities of :func:`project`, for targets ``V`` (N, K).

    Attributes:
        Z: (m, D) inducing inputs.
        weights: (m, K) ``L⁻ᵀ B⁻¹ A Λ^{-1/2} V``: the mean's weights of each column of ``V``.
        gram: (K, K) ``Vᵀ K̃⁻¹ V``.
        whiten: (m, m) ``L⁻¹``.
        post: (m, m) ``L_B⁻¹ L⁻¹``.
        logdet: ``log det K̃`` (the marginal likelihood's term).
        trace: ``tr(A Aᵀ) = Σ_i q_ii / λ_i`` (the collapsed bound's term).
    """

    Z: Float[Array, "m D"]
    weights: Float[Array, "m K"]
    gram: Float[Array, "K K"]
    whiten: Float[Array, "m m"]
    post: Float[Array, "m m"]
    logdet: Float[Array, ""]
    trace: Float[Array, ""]


class InducingGP(Predictor):
    """A values-only GP through inducing inputs (module docstring), ``M`` outputs sharing
    one kernel; a :class:`~gpg.gp.predictor.Predictor` like :class:`gpg.gp.exact.ExactGP`.

    Attributes:
        X: (m, D) the inducing inputs ``Z`` (named as the exact GP's rows: a kernel row is
            taken against them).
        weights: (m, M) ``w``.
        whiten: (m, m) ``L⁻¹``, lower triangular (empty in :meth:`mean_view`; the one
            triangle of :func:`variance_factor` in :meth:`variance_view`).
        post: (m, m) ``L_B⁻¹ L⁻¹``, lower triangular (empty in :meth:`mean_view` and
            :meth:`variance_view`).
        hyper: σ, the lengthscales and ``ν²``.
        output_scale: (M,) per-output variance scale.
        n_cases: the cases it was fitted on.
    """

    X: Float[Array, "m D"]
    weights: Float[Array, "m M"]
    whiten: Float[Array, "r m"]
    post: Float[Array, "r m"]
    hyper: Hyper
    output_scale: Float[Array, " M"]
    n_cases: int = eqx.field(static=True)

    @classmethod
    @float64
    def fit(
        cls,
        X: Float[ArrayLike, "N D"],
        Y: Float[ArrayLike, "N M"],
        Z: Float[ArrayLike, "m D"],
        *,
        hyper: Hyper,
        row_noise: Float[ArrayLike, " N"] | None = None,
        chunk: int = 4096,
    ) -> InducingGP:
        """Condition the GP on values ``Y`` at ``X`` through the inducing inputs ``Z``.

        Args:
            X: (N, D) inputs (normalised).
            Y: (N, M) values, or (N,) for one output.
            Z: (m, D) inducing inputs (:func:`inducing_inputs`).
            hyper: the kernel's σ and lengthscales and ``ν²`` (fitted elsewhere).
            row_noise: (N,) each case's own noise variance, added to ``ν²``.
            chunk: cases read at a time (memory ``O(m · chunk)``).

        Returns:
            The fitted GP (output scales ones).

        Raises:
            ValueError: shapes that do not match, non-finite values, or non-positive noise.
        """
        Yn = np.asarray(Y, float)
        Yn = Yn[:, None] if Yn.ndim == 1 else Yn
        p = project(X, Yn, Z, hyper=hyper, row_noise=row_noise, chunk=chunk)
        return cls(
            X=p.Z,
            weights=p.weights,
            whiten=p.whiten,
            post=p.post,
            hyper=hyper,
            output_scale=jnp.ones(Yn.shape[1]),
            n_cases=int(Yn.shape[0]),
        )

    @property
    def partition(self) -> None:
        return None

    @property
    def noise(self) -> Float[Array, ""]:
        return self.hyper.noise

    @property
    def n_inputs(self) -> int:
        return self.X.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.weights.shape[1]

    def with_output_scale(self, scale: Float[ArrayLike, " M"]) -> InducingGP:
        """This GP with ``output_scale`` replaced (the other arrays shared).

        Args:
            scale: (M,) the per-output variance scale.

        Returns:
            The GP with the new scale.
        """
        return eqx.tree_at(lambda m: m.output_scale, self, jnp.asarray(scale))

    def with_weights(self, weights: Float[ArrayLike, "m M"]) -> InducingGP:
        """This GP with the mean's weights replaced: the same kernel and inducing inputs on
        other targets (the weights are linear in the targets, :attr:`Projection.weights`).

        Args:
            weights: (m, M) the new ``w``.

        Returns:
            The GP with the new weights.

        Raises:
            ValueError: weights of another shape than the GP's.
        """
        w = jnp.asarray(weights)
        if w.shape != self.weights.shape:
            raise ValueError(f"weights must have shape {self.weights.shape}, got {w.shape}")
        return eqx.tree_at(lambda m: m.weights, self, w)

    def describe(self) -> dict[str, Any]:
        """The hyperparameters and sizes as plain values, for a checkpoint's metadata.

        Returns:
            ``{"hyperparameters": {...}, "inducing": m, "cases": N}``.
        """
        names = ("variance", "lengthscale", "noise")
        hyper = {k: plain(getattr(self.hyper, k)) for k in names}
        return {"hyperparameters": hyper, "inducing": int(self.X.shape[0]), "cases": self.n_cases}

    def _row(self, x: Float[Array, " D"]) -> Float[Array, " m"]:
        ls = jnp.broadcast_to(self.hyper.lengthscale, x.shape)
        return rbf_matrix(x[None] / ls, self.X / ls, self.hyper.variance)[0]

    @highest
    def mean_one(self, x: Float[Array, " D"]) -> Float[Array, " M"]:
        """The mean ``k_m(x)ᵀ w`` at one normalised query.

        Args:
            x: (D,) the query.

        Returns:
            (M,) the mean.
        """
        return self._row(x) @ self.weights

    @highest
    def mean_var_one(self, x: Float[Array, " D"]) -> tuple[Float[Array, " M"], Float[Array, ""]]:
        """The mean and latent variance ``σ − ‖L⁻¹k‖² + ‖L_B⁻¹L⁻¹k‖²`` at one query.

        Args:
            x: (D,) the normalised query.

        Returns:
            The (M,) mean and the latent variance (), not clipped.
        """
        k = self._row(x)
        a, b = self.whiten @ k, self.post @ k
        return k @ self.weights, self.hyper.variance - a @ a + b @ b

    def variance_view(self) -> InducingGP:
        """This GP with its latent variance's two triangles folded into one:
        ``whiten`` the triangle ``T`` of :func:`variance_factor` and ``post`` empty, so
        :meth:`mean_var_one` reads one (m, m) product a query instead of two (the loops that
        read the variance at every step, :func:`gpg.flight.online_step`). The same mean, the
        same variance to rounding. On the host (NumPy), once; not under ``jit``.

        Returns:
            The folded GP (itself if already folded).

        Raises:
            ValueError: a :meth:`mean_view`, which has no variance to fold.
        """
        if self.post.shape[0] == 0:
            if self.whiten.shape[0] == 0:
                raise ValueError("variance_view needs the GP's variance factors, not a mean_view")
            return self
        T = variance_factor(np.asarray(self.whiten), np.asarray(self.post))
        dtype = self.whiten.dtype  # a float32 copy (astype) stays one
        empty = jnp.zeros((0, T.shape[0]), dtype)
        return eqx.tree_at(lambda m: (m.whiten, m.post), self, (jnp.asarray(T, dtype), empty))

    def mean_view(self) -> InducingGP:
        """This GP without its variance's factors (the mean reads ``X`` and ``weights``).

        Returns:
            The lighter GP (its variance is not to be used).
        """
        empty = jnp.zeros((0, self.X.shape[0]), self.weights.dtype)
        return eqx.tree_at(lambda m: (m.whiten, m.post), self, (empty, empty))


class StackedInducing(eqx.Module):
    """Several one-output :class:`InducingGP` s of one size, stacked: their kernel rows,
    means and latent variances at one query in one program of a few fused operations
    instead of one of each per GP. A view for the loops that read all of them at every step
    (:func:`gpg.flight.online_step`); :meth:`of` builds it on the host, once.

    The same formulas as :class:`InducingGP` term for term (``σ exp(−½ r²)`` with ``r²`` the
    expanded square of the inputs divided by the lengthscales, the mean ``kᵀw``, the
    variance ``σ − ‖T k‖²`` of :meth:`InducingGP.variance_view`), so the same values to
    rounding.

    Attributes:
        scaled: (S, m, D) each GP's inducing inputs divided by its lengthscales.
        norm2: (S, m) their squared norms.
        lengthscale: (S, D) the lengthscales.
        variance: (S,) each GP's ``σ``.
        weights: (S, m) each GP's mean weights.
        tri: each GP's folded variance triangle ``T`` in row bands, stacked: band ``b``
            holds rows ``[e_b, e_{b+1})`` and the columns ``[0, e_{b+1})`` that can be
            non-zero (as :class:`gpg.linalg.tri.BlockTriangular`), so a query reads about
            half of the dense ``(S, m, m)``; empty: means only.
        output_scale: (S,) each GP's output scale.
        noise: (S,) each GP's value noise ``ν²`` (its predictive variance adds it).
    """

    scaled: Float[Array, "S m D"]
    norm2: Float[Array, "S m"]
    lengthscale: Float[Array, "S D"]
    variance: Float[Array, " S"]
    weights: Float[Array, "S m"]
    tri: tuple[Float[Array, "S b c"], ...]
    output_scale: Float[Array, " S"]
    noise: Float[Array, " S"]

    @classmethod
    def of(cls, gps: Sequence[InducingGP], variance: bool) -> StackedInducing | None:
        """``gps`` stacked, or None where they cannot be (not all one-output inducing-point
        GPs on inputs of one shape).

        Args:
            gps: the GPs, in the order their outputs are read.
            variance: keep their latent variances (folded: :meth:`InducingGP.variance_view`).

        Returns:
            The stack, or None.
        """
        if not gps or not all(isinstance(g, InducingGP) and g.weights.shape[1] == 1 for g in gps):
            return None
        if len({g.X.shape for g in gps}) != 1:
            return None
        D = gps[0].X.shape[1]
        ls = jnp.stack([jnp.broadcast_to(g.hyper.lengthscale, (D,)) for g in gps])
        scaled = jnp.stack([g.X for g in gps]) / ls[:, None, :]
        m = gps[0].X.shape[0]
        tri: tuple = ()
        if variance:
            T = np.stack([np.asarray(g.variance_view().whiten) for g in gps])
            edges = np.linspace(0, m, min(TRI_BANDS, m) + 1).astype(int)
            tri = tuple(_host.asarray(T[:, a:b, :b])
                        for a, b in zip(edges[:-1], edges[1:], strict=True))  # fmt: skip
        return cls(
            scaled=scaled,
            norm2=jnp.sum(scaled * scaled, 2),
            lengthscale=ls,
            variance=jnp.stack([jnp.reshape(g.hyper.variance, ()) for g in gps]),
            weights=jnp.stack([g.weights[:, 0] for g in gps]),
            tri=tri,
            output_scale=jnp.stack([g.output_scale[0] for g in gps]),
            noise=jnp.stack([jnp.reshape(g.noise, ()) for g in gps]),
        )

    @highest
    def rows(self, x: Float[Array, " D"]) -> Float[Array, "S m"]:
        """Each GP's kernel row ``k(x, Z)``.

        Args:
            x: (D,) the normalised query.

        Returns:
            (S, m) the rows, as each GP's own (:class:`InducingGP`).
        """
        a = x[None, :] / self.lengthscale
        r2 = (jnp.sum(a * a, 1)[:, None] + self.norm2
              - 2.0 * jnp.einsum("sd,smd->sm", a, self.scaled))  # fmt: skip
        return self.variance[:, None] * jnp.exp(-0.5 * jnp.maximum(r2, 0.0))

    @highest
    def means(self, x: Float[Array, " D"]) -> Float[Array, " S"]:
        """Each GP's mean (:meth:`InducingGP.mean_one`'s one output).

        Args:
            x: (D,) the normalised query.

        Returns:
            (S,) the means.
        """
        return jnp.einsum("sm,sm->s", self.rows(x), self.weights)

    @highest
    def latents(self, x: Float[Array, " D"]) -> Float[Array, " S"]:
        """Each GP's latent variance ``σ − ‖T k‖²``, not clipped.

        Args:
            x: (D,) the normalised query.

        Returns:
            (S,) the variances (a stack built without them has ``tri`` empty: ``σ``).
        """
        return self._latents(self.rows(x))

    @highest
    def evaluate(
        self, x: Float[Array, " D"]
    ) -> tuple[Float[Array, "S m"], Float[Array, " S"], Float[Array, " S"]]:
        """:meth:`rows`, :meth:`means` and :meth:`latents` from one evaluation of the rows.

        Args:
            x: (D,) the normalised query.

        Returns:
            The (S, m) kernel rows, the (S,) means and the (S,) latent variances (not
            clipped).
        """
        k = self.rows(x)
        return k, jnp.einsum("sm,sm->s", k, self.weights), self._latents(k)

    def _latents(self, k: Float[Array, "S m"]) -> Float[Array, " S"]:
        q = jnp.zeros_like(self.variance)
        for band in self.tri:  # each band its own array: no slice of a larger buffer
            t = jnp.einsum("sij,sj->si", band, k[:, : band.shape[2]])
            q = q + jnp.sum(t * t, 1)
        return self.variance - q


def variance_factor(
    whiten: Float[np.ndarray, "m m"], post: Float[np.ndarray, "m m"]
) -> Float[np.ndarray, "m m"]:
    """One lower triangle ``T`` with ``‖T k‖² = ‖W k‖² − ‖P k‖²`` for every ``k``: the
    latent variance's two triangles (``W = L⁻¹``, ``P = L_B⁻¹ L⁻¹``) as one, half the
    products a query.

    With ``P = L_B⁻¹ W``, ``WᵀW − PᵀP = Wᵀ(I − B⁻¹)W``, and ``B⁻¹ = SᵀS`` for
    ``S = P W⁻¹ = L_B⁻¹`` (``W⁻¹`` is ``K_mm``'s Cholesky factor, of entries at most
    ``√σ``). ``I − B⁻¹ = U diag(1 − e) Uᵀ`` from the eigenvalues ``e`` of ``SᵀS`` in
    (0, 1], so ``F = diag(√(1 − e)) Uᵀ W`` has ``FᵀF = WᵀW − PᵀP`` without the difference
    of two large matrices being formed; ``T`` is the triangle of ``F``'s QL decomposition
    (a QR of ``F`` with its columns reversed), ``TᵀT = FᵀF``.

    Args:
        whiten: (m, m) ``W``, lower triangular.
        post: (m, m) ``P``, lower triangular.

    Returns:
        (m, m) ``T``, lower triangular (NumPy, float64).
    """
    from scipy.linalg import solve_triangular

    W, P = np.asarray(whiten, np.float64), np.asarray(post, np.float64)
    S = P @ solve_triangular(W, np.eye(W.shape[0]), lower=True)
    e, U = np.linalg.eigh(S.T @ S)
    F = np.sqrt(np.clip(1.0 - e, 0.0, None))[:, None] * (U.T @ W)
    R = np.linalg.qr(F[:, ::-1], mode="r")
    return np.tril(R[::-1, ::-1])


@float64
def project(
    X: Float[ArrayLike, "N D"],
    V: Float[ArrayLike, "N K"],
    Z: Float[ArrayLike, "m D"],
    *,
    hyper: Hyper,
    row_noise: Float[ArrayLike, " N"] | None = None,
    chunk: int = 4096,
) -> Projection:
    """The projected-process quantities of targets ``V`` (module docstring): the mean's weights
    of each column, ``Vᵀ K̃⁻¹ V``, the variance's two factors and ``log det K̃``.

    Args:
        X: (N, D) inputs (normalised).
        V: (N, K) targets (columns: outputs, or basis columns beside them).
        Z: (m, D) inducing inputs.
        hyper: σ, lengthscales and ``ν²``.
        row_noise: (N,) each case's own noise variance, added to ``ν²``.
        chunk: cases read at a time.

    Returns:
        The :class:`Projection`.

    Raises:
        ValueError: shapes that do not match (naming the input), non-finite values, or a noise
            that is not positive for every case.
    """
    Xp, Vp, rn, real, Z = _chunked(X, V, Z, row_noise, chunk)
    noise = float(hyper.noise) + rn
    if not np.all(noise[real] > 0):
        raise ValueError("every case needs a positive noise variance (nu^2 plus its row noise)")
    # Padded cases get weight 0: they add nothing to B, A u or uᵀu.
    sw = np.where(real, 1.0 / np.sqrt(np.where(real, noise, 1.0)), 0.0)
    ls = np.broadcast_to(np.asarray(hyper.lengthscale, float), (Z.shape[1],))
    return _project(_host.asarray(Xp), _host.asarray(Vp), _host.asarray(sw), _host.asarray(Z),
                    jnp.asarray(hyper.variance, float), jnp.asarray(ls))  # fmt: skip


def _chunked(X, V, Z, row_noise, chunk: int):
    """The cases checked (each input named in its error) and cut into chunks of ``chunk``,
    the last one padded: ``(X, V, row noise, real)`` with a leading chunk axis, and ``Z``."""
    X, V, Z = (np.asarray(a, float) for a in (X, V, Z))
    if X.ndim != 2:
        raise ValueError(f"X must be (N, D), got shape {X.shape}")
    n, d = X.shape
    if V.ndim != 2 or V.shape[0] != n:
        raise ValueError(f"V must be ({n}, K) like X's rows, got shape {V.shape}")
    if Z.ndim != 2 or Z.shape[1] != d or Z.shape[0] < 1:
        raise ValueError(f"Z must be (m, {d}) with m >= 1, got shape {Z.shape}")
    rn = np.zeros(n)
    if row_noise is not None:
        rn = np.asarray(row_noise, float)
        if rn.shape != (n,):
            raise ValueError(f"row_noise must be ({n},), got shape {rn.shape}")
    for name, a in (("X", X), ("V", V), ("Z", Z), ("row_noise", rn)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} holds NaN or inf")
    if not int(chunk) >= 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    c = min(int(chunk), n)
    pad = (-n) % c
    Xp = np.concatenate([X, np.zeros((pad, d))]).reshape(-1, c, d)
    Vp = np.concatenate([V, np.zeros((pad, V.shape[1]))]).reshape(-1, c, V.shape[1])
    rn = np.concatenate([rn, np.zeros(pad)]).reshape(-1, c)
    real = np.concatenate([np.ones(n, bool), np.zeros(pad, bool)]).reshape(-1, c)
    return Xp, Vp, rn, real, Z


@jax.jit
@highest
def _project(Xp, Vp, sw, Z, var, ls) -> Projection:
    m = Z.shape[0]
    Kmm = rbf_matrix(Z / ls, Z / ls, var) + JITTER * var * jnp.eye(m, dtype=Z.dtype)
    L = jnp.linalg.cholesky(Kmm)

    def add(carry, part):
        B, T, G = carry
        x, v, s = part
        A = jsl.solve_triangular(L, rbf_matrix(Z / ls, x / ls, var), lower=True) * s[None]
        u = v * s[:, None]
        return (B + A @ A.T, T + A @ u, G + u.T @ u), None

    k = Vp.shape[2]
    zero = (jnp.zeros((m, m), Z.dtype), jnp.zeros((m, k), Z.dtype), jnp.zeros((k, k), Z.dtype))
    (AAt, T, G), _ = jax.lax.scan(add, zero, (Xp, Vp, sw))
    LB = jnp.linalg.cholesky(jnp.eye(m, dtype=Z.dtype) + AAt)
    S = jsl.solve_triangular(LB, T, lower=True)
    whiten = jsl.solve_triangular(L, jnp.eye(m, dtype=Z.dtype), lower=True)
    post = jsl.solve_triangular(LB, whiten, lower=True)
    weights = jsl.solve_triangular(L.T, jsl.solve_triangular(LB.T, S, lower=False), lower=False)
    # log det K̃ = log det B + Σ log λ_i (matrix determinant lemma); λ_i = 1/sw² on real cases
    real = sw > 0
    log_lam = jnp.sum(jnp.where(real, -2.0 * jnp.log(jnp.where(real, sw, 1.0)), 0.0))
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diag(LB))) + log_lam
    return Projection(Z, weights, G - S.T @ S, whiten, post, logdet, jnp.trace(AAt))


@float64
def collapsed_bound(
    X: Float[ArrayLike, "N D"],
    y: Float[ArrayLike, " N"],
    Z: Float[ArrayLike, "m D"],
    *,
    hyper: Hyper,
    row_noise: Float[ArrayLike, " N"] | None = None,
    chunk: int = 4096,
) -> float:
    """Titsias's (2009) collapsed lower bound on the log marginal likelihood of values ``y``,
    through the inducing inputs ``Z``: ``log N(y | 0, K̃) − ½ Σ_i (σ − q_ii) / λ_i``, with
    ``K̃ = Q + Λ`` the projected-process covariance (module docstring) and ``q_ii`` the
    diagonal of ``Q = K_nm K_mm⁻¹ K_mn``. The trace term is what makes it a bound: it
    penalises hyperparameters under which the inducing inputs do not explain the cases, so
    maximising it on every case does not trade the model away for a looser fit. With ``Z``
    every case it is the exact log marginal likelihood.

    Args:
        X: (N, D) inputs (normalised).
        y: (N,) values.
        Z: (m, D) inducing inputs.
        hyper: σ, lengthscales and ``ν²``.
        row_noise: (N,) each case's own noise variance, added to ``ν²``.
        chunk: cases read at a time.

    Returns:
        The bound (nats).

    Raises:
        ValueError: shapes that do not match (naming the input), non-finite values, or a noise
            that is not positive for every case.
    """
    Xp, yp, rn, real, Zc = _chunked(X, np.asarray(y, float).reshape(-1, 1), Z, row_noise, chunk)
    if not np.all((float(hyper.noise) + rn)[real] > 0):
        raise ValueError("every case needs a positive noise variance (nu^2 plus its row noise)")
    ls = np.broadcast_to(np.asarray(hyper.lengthscale, float), (Zc.shape[1],))
    args = (jnp.asarray(Xp), jnp.asarray(yp[..., 0]), jnp.asarray(rn), jnp.asarray(real),
            jnp.asarray(Zc))  # fmt: skip
    return float(_bound(*args, jnp.asarray(hyper.variance, float), jnp.asarray(ls),
                        jnp.asarray(hyper.noise, float)))  # fmt: skip


@jax.jit
def _bound(Xp, yp, rn, real, Z, var, ls, nu2):
    # the projection's own pass with the weights 1/√λ traced: what the bound does not read
    # (the mean's weights, the variance's factors) the compiler drops
    sw = jnp.where(real, 1.0 / jnp.sqrt(jnp.where(real, nu2 + rn, 1.0)), 0.0)
    p = _project(Xp, yp[..., None], sw, Z, var, ls)
    n = jnp.sum(real)
    trace = var * jnp.sum(sw * sw) - p.trace  # Σ_i (σ − q_ii) / λ_i
    return -0.5 * (n * jnp.log(2.0 * jnp.pi) + p.logdet + p.gram[0, 0] + trace)


def _collapsed_loss(p, a):
    """The negative collapsed bound per label at log-parameters ``p`` = (log σ, log ℓ,
    log(ν²/σ − floor)); ``a`` = (points, targets, noise, mask, inducing, count, floor)."""
    *data, n, floor = a
    var = jnp.exp(p[0])
    nll = -_bound(*data, var, jnp.exp(p[1:-1]), var * (floor + jnp.exp(p[-1]))) / n
    # A trial point whose K_mm or B is not positive definite gives NaN: a bad step.
    return jnp.where(jnp.isfinite(nll), nll, jnp.asarray(1e10))


@float64
def fit_collapsed(
    X: Float[ArrayLike, "N D"],
    y: Float[ArrayLike, " N"],
    Z: Float[ArrayLike, "m D"],
    *,
    init: Hyper,
    row_noise: Float[ArrayLike, " N"] | None = None,
    noise_floor: float = 1e-6,
    max_steps: int = 200,
    chunk: int = 4096,
) -> tuple[Hyper, bool]:
    """σ, the lengthscales and ``ν²`` by maximising :func:`collapsed_bound` on every case
    (optimistix BFGS on log-parameters, ``ν² = σ(floor + e^θ)`` as in
    :func:`gpg.gp.fit.fit_hyperparameters`), started from ``init``: ``O(N m²)`` a step, so
    the hyperparameters see every label where a dense likelihood sees a subset of them.

    Args:
        X: (N, D) inputs (normalised).
        y: (N,) values.
        Z: (m, D) inducing inputs (fixed).
        init: where the fit starts (a subset's fit is a good start).
        row_noise: (N,) each case's own noise variance, added to ``ν²``.
        noise_floor: ``ν²/σ`` stays above it.
        max_steps: BFGS steps (:func:`gpg.gp.fit.fit_hyperparameters`'s default: near a flat
            maximum the step test can take a hundred or more, and rounding moves when).
        chunk: cases read at a time.

    Returns:
        The hyperparameters and whether BFGS converged to a finite bound (where it did not,
        the better of the start and the last iterate).

    Raises:
        ValueError: shapes that do not match (naming the input), non-finite values, or
            ``init`` not positive.
    """
    Xp, yp, rn, real, Zc = _chunked(X, np.asarray(y, float).reshape(-1, 1), Z, row_noise, chunk)
    d = Zc.shape[1]
    ls0 = np.broadcast_to(np.asarray(init.lengthscale, float), (d,))
    var0, nu0 = float(init.variance), float(init.noise)
    if not (var0 > 0 and nu0 > 0 and np.all(ls0 > 0)):
        raise ValueError(f"init must have positive variance, lengthscales and noise, got {init}")
    # the data, the label count and the floor are arguments of one module-level loss (not a
    # closure): fits of equal shapes (a correction's six outputs) share one compiled program
    args = tuple(jnp.asarray(a) for a in (Xp, yp[..., 0], rn, real, Zc))
    args = (*args, jnp.asarray(float(np.sum(real))), jnp.asarray(float(noise_floor)))
    loss = _collapsed_loss
    ratio = max(nu0 / var0 - noise_floor, 1e-12)
    p0 = jnp.concatenate([jnp.log(jnp.array([var0])), jnp.log(jnp.asarray(ls0)),
                          jnp.log(jnp.array([ratio]))])  # fmt: skip
    sol = optx.minimise(loss, optx.BFGS(rtol=1e-6, atol=1e-6), p0, args=args,
                        max_steps=int(max_steps), throw=False)  # fmt: skip
    best = sol.value
    f0, f1 = float(loss(p0, args)), float(loss(best, args))
    ok = bool(sol.result == optx.RESULTS.successful) and f1 < 1e10
    if not f1 <= f0:
        best = p0
    var = jnp.exp(best[0])
    return Hyper(variance=var, lengthscale=jnp.exp(best[1 : 1 + d]),
                 noise=var * (noise_floor + jnp.exp(best[-1]))), ok  # fmt: skip


def inducing_inputs(
    X: Float[ArrayLike, "N D"], m: int, *, seed: int = 0, sample: int = 64
) -> np.ndarray:
    """``m`` inducing inputs among the cases ``X``: k-means centres (k-means++ start) of at
    most ``sample · m`` cases drawn at random (k-means on every case of ten hours of flight
    would cost more than the fit it serves), or the distinct cases themselves where there are
    at most ``m``.

    Args:
        X: (N, D) the cases' inputs.
        m: the most inducing inputs.
        seed: k-means' seed and the draw's.
        sample: cases per inducing input that k-means reads, at most.

    Returns:
        (m', D) the inducing inputs, ``m' <= m``.

    Raises:
        ValueError: ``X`` not (N, D) with N >= 1, or ``m`` under 1.
    """
    from scipy.cluster.vq import kmeans2

    pts = np.asarray(X, float)
    if pts.ndim != 2 or pts.shape[0] < 1:
        raise ValueError(f"X must be (N, D) with N >= 1, got shape {pts.shape}")
    if int(m) < 1:
        raise ValueError(f"m must be >= 1, got {m}")
    distinct = np.unique(pts, axis=0)
    if distinct.shape[0] <= m:
        return distinct
    if pts.shape[0] > sample * m:
        rng = np.random.default_rng(seed)
        pts = pts[np.sort(rng.choice(pts.shape[0], sample * int(m), replace=False))]
    Z, lab = kmeans2(pts, int(m), seed=seed, minit="++")
    # an empty cluster keeps a centre no case is near: drop it
    return Z[np.isin(np.arange(Z.shape[0]), lab)]
