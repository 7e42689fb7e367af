"""``experiments.generate_data`` end to end on a tiny config composed with Hydra."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from experiments.runs import generate_data
from gpg.data.dataset import Dataset
from tests.helpers import compose_plain

ROOT = Path(__file__).resolve().parents[2]


def config(tmp_path, *extra):
    overrides = [
        "data=smoke",
        "data.n_train=6",
        "data.n_test=4",
        "data.chunk=32",
        "sanity_points=4",
        f"cache_dir={tmp_path / 'cache'}",
        *extra,
    ]
    return compose_plain("generate_data", overrides)


def test_generate_data_run_from_cache(smoke_cache, tmp_path):
    """The entry point's run() on a cached dataset: files copied, results written."""
    cfg = compose_plain(
        "generate_data",
        ["data=smoke", "data.chunk=32", f"cache_dir={smoke_cache}", "figures=false"],
    )
    res = generate_data.run(cfg, tmp_path)
    assert res["dataset"]["cached"] is True
    assert Dataset.load(tmp_path / "train").n == 60
    assert json.loads((tmp_path / "results.json").read_text())["simple_model"]["P_F"] > 0


@pytest.mark.slow
def test_generate_data_run(tmp_path):
    out1, out2 = tmp_path / "run1", tmp_path / "run2"
    out1.mkdir()
    out2.mkdir()
    res = generate_data.run(config(tmp_path), out1)
    assert res["dataset"]["cached"] is False
    for name in ("train.npz", "train.json", "test.npz", "test.json", "results.json"):
        assert (out1 / name).is_file()
    for fig in ("thrust_vs_rpm", "wrench_vs_airspeed", "oaspl_vs_rpm", "fd_vs_exact_gradients"):
        assert (out1 / "figures" / f"{fig}.png").is_file()
    train = Dataset.load(out1 / "train")
    assert train.n == 6 and train.missing == () and train.meta["simple_model"]["P_F"] > 0
    assert Dataset.load(out1 / "test").missing == ("gradients", "noise gradients", "raw samples")
    saved = json.loads((out1 / "results.json").read_text())
    assert saved["config"]["data"]["n_train"] == 6 and 3300 < saved["hover_rpm_simple_model"] < 3900

    again = generate_data.run(config(tmp_path, "figures=false"), out2)  # from the cache
    assert again["dataset"]["cached"] is True and again["dataset"]["key"] == res["dataset"]["key"]
    assert (out1 / "train.npz").read_bytes() == (out2 / "train.npz").read_bytes()


@pytest.mark.parametrize(
    "override, match",
    [
        ("data.bounds.rpm=[7000.0,0.0]", r"bounds.rpm is inverted"),
        ("data.test_seed=0", r"must differ"),
        ("+data.generator.blades=3", r"unknown data.generator keys \['blades'\]"),
    ],
)
def test_bad_config_writes_nothing(tmp_path, override, match):
    out = tmp_path / "run"
    out.mkdir()
    with pytest.raises(ValueError, match=match):
        generate_data.run(config(tmp_path, override), out)
    assert list(out.iterdir()) == []
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def test_bad_numbers_name_their_key(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    with pytest.raises(ValueError, match=r"data.n_train must be an integer >= 1, got 'abc'"):
        generate_data.run(config(tmp_path, "data.n_train=abc"), out)


def _cli(tmp_path, run, cache):
    return [
        sys.executable,
        "-m",
        "experiments.generate_data",
        "data=smoke",
        "data.n_train=6",
        "data.n_test=4",
        "data.chunk=32",
        "figures=false",
        f"cache_dir={cache}",
        f"hydra.run.dir={run}",
    ]


def _leftovers(cache):
    return sorted(p.name for p in cache.glob("*partial*")) if cache.exists() else []


@pytest.mark.slow
def test_ctrl_c_exits_cleanly_and_a_rerun_completes(tmp_path):
    """SIGINT while the generator compiles: a message, exit 130 (no segfault), no partial cache
    entry; the next run generates the data."""
    cache, run = tmp_path / "cache", tmp_path / "run"
    p = subprocess.Popen(
        _cli(tmp_path, run, cache), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    deadline = time.monotonic() + 120
    while not (run / ".hydra").is_dir() and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.05)
    time.sleep(1.5)  # inside the run: importing done, the hover sweep compiling
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=300)
    err = err.decode()
    assert p.returncode == 130, err[-2000:]
    assert "interrupted: stopped cleanly" in err and "Traceback" not in err
    assert _leftovers(cache) == [] and not any(cache.glob("*/train.npz"))
    again = subprocess.run(
        _cli(tmp_path, tmp_path / "run2", cache), cwd=ROOT, capture_output=True, timeout=300
    )
    assert again.returncode == 0, again.stderr.decode()[-2000:]
    assert len(list(cache.glob("*/train.npz"))) == 1 and _leftovers(cache) == []


@pytest.mark.slow
def test_concurrent_writers_of_one_cache_both_succeed(tmp_path):
    cache = tmp_path / "cache"
    procs = [
        subprocess.Popen(
            _cli(tmp_path, tmp_path / f"run{i}", cache),
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for i in range(2)
    ]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err.decode()[-2000:]
    assert _leftovers(cache) == [] and len(list(cache.glob("*/train.npz"))) == 1
    a, b = ((tmp_path / f"run{i}" / "train.npz").read_bytes() for i in range(2))
    assert a == b
