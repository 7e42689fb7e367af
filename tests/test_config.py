"""Typed model configuration: one copy of the defaults (Python and YAML agree), frozen values,
and errors that name the key."""

import dataclasses
from pathlib import Path

import pytest

from experiments.runs.config import conf
from gpg import conf as gpg_conf
from gpg import models
from gpg.config import ModelConfig
from tests.helpers import compose_plain


def test_base_yaml_is_the_shared_defaults():
    assert conf("_base", "model") == ModelConfig().to_dict()


@pytest.mark.parametrize("name", models.NAMES)
def test_model_yaml_states_the_registry_defaults(name):
    """conf/model/<name>.yaml (its differences over _base) composes to exactly what
    models.resolve_config(name) gives without overrides."""
    y = conf(name, "model")
    assert y.pop("name") == name
    assert y == models.resolve_config(name).to_dict()


def test_hydra_composes_the_same_model_config():
    cfg = compose_plain("compare", ["+model=gpgs_hybrid"])
    assert cfg["model"] == conf("gpgs_hybrid", "model")


@pytest.mark.parametrize("entry", ["compare", "envelope"])
def test_entry_point_configs_read_without_hydra_as_hydra_composes_them(entry):
    """notebooks/02 runs the comparison from ``conf("compare")``: group defaults
    (``data: default``) go under their key, Hydra's own settings stay out."""
    assert conf(entry) == compose_plain(entry, [])


def test_defaults_hydra_alone_reads_are_refused(tmp_path, monkeypatch):
    import experiments.runs.config as common

    (tmp_path / "x.yaml").write_text("defaults:\n  - override data: smoke\n  - _self_\n")
    monkeypatch.setattr(common, "CONF_DIR", tmp_path)
    with pytest.raises(ValueError, match="'override data': 'smoke'.*needs Hydra"):
        conf("x")


def test_every_model_key_is_commented():
    for path in sorted(Path(str(gpg_conf.group("model"))).glob("*.yaml")):
        for i, line in enumerate(path.read_text().splitlines(), 1):
            code = line.strip()
            if code and not code.startswith("#"):
                assert "#" in line, f"{path.name}:{i} has no comment: {line!r}"


def test_config_is_frozen_and_resolved_once():
    cfg = models.resolve_config("gpgs", {"near": {"budget": 0.25}})
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.near.budget = 0.5
    assert models.resolve_config("gpgs", cfg) is cfg
    assert cfg.near.rule() == {"budget": 0.25}
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize(
    "over, match",
    [
        ({"hyper": {"subset": 0}}, "hyper.subset"),
        ({"hyper": {"fit": "yes"}}, "hyper.fit"),
        ({"hyper": {"full": 1}}, "hyper.full"),
        ({"hyper": {"probes": 0}}, "hyper.probes"),
        ({"hyper": {"cg_tol": 1.0}}, "hyper.cg_tol"),
        ({"hyper": {"cg_probe_tol": 0.0}}, "hyper.cg_probe_tol"),
        ({"hyper": {"full_ftol": -1e-5}}, "hyper.full_ftol"),
        ({"hyper": {"cg_max_iter": 0}}, "hyper.cg_max_iter"),
        ({"hyper": {"lengthscale": [1.0, -1.0]}}, "hyper.lengthscale"),
        ({"partition": {"scheme": "grid"}}, "partition.scheme"),
        ({"near": {"budget": 1.5}}, "near.budget"),
        ({"near": {"budget": None}}, "near needs one of"),
        ({"inducing": {"points": 0}}, "inducing.points"),
        ({"mean": "median"}, "mean"),
        ({"hyperr": {}}, "unknown key 'hyperr'"),
        ({"hyper": {"sigma": 1.0}}, "unknown key hyper.'sigma'"),
        ({"hyper": 3}, "hyper must be a mapping"),
    ],
)
def test_bad_values_name_their_key(over, match):
    with pytest.raises(ValueError, match=match):
        models.resolve_config("gpgs", over)


@pytest.mark.parametrize("config", [[("hyper", {})], ["hyper"], "hyper", 3])
def test_a_config_that_is_not_a_mapping_is_named(config):
    with pytest.raises(ValueError, match=r"config \(the model options\) must be a mapping"):
        models.resolve_config("gpg", config)


@pytest.mark.parametrize(
    "hyper, match",
    [
        ({"lengthscale": [1.0, 2.0, 3.0]}, "hyper.lengthscale has 3 values; the model has 8"),
        ({"lengthscale": [1.0] * 8, "ard": False}, "one value per input but hyper.ard is false"),
    ],
)
def test_a_lengthscale_of_the_wrong_length_is_named(hyper, match):
    """Checked against the data's inputs before any fit (it used to fail inside NumPy's
    broadcasting, with fitted and fixed hyperparameters alike)."""
    for fit in (True, False):
        cfg = models.resolve_config("gpg", {"hyper": {**hyper, "fit": fit}})
        with pytest.raises(ValueError, match=match):
            models.initial_hyper(cfg, 8, None)


def test_old_noise_keys_work_with_a_deprecation_warning():
    """hyper.jitter and friends (the value noise ν², before it was called noise) still
    configure the same model for one release."""
    old = {"jitter": 1e-5, "fit_jitter": False, "jitter_init": 0.05, "jitter_floor": 1e-4}
    with pytest.warns(DeprecationWarning, match="hyper.jitter is deprecated; use hyper.noise"):
        cfg = models.resolve_config("gpg", {"hyper": old})
    new = {"noise": 1e-5, "fit_noise": False, "noise_init": 0.05, "noise_floor": 1e-4}
    assert cfg == models.resolve_config("gpg", {"hyper": new})
    with pytest.warns(DeprecationWarning):
        assert ModelConfig.from_dict({**cfg.to_dict(), "hyper": old | {"fit": True}}).hyper.noise
