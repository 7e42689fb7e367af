"""gpg.flight.log: the FlightLog checks, the CSV form and its conversions."""

import csv
import math
import os
import stat
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gpg.flight.log import (
    CsvFormat,
    FlightLog,
    FlightLogWarning,
    matrix_to_quat,
    quat_to_matrix,
    read_csv,
    write_csv,
)
from tests.flight.flights import consistent_flight


def _log(n=400, rate=100.0, seed=0, **over):
    return consistent_flight(n=n, rate=rate, seed=seed, **over)


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
    with pytest.raises(ValueError, match=r"column 'vy' line 5 is not a number"):
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


# -- hostile input: every case refused or flagged, never read as another flight ---------------


def _table(tmp_path, log=None):
    path = write_csv(_log() if log is None else log, tmp_path / "a.csv")
    lines = path.read_text().splitlines()
    return path, lines[0].split(","), [r.split(",") for r in lines[1:]]


def test_flightlog_copies_its_arrays():
    log = _log(n=400)
    v = log.velocity.copy()
    own = _log(n=400, velocity=v)
    assert v.flags.writeable  # the caller's array stays the caller's
    v[3] = np.nan  # and writing into it afterwards does not reach the log
    assert np.isfinite(own.velocity).all() and not own.velocity.flags.writeable


def test_flightlog_refuses_values_of_another_range():
    base = _log(n=400)
    with pytest.raises(ValueError, match=r"command is outside 0..1 at \d+ row.*\(u \+ 1\) / 2"):
        _log(n=400, command=2 * base.command - 1)
    with pytest.raises(ValueError, match=r"voltage is 0 V or less at 400 row"):
        _log(n=400, voltage=np.zeros(400))
    with pytest.raises(ValueError, match=r"seconds declared as ms or us"):
        _log(n=400, t=base.t * 1e-3)  # seconds read as ms: a 0.4 s flight at 100 kHz


def test_csv_unit_order_and_time_mistakes_are_refused_naming_the_signals(tmp_path):
    path, header, rows = _table(tmp_path)
    col = {h: i for i, h in enumerate(header)}

    def scaled(names, k):
        out = [list(r) for r in rows]
        for r in out:
            for n in names:
                r[col[n]] = repr(float(r[col[n]]) * k)
        return _write(tmp_path / "m.csv", header, out)

    with pytest.raises(ValueError, match="position against velocity.*x 1e\\+03"):
        read_csv(scaled(("x", "y", "z"), 1000.0))  # positions in mm
    with pytest.raises(ValueError, match="attitude against rates.*z 0.0175.*deg/s"):
        read_csv(scaled(("p", "q", "r"), 180 / math.pi))  # rates in deg/s
    # a scalar-last quaternion written into qw..qz
    last = [list(r) for r in rows]
    for r in last:
        r[col["qw"]], r[col["qx"]], r[col["qy"]], r[col["qz"]] = (
            r[col["qx"]], r[col["qy"]], r[col["qz"]], r[col["qw"]])  # fmt: skip
    with pytest.raises(ValueError, match="attitude against rates.*inconsistent"):
        read_csv(_write(tmp_path / "q.csv", header, last))
    # seconds declared as ms
    with pytest.raises(ValueError, match="seconds declared as ms"):
        read_csv(path, time_unit="ms")
    # and unchecked, the log is read as it is
    assert read_csv(scaled(("x", "y", "z"), 1000.0), check=False).position.max() > 100


def test_csv_structure_mistakes_are_refused_naming_the_line(tmp_path):
    path, header, rows = _table(tmp_path)
    dup = list(header)
    dup[header.index("qx")] = "vx"  # a duplicated name: the last would win
    with pytest.raises(ValueError, match=r"column\(s\) \['vx'\] appear more than once"):
        read_csv(_write(tmp_path / "d.csv", dup, rows))
    text = path.read_text().splitlines()
    i = text[5].index(".")
    comma = text[:5] + [text[5][:i] + "," + text[5][i + 1 :]] + text[6:]  # 3500,5 unquoted
    (tmp_path / "c.csv").write_text("\n".join(comma) + "\n")
    n = len(header)
    with pytest.raises(ValueError, match=f"line 6 has {n + 1} fields, the header {n}: a decimal"):
        read_csv(tmp_path / "c.csv")
    (tmp_path / "u.csv").write_text("\n".join(text[:5] + ['"' + text[5]] + text[6:]) + "\n")
    with pytest.raises(ValueError, match="not valid CSV.*unclosed quote"):
        read_csv(tmp_path / "u.csv")


def test_csv_cut_inside_its_last_number_drops_that_row_with_a_warning(tmp_path):
    path, _, _ = _table(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[:-4])  # '3500.0' becomes '35' and no line break ends the file
    with pytest.warns(FlightLogWarning, match="does not end with a line break"):
        back = read_csv(path)
    _same(_log().slice(slice(0, 399)), back)


@pytest.mark.parametrize(
    ("encode", "match"),
    [
        (lambda s: s.encode("utf-16"), "not UTF-8 text.*UTF-16 or Latin-1"),
        (lambda s: s.replace("t,", "t°,", 1).encode("latin-1"), "not UTF-8 text"),
        (lambda s: s.encode("utf-16-le"), "NUL bytes"),
        (lambda s: b"ULog\x01\x12\x35\x01" + s.encode(), "a PX4 ULog file.*read_ulog"),
    ],
)
def test_csv_files_that_are_not_utf8_text_are_named(tmp_path, encode, match):
    path, _, _ = _table(tmp_path)
    path.write_bytes(encode(path.read_text()))
    with pytest.raises(ValueError, match=match):
        read_csv(path)


def test_csv_utf8_with_a_byte_order_mark_reads(tmp_path):
    path, _, _ = _table(tmp_path)
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    _same(_log(), read_csv(path))


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"columns": None}, "columns must be a mapping"),
        ({"columns": {"x": "px", "y": "px"}}, "one column to two"),
        ({"world": ["ned"]}, "world must be one of"),
        ({"rotor_order": None}, "rotor_order must be 4 distinct integer"),
        ({"rotor_order": "abcd"}, "rotor_order must be 4 distinct integer"),
        ({"rotor_order": "0123"}, "rotor_order must be 4 distinct integer"),
        ({"rotor_order": (0.5, 1, 2, 3)}, "rotor_order must be 4 distinct integer"),
        ({"rotor_order": (0, 1, 2, 5)}, r"names motor index 5, but the log has 4"),
    ],
)
def test_csv_format_errors_name_the_field(options, match):
    with pytest.raises(ValueError, match=match):
        CsvFormat(**options)


def test_write_csv_keeps_links_modes_and_the_source(tmp_path):
    log = _log()
    target = write_csv(log, tmp_path / "target.csv")
    target.chmod(0o600)
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    write_csv(log.slice(slice(0, 100)), link)
    assert link.is_symlink() and os.readlink(link) == str(target)  # the link kept
    assert read_csv(target).t.size == 100  # its target replaced
    assert stat.S_IMODE(target.stat().st_mode) == 0o600  # a private file stays private
    # over the file it was read from: refused, naming what would be lost
    path, header, rows = _table(tmp_path)
    _write(path, [*header, "battery_temp"], [[*r, "31.5"] for r in rows])
    read = read_csv(path)
    assert read.source == str(path)
    lost = r"lose its column\(s\) \['battery_temp'\].*replace_source"
    with pytest.raises(ValueError, match=lost):
        write_csv(read, path)
    write_csv(read, path, replace_source=True)
    assert "battery_temp" not in path.read_text()
    # paths that cannot be written name themselves
    with pytest.raises(ValueError, match="path must be a file path"):
        write_csv(log, "")
    assert read_csv(write_csv(log, tmp_path / ("n" * 246 + ".csv"))).t.size == log.t.size
    with pytest.raises(ValueError, match="file name is 304 bytes long, more than the 255"):
        write_csv(log, tmp_path / ("n" * 300 + ".csv"))


# -- the property: a written table, mangled by one of the mistakes above, is read back equal,
# or refused, or flagged; never read as other numbers without a word --------------------------

_GROUP_COLUMNS = {
    "position": ("x", "y", "z"),
    "velocity": ("vx", "vy", "vz"),
    "rates": ("p", "q", "r"),
    "specific_force": ("ax", "ay", "az"),
}
# The unit mistakes users make: mm, cm, km/h, deg/s, g, and their inverses.
_FACTORS = (1e-3, 1e-2, 1 / 3.6, 3.6, 180 / math.pi, math.pi / 180, 100.0, 1e3, 9.81, 1 / 9.81)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    log = _log()
    path = write_csv(log, tmp_path_factory.mktemp("prop") / "flight.csv")
    return log, path.read_text()


def _mangle(draw, text: str) -> tuple[str, bytes, dict]:
    """One mistake of the issue's list, its parameters drawn: (kind, the file's bytes, the
    format options it is read with)."""
    lines = text.splitlines(keepends=True)
    header = lines[0].strip().split(",")
    kind = draw(st.sampled_from(["cut", "comma", "duplicate", "time", "order", "units", "enc"]))
    opts: dict = {}
    if kind == "cut":
        data = text.encode()[: draw(st.integers(1, len(text) - 1))]
        return kind, data, opts
    if kind == "comma":
        r = draw(st.integers(1, len(lines) - 1))
        cells = lines[r].rstrip("\n").split(",")
        c = draw(st.sampled_from([i for i, v in enumerate(cells) if "." in v]))
        cells[c] = cells[c].replace(".", ",", 1)
        lines[r] = ",".join(cells) + "\n"
    elif kind == "duplicate":
        i, j = draw(st.lists(st.integers(0, len(header) - 1), min_size=2, max_size=2, unique=True))
        header[i] = header[j]
        lines[0] = ",".join(header) + "\n"
    elif kind == "time":
        opts["time_unit"] = draw(st.sampled_from(["ms", "us"]))
    elif kind == "order":
        perm = draw(st.permutations(["qw", "qx", "qy", "qz"]).filter(lambda p: p[0] != "qw"))
        idx = [header.index(q) for q in ("qw", "qx", "qy", "qz")]
        for i, name in zip(idx, perm, strict=True):
            header[i] = name
        lines[0] = ",".join(header) + "\n"
    elif kind == "units":
        names = _GROUP_COLUMNS[draw(st.sampled_from(sorted(_GROUP_COLUMNS)))]
        k = draw(st.sampled_from(_FACTORS))
        cols = [header.index(n) for n in names]
        for r in range(1, len(lines)):
            cells = lines[r].rstrip("\n").split(",")
            for c in cols:
                cells[c] = repr(float(cells[c]) * k)
            lines[r] = ",".join(cells) + "\n"
    elif kind == "enc":
        enc = draw(st.sampled_from(["utf-16", "utf-16-le", "latin-1"]))
        return kind, ("t°" + "".join(lines)[1:]).encode(enc), opts
    return kind, "".join(lines).encode(), opts


@settings(max_examples=80, deadline=None, derandomize=True, database=None)
@given(data=st.data())
def test_property_a_mangled_table_is_read_equal_or_refused_or_flagged(written, data):
    log, text = written
    kind, blob, opts = _mangle(data.draw, text)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "mangled.csv"
        path.write_bytes(blob)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                back = read_csv(path, **opts)
            except ValueError:
                return  # refused, with a message
    if any(issubclass(w.category, FlightLogWarning) for w in caught):
        return  # flagged
    # accepted silently: then it is the flight (or, cut exactly at a line break, its start)
    assert kind == "cut", kind
    _same(log.slice(slice(0, back.t.size)), back)
