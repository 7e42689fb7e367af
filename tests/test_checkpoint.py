"""Checkpoints: bit-for-bit round trips and clear errors for missing, damaged or foreign data."""

import json
import os
import shutil

import numpy as np
import pytest

from gpg import checkpoint
from gpg.checkpoint import CheckpointError
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset

CFG = {
    "hyper": {"fit": False, "lengthscale": 0.8, "jitter": 1e-4},
    "partition": {"bins": 3, "points_per_bin": None},
    "near": {"budget": 0.5, "points": None},
    "inducing": {"points": 6},
}


@pytest.fixture(scope="module")
def data():
    return synthetic_dataset(40, seed=5)[0]


@pytest.fixture(scope="module")
def surrogate(data):
    return Surrogate.fit(data, "gpgs_hybrid", CFG)


def queries(data):
    return (
        data.x[:6, :4],
        data.x[:6, 4:7],
        np.column_stack([data.x[:6, 7], np.zeros(6), np.ones(6)]),
    )


@pytest.mark.parametrize("name", ["gpgs_hybrid", "gpg_pic", "gpg"])
def test_round_trip_bit_for_bit(data, surrogate, tmp_path, name):
    if name == "gpgs_hybrid":
        sur = surrogate
    elif name == "gpg_pic":
        sur = Surrogate.fit(data, "gpg_pic", CFG)
    else:
        sur = Surrogate.fit(data, "gpg", {"hyper": {"fit": False}}, hover_speed=0.3)
    checkpoint.save(tmp_path / "ck", sur)
    back = checkpoint.load(tmp_path / "ck")
    a, b = sur.predict_batch(*queries(data)), back.predict_batch(*queries(data))
    for field in ("force", "torque", "noise", "variance", "in_domain"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert back.config == sur.config and back.output_names == sur.output_names
    assert back.hover_speed == sur.hover_speed
    meta = checkpoint.read_metadata(tmp_path / "ck")
    assert meta["model_name"] == name and meta["format_version"] == checkpoint.FORMAT_VERSION
    assert "y_std" in meta["normalisation"] and "lengthscale" in meta["hyperparameters"]
    if name != "gpg":
        assert meta["partition"]["n_bins"] == 3


def test_overwrite_and_existing(surrogate, tmp_path):
    checkpoint.save(tmp_path / "ck", surrogate)
    with pytest.raises(CheckpointError, match="exists; pass overwrite=True"):
        checkpoint.save(tmp_path / "ck", surrogate)
    checkpoint.save(tmp_path / "ck", surrogate, overwrite=True)
    assert sorted(os.listdir(tmp_path)) == ["ck"]


def test_missing_and_foreign(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        checkpoint.load(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="metadata.json is missing"):
        checkpoint.load(tmp_path / "empty")


def resign(meta):
    """Metadata edited on purpose, with a valid checksum (to reach the checks behind it)."""
    meta["metadata_sha256"] = checkpoint._meta_digest(meta)
    return json.dumps(meta)


def test_version_mismatch(surrogate, tmp_path):
    checkpoint.save(tmp_path / "ck", surrogate)
    meta = json.loads((tmp_path / "ck" / "metadata.json").read_text())
    meta["format_version"] = 7
    (tmp_path / "ck" / "metadata.json").write_text(resign(meta))
    with pytest.raises(CheckpointError, match="format version 7; this gpg .* reads version 4"):
        checkpoint.load(tmp_path / "ck")


def test_truncated_or_damaged(surrogate, tmp_path, capfd):
    checkpoint.save(tmp_path / "ck", surrogate)
    shutil.copytree(tmp_path / "ck", tmp_path / "ck2")
    # Truncate the biggest data file of the orbax checkpoint: named, and nothing else printed.
    files = [p for p in (tmp_path / "ck" / "arrays").rglob("*") if p.is_file()]
    big = max(files, key=lambda p: p.stat().st_size)
    big.write_bytes(big.read_bytes()[: big.stat().st_size // 2])
    capfd.readouterr()
    with pytest.raises(CheckpointError, match=f"{big.name} is damaged: it fails its checksum"):
        checkpoint.load(tmp_path / "ck")
    out, err = capfd.readouterr()
    assert "Traceback" not in err + out and "asyncio" not in err + out
    shutil.rmtree(tmp_path / "ck2" / "arrays")
    with pytest.raises(CheckpointError, match="incomplete: the arrays directory is missing"):
        checkpoint.load(tmp_path / "ck2")


def test_checksum_catches_silent_change(surrogate, tmp_path):
    checkpoint.save(tmp_path / "ck", surrogate)
    meta = json.loads((tmp_path / "ck" / "metadata.json").read_text())
    key = next(iter(meta["arrays"]))
    meta["arrays"][key]["sha256"] = "0" * 64
    (tmp_path / "ck" / "metadata.json").write_text(resign(meta))
    with pytest.raises(CheckpointError, match=f"array {key} .* fails its shape/dtype/checksum"):
        checkpoint.load(tmp_path / "ck")


def test_metadata_bit_flip_is_caught(surrogate, tmp_path):
    """One flipped bit in a static field (hover_speed 0.5 -> 0.7 in the module tree) changes
    predictions: the metadata's own checksum catches it."""
    checkpoint.save(tmp_path / "ck", surrogate)
    f = tmp_path / "ck" / "metadata.json"
    raw = bytearray(f.read_bytes())
    text = raw.decode()
    at = text.index('"hover_speed"')
    at = text.index("0.5", at) + 2  # the digit 5
    raw[at] ^= 0b10  # '5' (0x35) -> '7' (0x37)
    f.write_bytes(bytes(raw))
    assert json.loads(f.read_text())["skeleton"]["fields"]["hover_speed"] == 0.7
    with pytest.raises(CheckpointError, match="metadata.json is damaged: it fails its checksum"):
        checkpoint.load(tmp_path / "ck")


def test_non_utf8_metadata_is_a_checkpoint_error(surrogate, tmp_path):
    checkpoint.save(tmp_path / "ck", surrogate)
    f = tmp_path / "ck" / "metadata.json"
    f.write_bytes(b"\xff\xfe" + f.read_bytes()[2:])
    with pytest.raises(CheckpointError, match=r"metadata.json is damaged"):
        checkpoint.load(tmp_path / "ck")


def test_failed_save_leaves_nothing(surrogate, tmp_path, monkeypatch):
    import orbax.checkpoint as ocp

    def boom(self, *a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(ocp.StandardCheckpointer, "save", boom)
    with pytest.raises(OSError, match="disk full"):
        checkpoint.save(tmp_path / "ck", surrogate)
    assert os.listdir(tmp_path) == []


def test_save_rejects_other_objects(tmp_path):
    with pytest.raises(ValueError, match="save expects a gpg.Surrogate"):
        checkpoint.save(tmp_path / "x", {"a": 1})


def test_noise_model_round_trip(data, tmp_path):
    """A surrogate with M_noise: every array of it (the vehicle's acoustic data included) and
    its static settings come back."""
    import jax

    sur = Surrogate.fit(
        data, "gps_1x", {"hyper": {"fit": False}, "partition": {"bins": 2}}, noise_model=True
    )
    back = checkpoint.load(checkpoint.save(tmp_path / "ck", sur))
    a, ta = jax.tree.flatten(sur.noise)
    b, tb = jax.tree.flatten(back.noise)
    assert ta == tb and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
