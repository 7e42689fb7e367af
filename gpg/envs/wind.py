"""Wind for the environments: a constant mean, a sinusoidal gust, and Dryden turbulence.

Dryden (MIL-F-8785C / MIL-HDBK-1797, low altitude): the longitudinal component ``u`` (along
the mean wind) has the spectrum of a first-order filter, the lateral ``v`` and vertical ``w``
components ``Φ(ω) ∝ σ² (1 + 3τ²ω²)/(1 + τ²ω²)²`` with ``τ = L/V`` (frozen turbulence convected
at ``V``). Below 1000 ft: ``L_w = h``, ``L_u = L_v = h / (0.177 + 0.000823 h)^1.2`` and
``σ_u = σ_v = σ_w / (0.177 + 0.000823 h)^0.4`` (h in ft). Each filter is discretised exactly
for a step ``h_t`` (zero-order hold of the noise is not assumed: the state transition and the
noise covariance are the closed-form integrals of the continuous filter), and scaled so that
its stationary standard deviation is exactly ``σ``:

* ``u``: ``x ← a x + σ √(1 − a²) n`` with ``a = e^{−h_t/τ}`` (an Ornstein-Uhlenbeck process);
* ``v``, ``w``: the double pole ``1/(s + λ)²``, ``λ = 1/τ``, in Jordan form
  ``x ← e^{−λh}[[1, h], [0, 1]] x + chol(Q) n``, output
  ``y = σ √λ (λ(1 − √3) x₁ + √3 x₂)``, whose stationary variance is ``σ²``.

Everything is pure JAX on arrays: vmappable over environments, differentiable in the state.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from gpg._precision import highest

__all__ = ["Dryden"]

FT = 0.3048  # m
SQRT3 = math.sqrt(3.0)


class Dryden(eqx.Module):
    """One episode's Dryden turbulence: the discrete filters' coefficients (fixed for the
    episode) and their state.

    ``a_u``/``b_u`` the first-order filter of ``u``; for ``v`` and ``w`` (rows): ``a_vw`` the
    double-pole transition's diagonal ``e^{−λh}`` and off-diagonal ``h e^{−λh}``, ``chol_vw``
    the Cholesky factor of its noise covariance (l11, l21, l22) and ``c_vw`` the output row;
    ``x`` (5,) the state ``(u, v₁, v₂, w₁, w₂)``; ``axes`` (3, 3) the columns are the world
    directions of ``u``, ``v``, ``w``.
    """

    a_u: Float[Array, ""]
    b_u: Float[Array, ""]
    a_vw: Float[Array, "2 2"]
    chol_vw: Float[Array, "2 3"]
    c_vw: Float[Array, "2 2"]
    x: Float[Array, " 5"]
    axes: Float[Array, "3 3"]

    @classmethod
    def create(
        cls,
        key: PRNGKeyArray,
        sigma_w: Float[Array, ""],
        altitude: Float[Array, ""],
        mean_wind: Float[Array, " 3"],
        dt: Float[Array, ""],
        *,
        min_speed: float = 0.5,
    ) -> Dryden:
        """Filters for one episode, started from their stationary distribution.

        Starting stationary makes the first step already turbulent; the length scales and
        the horizontal intensities follow from ``altitude`` (in ft, at least ten) as in the
        module docstring, and ``u`` lies along the mean wind's horizontal direction (+x in
        calm air).

        Args:
            key: the initial state's randomness.
            sigma_w: the vertical intensity ``σ_w`` (m/s); 0 for no turbulence.
            altitude: the altitude ``h`` (m) of the length scales.
            mean_wind: (3,) the mean wind (world frame, m/s): its speed convects the
                turbulence, its dtype is the filters'.
            dt: the step ``h_t`` (s) the filters are discretised for.
            min_speed: the least convection speed (m/s), so that calm air keeps finite ``τ``.

        Returns:
            The turbulence at its initial state.
        """
        dtype = mean_wind.dtype
        h_ft = jnp.maximum(altitude / FT, 10.0)
        k = 0.177 + 0.000823 * h_ft
        L_w = h_ft * FT
        L_uv = h_ft / k**1.2 * FT
        s_w = sigma_w
        s_uv = sigma_w / k**0.4
        speed = jnp.maximum(jnp.linalg.norm(mean_wind), min_speed)
        lam_u, lam_v, lam_w = speed / L_uv, speed / L_uv, speed / L_w
        a_u = jnp.exp(-lam_u * dt)
        vw = [_double_pole(lam, dt, s) for lam, s in ((lam_v, s_uv), (lam_w, s_w))]
        # Start stationary: u ~ N(0, σ_u²); the double pole's stationary covariance in Jordan
        # form is [[1/(4λ³), 1/(4λ²)], [1/(4λ²), 1/(2λ)]].
        n = jax.random.normal(key, (5,), dtype=dtype)
        x_vw = [
            _stationary_sample(lam, n[1 + 2 * i : 3 + 2 * i])
            for i, lam in enumerate((lam_v, lam_w))
        ]
        horiz = mean_wind.at[2].set(0.0)
        hn = jnp.linalg.norm(horiz)
        e_u = jnp.where(
            hn > 1e-6, horiz / jnp.where(hn > 1e-6, hn, 1.0), jnp.array([1.0, 0.0, 0.0], dtype)
        )
        e_w = jnp.array([0.0, 0.0, 1.0], dtype)
        e_v = jnp.cross(e_w, e_u)
        return cls(
            a_u=a_u,
            b_u=s_uv * jnp.sqrt(1.0 - a_u**2),
            a_vw=jnp.stack([v[0] for v in vw]),
            chol_vw=jnp.stack([v[1] for v in vw]),
            c_vw=jnp.stack([v[2] for v in vw]),
            x=jnp.concatenate([s_uv * n[:1], *x_vw]).astype(dtype),
            axes=jnp.stack([e_u, e_v, e_w], axis=1),
        )

    @highest
    def velocity(self) -> Float[Array, " 3"]:
        """The turbulent wind of the current state.

        Returns:
            (3,) the turbulence's velocity (world frame, m/s), to add to the mean wind.
        """
        u = self.x[0]
        v = self.c_vw[0] @ self.x[1:3]
        w = self.c_vw[1] @ self.x[3:5]
        return self.axes @ jnp.stack([u, v, w])

    def step(self, key: PRNGKeyArray) -> Dryden:
        """One step of ``dt`` with fresh noise.

        Args:
            key: the step's noise.

        Returns:
            The turbulence one step later (the same filters, the new state).
        """
        n = jax.random.normal(key, (5,), dtype=self.x.dtype)
        u = self.a_u * self.x[0] + self.b_u * n[0]
        parts = [u[None]]
        for i in range(2):
            d, off = self.a_vw[i, 0], self.a_vw[i, 1]
            xi = self.x[1 + 2 * i : 3 + 2 * i]
            l11, l21, l22 = self.chol_vw[i, 0], self.chol_vw[i, 1], self.chol_vw[i, 2]
            ni = n[1 + 2 * i : 3 + 2 * i]
            parts.append(
                jnp.stack(
                    [d * xi[0] + off * xi[1] + l11 * ni[0], d * xi[1] + l21 * ni[0] + l22 * ni[1]]
                )
            )
        return eqx.tree_at(lambda s: s.x, self, jnp.concatenate(parts))


def _double_pole(lam, h, sigma):
    """Exact discretisation of ``x' = [[−λ, 1], [0, −λ]] x + [0, 1]ᵀ n`` (unit white noise):
    transition (diagonal, off-diagonal), the noise covariance's Cholesky factor, and the
    output row scaled to a stationary standard deviation ``sigma``."""
    e = jnp.exp(-lam * h)
    e2 = e * e
    q22 = (1.0 - e2) / (2.0 * lam)
    q12 = (1.0 - e2 * (1.0 + 2.0 * lam * h)) / (4.0 * lam**2)
    q11 = (2.0 - e2 * (2.0 + 4.0 * lam * h + 4.0 * (lam * h) ** 2)) / (8.0 * lam**3)
    l11 = jnp.sqrt(jnp.maximum(q11, 0.0))
    l21 = q12 / jnp.where(l11 > 0, l11, 1.0)
    l22 = jnp.sqrt(jnp.maximum(q22 - l21**2, 0.0))
    c = sigma * jnp.sqrt(lam) * jnp.stack([lam * (1.0 - SQRT3), jnp.full_like(lam, SQRT3)])
    return jnp.stack([e, e * h]), jnp.stack([l11, l21, l22]), c


def _stationary_sample(lam, n):
    p11, p12, p22 = 1.0 / (4.0 * lam**3), 1.0 / (4.0 * lam**2), 1.0 / (2.0 * lam)
    l11 = jnp.sqrt(p11)
    l21 = p12 / l11
    l22 = jnp.sqrt(jnp.maximum(p22 - l21**2, 0.0))
    return jnp.stack([l11 * n[0], l21 * n[0] + l22 * n[1]])
