"""``experiments.compare`` on smoke data, composed with Hydra, and its error messages."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments.compare import model_configs
from experiments.runs import compare
from tests.helpers import compose_plain, finite_numbers, synthetic_dataset

ROOT = Path(__file__).resolve().parents[2]


def config(tmp_path, *extra):
    overrides = ["data=smoke", "data.chunk=32", f"cache_dir={tmp_path / 'cache'}", "n_queries=20"]
    return compose_plain("compare", [*overrides, *extra])


@pytest.mark.slow
def test_whole_comparison_on_smoke(smoke_compare):
    out, res = smoke_compare
    saved = json.loads((out / "results.json").read_text())
    labels = {
        "gp",
        "gpg",
        "gps_1x",
        "gps_8x",
        "gpgs",
        "gpgs_schur",
        "gpgs_schur[mean=paper]",
        "gpgs_hybrid",
        "gpg_pic",
    }
    assert set(saved["models"]) == labels
    assert finite_numbers(saved)
    for r in saved["models"].values():
        for key in (
            "train_s",
            "predict_ms_median",
            "predict_ms_p95",
            "mae",
            "rmse",
            "nlpd",
            "coverage95",
            "negative_variance_count",
            "continuity",
            "noise_ratio",
            "output_scale",
            "near_fraction",
            "model_bytes",
            "peak_memory_bytes",
        ):
            assert key in r
        assert set(r["mae"]) == {"Fx", "Fy", "Fz", "Mx", "My", "Mz", "L1", "L2", "L3"}
        if r["negative_variance_count"] < res["n_test"]:
            assert r["coverage95_mean"] == pytest.approx(np.mean(list(r["coverage95"].values())))
        else:  # no usable variance at all: reported as missing, not as a huge NLPD
            assert r["nlpd_mean"] is None and r["coverage95_mean"] is None
        assert r["continuity"]["pairs"] > 0
    m = saved["models"]
    for name in ("gp", "gpg"):  # the exact GPs' 95 % intervals are not far off on smoke data
        assert m[name]["coverage95_mean"] > 0.5
    # The hybrid's mean is GP-G's mean (one hyperparameter fit shared), and continuous.
    for n in ("Fx", "Mx", "L1"):
        assert m["gpgs_hybrid"]["mae"][n] == pytest.approx(m["gpg"]["mae"][n], rel=1e-8)
        assert m["gpgs_hybrid"]["continuity"]["mean_jump_max"][n] < 1e-4 * m["gpg"]["mae"][n]
        assert m["gpgs"]["continuity"]["mean_jump_max"][n] > 1e-3 * m["gpg"]["mae"][n]
    assert m["gpgs_schur"]["diagnostics"]["far_correlation_median"] > 0
    assert m["gpg_pic"]["diagnostics"]["inducing_points"] == 20
    assert saved["models"]["gp"]["predict_ratio_to_gp"] == 1.0
    assert (out / "results.md").read_text().count("| gpgs_schur") == 2
    for fig in (
        "model_compare",
        "model_compare_all_outputs",
        "schur_compare",
        "schur_mean_forms",
        "error_vs_airspeed",
    ):
        assert (out / "figures" / f"{fig}.png").is_file()
        assert (out / "figures" / f"{fig}.pdf").is_file()
    assert res["n_train"] == 60 and res["n_test"] == 200


def user_dataset_config(tmp_path, *extra):
    """The comparison's config on a small saved train/test pair of the user's own."""
    synthetic_dataset(30, seed=1)[0].save(tmp_path / "train")
    synthetic_dataset(12, seed=2, raw=False)[0].save(tmp_path / "test")
    paths = [f"dataset.train={tmp_path / 'train'}", f"dataset.test={tmp_path / 'test'}"]
    return config(tmp_path, *paths, "figures=false", *extra)


def test_single_model_and_user_dataset(tmp_path):
    cfg = user_dataset_config(
        tmp_path, "+model=gpgs", "model.partition.bins=3", "model.hyper.fit=false"
    )
    out = tmp_path / "run"
    out.mkdir()
    res = compare.run(cfg, out, model_configs(cfg))
    assert list(res["models"]) == ["gpgs"] and finite_numbers(res)


def test_missing_gradients_single_model_is_an_error(tmp_path):
    train, _ = synthetic_dataset(30, seed=1)
    train.without("gradients").save(tmp_path / "train")
    synthetic_dataset(12, seed=2, raw=False)[0].save(tmp_path / "test")
    cfg = config(
        tmp_path,
        "+model=gpg",
        f"dataset.train={tmp_path / 'train'}",
        f"dataset.test={tmp_path / 'test'}",
        "figures=false",
    )
    with pytest.raises(ValueError, match="model 'gpg' needs gradients, which the dataset lacks"):
        compare.run(cfg, tmp_path, model_configs(cfg))
    # Running every model instead skips those that cannot run, saying why.
    cfg = config(
        tmp_path,
        f"dataset.train={tmp_path / 'train'}",
        f"dataset.test={tmp_path / 'test'}",
        "figures=false",
        "models=[gpg,gps_1x]",
        "n_queries=5",
    )
    res = compare.run(cfg, tmp_path, model_configs(cfg))
    assert "needs gradients" in res["models"]["gpg"]["skipped"] and "mae" in res["models"]["gps_1x"]


def test_unknown_model_in_list(tmp_path):
    with pytest.raises(ValueError, match=r"unknown model 'gpgs_shur' in models; valid: \['gp'"):
        model_configs(config(tmp_path, "models=[gpg,gpgs_shur]"))


def cli(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "experiments.compare", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_cli_errors_are_one_clear_message(tmp_path):
    """A bad config or input is one line on stderr, and a failed run leaves no run directory
    behind."""
    p = cli("+model=gpgs_shur", f"hydra.run.dir={tmp_path}", cwd=ROOT)
    assert p.returncode != 0
    assert "Could not find 'model/gpgs_shur'" in p.stderr and "gpgs_schur" in p.stderr
    run = tmp_path / "run"
    p = cli(
        "dataset.train=/no/such/train",
        "dataset.test=/no/such/test",
        f"hydra.run.dir={run}",
        cwd=ROOT,
    )
    assert p.returncode == 2 and not run.exists()
    assert (
        p.stderr.strip().splitlines()[-1] == "error: dataset file /no/such/train.npz does not exist"
    )


@pytest.mark.slow  # a whole comparison in a subprocess; the CLI's errors have fast tests
def test_cli_run_logs_its_table(smoke_cache, tmp_path):
    """A successful CLI run: results files readable by others, and the table in compare.log."""
    import os

    from gpg._io import umask

    run = tmp_path / "run"
    p = cli(
        "+model=gps_1x",
        "data=smoke",
        "data.chunk=32",
        f"cache_dir={smoke_cache}",
        "n_queries=5",
        "figures=false",
        f"hydra.run.dir={run}",
        cwd=ROOT,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    log = (run / "compare.log").read_text()
    assert "| model | train s |" in log and "| gps_1x |" in log
    for name in ("results.json", "results.md"):
        assert os.stat(run / name).st_mode & 0o777 == 0o666 & ~umask()


@pytest.mark.slow
def test_noise_model_both_runs_each_model_with_and_without_m_noise(tmp_path):
    train, _ = synthetic_dataset(30, seed=1)
    test, _ = synthetic_dataset(12, seed=2, raw=False)
    train.save(tmp_path / "train")
    test.save(tmp_path / "test")
    over = [f"dataset.train={tmp_path / 'train'}", f"dataset.test={tmp_path / 'test'}"]
    cfg = config(tmp_path, *over, "figures=false", "models=[gps_1x]", "noise_model=both")
    cfg["model_overrides"] = {"hyper": {"fit": False}, "partition": {"bins": 3}}
    out = tmp_path / "run"
    out.mkdir()
    res = compare.run(cfg, out, model_configs(cfg))
    assert list(res["models"]) == ["gps_1x", "gps_1x+M_noise"] and finite_numbers(res)
    plain, with_noise = (res["models"][k]["mae"] for k in ("gps_1x", "gps_1x+M_noise"))
    assert plain["Fx"] == pytest.approx(with_noise["Fx"], rel=1e-9)  # same targets, same fit
    assert plain["L3"] != with_noise["L3"]
    ref = res["noise_reference"]
    assert set(ref) == {"m_noise_alone", "training_mean"} and set(ref["training_mean"]) == {
        "L1",
        "L2",
        "L3",
    }
    assert "of `M_noise` alone: L1" in (out / "results.md").read_text()
    with pytest.raises(ValueError, match="noise_model must be true, false or both, got 'yes'"):
        compare.run({**cfg, "noise_model": "yes"}, out, model_configs(cfg))


@pytest.mark.parametrize(
    "override, match",
    [
        ("model_overrides=5", "model_overrides must be a mapping or null, got 5"),
        ("devices=abc", "devices must be null or a number of devices >= 1, got 'abc'"),
        ("n_queries=-1", "n_queries must be an integer >= 1, got -1"),
        ("figures=maybe", "figures must be true or false"),
    ],
)
def test_bad_overrides_fail_before_any_work(tmp_path, override, match):
    from experiments.runs import compare

    values = compose_plain(
        "compare",
        ["data=smoke", override, "dataset.train=/no/such/train", "dataset.test=/no/t"],
    )
    with pytest.raises(ValueError, match=match):  # not the missing dataset: checked first
        compare.run(values, tmp_path, model_configs(values))


def test_runs_started_in_the_same_second_get_their_own_directories():
    """The run directory carries a per-run id next to the time (the cache stays shared)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import experiments._hydra  # noqa: F401  (registers the resolver, as the entry points do)
    from experiments.runs.config import CONF_DIR

    dirs = []
    for _ in range(2):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name="compare", return_hydra_config=True)
            dirs.append(OmegaConf.to_container(cfg.hydra.run, resolve=True)["dir"])
            assert cfg.cache_dir == "data/cache"
    assert dirs[0] != dirs[1] and all(d.startswith("outputs/") for d in dirs)
