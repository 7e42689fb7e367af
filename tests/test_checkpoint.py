"""Checkpoints: bit-for-bit round trips and clear errors for missing, damaged or foreign data."""

import json
import os
import shutil

import numpy as np
import pytest

from gpg import checkpoint, models
from gpg.checkpoint import CheckpointError
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset, variance_rtol

CFG = {
    "hyper": {"fit": False, "lengthscale": 0.8, "noise": 1e-4},
    "partition": {"bins": 3, "points_per_bin": None},
    "near": {"budget": 0.5, "points": None},
    "inducing": {"points": 6},
}


@pytest.fixture(scope="module")
def data():
    return synthetic_dataset(40, seed=5)[0]


@pytest.fixture(scope="module")
def surrogate(data):
    return Surrogate.fit(data, "gpgs_hybrid", models.restrict("gpgs_hybrid", CFG))


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
        sur = Surrogate.fit(data, "gpg_pic", models.restrict("gpg_pic", CFG))
    else:
        sur = Surrogate.fit(data, "gpg", {"hyper": {"fit": False}}, hover_speed=0.3)
    checkpoint.save(tmp_path / "ck", sur)
    back = checkpoint.load(tmp_path / "ck")
    a, b = sur.predict_batch(*queries(data)), back.predict_batch(*queries(data))
    for field in ("force", "torque", "levels", "variance", "in_domain"):
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
    first = checkpoint.version_dir(tmp_path / "ck")
    checkpoint.save(tmp_path / "ck", surrogate, overwrite=True)
    assert sorted(os.listdir(tmp_path)) == ["ck"]  # no stray temporary or old directory
    second = checkpoint.version_dir(tmp_path / "ck")
    assert second != first and not first.exists()
    assert sorted(os.listdir(tmp_path / "ck")) == sorted([".lock", "CURRENT", second.name])
    # A regular file at the path is refused before anything is written.
    (tmp_path / "file").write_text("mine")
    with pytest.raises(CheckpointError, match="is not a checkpoint directory"):
        checkpoint.save(tmp_path / "file", surrogate, overwrite=True)
    assert (tmp_path / "file").read_text() == "mine"
    assert sorted(os.listdir(tmp_path)) == ["ck", "file"]


def test_version_4_layout_loads_and_is_replaced(surrogate, data, tmp_path):
    """A checkpoint of the previous format (arrays and metadata directly in the directory)
    loads, and an overwrite turns it into the new layout."""
    checkpoint.save(tmp_path / "ck", surrogate)
    v = checkpoint.version_dir(tmp_path / "ck")
    old = tmp_path / "old"
    shutil.copytree(v, old)
    meta = json.loads((old / "metadata.json").read_text())
    meta["format_version"] = 4
    (old / "metadata.json").write_text(resign(meta))
    back = checkpoint.load(old)
    np.testing.assert_array_equal(
        back.predict_batch(*queries(data)).force, surrogate.predict_batch(*queries(data)).force
    )
    checkpoint.save(old, surrogate, overwrite=True)
    assert not (old / "metadata.json").exists() and (old / "CURRENT").is_file()
    assert checkpoint.read_metadata(old)["format_version"] == checkpoint.FORMAT_VERSION


def test_concurrent_savers_and_readers(surrogate, tmp_path):
    """In-process threads: of two exclusive saves one wins and the other is told; loads during
    overwrites always get a complete checkpoint (the subprocess stress test is in the slow set)."""
    import threading

    results = []

    def save_excl():
        try:
            checkpoint.save(tmp_path / "ck", surrogate)
            results.append("saved")
        except Exception as exc:  # noqa: BLE001 - reported by the assertion below
            results.append(repr(exc))

    threads = [threading.Thread(target=save_excl) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(r == "saved" for r in results) == [False, True], results
    assert "exists" in next(r for r in results if r != "saved")
    assert sorted(p for p in os.listdir(tmp_path)) == ["ck"]
    failures = []

    def read():
        for _ in range(6):
            try:
                checkpoint.load(tmp_path / "ck")
            except Exception as exc:  # noqa: BLE001 - any failure is what this test counts
                failures.append(exc)

    reader = threading.Thread(target=read)
    reader.start()
    for _ in range(3):
        checkpoint.save(tmp_path / "ck", surrogate, overwrite=True)
    reader.join()
    assert failures == []
    assert len([p for p in os.listdir(tmp_path / "ck") if p.startswith("v-")]) == 1


def test_missing_and_foreign(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        checkpoint.load(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="metadata.json is missing"):
        checkpoint.load(tmp_path / "empty")
    (tmp_path / "file").write_text("x")
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        checkpoint.load(tmp_path / "file")


def resign(meta):
    """Metadata edited on purpose, with a valid checksum (to reach the checks behind it)."""
    meta["metadata_sha256"] = checkpoint._meta_digest(meta)
    return json.dumps(meta)


def test_version_mismatch(surrogate, tmp_path):
    checkpoint.save(tmp_path / "ck", surrogate)
    meta = json.loads((checkpoint.version_dir(tmp_path / "ck") / "metadata.json").read_text())
    meta["format_version"] = checkpoint.FORMAT_VERSION + 1
    (checkpoint.version_dir(tmp_path / "ck") / "metadata.json").write_text(resign(meta))
    newer = checkpoint.FORMAT_VERSION + 1
    with pytest.raises(CheckpointError, match=f"format version {newer}; this gpg .* reads"):
        checkpoint.load(tmp_path / "ck")


def test_truncated_or_damaged(surrogate, tmp_path, capfd):
    checkpoint.save(tmp_path / "ck", surrogate)
    shutil.copytree(tmp_path / "ck", tmp_path / "ck2")
    # Truncate the biggest data file of the orbax checkpoint: named, and nothing else printed.
    files = [
        p for p in (checkpoint.version_dir(tmp_path / "ck") / "arrays").rglob("*") if p.is_file()
    ]
    big = max(files, key=lambda p: p.stat().st_size)
    big.write_bytes(big.read_bytes()[: big.stat().st_size // 2])
    capfd.readouterr()
    with pytest.raises(CheckpointError, match=f"{big.name} is damaged: it fails its checksum"):
        checkpoint.load(tmp_path / "ck")
    out, err = capfd.readouterr()
    assert "Traceback" not in err + out and "asyncio" not in err + out
    shutil.rmtree(checkpoint.version_dir(tmp_path / "ck2") / "arrays")
    with pytest.raises(CheckpointError, match="incomplete: the arrays directory is missing"):
        checkpoint.load(tmp_path / "ck2")


def test_checksum_catches_silent_change(surrogate, tmp_path):
    checkpoint.save(tmp_path / "ck", surrogate)
    meta = json.loads((checkpoint.version_dir(tmp_path / "ck") / "metadata.json").read_text())
    key = next(iter(meta["arrays"]))
    meta["arrays"][key]["sha256"] = "0" * 64
    (checkpoint.version_dir(tmp_path / "ck") / "metadata.json").write_text(resign(meta))
    with pytest.raises(CheckpointError, match=f"array {key} .* fails its shape/dtype/checksum"):
        checkpoint.load(tmp_path / "ck")


def test_metadata_bit_flip_is_caught(surrogate, tmp_path):
    """One flipped bit in a static field (hover_speed 0.5 -> 0.7 in the module tree) changes
    predictions: the metadata's own checksum catches it."""
    checkpoint.save(tmp_path / "ck", surrogate)
    f = checkpoint.version_dir(tmp_path / "ck") / "metadata.json"
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
    f = checkpoint.version_dir(tmp_path / "ck") / "metadata.json"
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


def test_noise_model_round_trip(surrogate, tmp_path):
    """A surrogate with M_noise: every array of it (the vehicle's acoustic data included) and
    its static settings come back. (Fitting with noise_model=True is tested in test_surrogate
    and test_preprocess; the round trip needs only the module in place.)"""
    import equinox as eqx
    import jax

    from gpg.quadrotor.simple_noise import SimpleNoise
    from gpg.quadrotor.vehicle import load_vehicle

    noise = SimpleNoise.from_vehicle(load_vehicle("sui_endurance"), surrogate.simple)
    sur = eqx.tree_at(lambda s: s.noise_model, surrogate, noise, is_leaf=lambda x: x is None)
    back = checkpoint.load(checkpoint.save(tmp_path / "ck", sur))
    a, ta = jax.tree.flatten(sur.noise_model)
    b, tb = jax.tree.flatten(back.noise_model)
    assert ta == tb and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_load_keeps_the_saved_dtypes_in_a_float32_program(surrogate, data, tmp_path):
    """x64 off (a float32 program): the loaded surrogate holds the saved float64 arrays and
    predicts exactly what the saved one does there; ``dtype=`` converts on request."""
    import jax
    import jax.numpy as jnp

    path = checkpoint.save(tmp_path / "ck", surrogate)
    with jax.enable_x64(False):
        back = checkpoint.load(path)

        def dtypes(s):
            return [str(x.dtype) for x in jax.tree.leaves(s) if hasattr(x, "dtype")]

        assert dtypes(back) == dtypes(surrogate) and "float64" in dtypes(back)
        q = queries(data)
        np.testing.assert_array_equal(
            back.predict_batch(*q).force, surrogate.predict_batch(*q).force
        )
        small = checkpoint.load(path, dtype=jnp.float32)
        assert {str(x.dtype) for x in jax.tree.leaves(small) if hasattr(x, "dtype")} >= {"float32"}
        assert "float64" not in {
            str(x.dtype) for x in jax.tree.leaves(small) if hasattr(x, "dtype")
        }


@pytest.mark.parametrize("which", ["hybrid_noise_model", "gpg"])
def test_format_5_checkpoints_of_the_previous_release_load(which, data, tmp_path):
    """Checkpoints written by the previous release (format 5, with the value noise saved as
    ``jitter`` and M_noise as ``noise``) load with a DeprecationWarning and predict what that
    release predicted from them (its predictions stored beside them, float64); saving again
    writes the current format."""
    from pathlib import Path

    fixtures = Path(__file__).parent / "fixtures" / "checkpoints_v5"
    old = tmp_path / which
    shutil.copytree(fixtures / which, old)
    assert checkpoint.read_metadata(old)["format_version"] == 5
    with pytest.warns(DeprecationWarning, match="read as noise"):
        back = checkpoint.load(old)
    assert (back.noise_model is not None) == (which == "hybrid_noise_model")
    q = queries(data)
    p = back.predict_batch(*q)
    then = json.loads((fixtures / "predictions.json").read_text())[which]
    # Force, torque and levels are float64 sums (coefficients and kernel rows in float64): a
    # few hundred terms, so another summation order moves them by ~1e-14 relative.
    for field in ("force", "torque", "levels"):
        np.testing.assert_allclose(getattr(p, field), np.array(then[field]), rtol=1e-12, atol=1e-12)
    # The variance is only as accurate as the dtype of its stored factor (float32 for the
    # hybrid, in that release's storage too): each query's tolerance follows from the factor
    # and the kernel row (helpers.variance_rtol).
    rtol = variance_rtol(back, *q)
    assert np.all(rtol < 0.1), rtol  # the bound is informative, not vacuous
    np.testing.assert_array_less(
        np.abs(np.asarray(p.variance) - np.array(then["variance"])),
        rtol[:, None] * np.abs(np.array(then["variance"])),
    )
    checkpoint.save(old, back, overwrite=True)
    assert checkpoint.read_metadata(old)["format_version"] == checkpoint.FORMAT_VERSION


def test_a_damaged_or_deleted_current_names_current(surrogate, tmp_path):
    """``CURRENT`` truncated to a name the checkpoint does not hold, or deleted, is reported
    as such (with the versions that are there), not as a missing metadata.json."""
    path = checkpoint.save(tmp_path / "ck", surrogate)
    version = (path / "CURRENT").read_text().strip()
    (path / "CURRENT").write_text(version[:5])
    for read in (checkpoint.load, checkpoint.read_metadata):
        with pytest.raises(CheckpointError, match=rf"CURRENT names version '{version[:5]}'.*"
                           rf"holds \['{version}'\].*truncated"):  # fmt: skip
            read(path)
    (path / "CURRENT").unlink()
    for read in (checkpoint.load, checkpoint.read_metadata):
        with pytest.raises(CheckpointError, match=rf"CURRENT is missing.*\['{version}'\]"):
            read(path)
