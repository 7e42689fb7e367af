"""``experiments.envelope`` (experiments/runs/envelope.py): the airflow-frame cases seen from the
body, and the whole experiment at smoke scale (slow: a generator run and twelve fits)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.runs import envelope
from experiments.runs.common import world_arrays
from gpg.data.convert import body_inputs
from gpg.quadrotor.frames import R_WB
from tests.helpers import compose_plain, finite_numbers


def test_airflow_cases_seen_from_the_body():
    """``R_WB(θ)ᵀ V e_x`` by its definition, and the test states of either frame: the airflow
    frame's level air at the case's attitude, the body frame's air at the identity."""
    rng = np.random.default_rng(0)
    x = np.c_[rng.uniform(0, 7000, (5, 4)), rng.uniform(-1, 1, (5, 3)), rng.uniform(0, 20, 5)]
    xb = body_inputs(x)
    for r, rb in zip(x, xb, strict=True):
        want = np.asarray(R_WB(jnp.asarray(r[4:7]))).T @ np.array([r[7], 0.0, 0.0])
        np.testing.assert_allclose(rb[4:], want, atol=1e-12)
        assert np.array_equal(rb[:4], r[:4])
    for rows in (x, xb):
        rpm, euler, v = world_arrays(rows)
        assert np.array_equal(rpm, x[:, :4])
        # the same body-frame air either way: R_WB(euler)ᵀ v_air
        seen = np.einsum("nji,nj->ni", np.asarray(jax.vmap(R_WB)(jnp.asarray(euler))), v)
        np.testing.assert_allclose(seen, xb[:, 4:], atol=1e-12)
    states, group = envelope.jump_states(30, 0, 20.0)
    assert len(states[2]) == len(group) == 35 and np.all(np.linalg.norm(states[2], axis=1) <= 20)
    assert np.all(np.linalg.norm(states[2][group == 2][:, :2], axis=1) < 0.5)


@pytest.mark.slow
def test_envelope_run(smoke_cache, tmp_path):
    overrides = [
        "data=envelope_smoke",
        "airflow_data=smoke",
        f"cache_dir={smoke_cache}",
        "models=[gpgs_hybrid]",
        "jump.n_states=60",
        "env.n_envs=8",
        "env.steps=20",
        "env.tasks=[hover]",
        "env.wind_max=[5.0]",
        "symmetry.cases=15",
        "progress=false",
    ]
    res = envelope.run(compose_plain("envelope", overrides), tmp_path)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert finite_numbers({k: v for k, v in saved.items() if k != "jump"})
    rows = {(r["training"], r["test"]): r for r in res["accuracy"]}
    assert rows[("body (envelope)", "envelope")]["in_domain"] == 1.0
    assert rows[("airflow (paper box)", "envelope")]["in_domain"] < 0.8
    converted = rows[("body (paper data converted)", "paper box")]
    assert converted["runs"] == rows[("airflow (paper box)", "paper box")]["runs"]
    assert saved["env"]["body (envelope)"][0]["in_domain"] == 1.0
    assert len(saved["symmetry"]) == 5 and saved["symmetry"][2]["points"] == 60
