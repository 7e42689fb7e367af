"""Learning a policy on the surrogate (``python -m experiments.learn``).

A policy (:class:`gpg.envs.apg.MLPPolicy`, collective thrust and body rates) is trained by
analytic policy gradients through batched rollouts of :class:`gpg.envs.QuadrotorEnv` flown on
the surrogate (:mod:`gpg.envs.apg`), then flown against gpg's geometric controller (designed on
``M``) on the same evaluation scenarios: same resets, targets, wind, gusts and turbulence.
Written: ``results.json`` (learning curve, evaluation), ``policy.eqx`` (the trained policy,
``equinox.tree_serialise_leaves``) and the figures.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from experiments.runs.common import surrogate_from_config
from experiments.runs.config import check_options
from experiments.runs.output import report
from experiments.runs.timing import machine
from gpg.envs import apg
from gpg.envs.evaluation import evaluate
from gpg.envs.quadrotor import EnvParams, QuadrotorEnv
from gpg.quadrotor.vehicle import Vehicle
from gpg.runtime import float64, write_json

OPTIONS = {
    "figures": "bool",
    "progress": "bool",
    "cache_dir": "path",
    "surrogate_checkpoint": "path?",
}  # the run's own keys besides its config groups (runs.common.check_options)


# Long by design: the experiment's steps in order (config, data, train, evaluate, write).
@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Fit (or load) the surrogate, train the policy, evaluate both controllers; write the
    results into ``outdir``."""
    outdir = Path(outdir)
    check_options(cfg, OPTIONS)
    a = cfg["apg"]
    train_cfg = apg.APGConfig(**{k: a[k] for k in apg.APGConfig.__dataclass_fields__})
    e = cfg["env"]
    ev = cfg["evaluation"]
    for k in ("n_envs", "steps", "seed"):
        if isinstance(ev.get(k), bool) or not isinstance(ev.get(k), int) or ev[k] < 0:
            raise ValueError(f"evaluation.{k} must be a non-negative integer, got {ev.get(k)!r}")
    params = EnvParams.create(e["task"], **e.get("params", {}))
    vehicle = Vehicle.from_config(cfg["vehicle"])
    sur = surrogate_from_config(cfg, vehicle)
    # Training and evaluation run in float32, the RL setting (the fit above is float64).
    env = QuadrotorEnv.create(vehicle, sur, action=e["action"], dtype=jnp.float32)
    policy = apg.MLPPolicy.create(jax.random.key(train_cfg.seed), width=int(a["width"]))
    policy, curve = apg.train(env, params, policy, train_cfg, progress=cfg.get("progress", True))
    key = jax.random.key(int(ev["seed"]))
    learned = evaluate(env, params, lambda o, s: policy(o), key, ev["n_envs"], ev["steps"])
    geometric = evaluate(
        env, params, lambda o, s: env.geometric_action(s, params), key, ev["n_envs"], ev["steps"]
    )
    outdir.mkdir(parents=True, exist_ok=True)
    eqx.tree_serialise_leaves(outdir / "policy.eqx", policy)
    figures = []
    if cfg.get("figures", True):
        figures = _figures(
            curve,
            learned,
            geometric,
            float(e["params"].get("control_dt", 0.01)),
            outdir / "figures",
        )
    out = {
        "machine": machine(),
        "surrogate": {"model": sur.model_name},
        "curve": {k: v.tolist() for k, v in curve.items()},
        "evaluation": {"policy": learned, "geometric": geometric},
        "figures": [str(f.relative_to(outdir)) for f in figures],
        "config": cfg,
    }
    write_json(outdir / "results.json", out)
    (outdir / "policy.json").write_text(
        json.dumps({"width": a["width"], "action": e["action"]}) + "\n"
    )
    for name, r in out["evaluation"].items():
        report(
            f"{name:9s} RMS position error {r['rms_position_error_m']:.3f} m, final "
            f"{r['final_position_error_m']:.3f} m, "
            f"in domain {100 * r['in_domain_fraction']:.0f} %, "
            f"crashed {100 * r['crashed_fraction']:.0f} %"
        )
    return out


def _figures(curve, learned, geometric, dt: float, folder: Path) -> list[Path]:
    from matplotlib.figure import Figure

    folder.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(9, 3.2))
    ax1, ax2 = fig.subplots(1, 2)
    ax1.plot(-curve["loss"], label="mean reward per step")
    ax1.plot(curve["final_error"], label="final position error (m)")
    ax1.set_xlabel("gradient step")
    ax1.legend()
    for name, r in (("learned policy", learned), ("geometric controller", geometric)):
        err = np.asarray(r["error_per_step_m"])
        ax2.plot(dt * np.arange(1, err.size + 1), err, label=name)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("mean position error (m)")
    ax2.legend()
    fig.tight_layout()
    path = folder / "learning.png"
    fig.savefig(path, dpi=120)
    return [path]
