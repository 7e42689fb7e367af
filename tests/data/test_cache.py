"""The dataset cache: keys that follow the data's config, and publication by rename."""

import numpy as np
import pytest

from gpg.data import cache
from tests.helpers import compose_plain, synthetic_dataset


def smoke_config(*extra):
    return compose_plain("generate_data", ["data=smoke", *extra])


def test_cache_key_follows_smoke_config():
    a, b = smoke_config(), smoke_config("data.train_seed=5")
    assert cache.dataset_key(a["data"], a["vehicle"]) != cache.dataset_key(b["data"], b["vehicle"])
    for same in ("data.chunk=64", "data.workers=3"):  # how, not what: same data, same key
        c = smoke_config(same)
        assert cache.dataset_key(a["data"], a["vehicle"]) == cache.dataset_key(
            c["data"], c["vehicle"]
        )


def test_workers_must_be_a_positive_integer():
    for bad in (0, True, 1.5):
        with pytest.raises(ValueError, match="data.workers must be a positive integer"):
            cache.check_numbers({**smoke_config()["data"], "workers": bad})


def test_publish_lets_the_first_writer_win(tmp_path, monkeypatch):
    """The rename race, deterministically: another writer's complete entry appears first."""
    ds, _ = synthetic_dataset(8, raw=False)
    where = tmp_path / "entry"
    cache.publish(where, ds, ds)
    first = (where / "train.npz").read_bytes()
    cache.publish(where, ds.subset(np.arange(4)), ds)  # the loser's data are dropped
    assert (where / "train.npz").read_bytes() == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["entry"]


def test_unwritable_cache_is_found_before_generating(tmp_path):
    from experiments.runs.config import conf
    from gpg.data.cache import ensure_datasets

    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    with pytest.raises(
        ValueError, match="the dataset cache directory \\(cache_dir\\) .* is not writable"
    ):
        ensure_datasets(conf("smoke", "data"), conf("sui_endurance", "vehicle"), blocker / "cache")


def test_mirror_images_are_added_after_the_cache(tmp_path):
    """``data.mirror`` doubles (or quadruples) the body-frame training set as it is loaded,
    never the test set; it is not part of the cache key; airflow-frame data refuse it."""
    from tests.helpers import synthetic_body_dataset

    train, _ = synthetic_body_dataset(8, seed=0)
    test, _ = synthetic_body_dataset(5, seed=1)
    train.save(tmp_path / "train")
    test.save(tmp_path / "test")
    cfg = compose_plain("compare", ["data=envelope_smoke", "data.mirror=[x]"])
    cfg["dataset"] = {"train": str(tmp_path / "train"), "test": str(tmp_path / "test")}
    got_train, got_test, _ = cache.load_data(cfg)
    assert got_train.n == 16 and got_test.n == 5 and got_train.meta["mirrored"] == ["x"]
    plain = dict(cfg["data"], mirror=[])
    assert cache.dataset_key(cfg["data"], cfg["vehicle"]) == cache.dataset_key(
        plain, cfg["vehicle"]
    )
    with pytest.raises(ValueError, match="data.mirror takes body-frame data"):
        cache.check_numbers(dict(compose_plain("compare", ["data=smoke"])["data"], mirror=["x"]))
    with pytest.raises(ValueError, match="data.mirror must be a list of body axes"):
        cache.check_numbers(dict(cfg["data"], mirror=["z"]))
