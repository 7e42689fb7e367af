"""Model kinds (gpg/kinds): options a kind does not read are refused by name, and a kind
registered from outside gpg builds, predicts, checkpoints and takes part in the comparison."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array, ArrayLike, Float

from experiments.runs import compare
from gpg import checkpoint, models
from gpg.config import ModelConfig
from gpg.gp.predictor import Predictor
from gpg.kinds import KINDS, Arrays, Kind, Product
from gpg.results import read_results
from gpg.surrogate import Surrogate
from tests.helpers import synthetic_dataset


class PriorGP(Predictor):
    """The toy kind's predictor: the GP prior (mean zero, variance σ at every query)."""

    variance: Float[Array, ""]
    noise: Float[Array, ""]
    output_scale: Float[Array, " M"]
    dims: tuple[int, int] = eqx.field(static=True)

    @property
    def n_inputs(self) -> int:
        return self.dims[0]

    @property
    def n_outputs(self) -> int:
        return self.dims[1]

    @property
    def partition(self) -> None:
        return None

    def mean_one(self, x):
        return jnp.zeros(self.dims[1], x.dtype)

    def mean_var_one(self, x):
        return self.mean_one(x), self.variance + 0.0 * x[0]

    def with_output_scale(self, scale: Float[ArrayLike, " M"]) -> PriorGP:
        return eqx.tree_at(lambda m: m.output_scale, self, jnp.asarray(scale))

    def describe(self) -> dict[str, Any]:
        return {"hyperparameters": {"variance": float(self.variance), "noise": float(self.noise)}}


@dataclass(frozen=True)
class Prior(Kind):
    """A toy kind: fits nothing but the hyperparameters, predicts the prior."""

    name = "prior"
    reads = ()
    partitioned = False
    predictor = PriorGP

    def build(self, arrays: Arrays, hyper, cfg: ModelConfig, *, devices=None) -> Product:
        m = arrays.Y.shape[1]
        model = PriorGP(
            variance=hyper.variance,
            noise=hyper.noise,
            output_scale=jnp.ones(m),
            dims=(arrays.X.shape[1], m),
        )
        return Product(model, timings={"fit_s": 0.0})

    def required_bytes(self, cfg: ModelConfig, n_points: int, n_grad: int) -> int:
        return 0


@pytest.fixture
def toy():
    models.register("toy_prior", Prior(), "values", "Toy prior", {"hyper": {"subset": 20}})
    yield "toy_prior"
    models.unregister("toy_prior")


@pytest.mark.parametrize(
    "name, override, where",
    [
        ("gpgs_schur", {"route": "local"}, "unknown precompute route 'local'"),
        ("gpg", {"partition": {"bins": 4}}, "model 'gpg' does not read option 'partition.bins'"),
        ("gp", {"near": {"budget": 0.5}}, "model 'gp' does not read option 'near.budget'"),
        ("gpgs", {"inducing": {"points": 9}}, "does not read option 'inducing.points'"),
        ("gpgs", {"mean": "paper"}, "model 'gpgs' does not read option 'mean'"),
        ("gpgs_hybrid", {"route": "direct"}, "model 'gpgs_hybrid' does not read option 'route'"),
        ("gpg_pic", {"near": {"points": 9}}, "model 'gpg_pic' does not read option 'near.points'"),
    ],
)
def test_foreign_options_are_refused_by_name(name, override, where):
    with pytest.raises(ValueError, match=where.replace("(", r"\(")):
        models.resolve_config(name, override)


def test_a_resolved_config_of_another_model_is_refused():
    """A ModelConfig is checked too: gpgs_hybrid's own (kdtree bins) is foreign to gpg."""
    with pytest.raises(ValueError, match="model 'gpg' does not read option 'partition"):
        models.resolve_config("gpg", models.resolve_config("gpgs_hybrid"))
    assert models.resolve_config("gpgs", {"near": {"budget": 0.25}}).near.budget == 0.25


def test_every_model_kind_is_registered_and_reads_what_it_declares():
    assert set(KINDS) == {"exact", "local", "schur", "hybrid", "pic"}
    for name in models.NAMES:
        assert models.reads(name)[0] == "hyper"
        sections = {key.split(".")[0] for key in models.reads(name)}  # "solver.device"
        assert sections <= set(ModelConfig().to_dict())


def test_a_registered_toy_kind_builds_predicts_and_checkpoints(toy, tmp_path):
    data = synthetic_dataset(24, seed=3)[0]
    with pytest.raises(ValueError, match="model 'toy_prior' does not read option 'partition"):
        Surrogate.fit(data, toy, {"partition": {"bins": 2}})
    sur = Surrogate.fit(data, toy, {"hyper": {"fit": False, "variance": 2.0}})
    assert isinstance(sur.model, PriorGP) and sur.model_name == toy
    rpm, euler = data.x[:3, :4], data.x[:3, 4:7]
    v = np.column_stack([data.x[:3, 7], np.zeros(3), np.zeros(3)])
    p = sur.predict_batch(rpm, euler, v)
    assert np.all(np.isfinite(p.force)) and np.all(p.variance > 0)
    back = checkpoint.load(checkpoint.save(tmp_path / "toy", sur))
    q = back.predict_batch(rpm, euler, v)
    np.testing.assert_array_equal(q.force, p.force)
    np.testing.assert_array_equal(q.variance, p.variance)
    assert checkpoint.read_metadata(tmp_path / "toy")["hyperparameters"]["variance"] == 2.0
    # Differentiable like every gpg model.
    g = jax.grad(lambda r: sur.predict(r, euler[0], v[0]).force.sum())(jnp.asarray(rpm[0]))
    assert np.all(np.isfinite(g))


# A whole comparison run (the experiment): slow; the fast set builds, predicts and checkpoints
# the same registered kind (test_a_registered_toy_kind_builds_predicts_and_checkpoints).
@pytest.mark.slow
def test_a_registered_toy_kind_appears_in_the_comparison(toy, tmp_path):
    from tests.runs.test_compare import user_dataset_config

    cfg = user_dataset_config(tmp_path, "n_queries=2")
    out = tmp_path / "run"
    out.mkdir()
    fixed = {"hyper": {"fit": False}}
    res = compare.run(cfg, out, {toy: fixed, "gps_1x": {**fixed, "partition": {"bins": 2}}})
    comp = read_results(out)
    assert list(comp.ran) == [toy, "gps_1x"] and comp.ran[toy].title == "Toy prior"
    assert res["models"][toy]["mae"] == comp.ran[toy].mae
    assert "| toy_prior |" in (out / "results.md").read_text()


def test_register_refuses_bad_entries(toy):
    with pytest.raises(ValueError, match="already registered"):
        models.register(toy, Prior(), "values", "again")
    with pytest.raises(ValueError, match="Spec.data must be one of"):
        models.register("toy2", Prior(), "pixels", "bad data")
    with pytest.raises(ValueError, match="unknown key"):
        models.register("toy3", Prior(), "values", "bad", {"hyper": {"sbuset": 3}})
    with pytest.raises(ValueError, match="not added by register"):
        models.unregister("gpg")
    assert "toy2" not in models.SPECS and "toy3" not in models.SPECS
