"""Dryden turbulence: stationary intensities and the correlations of the continuous filters."""

import jax
import jax.numpy as jnp
import numpy as np

from gpg.envs.wind import FT, Dryden


def _sequence(sigma_w, altitude, mean, dt, n, seed=0):
    d = Dryden.create(
        jax.random.key(seed),
        jnp.asarray(sigma_w),
        jnp.asarray(altitude),
        jnp.asarray(mean),
        jnp.asarray(dt),
    )

    def step(d, k):
        d = d.step(k)
        return d, jnp.concatenate(
            [d.x[:1], d.c_vw[0] @ d.x[1:3][None].T, d.c_vw[1] @ d.x[3:5][None].T]
        )

    _, out = jax.lax.scan(step, d, jax.random.split(jax.random.key(seed + 1), n))
    return d, np.asarray(out)


def test_intensities_and_correlations_follow_the_dryden_spectra():
    h, sigma_w, V, dt = 10.0, 1.2, 4.0, 0.5  # 6000 correlation lengths of u
    d, uvw = _sequence(sigma_w, h, [V, 0.0, 0.0], dt, 200000)
    h_ft = h / FT
    k = 0.177 + 0.000823 * h_ft
    L_uv, L_w = h_ft / k**1.2 * FT, h_ft * FT
    sigma_uv = sigma_w / k**0.4
    np.testing.assert_allclose(uvw.std(0), [sigma_uv, sigma_uv, sigma_w], rtol=0.04)
    # Lag-one correlations: exp(−ξ/L) for u; (1 − ξ/2L) exp(−ξ/L) for v and w (ξ = V dt).
    xi = V * dt
    want = [
        np.exp(-xi / L_uv),
        (1 - xi / (2 * L_uv)) * np.exp(-xi / L_uv),
        (1 - xi / (2 * L_w)) * np.exp(-xi / L_w),
    ]
    got = [np.corrcoef(uvw[:-1, i], uvw[1:, i])[0, 1] for i in range(3)]
    np.testing.assert_allclose(got, want, atol=0.006)
    # The components point along the mean wind, across it, and down.
    np.testing.assert_allclose(d.axes, np.eye(3), atol=1e-12)


def test_calm_air_and_zero_intensity():
    d, uvw = _sequence(0.0, 10.0, [0.0, 0.0, 0.0], 0.01, 50)
    assert np.all(uvw == 0.0) and np.all(np.isfinite(np.asarray(d.velocity())))
