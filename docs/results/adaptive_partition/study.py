"""Where finer partitions could pay for ``gpgs``: bins, per-bin hyperparameters, near budgets.

``python docs/results/adaptive_partition/study.py`` (about 5 minutes on 2 cores) writes
``study.md`` next to this file. On data=default, each variant is ``gpgs``'s mean (every bin a
GP-G on its near set; gradients, M residuals, the same fitted global hyperparameters as
``experiments.compare``), scored on the test set overall and above 15 m/s:

* ``slab`` / ``adaptive``: equal-count slabs against slabs with equal shares of the outputs'
  local variation (``partition.scheme``), same bins (10) and near budget (1/8);
* ``per-bin hyper``: each bin's σ, ARD lengthscales and ν² refitted by marginal likelihood on
  its own near set, started from the global fit (shorter lengthscales where the outputs change
  fast is what narrower bins would be for);
* ``near ∝ wᵖ``: the same total near-set size (N/8 per bin on average), each bin keeping its
  own points and the rest shared out in proportion to ``mean(w)ᵖ · n_b`` (``w`` the
  local-variation weights): more near points where the outputs change fastest. ``p = 8`` is
  the rule that equalises ``w · n^(-1/D)`` error estimates in D = 8 inputs.

This is a study, not part of the library: none of these variants reached the 15 % target, so
none became an option.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import numpy as np
import yaml

from experiments.runs.config import CONF_DIR, conf
from gpg import models
from gpg.data.cache import load_data
from gpg.data.preprocess import prepare, restore, simple_model_for
from gpg.gp import ExactGP, partition
from gpg.gp.fit import fit_hyperparameters
from gpg.names import AERO
from gpg.quadrotor.vehicle import load_vehicle

HERE = Path(__file__).parent
FAST = 15.0  # m/s


def _data():
    cfg = yaml.safe_load(open(CONF_DIR / "compare.yaml"))
    cfg.pop("defaults")
    cfg["vehicle"] = conf("sui_endurance", "vehicle")
    cfg["data"] = conf("default", "data")
    return load_data(cfg)[:2]


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    train, test = _data()
    training = prepare(train, simple_model_for(train, load_vehicle("sui_endurance")), None)
    X, Y, dY, dims = models.training_arrays("gpgs", training)
    hyper, _, _ = models.fit_hyper("gpgs", training, models.resolve_config("gpgs", {}))
    Xt = np.asarray(training.normalizer.x(test.x))
    fast = test.x[:, 7] > FAST
    w = partition.variation_weights(X, Y)

    def score(scheme: str, local_hyper: bool, power: float | None) -> dict:
        cfg = models.resolve_config("gpgs", {"partition": {"scheme": scheme}})
        part = models.build_partition(X, cfg, Y)
        bins = np.asarray(part.lookup_batch(X))
        B, n = part.n_bins, X.shape[0]
        total = int(np.ceil(cfg.near.budget * n)) * B
        if power is None:
            near = partition.near_sets(X, part, hyper.lengthscale, budget=cfg.near.budget).near
        else:
            own = np.bincount(bins, minlength=B)
            share = np.array([w[bins == b].mean() for b in range(B)]) ** power * own
            sizes = own + np.floor(share / share.sum() * (total - n)).astype(int)
            near = [
                partition.near_sets(X, part, hyper.lengthscale, points=int(sizes[b])).near[b]
                for b in range(B)
            ]
        query_bins = np.asarray(part.lookup_batch(Xt))
        pred = np.zeros((Xt.shape[0], Y.shape[1]))
        t0 = time.perf_counter()
        for b, idx in enumerate(near):
            h = hyper
            if local_hyper:
                h = fit_hyperparameters(
                    X[idx],
                    Y[idx],
                    dY[idx],
                    grad_dims=dims,
                    init=hyper,
                    subset_size=None,
                    max_steps=100,
                ).hyper
            gp = ExactGP.fit(X[idx], Y[idx], dY[idx], grad_dims=dims, hyper=h)
            q = query_bins == b
            if q.any():
                pred[q] = np.asarray(gp.predict(Xt[q])[0])
        err = np.abs(restore(training, test.x, pred) - test.y)[:, : len(AERO)]
        return {
            "all": err.mean(0).tolist(),
            "fast": err[fast].mean(0).tolist(),
            "near_sizes": [int(len(i)) for i in near],
            "seconds": time.perf_counter() - t0,
        }

    variants = {
        "slab": ("slab", False, None),
        "adaptive": ("adaptive", False, None),
        "slab, per-bin hyper": ("slab", True, None),
        "adaptive, per-bin hyper": ("adaptive", True, None),
        "slab, near ∝ w¹": ("slab", False, 1.0),
        "slab, near ∝ w⁸": ("slab", False, 8.0),
        "slab, near ∝ w²⁰": ("slab", False, 20.0),
    }
    results = {}
    for label, args in variants.items():
        results[label] = score(*args)
        print(label, json.dumps({k: np.round(v, 3).tolist() for k, v in results[label].items()}))
    base = np.array(results["slab"]["fast"])
    lines = [
        f"<!-- python {Path(__file__).relative_to(HERE.parents[2])} -->",
        f"`gpgs` mean on data=default, {int(fast.sum())} of {len(fast)} test points above "
        f"{FAST:g} m/s; MAE in N and N·m, change against equal-count slabs in brackets.",
        "",
        "| variant | near-set sizes | "
        + " | ".join(f"{a} >{FAST:g}" for a in AERO)
        + " | Fx all | My all |",
        "|---" * (len(AERO) + 4) + "|",
    ]
    for label, r in results.items():
        fast_cells = [
            f"{v:.3f} ({100 * (v / b - 1):+.0f} %)" for v, b in zip(r["fast"], base, strict=True)
        ]
        sizes = r["near_sizes"]
        lines.append(
            f"| {label} | {min(sizes)}–{max(sizes)} (Σ {sum(sizes)}) | "
            + " | ".join(fast_cells)
            + f" | {r['all'][0]:.3f} | {r['all'][4]:.3f} |"
        )
    (HERE / "study.md").write_text("\n".join(lines) + "\n")
    (HERE / "study.json").write_text(json.dumps(results, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
