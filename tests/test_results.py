"""The comparison's typed results: one record per model run, written and read by one pair."""

import json

import pytest

from gpg.results import Comparison, ModelRun, Skipped, read_results, write_results


def run_record(**over) -> ModelRun:
    names = ["Fx", "L1"]
    per = dict(zip(names, [0.5, 1.25], strict=True))
    kw = dict(
        model="gpgs",
        title="GP-G-S",
        config={"hyper": {"noise": 1e-8}},
        timings={"hyper_s": 1.5, "partition_s": 0.25, "fit_s": 2.0},
        train_s=3.75,
        mae=per,
        rmse=per,
        nlpd=per,
        nlpd_mean=0.875,
        coverage95=per,
        coverage95_mean=0.9,
        negative_variance_count=0,
        negative_variance_fraction=0.0,
        continuity={"pairs": 3, "mean_jump_max": per},
        output_scale=[1.0, 2.0],
        hyper_converged=True,
        lengthscale=[0.5, 0.7],
        signal_variance=1.2,
        noise_variance=1e-3,
        noise_ratio=1e-3 / 1.2,
        diagnostics={},
        near_fraction=0.125,
        near_epsilon=0.3,
        model_bytes=1024,
        peak_memory_bytes=None,
        error_vs_airspeed={"edges": [0.0, 1.0], "mean_abs_error": [[0.1, 0.2]]},
        predict_ms_median=0.4,
        predict_ms_p95=0.6,
        predict_mean_ms_median=0.01,
        predict_mean_ms_p95=0.02,
    )
    return ModelRun(**{**kw, **over})


def test_results_round_trip_through_the_typed_record(tmp_path):
    comp = Comparison(
        models={
            "gpgs": run_record(predict_ratio_to_gp=0.05),
            "gpgs[near.budget=0.25]": run_record(near_fraction=0.25),
            "gpg": Skipped("gpg", "needs gradients, which the dataset lacks"),
        },
        outputs=["Fx", "L1"],
        n_train=30,
        n_test=12,
        data={"key": "smoke"},
        noise_reference=None,
        figures=[],
        wall_s=4.0,
        machine={"cpu": "test"},
        config={"n_queries": 5},
    )
    write_results(tmp_path / "results.json", comp)
    back = read_results(tmp_path)
    assert back == comp
    raw = json.loads((tmp_path / "results.json").read_text())
    # The file's layout: timings flat beside train_s, a skipped run as its reason.
    assert raw["models"]["gpgs"]["fit_s"] == 2.0 and "timings" not in raw["models"]["gpgs"]
    assert raw["models"]["gpg"] == {"model": "gpg", "skipped": comp.models["gpg"].reason}
    assert "predict_ratio_to_gp" not in raw["models"]["gpgs[near.budget=0.25]"]
    assert list(back.ran) == ["gpgs", "gpgs[near.budget=0.25]"]


def test_an_unknown_key_in_a_results_entry_is_an_error():
    entry = run_record().to_json() | {"mea": {}}
    with pytest.raises(ValueError, match=r"unknown keys \['mea'\]"):
        ModelRun.from_json(entry)
