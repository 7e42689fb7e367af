"""``experiments.learn`` and ``experiments.mpc`` end to end on a small surrogate, composed with
Hydra (a few gradient steps and MPC solves: the plumbing, not the figures of the README). Whole
experiments: the slow set (their pieces have fast tests in tests/envs and tests/test_mpc.py)."""

import json

import equinox as eqx
import jax
import numpy as np
import pytest

from experiments.runs import learn, mpc
from gpg import checkpoint
from gpg.envs import apg
from tests.helpers import compose_plain, finite_numbers

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def saved_surrogate(synthetic_surrogate, tmp_path_factory):
    return checkpoint.save(tmp_path_factory.mktemp("sur") / "surrogate", synthetic_surrogate)


def test_learn_run(saved_surrogate, tmp_path):
    overrides = [
        f"surrogate_checkpoint={saved_surrogate}",
        "apg.n_envs=4",
        "apg.horizon=12",
        "apg.iterations=3",
        "apg.width=8",
        "evaluation.n_envs=4",
        "evaluation.steps=20",
        "progress=false",
    ]
    res = learn.run(compose_plain("learn", overrides), tmp_path)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert finite_numbers(saved) and len(saved["curve"]["loss"]) == 3
    for name in ("policy", "geometric"):
        r = saved["evaluation"][name]
        assert 0 <= r["in_domain_fraction"] <= 1 and len(r["error_per_step_m"]) == 20
    # The saved policy loads back into the same structure and acts the same.
    like = apg.MLPPolicy.create(jax.random.key(0), width=8)
    pol = eqx.tree_deserialise_leaves(tmp_path / "policy.eqx", like)
    obs = np.zeros(25, np.float32)
    assert pol(obs).shape == (4,) and res["evaluation"]["policy"]["crashed_fraction"] <= 1
    assert (tmp_path / "figures" / "learning.png").is_file()


def test_mpc_run(saved_surrogate, tmp_path):
    overrides = [
        f"surrogate_checkpoint={saved_surrogate}",
        "flight.leg_time=1.0",
        "flight.start_time=0.2",
        "flight.settle_time=0.2",
        "mpc.horizon=6",
        "mpc.samples=8",
        "mpc.knots=3",
        "mpc.caution_points=2",
        "casadi.horizon=4",
        "casadi.knots=2",
        "casadi.caution_points=1",
        "casadi.max_iter=5",
    ]
    res = mpc.run(compose_plain("mpc", overrides), tmp_path)
    assert finite_numbers(json.loads((tmp_path / "results.json").read_text()))
    f = res["flights"]
    assert set(f) == {"geometric", "mpc", "mpc_cautious", "casadi"}
    assert f["casadi"]["solves"] > 0 and f["casadi"]["finite"]
    assert f["mpc"]["solves"] > 0 and f["mpc"]["solve_ms_median"] > 0 and f["geometric"]["finite"]
    with pytest.raises(ValueError, match="mpc.knots"):
        mpc.run(compose_plain("mpc", [*overrides, "mpc.knots=40"]), tmp_path / "bad")
