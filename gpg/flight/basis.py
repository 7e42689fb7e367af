"""Explicit physical basis functions of the flight correction, their coefficients integrated out
(Rasmussen and Williams, section 2.7).

Each load output ``j`` of the corrected model is

    y_j(x) = h_j(x)ᵀ β_j + δ_j(x) + ε,    β_j ~ N(b, B),    δ_j ~ GP(0, k_j),

with ``h_j`` the basis columns at ``x``: the prior's mean (its coefficient is the co-kriging
scale ``ρ``), ``M``'s own loads (``κ``) and the terms of :class:`PhysicalBasis`, which carry
physics into the regions no flight reached: airframe drag per body axis
(``−½ ρ_air ‖v‖ v_a e_a``: the coefficient is a drag area, m²), rotor drag (each rotor's
in-plane force ``∝ Ω_i v_⊥``), the thrust's change with the inflow through the disks
(``∝ Ω_i v_z``) and with edgewise speed (``∝ v_xy²``). With ``β`` integrated out, the posterior
mean is ``hᵀβ̄ + k_*ᵀ K⁻¹ (y − Hβ̄)`` and the variance adds ``Rᵀ A⁻¹ R`` to the GP's, with
``A = B⁻¹ + Hᵀ K⁻¹ H``, ``β̄ = A⁻¹ (Hᵀ K⁻¹ y + B⁻¹ b)`` and ``R = h_* − Hᵀ K⁻¹ k_*``: the band
widens where the basis extrapolates (a wind faster than any flight's), instead of reverting to
the GP's mean with the GP's confidence. Where the correction held flights out, the
coefficients' covariance is ``A⁻¹`` plus their spread between those flights
(``gpg.flight.correct``'s ``coefficient_spread``), in place of ``A⁻¹`` below.

Units: the physics' columns are in newtons (N·m for torques) per unit coefficient before the
outputs' normalisation; a column and the targets are divided by the same output scale, so the
coefficients keep their physical units and :data:`PRIORS` states their prior in them.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from gpg._precision import highest
from gpg.data.preprocess import Normalizer
from gpg.quadrotor.frames import R_WB

__all__ = ["PRIORS", "TERMS", "Explicit", "PhysicalBasis", "posterior", "posterior_gram"]

AIR_DENSITY = 1.225  # kg/m³: a drag column's coefficient is the drag area at sea level
RPM_REF = 4000.0  # rpm: the rotor terms' coefficients are per rotor at this speed

TERMS = ("drag_x", "drag_y", "drag_z", "rotor_drag", "inflow", "edgewise")
"""The physical columns of :class:`PhysicalBasis`, in order."""

PRIORS = {
    "prior": 0.3,  # ρ about 1: the simulator's own scale, give or take a third
    "simple": 0.3,  # κ about 0: M's coefficients, give or take a third
    "drag_x": 0.1,  # m², a drag area (a small quadrotor's are a few hundredths)
    "drag_y": 0.1,
    "drag_z": 0.1,
    "rotor_drag": 0.5,  # N per m/s, per rotor at RPM_REF
    "inflow": 2.0,  # N per m/s of flow through the disk, per rotor at RPM_REF
    "edgewise": 0.05,  # N per (m/s)², per rotor
}
"""The prior standard deviations of the coefficients, in their physical units; the prior
mean is 0 but for ``ρ`` (1 where the prior's mean is a column)."""


class PhysicalBasis(eqx.Module):
    """The physical columns :data:`TERMS` at a normalised input, in the GP's frame and the
    outputs' normalised units: ``(6, len(TERMS))``.

    Attributes:
        normalizer: the surrogate's (inputs back to physical units, outputs' scales).
        positions: (4, 3) hub positions, body FRD (m): the rotor terms' moments.
        frame: ``"airflow"`` or ``"body"``.
    """

    normalizer: Normalizer
    positions: Float[Array, "4 3"]
    frame: str = eqx.field(static=True, default="airflow")

    @property
    def air_density(self) -> float:
        """kg/m³ of the drag columns (:data:`AIR_DENSITY`; for the exports)."""
        return AIR_DENSITY

    @property
    def rpm_ref(self) -> float:
        """rpm the rotor columns are per (:data:`RPM_REF`; for the exports)."""
        return RPM_REF

    @highest
    def __call__(self, xn: Float[Array, " D"]) -> Float[Array, "6 T"]:
        x = self.normalizer.x_inv(xn)
        rpm = x[:4]
        if self.frame == "body":
            v_B, R = x[4:7], jnp.eye(3, dtype=x.dtype)
        else:
            R = R_WB(x[4:7])  # the body's attitude to the airflow frame, R_HB
            v_B = R.T @ jnp.stack([x[7], jnp.zeros_like(x[7]), jnp.zeros_like(x[7])])
        speed = jnp.sqrt(jnp.sum(v_B**2) + 1e-12)
        eye = jnp.eye(3, dtype=x.dtype)
        drag = [-0.5 * AIR_DENSITY * speed * v_B[a] * eye[a] for a in range(3)]
        w = rpm / RPM_REF  # (4,)
        v_xy = v_B * jnp.array([1.0, 1.0, 0.0], x.dtype)
        # Each rotor's force at its hub: its moment about the centre of mass is p_i × f_i.
        f_drag = -w[:, None] * v_xy[None, :]  # (4, 3) in-plane, against the airflow
        f_inflow = w[:, None] * (v_B[2] * eye[2])[None, :]  # along z_B, with the through-flow
        f_edge = jnp.broadcast_to(-(v_B[0] ** 2 + v_B[1] ** 2) * eye[2], (4, 3))
        zero = jnp.zeros(3, x.dtype)
        cols = [jnp.concatenate([d, zero]) for d in drag]
        for f in (f_drag, f_inflow, f_edge):
            tau = jnp.sum(jnp.cross(self.positions, f), 0)
            cols.append(jnp.concatenate([jnp.sum(f, 0), tau]))
        out = jnp.stack(cols, 1)  # (6, T) body frame
        out = jnp.concatenate([R @ out[:3], R @ out[3:]], 0)
        return out / self.normalizer.y_std[:6, None]


class Explicit(eqx.Module):
    """The integrated basis of a corrected model, per load output ``j`` (module docstring).

    The coefficients of the prior's mean and of ``M`` live in the corrected model's
    ``scale`` and ``kappa``; :attr:`beta` holds the physical columns'. :attr:`G` and
    :attr:`cov_chol` give the variance term ``‖Cᵀ(h_* − Gᵀ k_*)‖²``.

    Attributes:
        physics: the physical columns.
        beta: (6, T) the physical columns' posterior mean coefficients (physical units).
        G: (6, N, P) ``K_j⁻¹ H_j`` over all P columns (prior, ``M``, physics); for an
            inducing-point discrepancy (:class:`gpg.gp.inducing.InducingGP`) ``N`` is its
            ``m`` inducing inputs and ``G = K_mm⁻¹ K_mn K̃⁻¹ H`` (its kernel row is taken
            against them).
        cov_chol: (6, P, P) a Cholesky factor ``C`` of the coefficients' covariance:
            ``A_j⁻¹``, their posterior's (times the held-out calibration's factor), plus
            their spread between the flights held out where the correction measured it
            (``gpg.flight.correct``'s ``coefficient_spread``).
        with_prior: the prior's mean is the first column.
        with_simple: ``M``'s loads are a column (after the prior's).
    """

    physics: PhysicalBasis
    beta: Float[Array, "6 T"]
    G: Float[Array, "6 N P"]
    cov_chol: Float[Array, "6 P P"]
    with_prior: bool = eqx.field(static=True, default=True)
    with_simple: bool = eqx.field(static=True, default=True)

    @property
    def columns(self) -> tuple[str, ...]:
        """The columns' names, in order."""
        return (
            (("prior",) if self.with_prior else ())
            + (("simple",) if self.with_simple else ())
            + TERMS
        )

    def mean(self, xn: Float[Array, " D"]) -> Float[Array, " 6"]:
        """The physical columns' part of the mean, ``Σ_t β_jt h_jt(x)`` (normalised units).

        Args:
            xn: (D,) a normalised input.

        Returns:
            (6,) the term per load output.
        """
        return self.mean_of(self.physics(xn))

    def mean_of(self, h: Float[Array, "6 T"]) -> Float[Array, " 6"]:
        """:meth:`mean` from the physical columns at the input, where the caller has them.

        Args:
            h: (6, T) :attr:`physics` at the input.

        Returns:
            (6,) the term per load output.
        """
        return jnp.sum(h * self.beta, 1)

    @highest
    def variance(self, h: Float[Array, "6 P"], k: Float[Array, "6 N"]) -> Float[Array, " 6"]:
        """``Rᵀ Σ_β R`` per output, ``R = h_* − Gᵀ k_*``, ``Σ_β`` the coefficients'
        covariance (:attr:`cov_chol`).

        Args:
            h: (6, P) all the columns at the query.
            k: (6, N) each discrepancy's kernel between the query and the labels.

        Returns:
            (6,) the coefficients' share of the predictive variance (normalised units).
        """
        r = h - jnp.einsum("jnp,jn->jp", self.G, k)
        u = jnp.einsum("jpq,jp->jq", self.cov_chol, r)
        return jnp.sum(u * u, 1)


def posterior(
    H: np.ndarray, Kinv_H: np.ndarray, Kinv_y: np.ndarray, b: np.ndarray, sd: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The coefficients' posterior given the GP: ``β̄`` and a Cholesky factor of ``A⁻¹``.

    Args:
        H: (N, P) the columns at the labels.
        Kinv_H: (N, P) ``K⁻¹ H``.
        Kinv_y: (N,) ``K⁻¹ y``.
        b: (P,) the prior mean.
        sd: (P,) the prior standard deviations (``B = diag(sd²)``).

    Returns:
        ``β̄`` (P,) and ``C`` (P, P), lower, with ``C Cᵀ = A⁻¹``.
    """
    return posterior_gram(H.T @ Kinv_H, H.T @ Kinv_y, b, sd)


def posterior_gram(
    HtKH: np.ndarray, HtKy: np.ndarray, b: np.ndarray, sd: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`posterior` from ``Hᵀ K⁻¹ H`` and ``Hᵀ K⁻¹ y`` (what an inducing-point
    discrepancy gives without forming ``K⁻¹ H``, :func:`gpg.gp.inducing.project`).

    Args:
        HtKH: (P, P) ``Hᵀ K⁻¹ H``.
        HtKy: (P,) ``Hᵀ K⁻¹ y``.
        b: (P,) the prior mean.
        sd: (P,) the prior standard deviations.

    Returns:
        ``β̄`` (P,) and ``C`` (P, P), lower, with ``C Cᵀ = A⁻¹``.
    """
    A = np.diag(1.0 / sd**2) + HtKH
    A = 0.5 * (A + A.T)
    rhs = HtKy + b / sd**2
    L = np.linalg.cholesky(A)
    beta = np.linalg.solve(L.T, np.linalg.solve(L, rhs))
    Linv = np.linalg.solve(L, np.eye(A.shape[0]))
    cov = Linv.T @ Linv
    return beta, np.linalg.cholesky(0.5 * (cov + cov.T))
