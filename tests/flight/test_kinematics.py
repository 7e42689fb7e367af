"""gpg.flight.kinematics: each kinematic check against the closed form of a flight whose signals
agree exactly (tests/flight/flights.py), and each unit, order and frame mistake it must name."""

import dataclasses
import math

import numpy as np
import pytest

from gpg.flight import kinematics
from gpg.flight.kinematics import ERROR, RATIO, Agreement, consistency
from gpg.flight.log import FlightLog, FlightLogWarning, enforce
from tests.flight.flights import consistent_flight

# The trapezoid rule's error on these slow signals (periods of seconds, 100 Hz) is about
# h²|x''|/12 ≈ 1e-5 relative; the tolerance on a ratio of 1 is ten times that.
EXACT = 1e-4


@pytest.fixture(scope="module")
def log():
    return consistent_flight()


def _changed(log: FlightLog, **changes) -> FlightLog:
    kw = {f.name: getattr(log, f.name) for f in dataclasses.fields(log)}
    kw.update(changes)
    return FlightLog(**kw)


def _by_rate(checks) -> dict[str, Agreement]:
    return {c.rate: c for c in checks}


def test_a_consistent_flight_agrees_to_the_trapezoid_rule(log):
    checks = _by_rate(consistency(log))
    assert set(checks) == {"velocity", "rates", "specific_force"}
    for c in checks.values():
        assert c.verdict == "consistent", c.describe()
        assert c.error < EXACT and c.windows >= 5
        for r in c.ratio:
            assert r is None or abs(r - 1) < EXACT
    # without the accelerometer, the thrust axis (here tilted 10° by the fixed roll and pitch,
    # the accelerations a tenth of gravity): within ANGLE's first bound
    axis = _by_rate(consistency(_changed(log, specific_force=None)))["thrust_axis"]
    assert axis.verdict == "consistent" and axis.error < math.radians(15)


def test_hard_rolling_and_pitching_with_little_yaw_agrees(monkeypatch):
    """The yaw axis beside a hard roll and pitch (up to 6 rad/s): over a window the rotation's
    second-order terms rival the little yaw, so an axis counts only where it carries
    DOMINANCE of the motion (a figure-eight of the hard scenario was refused before, its yaw
    ratio 0.37). Every axis counted, the same flight is refused."""
    log = consistent_flight(n=1500, rate=50.0, rocking=True)
    checks = _by_rate(consistency(log))
    assert checks["rates"].verdict == "consistent", checks["rates"].describe()
    assert all(c.verdict == "consistent" for c in checks.values())
    monkeypatch.setattr(kinematics, "DOMINANCE", 0.0)
    monkeypatch.setitem(kinematics._CHECKS, "attitude", (0.25, 0.2))
    assert _by_rate(consistency(log))["rates"].verdict == "inconsistent"


@pytest.mark.parametrize(
    ("mistake", "rate", "ratio"),
    [
        ({"position": 1000.0}, "velocity", 1000.0),  # mm against m/s
        ({"position": 3.0}, "velocity", 3.0),  # a closed form: the ratio is the scale
        ({"velocity": 3.6}, "velocity", 1 / 3.6),  # km/h
        ({"rates": 180 / math.pi}, "rates", math.pi / 180),  # deg/s
        ({"specific_force": 1 / 9.81}, "specific_force", 9.81),  # in g
    ],
)
def test_unit_mistakes_are_named_with_their_ratio(log, mistake, rate, ratio):
    ((field, scale),) = mistake.items()
    checks = _by_rate(consistency(_changed(log, **{field: getattr(log, field) * scale})))
    c = checks[rate]
    assert c.verdict == "inconsistent", c.describe()
    got = [r for r in c.ratio if r is not None]
    assert got and all(abs(r / ratio - 1) < 1e-3 for r in got)
    with pytest.raises(ValueError, match=f"against {rate}.*inconsistent.*check=False"):
        enforce(tuple(checks.values()), "f")


def test_order_and_frame_mistakes_are_named(log):
    scalar_last = log.quaternion[:, [1, 2, 3, 0]]
    checks = _by_rate(consistency(_changed(log, quaternion=scalar_last)))
    assert checks["rates"].verdict == "inconsistent"
    assert checks["specific_force"].verdict == "inconsistent"
    # without an IMU the thrust axis still sees it
    no_imu = _by_rate(consistency(_changed(log, quaternion=scalar_last, specific_force=None)))
    assert no_imu["thrust_axis"].verdict == "inconsistent"
    # rates in FLU against an FRD attitude: the turning axis's ratio is -1
    flu = _by_rate(consistency(_changed(log, rates=log.rates * [1, -1, -1])))["rates"]
    assert flu.verdict == "inconsistent" and min(r for r in flu.ratio if r is not None) < 0


def test_a_still_flight_is_uninformative_not_passed_or_refused(log):
    n = log.t.size
    still = _changed(
        log,
        position=np.ones((n, 3)),
        velocity=np.zeros((n, 3)),
        rates=np.zeros((n, 3)),
        quaternion=np.tile([1.0, 0, 0, 0], (n, 1)),
        specific_force=np.tile([0.0, 0, -9.81], (n, 1)),
    )
    checks = _by_rate(consistency(still))
    assert checks["velocity"].verdict == "uninformative"
    assert checks["rates"].verdict == "uninformative"
    assert checks["specific_force"].verdict == "consistent"  # gravity alone is motion enough
    enforce(tuple(checks.values()), "still")  # nothing raised


def test_loose_agreement_warns(log):
    scale = 1.4  # a ratio and a relative error (0.4) between their bounds
    assert RATIO[0] < scale < RATIO[1] and ERROR[0] < scale - 1 < ERROR[1]
    checks = consistency(_changed(log, position=log.position * scale))
    assert _by_rate(checks)["velocity"].verdict == "doubtful"
    with pytest.warns(FlightLogWarning, match="agree only loosely: position against velocity"):
        enforce(checks, "f")
