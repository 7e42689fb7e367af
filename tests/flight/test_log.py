"""gpg.flight.log: the FlightLog checks, the CSV form and its conversions."""

import csv
import math

import numpy as np
import pytest

from gpg.flight.log import (
    CsvFormat,
    FlightLog,
    FlightLogWarning,
    matrix_to_quat,
    quat_to_matrix,
    read_csv,
    write_csv,
)


def _log(n=50, rate=100.0, seed=0, **over):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    kw = dict(
        t=t,
        position=rng.normal(size=(n, 3)),
        velocity=rng.normal(size=(n, 3)),
        quaternion=q * np.sign(q[:, :1]),
        rates=rng.normal(size=(n, 3)),
        rpm=rng.uniform(2000, 5000, (n, 4)),
        command=rng.uniform(0.2, 0.8, (n, 4)),
        specific_force=rng.normal(size=(n, 3)),
        wind=rng.normal(size=(n, 3)),
        voltage=rng.uniform(14, 16, n),
        name="log",
    )
    kw.update(over)
    return FlightLog(**kw)


def _same(a: FlightLog, b: FlightLog, tol=1e-12):
    for f in (
        "t",
        "position",
        "velocity",
        "rates",
        "rpm",
        "command",
        "specific_force",
        "wind",
        "voltage",
    ):
        np.testing.assert_allclose(getattr(a, f), getattr(b, f), rtol=tol, atol=tol, err_msg=f)
    # a quaternion and its negative are one rotation
    np.testing.assert_allclose(a.R_WB(), b.R_WB(), atol=1e-12)


def test_quaternion_matrix_round_trip(rng):
    q = rng.normal(size=(20, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    R = quat_to_matrix(q)
    np.testing.assert_allclose(
        np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)
    # a rotation of 90° about z takes x to y
    qz = np.array([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])
    np.testing.assert_allclose(quat_to_matrix(qz) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_csv_round_trip(tmp_path):
    log = _log()
    back = read_csv(write_csv(log, tmp_path / "f.csv"))
    _same(log, back)
    assert back.name == "f"


def test_csv_conventions_converted(tmp_path):
    """A log written by hand in ENU / FLU, ms, rad/s, other names and rotor order reads back as
    the NED / FRD original: the conversion built here independently of the reader."""
    log = _log()
    T = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])  # NED -> ENU (its own inverse)
    F = np.diag([1.0, -1, -1])  # FRD -> FLU
    R_enu_flu = T @ log.R_WB() @ F
    q = matrix_to_quat(R_enu_flu)
    order = [2, 0, 3, 1]  # the log's column j holds gpg's rotor order.index(j)
    inv = np.argsort(order)
    rpm_log = log.rpm[:, inv] * 2 * np.pi / 60
    names = {"t": "time_ms", "x": "pos_e", "y": "pos_n", "z": "pos_u", "qw": "q0", "rpm1": "w_a"}
    cols = {
        "time_ms": log.t * 1e3,
        "pos_e": (log.position @ T.T)[:, 0],
        "pos_n": (log.position @ T.T)[:, 1],
        "pos_u": (log.position @ T.T)[:, 2],
        **{k: (log.velocity @ T.T)[:, i] for i, k in enumerate(("vx", "vy", "vz"))},
        "q0": q[:, 0],
        "qx": q[:, 1],
        "qy": q[:, 2],
        "qz": q[:, 3],
        **{k: (log.rates @ F.T)[:, i] for i, k in enumerate("pqr")},
        "w_a": rpm_log[:, 0],
        "rpm2": rpm_log[:, 1],
        "rpm3": rpm_log[:, 2],
        "rpm4": rpm_log[:, 3],
        **{f"u{i + 1}": log.command[:, inv][:, i] for i in range(4)},
        **{k: (log.specific_force @ F.T)[:, i] for i, k in enumerate(("ax", "ay", "az"))},
        **{k: (log.wind @ T.T)[:, i] for i, k in enumerate(("wind_x", "wind_y", "wind_z"))},
        "voltage": log.voltage,
    }
    path = tmp_path / "enu.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        w.writerows(np.stack(list(cols.values()), 1).tolist())
    fmt = CsvFormat(
        columns=names,
        world="enu",
        body="flu",
        time_unit="ms",
        rotor_speed="rad/s",
        rotor_order=order,
    )
    _same(log, read_csv(path, fmt), tol=1e-9)


def _write(path, header, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


def test_csv_errors_name_the_column_and_row(tmp_path):
    log = _log(n=10)
    path = write_csv(log, tmp_path / "a.csv")
    text = path.read_text().splitlines()
    header = text[0].split(",")
    rows = [r.split(",") for r in text[1:]]
    # a missing required column
    drop = header.index("qx")
    p = _write(
        tmp_path / "b.csv",
        [h for i, h in enumerate(header) if i != drop],
        [[c for i, c in enumerate(r) if i != drop] for r in rows],
    )
    with pytest.raises(ValueError, match=r"missing column\(s\) \['qx'\] for quaternion"):
        read_csv(p)
    # a cell that is not a number: its column and file row
    bad = [list(r) for r in rows]
    bad[3][header.index("vy")] = "abc"
    with pytest.raises(ValueError, match=r"column 'vy' row 5 is not a number"):
        read_csv(_write(tmp_path / "c.csv", header, bad))
    # a columns map naming no gpg name
    with pytest.raises(ValueError, match="unknown name"):
        CsvFormat(columns={"speed": "v"})
    with pytest.raises(ValueError, match="world must be one of"):
        CsvFormat(world="ecef")
    with pytest.raises(ValueError, match="rotor_order"):
        CsvFormat(rotor_order=(0, 1, 1, 2))
    # neither rotor speeds nor commands
    keep = [i for i, h in enumerate(header) if not h.startswith(("rpm", "u"))]
    p = _write(tmp_path / "d.csv", [header[i] for i in keep], [[r[i] for i in keep] for r in rows])
    with pytest.raises(ValueError, match="needs rotor speed or command columns"):
        read_csv(p)


def test_flightlog_checks():
    base = _log(n=20)
    t = base.t.copy()
    t[7] = t[6]
    with pytest.raises(ValueError, match=r"repeated timestamps\) at 1 row\(s\): \[7\]"):
        _log(n=20, t=t)
    t = base.t.copy()
    t[5], t[6] = t[6], t[5]
    with pytest.raises(ValueError, match="non-monotonic timestamps"):
        _log(n=20, t=t)
    with pytest.raises(ValueError, match="looks like ms or us"):
        _log(n=20, t=base.t * 1e3)
    v = base.velocity.copy()
    v[[3, 9]] = np.nan
    with pytest.raises(ValueError, match=r"velocity holds NaN or inf at 2 row\(s\): \[3, 9\]"):
        _log(n=20, velocity=v)
    q = base.quaternion.copy()
    q[4] *= 1.2
    with pytest.raises(ValueError, match=r"quaternion is far from unit norm at 1 row\(s\): \[4\]"):
        _log(n=20, quaternion=q)
    with pytest.raises(ValueError, match="rpm is negative"):
        _log(n=20, rpm=-base.rpm)
    with pytest.raises(ValueError, match="needs rotor speeds"):
        _log(n=20, rpm=None, command=None)
    with pytest.raises(ValueError, match=r"rates must have shape \(20, 3\)"):
        _log(n=20, rates=base.rates[:, :2])
    t = base.t.copy()
    t[12:] += 1.0
    with pytest.warns(FlightLogWarning, match=r"1 gap\(s\)"):
        _log(n=20, t=t)
    # small rounding of the quaternion is normalised, not refused
    assert np.allclose(
        np.linalg.norm(_log(quaternion=base.quaternion * 1.001, n=20).quaternion, axis=1), 1.0
    )


def test_slice_keeps_checks():
    log = _log(n=40)
    part = log.slice(slice(10, 30))
    assert part.t.size == 20 and part.rpm.shape == (20, 4)
    with pytest.raises(ValueError, match="at least 4 samples"):
        log.slice(slice(0, 2))
