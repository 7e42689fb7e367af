"""gpg.runs moved to the repository's experiments/runs (not installed with gpg): the old
names still import, with a DeprecationWarning, for one release."""

import sys

import pytest


def test_old_names_forward_to_the_new_places_with_a_warning(monkeypatch):
    import experiments.runs.common
    import gpg.results

    for name in ("gpg.runs.common", "gpg.runs.results"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    with pytest.warns(DeprecationWarning, match="gpg.runs.common moved to experiments.runs"):
        from gpg.runs.common import conf
    assert conf is experiments.runs.common.conf
    assert sys.modules["gpg.runs.common"] is experiments.runs.common
    assert experiments.runs.common.__spec__.name == "experiments.runs.common"
    with pytest.warns(DeprecationWarning, match="gpg.runs.results moved to gpg.results"):
        from gpg.runs import results
    assert results is gpg.results
