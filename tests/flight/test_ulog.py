"""gpg.flight.read_ulog on a real PX4 log (a SITL quadrotor's hop: takeoff to 2.1 m and landing,
from pyulog's test data: tests/data/flight/LICENSE-pyulog.md), and its topic selection on
made-up topic tables."""

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

pyulog = pytest.importorskip("pyulog")

from gpg.flight.log import FlightLogWarning  # noqa: E402
from gpg.flight.ulog import _select, _window, cut_bytes, read_ulog  # noqa: E402

FIXTURE = Path(__file__).parents[1] / "data" / "flight" / "px4_sitl_hop.ulg"
# The topics read_ulog takes from this log (it has all of them): their common window.
USED = (
    "vehicle_local_position",
    "vehicle_attitude",
    "vehicle_angular_velocity",
    "vehicle_acceleration",
    "battery_status",
    "esc_status",
    "actuator_motors",
)
DEFAULT_ORDER = (3, 1, 2, 0)  # gpg r1 rear-right = PX4 motor 4, ...


@pytest.fixture(scope="module")
def raw():
    """The fixture's topics at instance 0, as pyulog reads them."""
    ulog = pyulog.ULog(str(FIXTURE))
    return {d.name: d.data for d in ulog.data_list if d.multi_id == 0}


@pytest.fixture(scope="module")
def log():
    # The estimator resets its position once on the ground, before which xy is invalid.
    with pytest.warns(FlightLogWarning, match=r"xy_reset 1 time.*xy_valid false in \d+"):
        return read_ulog(FIXTURE)


def _start_us(raw) -> int:
    return max(int(raw[t]["timestamp"][0]) for t in USED)


def _at(raw, log, topic, field):
    """A raw field linearly interpolated onto the log's time base."""
    t_us = log.t * 1e6 + _start_us(raw)
    return np.interp(t_us, raw[topic]["timestamp"].astype(float), raw[topic][field])


def test_fixture_reads_into_a_sane_flight(log, raw):
    assert log.name == "px4_sitl_hop"
    assert log.t[0] == 0.0 and np.all(np.diff(log.t) > 0)
    lp_rate = 1e6 / np.median(np.diff(raw["vehicle_local_position"]["timestamp"]))
    assert log.rate == pytest.approx(lp_rate, rel=1e-9)  # the default rate: the position's
    assert 30.0 < log.duration < 31.2  # the common window of a 31.1 s log
    np.testing.assert_allclose(np.linalg.norm(log.quaternion, axis=1), 1.0, atol=1e-12)
    # Continuous in sign (consecutive samples 0.1 s apart are close rotations).
    assert log.quaternion[0, 0] >= 0
    assert np.all(np.sum(log.quaternion[1:] * log.quaternion[:-1], axis=1) > 0.9)
    assert log.rpm is not None and log.command is not None
    assert np.all((log.command >= 0) & (log.command <= 1))
    # A hop: up to 2.1 m above the start (NED: z negative), rotors near 3300 rpm then.
    assert -2.2 < log.position[:, 2].min() < -2.0
    assert 3000 < log.rpm.max() < 3500
    assert np.all((log.voltage > 10) & (log.voltage < 20))  # a 4S battery
    # On the ground with the motors idle or off: the accelerometer reads the ground's push,
    # 1 g up (FRD: -z), whatever the noise.
    still = (log.command.max(1) < 0.05) & (np.linalg.norm(log.velocity, axis=1) < 0.1)
    assert still.sum() > 100
    f = log.specific_force[still]
    assert np.linalg.norm(f, axis=1).mean() == pytest.approx(9.81, abs=0.05)
    assert np.all(f[:, 2] < -9.5)


def test_position_matches_integrated_velocity(log):
    """Over the airborne part, p(t) − p(a) = ∫ₐᵗ v, to a tolerance of two parts.

    Numerics: the trapezoid rule on samples of v; its error per step h is h³|v''|/12, with
    |v''| ≈ |Δ²v|/h², so the bound Σ h|Δ²v|/12 is computed from the data (millimetres).
    The estimator: EKF2 corrects its position directly from GNSS and barometer fusions,
    not only through its velocity, so p drifts from ∫v by the fused corrections: allowed
    5 cm (the noise scale of a GNSS/baro correction) plus 5 % of the distance travelled on
    that axis. Both stay an order of magnitude below what a wrong sign, unit, axis or time
    scale gives (a flipped vz misses by twice the 2.1 m climb), which the test checks too.
    On the ground, EKF2's landed constraints correct position without velocity (after
    touchdown here ∫vz runs 1 m off), so that part is left out.
    """
    ground = np.median(log.position[:50, 2])
    air = np.flatnonzero(log.position[:, 2] < ground - 0.2)  # 20 cm up: off the ground
    s = slice(air[0], air[-1] + 1)
    t, p, v = log.t[s], log.position[s], log.velocity[s]
    assert t[-1] - t[0] > 5.0
    h = np.diff(t)[:, None]

    def residual(v):
        integral = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (v[1:] + v[:-1]) * h, 0)])
        return np.abs((p - p[0]) - integral).max(0)

    trapezoid = (np.abs(np.diff(v, 2, axis=0)) * h[1:] / 12).sum(0)
    path = np.abs(np.diff(p, axis=0)).sum(0)
    tol = trapezoid + 0.05 + 0.05 * path
    assert np.all(residual(v) < tol), (residual(v), tol)
    assert residual(v * [1, 1, -1])[2] > 5 * tol[2]  # the check has the power claimed


def test_signals_are_the_raw_topics_resampled(log, raw):
    """Same values as pyulog's at the same instants: the time base and its origin are right."""
    for k, axis in enumerate("xyz"):
        expect = _at(raw, log, "vehicle_local_position", axis)
        np.testing.assert_allclose(log.position[:, k], expect, rtol=0, atol=1e-6)
        expect = _at(raw, log, "vehicle_angular_velocity", f"xyz[{k}]")
        np.testing.assert_allclose(log.rates[:, k], expect, rtol=0, atol=1e-6)


def test_rotor_order_maps_px4_motors_onto_gpg_rotors(log, raw):
    motors = raw["actuator_motors"]
    # The four motors' commands differ, so a wrong mapping would show.
    assert not np.allclose(motors["control[3]"], motors["control[0]"])
    # gpg r1 (rear-right) is PX4 motor 4 (0-based 3): its command and its ESC's rpm.
    np.testing.assert_allclose(log.command[:, 0], _at(raw, log, "actuator_motors", "control[3]"))
    esc = raw["esc_status"]
    (i,) = [i for i in range(8) if np.all(esc[f"esc[{i}].actuator_function"] == 104)]  # Motor4
    np.testing.assert_allclose(log.rpm[:, 0], _at(raw, log, "esc_status", f"esc[{i}].esc_rpm"))
    # Any other order permutes the same columns.
    with pytest.warns(FlightLogWarning):
        px4 = read_ulog(FIXTURE, rotor_order=(0, 1, 2, 3))
    np.testing.assert_array_equal(log.command, px4.command[:, list(DEFAULT_ORDER)])
    np.testing.assert_array_equal(log.rpm, px4.rpm[:, list(DEFAULT_ORDER)])


def test_rate_argument(log):
    with pytest.warns(FlightLogWarning):
        fast = read_ulog(FIXTURE, rate=25.0, name="hop")
    assert fast.name == "hop"
    assert fast.rate == pytest.approx(25.0, rel=1e-9)
    np.testing.assert_allclose(np.diff(fast.t), 0.04, rtol=1e-9)
    assert abs(fast.duration - log.duration) < 1 / log.rate  # the same window
    # The same flight: the slower log's samples lie on the faster one's interpolant.
    z = np.interp(log.t, fast.t, fast.position[:, 2])
    np.testing.assert_allclose(z, log.position[:, 2], atol=0.05)
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(ValueError, match="rate must be"):
            read_ulog(FIXTURE, rate=bad)


def test_missing_topic_names_it_and_the_topics_the_file_has(tmp_path):
    # The fixture without vehicle_attitude, written by pyulog itself.
    path = tmp_path / "no_attitude.ulg"
    pyulog.ULog(str(FIXTURE), ["vehicle_local_position", "cpuload"]).write_ulog(str(path))
    with pytest.raises(ValueError, match=r"vehicle_attitude.*\['cpuload', 'vehicle_local_pos"):
        read_ulog(path)


def _topics(extra=None, n=20):
    """A made-up table of the required topics, stamped every 0.1 s from 1 s (µs)."""
    t = 1_000_000 + 100_000 * np.arange(n, dtype=np.uint64)
    zeros = np.zeros(n)
    topics = {
        ("vehicle_local_position", 0): {
            "timestamp": t,
            **dict.fromkeys(["x", "y", "z", "vx", "vy", "vz"], zeros),
        },
        ("vehicle_attitude", 0): {
            "timestamp": t,
            "q[0]": zeros + 1,
            **dict.fromkeys(["q[1]", "q[2]", "q[3]"], zeros),
        },
        ("sensor_combined", 0): {"timestamp": t, **{f"gyro_rad[{k}]": zeros for k in range(3)}},
    }
    topics.update(extra or {})
    return topics


def _select_plain(topics, instance=0):
    return _select(topics, DEFAULT_ORDER, instance, (1000.0, 2000.0))


def test_topic_selection_falls_back_and_reports_what_it_tried():
    t = 1_000_000 + 100_000 * np.arange(20, dtype=np.uint64)
    # ESCs without rpm telemetry (all 0) are skipped; PWM outputs of instance 1 are read.
    esc = {"timestamp": t, **{f"esc[{i}].esc_rpm": np.zeros(20) for i in range(4)}}
    pwm = {"timestamp": t, **{f"output[{i}]": np.full(20, 1000.0 + 100 * i) for i in range(4)}}
    out = _select_plain(_topics({("esc_status", 0): esc, ("actuator_outputs", 1): pwm}), 1)
    assert out["rpm"] is None and out["rates"][0] == "sensor_combined"
    np.testing.assert_allclose(out["command"][2][0], [0.3, 0.1, 0.2, 0.0])  # motors 4, 2, 3, 1
    with pytest.raises(ValueError, match="esc_status.*actuator_motors.*actuator_outputs inst"):
        _select_plain(_topics({("esc_status", 0): esc, ("actuator_outputs", 1): pwm}), 0)
    topics = _topics()
    del topics[("sensor_combined", 0)]
    with pytest.raises(ValueError, match=r"vehicle_angular_velocity.*or sensor_combined.*has \["):
        _select_plain(topics)


def test_timestamps_sorted_deduplicated_and_windows_checked():
    v = np.arange(6.0)[:, None]
    t = np.array([0, 100_000, 100_000, 300_000, 200_000, 400_000], dtype=np.int64)
    raw = {"position": ("vehicle_local_position", t, v), "voltage": None}
    with pytest.warns(FlightLogWarning, match=r"1 step\(s\) backwards, 1 repeated of 6"):
        series, start, end = _window(raw, "fake")
    _, ts, vs = series["position"]
    np.testing.assert_array_equal(ts, [0, 100_000, 200_000, 300_000, 400_000])
    np.testing.assert_array_equal(vs[:, 0], [0, 1, 4, 3, 5])  # the first of a repeat kept
    assert (start, end) == (0, 400_000)
    late = ("vehicle_attitude", np.array([500_000, 600_000]), np.zeros((2, 4)))
    with pytest.raises(ValueError, match=r"no time window.*vehicle_attitude 0\.500\.\.0\.600 s"):
        _window({"position": series["position"], "quaternion": late}, "fake")


def test_missing_pyulog_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyulog", None)
    with pytest.raises(ImportError, match=r"pip install 'gpg\[logs\]'"):
        read_ulog(FIXTURE)


# -- damaged and partial logs: refused, or read whole with what was done said ---------------


@pytest.mark.parametrize("fraction", [0.25, 0.5, 0.99])
def test_a_truncated_log_is_refused_unless_asked(tmp_path, fraction):
    data = FIXTURE.read_bytes()
    path = tmp_path / "cut.ulg"
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(ValueError, match=r"cut short: it ends \d+ byte\(s\) into a message"):
        read_ulog(path)
    with pytest.warns(FlightLogWarning, match=r"cut short.*the flight ends at"):
        part = read_ulog(path, allow_damaged=True, check=False)
    assert part.duration < 31.0 * fraction + 1.0


def test_cut_bytes_counts_what_the_last_message_lacks(tmp_path):
    data = FIXTURE.read_bytes()
    assert cut_bytes(FIXTURE) == 0  # the whole log ends on a message's end
    for k in (1, 2, 7):  # so a file k bytes shorter lacks k bytes of its last message
        (tmp_path / "c.ulg").write_bytes(data[:-k])
        assert cut_bytes(tmp_path / "c.ulg") == k
    (tmp_path / "e.ulg").write_bytes(b"")
    assert cut_bytes(tmp_path / "e.ulg") == 16  # not even the file's header


def test_a_log_with_garbage_inside_is_refused_unless_asked(tmp_path):
    data = FIXTURE.read_bytes()
    mid = len(data) // 2
    garbage = np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    path = tmp_path / "garbage.ulg"
    path.write_bytes(data[:mid] + garbage + data[mid:])
    with pytest.raises(ValueError, match="corrupt data.*allow_damaged=True"):
        read_ulog(path)
    with pytest.warns(FlightLogWarning) as caught:
        log = read_ulog(path, allow_damaged=True)
    said = " ".join(str(w.message) for w in caught)
    assert "corrupt data" in said and "dropouts: vehicle_local_position" in said
    # what pyulog skipped is a gap of the log, not interpolated samples
    assert np.diff(log.t).max() > 5 * np.median(np.diff(log.t))


def _edited(tmp_path, name, edit):
    """The fixture with some topics' messages dropped (``edit(data_name, stamps_s)`` gives the
    samples to keep), written by pyulog."""
    ulog = pyulog.ULog(str(FIXTURE))
    for d in ulog.data_list:
        keep = edit(d.name, (d.data["timestamp"].astype(np.int64) - ulog.start_timestamp) * 1e-6)
        if keep is not None:
            for k in list(d.data):
                d.data[k] = d.data[k][keep]
    path = tmp_path / f"{name}.ulg"
    ulog.write_ulog(str(path))
    return path


def _quiet_read(path, **kw):
    with pytest.warns(FlightLogWarning) as caught:
        log = read_ulog(path, **kw)
    return log, " ".join(str(w.message) for w in caught)


def test_a_partial_optional_topic_is_left_out_not_the_flight_cut(tmp_path, log):
    battery = _edited(tmp_path, "b", lambda n, s: s < 5.0 if n == "battery_status" else None)
    part, said = _quiet_read(battery)
    assert part.voltage is None and part.duration == pytest.approx(log.duration, abs=0.2)
    assert "battery_status covers" in said and "voltage left out" in said
    late = _edited(tmp_path, "a", lambda n, s: s > 25.0 if n == "vehicle_acceleration" else None)
    part, said = _quiet_read(late)
    assert part.specific_force is None and part.duration == pytest.approx(log.duration, abs=0.2)
    assert "specific_force left out" in said


def test_a_dropout_is_a_gap_of_the_log_and_no_label_falls_in_it(tmp_path):
    from gpg.flight.labels import label
    from gpg.quadrotor.simple_model import SimpleModel
    from gpg.quadrotor.vehicle import load_vehicle

    def drop(n, s):
        return ((s < 12.0) | (s > 16.0)) if n == "vehicle_local_position" else None

    log, said = _quiet_read(_edited(tmp_path, "d", drop))
    assert "dropouts: vehicle_local_position 1 (longest 4" in said
    start = np.flatnonzero(np.diff(log.t) > 3.5)
    assert start.size == 1  # one gap, no samples made up inside it
    lo, hi = log.t[start[0]], log.t[start[0] + 1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FlightLogWarning)
        veh = load_vehicle("sui_endurance")
        M = SimpleModel.from_vehicle(veh, float(veh.weight) / (4 * 3000.0**2), 1e-9)
        lab = label(log, veh, reference=M, rate=5.0, source="imu")
    assert not np.any((lab.t > lo) & (lab.t < hi))
    assert lab.t.size > 10  # the flight around it is labelled


def test_a_topic_too_sparse_to_resample_is_refused(tmp_path):
    def two(n, s):
        return np.isin(np.arange(s.size), [0, s.size - 1]) if n == "vehicle_attitude" else None

    with pytest.raises(ValueError, match="vehicle_attitude has 2 sample.*too sparse"):
        read_ulog(_edited(tmp_path, "two", two))


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"rotor_order": (0, 1, 2, 5)}, "names motor index 5, but the log has 4 motors"),
        ({"rotor_order": None}, "rotor_order must be 4 distinct integer"),
        ({"rotor_order": "0123"}, "rotor_order must be 4 distinct integer"),
        ({"rotor_order": (0.5, 1, 2, 3)}, "rotor_order must be 4 distinct integer"),
        ({"rate": "50"}, "rate must be a positive number"),
        ({"rate": 1000.0}, "faster than every topic read.*50 Hz"),
        ({"pwm_range": (1000,)}, r"pwm_range must be \(low, high\)"),
        ({"pwm_range": None}, r"pwm_range must be \(low, high\)"),
        ({"instance": -1}, "instance must be a non-negative integer"),
    ],
)
def test_bad_arguments_are_named(kw, match):
    with pytest.raises(ValueError, match=match):
        read_ulog(FIXTURE, **kw)


def test_a_file_that_is_not_a_ulog_is_named(tmp_path):
    path = tmp_path / "f.csv"
    path.write_text("t,x\n0,1\n")
    with pytest.raises(ValueError, match="not a PX4 ULog file.*read_csv"):
        read_ulog(path)
