"""The configs shipped inside the package (gpg.conf): read and composed without Hydra, in an
installed gpg as in a checkout."""

import pytest

from gpg import conf


def test_a_model_config_is_its_options_over_the_base():
    base, hybrid = conf.load("_base", "model"), conf.load("gpgs_hybrid", "model")
    assert hybrid["name"] == "gpgs_hybrid"
    assert set(base) <= set(hybrid)
    assert conf.load("smoke", "data")["n_train"] > 0


def test_unknown_configs_and_groups_are_named():
    with pytest.raises(ValueError, match=r"no config gpg/conf/data/nope\.yaml; known: .*'smoke'"):
        conf.load("nope", "data")
    with pytest.raises(ValueError, match="unknown config group 'compare'"):
        conf.load("compare", "compare")


def test_compose_merges_a_defaults_list_as_hydra_does():
    """``name`` entries merge a config of the same group, ``group: name`` entries go under
    their key, ``_self_`` places the file's own keys (last when absent), ``hydra`` is dropped."""
    store = {("a", "g"): {"x": 1, "y": {"p": 1, "q": 2}}, ("s", "data"): {"n": 3}}

    def load(name, group):
        return dict(store[(name, group)])

    own = {"defaults": ["a", {"data": "s"}], "y": {"q": 5}, "hydra": {"run": 1}}
    assert conf.compose(own, "f.yaml", "g", load) == {
        "x": 1,
        "y": {"p": 1, "q": 5},
        "data": {"n": 3},
    }
    first = {"defaults": ["_self_", "a"], "x": 0}
    assert conf.compose(first, "f.yaml", "g", load)["x"] == 1
    with pytest.raises(ValueError, match=r"f\.yaml: the defaults entry .* needs Hydra"):
        conf.compose({"defaults": [{"override data": "s"}]}, "f.yaml", None, load)


def test_deep_merge_leaves_its_arguments_alone():
    base, over = {"a": {"b": 1, "c": 2}}, {"a": {"c": 3}}
    assert conf.deep_merge(base, over) == {"a": {"b": 1, "c": 3}}
    assert base == {"a": {"b": 1, "c": 2}} and conf.deep_merge(base, None) == base
