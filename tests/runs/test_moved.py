"""gpg.runs moved to the repository's experiments/runs (not installed with gpg): the old
names still import, with a DeprecationWarning, for one release."""

import sys

import pytest


def test_old_names_forward_to_the_new_places_with_a_warning(monkeypatch):
    import experiments.runs.config
    import experiments.runs.simulate
    import gpg.results

    for name in ("gpg.runs.common", "gpg.runs.results", "gpg.runs.simulate"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    with pytest.warns(DeprecationWarning, match="gpg.runs.simulate moved to experiments.runs"):
        from gpg.runs import simulate
    assert simulate is experiments.runs.simulate
    assert simulate.__spec__.name == "experiments.runs.simulate"
    # gpg.runs.common was split by concern: its names still read from the old place.
    with pytest.warns(DeprecationWarning, match="gpg.runs.common moved"):
        from gpg.runs.common import conf, table
    assert conf is experiments.runs.config.conf and callable(table)
    with pytest.warns(DeprecationWarning, match="gpg.runs.results moved to gpg.results"):
        from gpg.runs import results
    assert results is gpg.results
