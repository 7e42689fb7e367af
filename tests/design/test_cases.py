"""The ask/tell files: the runs written for an external solver, read back through from_csv,
with forward-difference gradients where a perturbation was run and NaN elsewhere."""

import numpy as np
import pytest

from gpg.data.sampling import FDSteps
from gpg.design import cases
from gpg.names import AERO, INPUTS


def linear(x):
    """Outputs linear in the inputs, so forward differences are exact to rounding."""
    W = np.arange(48, dtype=float).reshape(8, 6) / 100.0
    return x @ W + 1.0


def answer(ask, out, columns=None, units=None, scale_in=None, scale_out=1.0):
    rows = ask.read_text().splitlines()
    head = rows[0].split(",")
    idx = [head.index((columns or {}).get(k, k)) for k in INPUTS]
    lines = [rows[0] + "," + ",".join(AERO)]
    for r in rows[1:]:
        cells = r.split(",")
        x = np.array([float(cells[i]) for i in idx]) * (1.0 if scale_in is None else scale_in)
        lines.append(r + "," + ",".join(repr(float(v)) for v in linear(x) / scale_out))
    out.write_text("\n".join(lines) + "\n")
    return out


def test_ask_tell_round_trip_through_from_csv(tmp_path):
    x = np.array([[1000.0, 2000, 3000, 4000, 0.1, -0.2, 0.3, 5.0],
                  [5000.0, 1000, 2000, 3000, -0.4, 0.5, -0.6, 9.0]])  # fmt: skip
    grads = np.zeros((2, 7), bool)
    grads[0, [0, 4]] = True
    grads[1, 6] = True
    ask = cases.write_ask(tmp_path / "ask.csv", x, grads, fd=FDSteps())
    assert len(ask.read_text().splitlines()) == 1 + 2 + 3  # header, bases, perturbations
    ds = cases.read_tell(answer(ask, tmp_path / "answered.csv"))
    np.testing.assert_allclose(ds.x, x, rtol=1e-15)
    np.testing.assert_allclose(ds.y_aero, linear(x), rtol=1e-12)
    W = np.arange(48, dtype=float).reshape(8, 6) / 100.0
    np.testing.assert_array_equal(ds.gradient_mask, grads)
    for i in range(2):
        for g in np.flatnonzero(grads[i]):
            np.testing.assert_allclose(ds.jac_aero[i, :, g], W[g], rtol=1e-6)
    assert np.isnan(ds.jac_aero[~grads[:, None, :].repeat(6, 1)]).all()
    assert ds.runs == 2 + 3


def test_units_and_columns_of_the_solver(tmp_path):
    x = np.array([[1000.0, 2000, 3000, 4000, 0.1, -0.2, 0.3, 5.0]])
    grads = np.zeros((1, 7), bool)
    grads[0, 5] = True
    cols = {"airspeed": "V_inf", "pitch": "theta"}
    units = {"pitch": "deg", "yaw": "deg", "roll": "deg", "airspeed": "km/h"}
    ask = cases.write_ask(tmp_path / "ask.csv", x, grads, columns=cols, units=units)
    head = ask.read_text().splitlines()[0].split(",")
    assert "V_inf" in head and "theta" in head
    to_si = np.array([1, 1, 1, 1, np.pi / 180, np.pi / 180, np.pi / 180, 1 / 3.6])
    answered = answer(ask, tmp_path / "ans.csv", cols, units, scale_in=to_si)
    ds = cases.read_tell(answered, {**{k: cols.get(k, k) for k in INPUTS}, **{a: a for a in AERO}},
                         units=units)  # fmt: skip
    np.testing.assert_allclose(ds.x, x, rtol=1e-12)
    W = np.arange(48, dtype=float).reshape(8, 6) / 100.0
    np.testing.assert_allclose(ds.jac_aero[0, :, 5], W[5], rtol=1e-6)


def test_broken_answers_are_named(tmp_path):
    x = np.array([[1000.0, 2000, 3000, 4000, 0.1, -0.2, 0.3, 5.0]])
    ask = cases.write_ask(tmp_path / "ask.csv", x, np.ones((1, 7), bool))
    good = answer(ask, tmp_path / "a.csv").read_text().splitlines()
    (tmp_path / "nobase.csv").write_text("\n".join([good[0]] + good[2:]) + "\n")
    with pytest.raises(ValueError, match="no base run"):
        cases.read_tell(tmp_path / "nobase.csv")
    bad = good[:2] + [good[2].replace(",r1,", ",rotor9,")] + good[3:]
    (tmp_path / "label.csv").write_text("\n".join(bad) + "\n")
    with pytest.raises(ValueError, match="neither 'base' nor"):
        cases.read_tell(tmp_path / "label.csv")
    with pytest.raises(ValueError, match="x must be"):
        cases.write_ask(tmp_path / "x.csv", x[:, :7], np.ones((1, 7), bool))
