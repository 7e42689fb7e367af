"""``experiments.simulate`` on smoke data, composed with Hydra. A whole experiment: the slow
set (its pieces have fast tests in tests/quadrotor and tests/envs)."""

import json

import pytest

from experiments.runs import simulate
from tests.helpers import compose_plain, finite_numbers

pytestmark = pytest.mark.slow


def test_simulate_run(smoke_cache, tmp_path):
    overrides = [
        "data=smoke",
        "data.chunk=32",
        f"cache_dir={smoke_cache}",
        "flight.leg_time=4.0",
        "flight.settle_time=2.0",
        "rollouts.n_envs=16",
        "rollouts.n_steps=50",
    ]
    res = simulate.run(compose_plain("simulate", overrides), tmp_path)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert finite_numbers(saved)
    for name in ("simplified", "surrogate"):
        f = saved["flights"][name]
        assert len(f["legs"]) == 2 and f["mean_rpm"] > 0
        assert f["max_tracking_error_m"] < 10.0  # a 60-point surrogate flies, if not well
    simple = saved["flights"]["simplified"]
    assert simple["legs"][0]["time_to_reach_s"] is not None and simple["max_tracking_error_m"] < 1.0
    assert res["speed"]["batch_env_steps_per_s"] > 0 and res["speed"]["batch_finite"]
    for fig in ("path_yz", "tracking_error", "average_rpm", "microphone_levels"):
        assert (tmp_path / "figures" / f"{fig}.png").is_file()
