"""``python -m experiments.design step=merge``: the curves of several runs joined, a later
run's seed replacing an earlier one's, and the summary's medians and ranges at each budget
against values computed here."""

import json

import numpy as np
import pytest

from experiments.runs import design
from tests.helpers import compose_plain


def _curve(runs, base):
    return [{"runs": r, "cases": r, "Fx": base / r, "Mx": base / (2 * r), "L1": base / (3 * r)}
            for r in runs]  # fmt: skip


def test_merge_joins_runs_and_summarises_by_budget(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    (a / "curves.json").write_text(json.dumps({
        "lhs_values": {"0": _curve([200, 500, 1000], 100.0), "1": _curve([200, 500], 120.0)},
        "active_choose": {"0": _curve([200, 250, 300], 50.0)},
    }))  # fmt: skip
    # b runs seed 0 of the active design again, longer: it replaces a's curve
    (b / "curves.json").write_text(
        json.dumps({"active_choose": {"0": _curve(range(200, 1050, 50), 60.0)}})
    )
    cfg = compose_plain("design", ["step=merge", f"merge.runs=[{a},{b}]", "figures=false",
                                   "merge.budgets=[200,500,1000]"])  # fmt: skip
    res = design.run(cfg, tmp_path / "out")
    merged = json.loads((tmp_path / "out" / "curves.json").read_text())
    assert list(merged) == ["lhs_values", "active_choose"]  # the order of design.ARMS
    assert merged["active_choose"]["0"][-1]["runs"] == 1000
    rows = {(r["design"], r["budget"]): r for r in res["summary"]}
    # lhs_values at 500: both seeds, median of 100/500 and 120/500, range between them
    r = rows[("lhs_values", 500)]
    assert r["seeds"] == 2 and r["Fx"] == pytest.approx((0.22, 0.2, 0.24))
    # at 1000 only seed 0 went that far
    assert rows[("lhs_values", 1000)]["seeds"] == 1
    assert rows[("active_choose", 1000)]["Mx"] == pytest.approx((0.03, 0.03, 0.03))
    np.testing.assert_allclose(rows[("active_choose", 500)]["L1"][0], 60.0 / 1500)
    text = (tmp_path / "out" / "summary.md").read_text()
    assert "| lhs_values | 500 | 2 | 0.22 (0.2-0.24) |" in text


def test_merge_refuses_what_it_cannot_read(tmp_path):
    with pytest.raises(ValueError, match="merge.runs"):
        design.run(compose_plain("design", ["step=merge"]), tmp_path / "x")
    with pytest.raises(ValueError, match="no curves.json"):
        design.run(compose_plain("design", ["step=merge", f"merge.runs=[{tmp_path}]"]),
                   tmp_path / "y")  # fmt: skip
    (tmp_path / "curves.json").write_text(json.dumps({"lhs_fancy": {}}))
    with pytest.raises(ValueError, match="unknown arms"):
        design.run(compose_plain("design", ["step=merge", f"merge.runs=[{tmp_path}]"]),
                   tmp_path / "z")  # fmt: skip
