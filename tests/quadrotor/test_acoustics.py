"""Tonal noise: Bessel functions, rise with rpm, plausible levels, tones below when edgewise."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special as sp

from gpg.quadrotor import acoustics


def test_bessel_against_scipy():
    n = np.arange(-40, 41)
    z = np.array([0.0, 1e-9, 0.05, 0.7, 2.0, 5.0, 9.0, 11.0])
    J = np.asarray(acoustics.bessel_j(jnp.asarray(n)[:, None], jnp.asarray(z)[None]))
    np.testing.assert_allclose(J, sp.jv(n[:, None], z[None]), atol=2e-14)
    g = jax.grad(lambda t: jnp.sum(acoustics.bessel_j(jnp.arange(0.0, 6.0), t)))(0.0)
    assert np.isfinite(g) and abs(float(g) - 0.5) < 1e-14  # J_1'(0) = 1/2, others 0


def noise(y_of, rpm, V=0.0):
    return np.asarray(y_of([rpm] * 4 + [0.0, 0.0, 0.0, V]))[6:]


def test_oaspl_rises_with_rpm(y_of):
    levels = np.array([noise(y_of, rpm) for rpm in np.arange(1000.0, 7001.0, 1000.0)])
    assert np.all(np.diff(levels, axis=0) > 0)


def test_plausible_band_at_hover(y_of):
    L = noise(y_of, 3550.0)
    # Tonal OASPL at 20 R = 3.8 m from a 2.7 kg quadrotor: tens of dB, far from 0 or 120.
    assert np.all((L[:2] > 40) & (L[:2] < 80))
    assert L[2] < L[0]  # below the vehicle only the rotors' small offsets from the axis radiate


def test_mic_below_hears_edgewise_flight(y_of, aero, gen):
    hover, edge = noise(y_of, 3550.0), noise(y_of, 3550.0, 10.0)
    assert edge[2] > 45 and edge[2] > hover[2] + 20
    msq = jax.jit(lambda res: acoustics.harmonic_msq(gen.vehicle, res))
    load, thick = msq(aero([3550.0] * 4, [0, 0, 0], 10.0))
    assert float(jnp.sum(load[:, 2])) > 100 * float(jnp.sum(thick[:, 2]))  # unsteady loading


@pytest.mark.slow  # compiles the generator's exact Jacobian (20 s); see test_bemt
def test_silent_at_zero_rpm(y_of, jac_of):
    x = [0.0] * 4 + [0.2, -0.1, 0.3, 8.0]
    np.testing.assert_allclose(noise(y_of, 0.0, 8.0), 0.0, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(y_of(x))))
    assert np.all(np.isfinite(np.asarray(jac_of(x))))
