"""Dataset files: exact round trips, partial datasets, CSV import, and clear errors."""

import json
import os

import numpy as np
import pytest

from gpg.data.dataset import Dataset, from_csv


def make(rng, n=12, noise=True, grads=True, raw=True):
    x = np.column_stack(
        [rng.uniform(0, 7000, (n, 4)), rng.uniform(-1, 1, (n, 3)), rng.uniform(0, 20, n)]
    )
    return Dataset(
        x=x,
        y_aero=rng.normal(size=(n, 6)),
        jac_aero=rng.normal(size=(n, 6, 7)) if grads else None,
        y_noise=rng.normal(50, 5, (n, 3)) if noise else None,
        jac_noise=rng.normal(size=(n, 3, 7)) if noise and grads else None,
        x_raw=np.repeat(x, 8, axis=0) if raw else None,
        y_raw=rng.normal(size=(8 * n, 9 if noise else 6)) if raw else None,
        meta={"seed": 3, "bounds": {"rpm": [0.0, 7000.0]}},
    )


ARRAYS = ("x", "y_aero", "jac_aero", "y_noise", "jac_noise", "x_raw", "y_raw")


def test_round_trip_exact_and_deterministic(rng, tmp_path):
    ds = make(rng)
    ds.save(tmp_path / "a")
    back = Dataset.load(tmp_path / "a")
    for k in ARRAYS:
        np.testing.assert_array_equal(getattr(back, k), getattr(ds, k))
    assert back.meta == ds.meta
    ds.save(tmp_path / "b.npz")  # suffix is optional
    for ext in (".npz", ".json"):
        assert (tmp_path / f"a{ext}").read_bytes() == (tmp_path / f"b{ext}").read_bytes()
    side = json.loads((tmp_path / "a.json").read_text())
    assert side["schema_version"] == 1 and side["units"]["yaw"] == "rad" and side["n"] == 12


@pytest.mark.parametrize(
    "kw, lacks",
    [
        (dict(noise=False), ("noise",)),
        (dict(grads=False), ("gradients", "noise gradients")),
        (dict(raw=False), ("raw samples",)),
        (dict(noise=False, grads=False, raw=False), ("noise", "gradients", "raw samples")),
    ],
)
def test_partial_datasets_load_and_say_what_they_lack(rng, tmp_path, kw, lacks):
    ds = make(rng, **kw)
    ds.save(tmp_path / "p")
    back = Dataset.load(tmp_path / "p")
    assert back.missing == lacks
    assert "lacks: " + ", ".join(lacks) in back.summary()
    assert back.y.shape[1] == (6 if "noise" in lacks else 9)
    assert (back.jac is None) == ("gradients" in lacks)


def test_without_and_subset(rng):
    ds = make(rng)
    assert ds.without("noise").missing == ("noise",)
    assert ds.without("noise").y_raw.shape == (96, 6)
    sub = ds.subset(np.array([2, 5]))
    np.testing.assert_array_equal(sub.x_raw, ds.x_raw[16:24].tolist() + ds.x_raw[40:48].tolist())
    with pytest.raises(ValueError, match="unknown parts"):
        ds.without("colour")


@pytest.mark.parametrize(
    "field, bad_row", [("x", 3), ("y_aero", 0), ("jac_aero", 7), ("y_noise", 11), ("y_raw", 40)]
)
def test_nan_rows_reported_by_index(rng, field, bad_row):
    ds = make(rng)
    arrays = {k: getattr(ds, k) for k in ARRAYS}
    arrays[field] = arrays[field].copy()
    arrays[field][bad_row].flat[0] = np.inf if bad_row % 2 else np.nan
    with pytest.raises(ValueError, match=rf"{field} holds NaN or inf in 1 row\(s\): {bad_row}$"):
        Dataset(**arrays)


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda a: a.update(x=a["x"][:, :7]), r"x must have shape \(\*, 8\)"),
        (lambda a: a.update(y_aero=a["y_aero"][:5]), r"y_aero must have shape \(12, 6\)"),
        (lambda a: a.update(jac_aero=a["jac_aero"][:, :, :6]), r"jac_aero must have shape"),
        (lambda a: a.update(y_raw=None), r"x_raw and y_raw must be given together"),
        (
            lambda a: a.update(y_noise=None, y_raw=a["y_raw"][:, :6]),
            r"jac_noise given without y_noise",
        ),
    ],
)
def test_wrong_shapes(rng, edit, match):
    ds = make(rng)
    arrays = {k: getattr(ds, k) for k in ARRAYS}
    edit(arrays)
    with pytest.raises(ValueError, match=match):
        Dataset(**arrays)


def test_negative_rpm_rejected(rng):
    ds = make(rng)
    x = ds.x.copy()
    x[4, 2] = -1.0
    with pytest.raises(ValueError, match=r"negative rotor speeds in row\(s\) \[4\]"):
        Dataset(x=x, y_aero=ds.y_aero)


def test_load_errors(rng, tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        Dataset.load(tmp_path / "nothing")
    make(rng).save(tmp_path / "d")
    side = json.loads((tmp_path / "d.json").read_text())
    side["schema_version"] = 99
    (tmp_path / "d.json").write_text(json.dumps(side))
    with pytest.raises(ValueError, match="schema version 99"):
        Dataset.load(tmp_path / "d")
    make(rng).save(tmp_path / "e")
    (tmp_path / "e.npz").write_bytes((tmp_path / "e.npz").read_bytes()[:100])
    with pytest.raises(ValueError, match="not a readable .npz"):
        Dataset.load(tmp_path / "e")


def test_nothing_written_on_failure(rng, tmp_path):
    (tmp_path / "blocker").write_text("a file where a directory should be")
    with pytest.raises(OSError):
        make(rng).save(tmp_path / "blocker" / "d")
    ds = make(rng)
    object.__setattr__(ds, "y_aero", ds.y_aero[:3])  # corrupt after construction
    with pytest.raises(ValueError):
        ds.save(tmp_path / "bad")
    assert sorted(os.listdir(tmp_path)) == ["blocker"]


# ----------------------------------------------------------------------------------------------
# CSV import
# ----------------------------------------------------------------------------------------------

COLUMNS = {
    "r1": "rpm_1",
    "r2": "rpm_2",
    "r3": "rpm_3",
    "r4": "rpm_4",
    "yaw": "yaw_deg",
    "pitch": "pitch_deg",
    "roll": "roll_deg",
    "airspeed": "V_kmh",
    "Fx": "fx",
    "Fy": "fy",
    "Fz": "fz",
    "Mx": "mx",
    "My": "my",
    "Mz": "mz",
}
UNITS = {"yaw": "deg", "pitch": "deg", "roll": "deg", "airspeed": "km/h", "Fz": "lbf"}


def write_csv(path, rows, header):
    path.write_text(
        ",".join(header) + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n"
    )


def test_csv_import_converts_units(rng, tmp_path):
    n = 5
    raw = np.column_stack(
        [
            rng.uniform(0, 7000, (n, 4)),
            rng.uniform(-80, 80, (n, 3)),
            rng.uniform(0, 70, n),
            rng.normal(size=(n, 6)),
        ]
    )
    header = list(COLUMNS.values()) + ["dFx/dyaw_per_deg"]
    dfx = rng.normal(size=n)
    write_csv(tmp_path / "t.csv", np.column_stack([raw, dfx]), header)
    ds = from_csv(tmp_path / "t.csv", COLUMNS, units=UNITS)
    np.testing.assert_allclose(ds.x[:, 4:7], np.deg2rad(raw[:, 4:7]), rtol=1e-15)
    np.testing.assert_allclose(ds.x[:, 7], raw[:, 7] / 3.6, rtol=1e-15)
    np.testing.assert_allclose(ds.y_aero[:, 2], raw[:, 10] * 4.4482216152605, rtol=1e-15)
    assert ds.missing == ("noise", "gradients", "raw samples")
    assert ds.meta["source"] == "csv:t.csv"


def test_csv_gradients_converted(rng, tmp_path):
    n = 3
    cols = dict(COLUMNS)
    grads = {
        f"d{o}/d{i}": f"g_{o}_{i}"
        for o in ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
        for i in ("r1", "r2", "r3", "r4", "yaw", "pitch", "roll")
    }
    cols.update(grads)
    data = rng.normal(size=(n, len(cols))) + 100
    write_csv(tmp_path / "g.csv", data, list(cols.values()))
    ds = from_csv(tmp_path / "g.csv", cols, units={"yaw": "deg", "Fz": "lbf"})
    j = list(cols).index("dFz/dyaw")
    np.testing.assert_allclose(
        ds.jac_aero[:, 2, 4], data[:, j] * 4.4482216152605 / (np.pi / 180), rtol=1e-14
    )
    assert ds.missing == ("noise", "raw samples")


@pytest.mark.parametrize(
    "cols, units, match",
    [
        ({**COLUMNS, "Fw": "fw"}, {}, r"unknown schema fields \['Fw'\]"),
        ({**COLUMNS, "Fx": "force_x"}, {}, r"CSV columns \['force_x'\] not in"),
        (COLUMNS, {"yaw": "gradians"}, r"unknown unit 'gradians' for yaw"),
        (COLUMNS, {"wind": "m/s"}, r"units given for unknown fields \['wind'\]"),
        ({k: v for k, v in COLUMNS.items() if k != "Mz"}, {}, r"lacks required fields \['Mz'\]"),
        ({**COLUMNS, "L1": "fx"}, {}, r"noise needs all of"),
    ],
)
def test_csv_errors(rng, tmp_path, cols, units, match):
    write_csv(tmp_path / "e.csv", rng.uniform(1, 2, (3, 14)), list(COLUMNS.values()))
    with pytest.raises(ValueError, match=match):
        from_csv(tmp_path / "e.csv", cols, units=units)


def test_csv_bad_values_named_by_line_and_column(rng, tmp_path):
    rows = rng.uniform(1, 2, (4, 14)).astype(object)
    rows[2, 9] = "nan"  # data row 3 = CSV line 4 (the header is line 1), column "fy"
    rows[0, 0] = "inf"
    write_csv(tmp_path / "n.csv", rows, list(COLUMNS.values()))
    with pytest.raises(
        ValueError, match=r"line 2, column 1 \('rpm_1'\): inf; line 4, column 10 \('fy'\): nan$"
    ):
        from_csv(tmp_path / "n.csv", COLUMNS)
    rows[0, 0] = 1.0
    rows[2, 9] = "abc"
    write_csv(tmp_path / "n.csv", rows, list(COLUMNS.values()))
    with pytest.raises(ValueError, match=r"line 4, column 10 \('fy'\): not a number \('abc'\)"):
        from_csv(tmp_path / "n.csv", COLUMNS)
    with pytest.raises(ValueError, match="does not exist"):
        from_csv(tmp_path / "missing.csv", COLUMNS)


def test_csv_gradients_by_pattern_with_units(rng, tmp_path):
    """42 gradient columns named from the CSV's own headers, converted per deg and per lbf."""
    n = 4
    grad_heads = [
        f"d{COLUMNS[o]}_d{COLUMNS[i]}"
        for o in ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
        for i in ("r1", "r2", "r3", "r4", "yaw", "pitch", "roll")
    ]
    data = rng.uniform(1, 2, (n, 14 + 42))
    write_csv(tmp_path / "p.csv", data, list(COLUMNS.values()) + grad_heads)
    ds = from_csv(tmp_path / "p.csv", COLUMNS, units=UNITS, gradients="d{output}_d{input}")
    j = 14 + grad_heads.index("dfz_dyaw_deg")
    np.testing.assert_allclose(
        ds.jac_aero[:, 2, 4], data[:, j] * 4.4482216152605 / (np.pi / 180), rtol=1e-14
    )
    j = 14 + grad_heads.index("dmx_drpm_2")
    np.testing.assert_allclose(ds.jac_aero[:, 3, 1], data[:, j], rtol=1e-15)
    # Schema names in the pattern work too; a header the pattern names but the file lacks fails.
    write_csv(tmp_path / "q.csv", data[:, :20], list(COLUMNS.values()) + grad_heads[:6])
    with pytest.raises(ValueError, match=r"CSV columns \[.*'dfx_droll_deg'.*not in q.csv"):
        from_csv(tmp_path / "q.csv", COLUMNS, gradients="d{output}_d{input}")
    with pytest.raises(ValueError, match="bad gradients pattern"):
        from_csv(tmp_path / "p.csv", COLUMNS, gradients="d{out}_d{input}")
    with pytest.raises(ValueError, match="gives the same header twice"):
        from_csv(tmp_path / "p.csv", COLUMNS, gradients="d{output}")


def test_csv_records_vehicle_and_bounds(rng, tmp_path):
    rows = rng.uniform(1, 2, (3, 14))
    rows[:, 4:7] = 0.5  # radians, inside the default box of the bounds not given
    write_csv(tmp_path / "v.csv", rows, list(COLUMNS.values()))
    bounds = {"rpm": [0.0, 9000.0], "airspeed": [0.0, 15.0]}
    ds = from_csv(tmp_path / "v.csv", COLUMNS, vehicle="minimal_example", bounds=bounds)
    assert ds.meta["vehicle"]["name"] == "minimal_example" and ds.meta["bounds"] == bounds
    ds.save(tmp_path / "saved")
    assert Dataset.load(tmp_path / "saved").meta["vehicle"]["mass"] == 0.5
    with pytest.raises(ValueError, match=r"bounds.rpm is inverted"):
        from_csv(tmp_path / "v.csv", COLUMNS, bounds={"rpm": [10.0, 0.0]})
    with pytest.raises(ValueError, match="no vehicle file 'no_such_quad'"):
        from_csv(tmp_path / "v.csv", COLUMNS, vehicle="no_such_quad")


def test_saved_files_are_not_private(rng, tmp_path):
    """Results and datasets get a plain file's permissions, not mkstemp's 0600."""
    import os

    from gpg._io import umask

    npz, side = Dataset(x=rng.uniform(0, 1, (3, 8)), y_aero=rng.normal(size=(3, 6))).save(
        tmp_path / "d"
    )
    for p in (npz, side):
        assert os.stat(p).st_mode & 0o777 == 0o666 & ~umask()


def test_names_table_is_consistent():
    """One table: the gradient dims name the rotor speeds and angles, and every column has a
    unit."""
    from gpg import names

    assert names.GRAD_INPUTS == ("r1", "r2", "r3", "r4", "yaw", "pitch", "roll")
    assert set(names.UNITS) == set(names.INPUTS + names.BODY_INPUTS + names.OUTPUTS)


def test_csv_refuses_what_it_cannot_read_unambiguously(rng, tmp_path):
    header = list(COLUMNS.values())
    rows = rng.uniform(1, 2, (3, 14)).round(3)
    good = ",".join(header) + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n"
    f = tmp_path / "x.csv"
    # An unquoted thousands separator: one field more on that line, named with a hint.
    lines = good.splitlines()
    lines[2] = "3,600.5," + lines[2].split(",", 1)[1]
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(
        ValueError, match="x.csv, line 3: 15 fields, but the header has 14 .*thousands"
    ):
        from_csv(f, COLUMNS)
    lines = good.splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0]
    f.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match="x.csv, line 4: 13 fields, but the header has 14"):
        from_csv(f, COLUMNS)
    # A duplicated header name would let one of the two columns silently win.
    f.write_text(good.replace("rpm_2", "rpm_1", 1))
    with pytest.raises(ValueError, match="header 'rpm_1' appears twice \\(columns 1 and 2\\)"):
        from_csv(f, COLUMNS)
    # One CSV column mapped to two fields.
    f.write_text(good)
    with pytest.raises(ValueError, match="CSV column 'fx' is mapped to 2 fields \\['Fx', 'Fy'\\]"):
        from_csv(f, {**COLUMNS, "Fy": "fx"})
    # A UTF-8 byte-order mark is read (Excel writes one); other encodings are named.
    f.write_bytes(b"\xef\xbb\xbf" + good.encode())
    np.testing.assert_allclose(from_csv(f, COLUMNS).x[:, 0], rows[:, 0])
    f.write_bytes(good.encode().replace(b"rpm_3", b"rpm\xe9_3", 1))
    with pytest.raises(ValueError, match="x.csv, line 1, byte 16: not UTF-8"):
        from_csv(f, COLUMNS)
    # A cell beyond the csv module's limit (131072 characters).
    f.write_text(good.replace(str(rows[1, 0]), '"' + "1" * 200_000 + '"', 1))
    with pytest.raises(ValueError, match="x.csv, line 3: unreadable CSV: field larger"):
        from_csv(f, COLUMNS)
    f.write_text("")
    with pytest.raises(ValueError, match="x.csv is empty"):
        from_csv(f, COLUMNS)


def test_dataset_values_checked_where_they_enter():
    from tests.helpers import synthetic_dataset

    ds, _ = synthetic_dataset(6, seed=2)
    x = ds.x.copy()
    x[2, 7] = -1.0
    with pytest.raises(ValueError, match=r"negative airspeed .* row\(s\) \[2\]"):
        Dataset(x=x, y_aero=ds.y_aero)
    with pytest.raises(ValueError, match="x must be real, got a complex array"):
        Dataset(x=ds.x + 1j, y_aero=ds.y_aero)
    with pytest.raises(ValueError, match="y_aero must be numbers, got a boolean array"):
        Dataset(x=ds.x, y_aero=ds.y_aero > 0)
    with pytest.raises(ValueError, match="x_raw has 47 rows; .* 8 per point \\(48 rows"):
        Dataset(x=ds.x, y_aero=ds.y_aero, x_raw=ds.x_raw[:47], y_raw=ds.y_raw[:47, :6])


def test_cases_outside_the_declared_bounds_are_refused(rng, tmp_path):
    """A CSV whose angles lie far outside the box the same call declares (degrees read as
    radians, yaw 400°), and metadata whose bounds are inverted: refused, naming rows, input
    and value. Cases on the box's edge are inside."""
    rows = rng.uniform(1, 2, (4, 14))
    rows[:, 4:7] = [[10, 5, 0]] * 4
    rows[1, 4], rows[3, 5] = 400.0, 1e6
    write_csv(tmp_path / "a.csv", rows, list(COLUMNS.values()))
    units = {"yaw": "deg", "pitch": "deg", "roll": "deg"}
    bounds = {"yaw_deg": [-90, 90], "pitch_deg": [-60, 60]}
    with pytest.raises(ValueError, match=r"2 case\(s\) outside .* row\(s\) \[1, 3\]: row 1 has "
                       r"yaw = 400°, outside \[-90, 90\]°"):  # fmt: skip
        from_csv(tmp_path / "a.csv", COLUMNS, units=units, bounds=bounds)
    rows[1, 4], rows[3, 5] = 90.0, -60.0
    write_csv(tmp_path / "b.csv", rows, list(COLUMNS.values()))
    from_csv(tmp_path / "b.csv", COLUMNS, units=units, bounds=bounds)
    ds = make(rng)
    with pytest.raises(ValueError, match=r"meta\['bounds'\].yaw_deg is inverted"):
        Dataset(x=ds.x, y_aero=ds.y_aero, meta={"bounds": {"yaw_deg": [90, -90]}})
    with pytest.raises(ValueError, match=r"meta\['bounds'\] must be a mapping"):
        Dataset(x=ds.x, y_aero=ds.y_aero, meta={"bounds": [[0, 7000]]})


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"columns": None}, "from_csv: columns is required"),
        ({"columns": list(COLUMNS)}, "from_csv: columns must be a mapping"),
        ({"units": ["deg"]}, "from_csv: units must be a mapping"),
        ({"bounds": [[-90, 90]]}, "bounds must be a mapping of"),
        ({"bounds": {"yaw_deg": ["a", "b"]}}, r"bounds.yaw_deg must be two numbers"),
    ],
)
def test_csv_arguments_of_the_wrong_kind_are_named(rng, tmp_path, kwargs, match):
    write_csv(tmp_path / "a.csv", rng.uniform(1, 2, (3, 14)), list(COLUMNS.values()))
    with pytest.raises(ValueError, match=match):
        from_csv(tmp_path / "a.csv", **{"columns": COLUMNS, **kwargs})


def test_an_npz_member_that_is_not_an_array_is_named(rng, tmp_path):
    import zipfile

    make(rng).save(tmp_path / "d")
    with zipfile.ZipFile(tmp_path / "d.npz", "a") as z:
        z.writestr("notes.txt", "hello")
    with pytest.raises(ValueError, match=r"members that are not numeric arrays: \['notes.txt'\]"):
        Dataset.load(tmp_path / "d")


def test_repeated_inputs_are_found_and_warned_about(rng):
    """Identical inputs with different outputs (or gradients) and exact copies: grouped by
    row; ``prepare`` warns with how many, where, and what the fitted noise does."""
    from gpg.data import prepare

    ds = make(rng, raw=False)
    x, y, jac = ds.x.copy(), ds.y_aero.copy(), ds.jac_aero.copy()
    x[[5, 9]], y[[5, 9]], jac[[5, 9]] = x[2], y[2], jac[2]  # row 2 three times, equal
    x[7], y[7], jac[7] = x[1], y[1], jac[1] + 1.0  # row 1 twice, other gradients
    noise, jac_noise = ds.y_noise.copy(), ds.jac_noise.copy()
    noise[[5, 9]], noise[7] = noise[2], noise[1]
    jac_noise[[5, 9]], jac_noise[7] = jac_noise[2], jac_noise[1]
    rep = Dataset(x=x, y_aero=y, jac_aero=jac, y_noise=noise, jac_noise=jac_noise)
    conflicting, identical = rep.repeated_inputs()
    assert [g.tolist() for g in conflicting] == [[1, 7]]
    assert [g.tolist() for g in identical] == [[2, 5, 9]]
    assert make(rng).repeated_inputs() == ([], [])
    with pytest.warns(UserWarning, match=r"1 group\(s\) of cases share an identical input but "
                      r"have different outputs or gradients: rows \[\[1, 7\]\].*value noise ν² "
                      r"grows"):  # fmt: skip
        with pytest.warns(UserWarning, match=r"exact copies .* rows \[\[2, 5, 9\]\]"):
            prepare(rep, None)


def test_body_frame_dataset_shapes_ball_and_csv(rng, tmp_path):
    """``meta["frame"] == "body"``: seven inputs ``r1..r4, u, v, w``, the ball of the declared
    airspeed (a case in its box but outside the ball is named), and a CSV import of body-frame
    columns with gradients along ``u, v, w``."""
    n = 4
    x = np.column_stack([rng.uniform(0, 7000, (n, 4)), rng.uniform(-5, 5, (n, 3))])
    meta = {"frame": "body", "bounds": {"rpm": [0.0, 7000.0], "airspeed": [0.0, 20.0]}}
    ds = Dataset(
        x=x, y_aero=rng.normal(size=(n, 6)), jac_aero=rng.normal(size=(n, 6, 7)), meta=meta
    )
    assert ds.inputs == ("r1", "r2", "r3", "r4", "u", "v", "w")
    ds.save(tmp_path / "body")
    back = Dataset.load(tmp_path / "body")
    assert back.frame == "body" and np.array_equal(back.jac_aero, ds.jac_aero)
    assert json.loads((tmp_path / "body.json").read_text())["inputs"][4:] == ["u", "v", "w"]
    with pytest.raises(ValueError, match=r"x must have shape \(\*, 7\)|x must have shape"):
        Dataset(x=np.c_[x, np.ones(n)], y_aero=ds.y_aero, meta=meta)
    far = x.copy()
    far[2, 4:] = [12.0, 12.0, 12.0]
    with pytest.raises(
        ValueError, match=r"outside the ball .* row\(s\) \[2\]: row 2 has \|\(u, v, w\)\| = 20.78"
    ):
        Dataset(x=far, y_aero=ds.y_aero, meta=meta)
    with pytest.raises(ValueError, match="meta\\['frame'\\] must be one of"):
        Dataset(x=x, y_aero=ds.y_aero, meta={"frame": "wind"})
    cols = {f: f.upper() for f in ("r1", "r2", "r3", "r4", "u", "v", "w")}
    cols.update({f: f for f in ("Fx", "Fy", "Fz", "Mx", "My", "Mz")})
    header = list(cols.values()) + [
        f"d{o}_d{i}"
        for o in ("Fx", "Fy", "Fz", "Mx", "My", "Mz")
        for i in cols
        if i in "r1r2r3r4uvw"
    ]
    body = np.column_stack([x, ds.y_aero, ds.jac_aero.reshape(n, -1)])
    write_csv(tmp_path / "b.csv", body, header)
    got = from_csv(
        tmp_path / "b.csv",
        cols,
        gradients="d{output_field}_d{input_field}",
        units={"u": "km/h"},
        bounds={"rpm": [0, 7000], "airspeed": [0, 30]},
        frame="body",
    )
    assert got.frame == "body"
    np.testing.assert_allclose(got.x[:, 4], x[:, 4] / 3.6, rtol=1e-15)
    np.testing.assert_allclose(got.jac_aero[:, :, 5:], ds.jac_aero[:, :, 5:], rtol=1e-15)
    np.testing.assert_allclose(got.jac_aero[:, :, 4], ds.jac_aero[:, :, 4] * 3.6, rtol=1e-14)
    with pytest.raises(ValueError, match=r"unknown schema fields \['yaw'\] \(frame 'body'\)"):
        from_csv(tmp_path / "b.csv", {**cols, "yaw": "R1"}, frame="body")
