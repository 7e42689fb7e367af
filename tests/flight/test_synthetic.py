"""gpg.flight.synthetic's plans and sensor options (the flights themselves run in the
benchmark's slow test)."""

import numpy as np
import pytest

from gpg.flight.synthetic import Sensors, figure_eight


def test_figure_eight_is_a_lemniscate():
    """Waypoints on ``x = a sin s``, ``y = b sin s cos s`` around the centre, enough laps for
    the duration, the hover held first."""
    plan = figure_eight(20.0, center=(1.0, 2.0, -5.0), size=(3.0, 1.5), period=8.0, points=16,
                        hold_s=4.0)  # fmt: skip
    w = np.asarray(plan.waypoints)
    s = np.linspace(0.0, 2 * np.pi * 4, 16 * 4 + 1)  # ceil(20 / 8) + 1 laps
    np.testing.assert_allclose(w[:, 0], 1.0 + 3.0 * np.sin(s), atol=1e-12)
    np.testing.assert_allclose(w[:, 1], 2.0 + 1.5 * np.sin(s) * np.cos(s), atol=1e-12)
    np.testing.assert_allclose(w[:, 2], -5.0)
    assert float(plan.leg_time) == pytest.approx(0.5) and float(plan.start_time) == 4.0
    np.testing.assert_allclose(np.asarray(plan.yaw), 0.0)


def test_sensors_log_rate_divides_the_rate():
    assert Sensors(rate=200.0, log_rate=50.0).every == 4
    assert Sensors().every == 1
    with pytest.raises(ValueError, match="log_rate must divide rate"):
        Sensors(rate=200.0, log_rate=60.0)
