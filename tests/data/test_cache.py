"""The dataset cache: keys that follow the data's config, and publication by rename."""

import numpy as np

from gpg.data import cache
from tests.helpers import compose_plain, synthetic_dataset


def smoke_config(*extra):
    return compose_plain("generate_data", ["data=smoke", *extra])


def test_cache_key_follows_smoke_config():
    a, b = smoke_config(), smoke_config("data.train_seed=5")
    assert cache.dataset_key(a["data"], a["vehicle"]) != cache.dataset_key(b["data"], b["vehicle"])
    c = smoke_config("data.chunk=64")  # memory only: same data, same key
    assert cache.dataset_key(a["data"], a["vehicle"]) == cache.dataset_key(c["data"], c["vehicle"])


def test_publish_lets_the_first_writer_win(tmp_path, monkeypatch):
    """The rename race, deterministically: another writer's complete entry appears first."""
    ds, _ = synthetic_dataset(8, raw=False)
    where = tmp_path / "entry"
    cache.publish(where, ds, ds)
    first = (where / "train.npz").read_bytes()
    cache.publish(where, ds.subset(np.arange(4)), ds)  # the loser's data are dropped
    assert (where / "train.npz").read_bytes() == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["entry"]
