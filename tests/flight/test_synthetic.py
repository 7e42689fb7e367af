"""gpg.flight.synthetic's plans and sensor options (the flights themselves run in the
benchmark's slow test)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpg.flight.synthetic import Sensors, figure_eight


def test_figure_eight_is_a_lemniscate():
    """The reference on ``x = a sin s``, ``y = b sin s cos s`` around the centre, at rest in
    the hold, its phase run up uniformly; velocity and acceleration the derivatives of the
    position (central differences)."""
    plan = figure_eight(center=(1.0, 2.0, -5.0), size=(3.0, 1.5), period=8.0, yaw=0.5,
                        hold_s=4.0, ramp_s=2.0)  # fmt: skip
    ref = jax.vmap(plan)(jnp.linspace(0.0, 4.0, 5))
    np.testing.assert_allclose(ref.p, np.tile([1.0, 2.0, -5.0], (5, 1)), atol=1e-12)
    np.testing.assert_allclose(ref.v, 0.0, atol=1e-12)
    w = 2 * np.pi / 8.0
    t = jnp.asarray([4.5, 5.5, 7.0, 13.3])
    s = np.where(t - 4.0 < 2.0, 0.5 * w * (t - 4.0) ** 2 / 2.0, w * (t - 4.0 - 1.0))
    r = jax.vmap(plan)(t)
    np.testing.assert_allclose(r.p[:, 0], 1.0 + 3.0 * np.sin(s), atol=1e-12)
    np.testing.assert_allclose(r.p[:, 1], 2.0 + 1.5 * np.sin(s) * np.cos(s), atol=1e-12)
    np.testing.assert_allclose(r.yaw, 0.5)
    h = 1e-4
    up, dn = jax.vmap(plan)(t + h), jax.vmap(plan)(t - h)
    np.testing.assert_allclose(r.v, (up.p - dn.p) / (2 * h), atol=1e-6)
    np.testing.assert_allclose(r.a, (up.v - dn.v) / (2 * h), atol=1e-5)


def test_sensors_log_rate_divides_the_rate():
    assert Sensors(rate=200.0, log_rate=50.0).every == 4
    assert Sensors().every == 1
    with pytest.raises(ValueError, match="log_rate must divide rate"):
        Sensors(rate=200.0, log_rate=60.0)
