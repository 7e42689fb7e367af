"""``experiments.design`` composed with Hydra on smoke data: the unattended loop for two
rounds (the generator answering the ask files), ask then tell for an external solver, and the
bench suite. Whole experiments: the slow set (their pieces have fast tests in tests/design and
tests/gp/test_update.py)."""

import json

import numpy as np
import pytest

from experiments.runs import design
from gpg.data.dataset import Dataset
from gpg.design import cases
from tests.helpers import compose_plain, finite_numbers

pytestmark = pytest.mark.slow

SMALL = [
    "data=smoke",
    "design.batch=4",
    "design.candidates=300",
    "design.reference=64",
    "progress=false",
    "model.name=gpg",
]


def test_active_loop_runs_two_rounds(smoke_cache, tmp_path):
    overrides = SMALL + [
        f"cache_dir={smoke_cache}",
        "+experiment=active",
        "active.arms=[active_gradients]",
        "active.seeds=[0]",
        "active.initial=10",
        "active.budget=144",  # 80 runs to start, 32 per round: two rounds
        "+model.hyper.max_steps=5",
        "active.lhs_runs=[64]",
        "figures=true",
    ]
    res = design.run(compose_plain("design", overrides), tmp_path)
    curve = res["curves"]["active_gradients"]["0"]
    assert [p["runs"] for p in curve] == [80, 112, 144]
    assert [p.get("update") for p in curve] == [None, "condition", "refit"]
    assert finite_numbers(json.loads((tmp_path / "results.json").read_text()))
    assert (tmp_path / "figures" / "learning_curves.png").is_file()
    assert (tmp_path / "seed0" / "all" / "round02" / "answered.csv").is_file()


def test_ask_then_tell(smoke_cache, tmp_path):
    asked = design.run(
        compose_plain("design", SMALL + [f"cache_dir={smoke_cache}", "step=ask"]), tmp_path / "a"
    )
    assert asked["cases"] == 4
    from experiments.runs.config import conf
    from gpg.data.cache import build_generator

    gen = build_generator(conf("smoke", "data"), conf("sui_endurance", "vehicle"))
    answered = design.answer(gen, tmp_path / "a" / "ask.csv", tmp_path / "answered.csv")
    told = design.run(
        compose_plain("design", SMALL + [f"cache_dir={smoke_cache}", "step=tell",
                                         f"tell.results={answered}"]),
        tmp_path / "t",
    )  # fmt: skip
    grown = Dataset.load(told["dataset"])
    assert grown.n == 60 + 4 and told["runs"] == asked["runs"]
    assert np.array_equal(cases.read_tell(answered).x, grown.x[60:])
    with pytest.raises(ValueError, match="step must be one of"):
        design.run(compose_plain("design", SMALL + ["step=fly"]), tmp_path / "x")
    with pytest.raises(ValueError, match="design.batch|batch must be"):
        design.run(compose_plain("design", SMALL + ["design.batch=0"]), tmp_path / "y")


def test_bench_design_suite(smoke_cache):
    """The ``design`` bench suite on smoke data: conditioning equals the rebuild; the refit
    with its likelihood fit is timed when asked for."""
    from experiments.runs.bench_design import bench_design, design_table
    from experiments.runs.config import conf

    cfg = {"data": conf("smoke", "data"), "vehicle": conf("sui_endurance", "vehicle"),
           "cache_dir": str(smoke_cache), "added": 6, "models": ["gpg"], "candidates": 200,
           "reference": 32, "batch": 3, "isolate": True, "refit": True}  # fmt: skip
    res = bench_design(cfg)
    assert res["gpg"]["max_diff_mean"] < 1e-8 and res["gpg"]["max_diff_var"] < 1e-8
    g = res["gpg"]
    assert g["refit_s"] > 0 and g["ratio_refit"] == pytest.approx(g["condition_s"] / g["refit_s"])
    assert res["propose"]["batch"] == 3
    assert "condition s" in design_table(res)
