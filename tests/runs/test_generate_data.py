"""``experiments.generate_data`` end to end on a tiny config composed with Hydra."""

import json

import pytest

from gpg.data.dataset import Dataset
from gpg.runs import generate_data
from tests.helpers import compose_plain


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


def test_cache_key_follows_config(tmp_path):
    a, b = config(tmp_path), config(tmp_path, "data.train_seed=5")
    assert generate_data.dataset_key(a["data"], a["vehicle"]) != generate_data.dataset_key(
        b["data"], b["vehicle"]
    )
    c = config(tmp_path, "data.chunk=64")  # memory only: same data, same key
    assert generate_data.dataset_key(a["data"], a["vehicle"]) == generate_data.dataset_key(
        c["data"], c["vehicle"]
    )


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
