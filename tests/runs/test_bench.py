"""``experiments.bench`` on smoke data with small sizes: both suites run and write their JSON,
including the float32 check of the surrogate."""

import json

import numpy as np
import pytest

from experiments.runs import bench
from tests.helpers import compose_plain, finite_numbers


@pytest.mark.slow  # the whole bench entry point (a whole experiment)
def test_bench_run(smoke_cache, tmp_path):
    overrides = [
        "data=smoke",
        f"models.cache_dir={smoke_cache}",
        "exact_gp.n_points=20",
        "exact_gp.n_queries=3",
        "exact_gp.batch=8",
        "exact_gp.repeats=1",
        "models.models=[gps_1x]",
        "models.n_queries=3",
        "models.batch=8",
        "models.batch_repeats=2",
        "models.compile_repeats=1",
        "+models.model.hyper.fit=false",
        "+models.model.partition.bins=2",
        "suites=[exact_gp,models,solver]",
        f"solver.cache_dir={smoke_cache}",
        "solver.tols=[1e-6]",
        "+solver.model.hyper.fit=false",
        "+solver.model.solver.points=20",
    ]
    bench.run(compose_plain("bench", overrides), tmp_path)
    saved = json.loads((tmp_path / "bench.json").read_text())
    assert finite_numbers({k: v for k, v in saved.items() if k != "config"})
    assert saved["exact_gp"]["rows"] == 20 * 8
    hyb = saved["models"]["models"]["gps_1x"]
    assert hyb["mean_batch_per_s"] > 0 and hyb["surrogate_predict_1"]["n"] == 3
    assert hyb["surrogate_compile"]["median_s"] > 0
    f32 = hyb["float32"]
    assert f32["dtype"] == "float32" and 0 <= f32["mean_error_over_std_max"] < 1e-2
    assert np.isfinite(f32["variance_error_over_var_max"])
    runs = saved["solver"]["runs"]
    assert set(runs) == {"cg tol=1e-06", "cholesky"} and runs["cg tol=1e-06"]["cg_iterations"] > 0
    assert max(runs["cg tol=1e-06"]["max_diff_std"].values()) < 1e-3


@pytest.mark.slow
def test_bench_derivatives_and_envs_suites(smoke_cache, tmp_path):
    overrides = [
        "data=smoke",
        "suites=[derivatives,envs]",
        f"derivatives.cache_dir={smoke_cache}",
        f"envs.cache_dir={smoke_cache}",
        "derivatives.models=[gpgs]",
        "derivatives.n_states=4",
        "derivatives.repeats=1",
        "+derivatives.model.hyper.fit=false",
        "+derivatives.model.partition.bins=2",
        "+derivatives.model.near.budget=0.5",
        "+envs.model.hyper.fit=false",
        "+envs.model.partition.points_per_bin=30",
        "envs.n_envs=[2]",
        "envs.steps=3",
        "envs.repeats=1",
    ]
    bench.run(compose_plain("bench", overrides), tmp_path)
    saved = json.loads((tmp_path / "bench.json").read_text())
    d = saved["derivatives"]["models"]["gpgs"]
    assert d["force"]["rev_vs_fd_max"] < 1e-5 and d["variance"]["fwd_vs_rev_max"] < 1e-8
    assert d["jacrev_batch"]["states_per_s"] > 0
    assert set(saved["envs"]["runs"]) == {"surrogate/2", "M/2"}
    assert all(r["env_steps_per_s"] > 0 for r in saved["envs"]["runs"].values())


@pytest.mark.slow
def test_bench_devices_suite(smoke_cache, tmp_path):
    overrides = [
        "data=smoke",
        "suites=[devices]",
        f"devices.cache_dir={smoke_cache}",
        "devices.device_counts=[1]",
        "devices.train_models=[gps_1x]",
        "devices.predict_model=gps_1x",
        "+devices.model.hyper.fit=false",
        "+devices.model.partition.bins=2",
        "devices.repeats=1",
        "devices.batches=[40]",
        "devices.chunk=16",
        "devices.batch_repeats=1",
        "devices.workers=[1]",
        "devices.generate_rows=32",
        "devices.chunk_generate=32",
    ]
    bench.run(compose_plain("bench", overrides), tmp_path)
    saved = json.loads((tmp_path / "bench.json").read_text())["devices"]
    assert finite_numbers(saved)
    assert set(saved["build"]["gps_1x"]) == {"host", "1"}
    assert set(saved["predict"]) == {"40/mean/1", "40/mean_var/1"}
    assert saved["predict"]["40/mean/1"]["per_s"] > 0
    assert saved["generate"]["rows"] == 32 and set(saved["generate"]["seconds"]) == {"1"}


@pytest.mark.slow  # compiles the export and its timing driver twice
def test_bench_export_suite(tmp_path):
    overrides = ["suites=[export]", "export.n_points=[60]", "export.c_calls=200",
                 "export.jax_calls=20", "export.runs=3"]  # fmt: skip
    bench.run(compose_plain("bench", overrides), tmp_path)
    row = json.loads((tmp_path / "bench.json").read_text())["export"]["sizes"]["60"]
    for dtype, size in (("double", 8), ("float", 4)):
        # the mean's positions (double) and coefficients, then the variance's bins
        assert row[dtype]["constant_bytes"] > 60 * 8 * 8 + 60 * 72 * size
        assert 0 < row[dtype]["median_us"] <= row[dtype]["p95_us"]
        runs = row[dtype]["runs_median_us"]  # the mean's three runs, its figures the middle's
        assert len(runs) == 3 and row[dtype]["median_us"] == sorted(runs)[1]
        assert 0 < row[dtype]["predict"]["median_us"] <= row[dtype]["predict"]["p95_us"]
        assert row[dtype]["in_domain"] == 200 == row[dtype]["predict"]["in_domain"]
    assert row["realtime_over_c_double"] > 0
    assert row["casadi"]["generated_c"]["in_domain"] == 200
    assert row["casadi"]["python_call"]["median_s"] > 0


@pytest.mark.slow  # a whole bench suite at a smoke size: corrections, C compiled and timed
def test_bench_flight_suite(tmp_path):
    """``suites=[flight]`` at a smoke size (the parallel logs left out: spawned processes):
    every part writes finite figures, and the C part times the adapted and the tracked
    model's calls (with a wind state too) in both dtypes."""
    overrides = ["suites=[flight]", "flight.log.repeats=1", "flight.update.n_points=40",
                 "flight.update.labels=60", "flight.update.inducing=6", "flight.update.updates=20",
                 "flight.update.stacked.labels=80", "flight.update.stacked.inducing=16",
                 "flight.update.stacked.updates=20", "flight.update.stacked.block=10",
                 "flight.update.stacked.rounds=2",
                 "flight.update.stacked.bank.inducing=4",
                 "flight.parallel=null", "flight.c.n_points=40", "flight.c.labels=60",
                 "flight.c.inducing=12", "flight.c.online=6", "flight.c.c_calls=50",
                 "flight.c.python_calls=30",
                 "flight.every_label.n_points=40", "flight.every_label.hours=[0.01]",
                 "flight.every_label.inducing=12", "flight.every_label.warmup=60"]  # fmt: skip
    bench.run(compose_plain("bench", overrides), tmp_path)
    res = json.loads((tmp_path / "bench.json").read_text())["flight"]
    assert finite_numbers(res) and set(res) == {"log", "update", "c", "every_label"}
    calls = ("mean", "predict", "online_update", "online_predict", "tracked_update",
             "tracked_predict", "wind_update", "wind_predict", "bank_update",
             "bank_predict")  # fmt: skip
    for dtype in ("double", "float"):
        for key in calls:
            t = res["c"][dtype][key]
            assert t["n"] == 50 and 0 < t["median_us"] <= t["p95_us"], (dtype, key)
        for kind in ("tracked", "wind", "bank"):  # from Python, through gpg.export.to_native
            for key in ("update", "predict"):
                t = res["c"][dtype][f"{kind}_python"][key]
                assert t["n"] == 30 and 0 < t["median_us"] <= t["p95_us"], (dtype, kind, key)
    assert res["every_label"]["runs"][0]["labels"] == 360
    for name in ("tracked", "wind_state", "bank"):  # three forms interleaved, ratios a round
        st = res["update"]["stacked"][name]
        assert len(st["ratio"]) == 2 == len(st["donated_ratio"]) == len(st["donated_median_s"])
    assert res["update"]["stacked"]["bank"]["inducing"] == 4
    band = res["update"]["stacked"]["bank"]["offline_band"]  # the bank's step's band alone
    assert band["update_s"]["n"] == 20 and band["share_of_stacked"] > 0 and band["view_bytes"] > 0


@pytest.mark.slow  # a whole bench suite, like the others (its parts: tests/gp/test_binned.py,
# tests/linalg/test_device.py, tests/test_precision.py)
def test_bench_gpu_suite_on_the_cpu(smoke_cache, synthetic_surrogate, tmp_path):
    """The accelerator suite runs on whatever JAX's default device is (here the CPU): fits,
    throughput in both dtypes, the float32 error in newtons, environment steps."""
    from experiments.runs.bench_gpu import bench_gpu, gpu_table

    cfg = compose_plain("bench", ["data=smoke"])
    sub = {
        **cfg["gpu"],
        "data": cfg["data"],
        "vehicle": cfg["vehicle"],
        "cache_dir": str(smoke_cache),
        "fits": [
            {
                "data": "smoke",
                "model": "gpgs_hybrid",
                "overrides": {
                    "hyper": {"fit": False},
                    "partition": {"points_per_bin": None, "bins": 2},
                    "near": {"points": 20},
                },
            }
        ],
        "states": 40,
        "error_states": 40,
        "chunks": [16],
        "repeats": 1,
        "n_envs": [4],
        "env_steps": 2,
    }
    res = bench_gpu(sub)
    assert res["platform"] == "cpu" and finite_numbers(res["throughput"])
    assert set(res["throughput"]) == {"float64", "float32"}
    assert set(res["throughput"]["float32"]) == {"mean/chunk=16", "mean+var/chunk=16"}
    # The float32 program's force within float32 rounding of forces of tens of newtons.
    assert 0 <= res["float32_error"]["force_max"] < 1e-2
    assert res["env"]["4"]["env_steps_per_s"] > 0
    assert res["fits"]["gpgs_hybrid@smoke"]["fit_s"] > 0
    assert "M states/s" in gpu_table(res)
    # A saved model instead of a fit (the same model on every machine), more gathered tiles.
    from gpg import checkpoint

    path = checkpoint.save(tmp_path / "sur", synthetic_surrogate)
    res = bench_gpu({**sub, "fits": [], "checkpoint": str(path), "tiles": [8]})
    assert res["checkpoint"] == str(path) and "gather/tile=8" in res["variance_methods"]
    assert 0 <= res["float32_error_test_set"]["force_max"] < 1e-2
