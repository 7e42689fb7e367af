"""The whole flight envelope: the body-frame formulation against the paper's airflow frame
(``python -m experiments.envelope``).

Five training sets of the same number of simulator runs (8 a case: the base point and 7
forward differences), chosen by ``trainings``: the paper's (``airflow_data``, airflow-frame
inputs), **the same cases in the body frame** (``x_B = (rpm, R(θ)ᵀ V e_x)``, differences along
``u, v, w`` instead of the angles), **the paper's data converted** (no new runs:
:func:`gpg.data.convert.to_body`, its angle gradients as derivatives along two directions of
``u, v, w``; ``converted_no_angles`` drops them, to show what they add) and the whole
envelope (``data``, :mod:`gpg.data.sampling`'s body-frame ball). Each
model of ``models`` is fitted on each, and every surrogate is asked through
:meth:`gpg.Surrogate.predict_batch` (world-frame states, so both formulations answer the same
question) at two test sets: the paper's box (the airflow test set) and the envelope (the body
test set). Reported: mean absolute error of ``Fx`` (N), ``Mx`` (N·m) and, where the test set
is in the surrogate's own frame, ``L1`` (dB: the microphones are fixed to the airflow frame in
one formulation and to the body in the other, so the levels are not the same quantity across
frames), and the share of test states ``in_domain``.

Then, for the ``env.model`` of each formulation: the **jump** (the largest change of the
predicted force for ``jump.step`` m/s of air along each world axis at ``jump.n_states`` states:
a third anywhere in the ball, a third near hover, a third near vertical air) and **the RL
environment's in-domain share** (the geometric controller, ``env.n_envs`` environments for
``env.steps`` steps, each task of ``env.tasks`` and each wind of ``env.wind_max``, wind from any
direction). ``results.json`` holds everything with the resolved config.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from experiments.runs.common import world_arrays
from experiments.runs.config import check_options, conf
from experiments.runs.output import report, table
from experiments.runs.timing import machine
from gpg.data.bounds import Bounds
from gpg.data.cache import build_generator, ensure_datasets
from gpg.data.convert import body_inputs, body_meta, to_body
from gpg.data.dataset import Dataset
from gpg.data.sampling import FDSteps, fd_meta, forward_differences, raw_samples
from gpg.quadrotor.frames import R_WB
from gpg.quadrotor.generator import evaluate_batch, vortex_ring_state
from gpg.runtime import float64, write_json

# The training sets, in order (see the module docstring)
TRAININGS = ("airflow", "same_cases", "converted", "converted_no_angles", "envelope")
STEPS = ("accuracy", "jump", "env", "symmetry")  # what a run measures (accuracy: always)
OPTIONS = {
    "cache_dir": "path",
    "airflow_data": "path",
    "progress": "bool",
}  # the run's own keys besides its config groups (runs.common.check_options)


@float64
def same_cases_in_body_frame(
    gen, train: Dataset, fd: FDSteps, *, chunk: int = 512, progress: bool = False
) -> Dataset:
    """The cases of the airflow-frame ``train`` run again in the body frame with body-frame
    forward differences: as many simulator runs as ``train`` (8 a case), the same points."""
    x = body_inputs(train.x)
    x_raw, h = raw_samples(x, fd)
    y_raw = evaluate_batch(
        gen, x_raw, chunk=chunk, progress="body frame, same cases" if progress else False,
        frame="body",
    )  # fmt: skip
    y, jac = forward_differences(y_raw, h)
    meta = {
        **body_meta(train.meta, "the airflow-frame training cases, in the body frame"),
        "fd": fd_meta(fd, "body"),
    }
    return Dataset(
        x=x, y_aero=y[:, :6], jac_aero=jac[:, :6],
        y_noise=y[:, 6:] if train.has_noise else None,
        jac_noise=jac[:, 6:] if train.has_noise else None,
        x_raw=x_raw, y_raw=y_raw if train.has_noise else y_raw[:, :6], meta=meta,
    )  # fmt: skip


def test_errors(sur, test: Dataset) -> dict[str, Any]:
    """Mean absolute errors of Fx, Mx (and L1 in the surrogate's own frame) over every test
    state, and the share of them in domain."""
    p = sur.predict_batch(*world_arrays(test.x), mean_only=True)
    force, torque, ok = (np.asarray(a) for a in (p.force, p.torque, p.in_domain))
    out = {
        "Fx_mae": float(np.mean(np.abs(force[:, 0] - test.y_aero[:, 0]))),
        "Mx_mae": float(np.mean(np.abs(torque[:, 0] - test.y_aero[:, 3]))),
        "L1_mae": None,
        "in_domain": float(np.mean(ok)),
        "Fx_mae_in_domain": float(np.mean(np.abs(force[ok, 0] - test.y_aero[ok, 0])))
        if ok.any()
        else None,
    }
    if sur.frame == test.frame and test.has_noise and sur.n_levels:
        out["L1_mae"] = float(np.mean(np.abs(np.asarray(p.levels)[:, 0] - test.y_noise[:, 0])))
    return out


GROUPS = ("ball", "near hover", "near vertical")


def jump_states(n: int, seed: int, speed: float) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """``n`` states and their group (:data:`GROUPS`): rotor speeds about hover, random headings
    and tilts, and air velocities a third anywhere in the ball of radius ``speed``, a third
    within 0.5 m/s of hover, a third near vertical (horizontal part under 0.3 m/s, vertical up
    to ``speed`` either way, exact hover and vertical 3 and 10 m/s among them)."""
    rng = np.random.default_rng(seed)
    k = n // 3
    d = rng.normal(size=(2 * k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.concatenate([speed * rng.uniform(size=k) ** (1 / 3), 0.5 * rng.uniform(size=k)])
    vert = np.concatenate(
        [0.3 * rng.uniform(-1, 1, (n - 2 * k, 2)), rng.uniform(-speed, speed, (n - 2 * k, 1))], 1
    )
    special = np.array([[0, 0, 0], [0, 0, 3], [0, 0, -3], [0, 0, 10], [0, 0, -10.0]])
    v = np.concatenate([d * r[:, None], vert, special])
    group = np.array([0] * k + [1] * k + [2] * (n - 2 * k) + [1] + [2] * 4)
    m = v.shape[0]
    rpm = rng.uniform(3000, 4500, (m, 4))
    euler = np.stack(
        [rng.uniform(-np.pi, np.pi, m), rng.uniform(-0.5, 0.5, m), rng.uniform(-0.5, 0.5, m)], 1
    )
    return (rpm, euler, v), group


def force_changes(force_at, states, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Per state, the largest change of any force component for ``step`` m/s of air along any
    world axis, and whether ``force_at`` flagged the state in domain at both ends."""
    rpm, euler, v = states
    f0, ok0 = force_at(rpm, euler, v)
    change, ok = np.zeros(len(v)), ok0.copy()
    for axis in range(3):
        dv = np.zeros(3)
        dv[axis] = step
        f1, ok1 = force_at(rpm, euler, v + dv)
        change = np.maximum(change, np.abs(f1 - f0).max(1))
        ok &= ok1
    return change, ok


def jump(sur, states, group: np.ndarray, step: float, truth: np.ndarray) -> dict[str, Any]:
    """The surrogate's largest force change for ``step`` m/s of air, per group of states, over
    all of them and over those in domain, beside the generator's own (``truth``, per state)."""

    def force_at(rpm, euler, v):
        p = sur.predict_batch(rpm, euler, v, mean_only=True)
        return np.asarray(p.force), np.asarray(p.in_domain)

    change, ok = force_changes(force_at, states, step)
    out = {"in_domain": float(np.mean(ok))}
    for g, name in enumerate(GROUPS):
        sel = group == g
        i = int(np.argmax(np.where(sel, change, -1.0)))
        out[name] = {
            "max_change_N": float(change[sel].max()),
            "at_v_air": states[2][i].tolist(),
            "max_change_in_domain_N": float(change[sel & ok].max()) if (sel & ok).any() else None,
            "generator_max_change_N": float(truth[sel].max()),
        }
    return out


def generator_changes(gen, states, step: float) -> np.ndarray:
    """The generator's own largest force change for ``step`` m/s of air at the states (the
    world-frame force of the body-frame generator at ``R_WBᵀ v``, rotated back)."""
    R = np.asarray(jax.vmap(R_WB)(jnp.asarray(states[1])))

    def force_at(rpm, euler, v):
        xb = np.concatenate([rpm, np.einsum("nji,nj->ni", R, v)], axis=1)
        y = evaluate_batch(gen, xb, frame="body")
        return np.einsum("nij,nj->ni", R, y[:, :3]), np.ones(len(v), bool)

    return force_changes(force_at, states, step)[0]


def env_in_domain(sur, vehicle, ecfg: dict[str, Any]) -> list[dict[str, Any]]:
    """The geometric controller in the RL environment on ``sur``: the share of steps in
    domain for each task and wind (any direction), ``n_envs`` environments, ``steps`` steps."""
    from gpg.envs.evaluation import evaluate
    from gpg.envs.quadrotor import EnvParams, QuadrotorEnv

    env = QuadrotorEnv.create(vehicle, sur, action="ctbr", dtype=jnp.float32)
    rows = []
    for task in ecfg["tasks"]:
        for wind in ecfg["wind_max"]:
            params = EnvParams.create(task, wind_max=float(wind), wind_spread=3.1416)
            r = evaluate(
                env, params, lambda o, s, p=params: env.geometric_action(s, p),
                jax.random.key(int(ecfg["seed"])), int(ecfg["n_envs"]), int(ecfg["steps"]),
            )  # fmt: skip
            rows.append(
                {
                    "task": task,
                    "wind_max": float(wind),
                    "in_domain": r["in_domain_fraction"],
                    "rms_position_error_m": r["rms_position_error_m"],
                    "crashed": r["crashed_fraction"],
                }
            )
    return rows


def symmetry_rows(scfg: dict[str, Any], train: Dataset, test: Dataset, vehicle) -> list[dict]:
    """Whether mirror images pay per simulator run: ``scfg["model"]`` fitted on the first
    ``cases`` envelope cases, on them with their mirror images across each set of
    ``axes`` (no extra runs; levels dropped where a mirror does not keep the microphones), and
    on 2x and 4x as many real cases; Fx and Mx errors on the envelope test set."""
    from gpg.data.symmetry import augment, keeps_levels
    from gpg.surrogate import Surrogate

    n = int(scfg["cases"])
    if 4 * n > train.n:
        raise ValueError(f"symmetry.cases={n}: 4x as many real cases exceed the {train.n} there")
    base = train.subset(np.arange(n)).without("raw samples")
    variants = [(f"{n} cases", base, base.runs)]
    for axes in scfg["axes"]:
        axes = tuple(axes)
        keeps = all(keeps_levels(vehicle, a) for a in axes)
        ds = augment(base if keeps else base.without("noise"), vehicle, axes)
        variants.append((f"{n} cases + mirrors {'/'.join(axes)}", ds, base.runs))
    for k in (2, 4):
        real = train.subset(np.arange(k * n)).without("raw samples")
        variants.append((f"{k * n} cases", real, real.runs))
    rows = []
    for name, ds, runs in variants:
        t0 = time.perf_counter()
        sur = Surrogate.fit(ds, scfg["model"], vehicle=vehicle)
        e = test_errors(sur, test)
        rows.append({"training": name, "points": ds.n, "runs": runs,
                     "fit_s": time.perf_counter() - t0, **e})  # fmt: skip
        report(f"symmetry {name} ({runs} runs): Fx {e['Fx_mae']:.4f} N, Mx {e['Mx_mae']:.5f} N*m")
    return rows


# Long by design: the experiment's steps in order (data, fits, tests, jump, environment).
@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """Fit every model on the three training sets, test them, measure the jump and the
    environment's in-domain share; write ``results.json`` into ``outdir``."""
    from gpg.quadrotor.vehicle import Vehicle
    from gpg.surrogate import Surrogate

    outdir = Path(outdir)
    check_options(cfg, OPTIONS)
    if cfg["data"].get("frame") != "body":
        raise ValueError(
            f"data must be a body-frame config (frame: body), got {cfg['data']['name']!r}"
        )
    air_cfg = conf(cfg["airflow_data"], "data")
    if air_cfg.get("frame", "airflow") != "airflow":
        raise ValueError(
            f"airflow_data must be an airflow-frame data config, got {cfg['airflow_data']!r}"
        )
    progress = bool(cfg.get("progress", True))
    chosen, steps = list(cfg["trainings"]), list(cfg["steps"])
    if set(chosen) - set(TRAININGS) or set(steps) - set(STEPS):
        raise ValueError(
            f"trainings must be among {list(TRAININGS)} and steps among {list(STEPS)}, got "
            f"{chosen} and {steps}"
        )
    if {"jump", "env"} & set(steps) and not {"airflow", "envelope"} <= set(chosen):
        raise ValueError("steps jump and env compare trainings airflow and envelope: keep both")
    vehicle = Vehicle.from_config(cfg["vehicle"])
    air_train, air_test, _, _ = ensure_datasets(
        air_cfg, cfg["vehicle"], cfg["cache_dir"], progress=progress
    )
    env_train, env_test, _, _ = ensure_datasets(
        cfg["data"], cfg["vehicle"], cfg["cache_dir"], progress=progress
    )
    gen = build_generator(air_cfg, cfg["vehicle"])
    fd = FDSteps(
        **{
            **air_cfg.get("fd", {}),
            **{k: v for k, v in cfg["data"].get("fd", {}).items() if k == "velocity"},
        }
    )
    t0 = time.perf_counter()
    same_body = None
    if "same_cases" in chosen:
        same_body = same_cases_in_body_frame(gen, air_train, fd, progress=progress)
    gen_s = time.perf_counter() - t0
    sets = {
        "airflow": ("airflow (paper box)", lambda: air_train),
        "same_cases": ("body (same cases)", lambda: same_body),
        "converted": ("body (paper data converted)", lambda: to_body(air_train)),
        "converted_no_angles": (
            "body (converted, angle gradients dropped)",
            lambda: to_body(air_train, angle_gradients=False),
        ),
        "envelope": ("body (envelope)", lambda: env_train),
    }
    trainings = {sets[k][0]: sets[k][1]() for k in TRAININGS if k in chosen}
    # The converted cases keep the runs behind them: 8 a case, 3 angle runs giving 2 rows.
    runs = {name: train.runs for name, train in trainings.items()}
    for key in ("converted", "converted_no_angles"):
        if key in chosen:
            runs[sets[key][0]] = air_train.runs
    tests = {"paper box": air_test, "envelope": env_test}
    rows, surrogates = [], {}
    for model in cfg["models"]:
        for tname, train in trainings.items():
            t0 = time.perf_counter()
            sur = Surrogate.fit(train, model, vehicle=vehicle)
            fit_s = time.perf_counter() - t0
            surrogates[(model, tname)] = sur
            for test_name, test in tests.items():
                e = test_errors(sur, test)
                rows.append(
                    {
                        "model": model,
                        "training": tname,
                        "runs": runs[tname],
                        "test": test_name,
                        "fit_s": fit_s,
                        **e,
                    }
                )
                report(
                    f"{model} on {tname} -> {test_name}: Fx {e['Fx_mae']:.4f} N, "
                    f"Mx {e['Mx_mae']:.5f} N*m, in domain {100 * e['in_domain']:.1f} %"
                )
    jcfg = cfg["jump"]
    ecfg = cfg["env"]
    jumps, envs = {}, {}
    if "jump" in steps:
        states, group = jump_states(
            int(jcfg["n_states"]),
            int(jcfg["seed"]),
            float(Bounds.from_config(cfg["data"]["bounds"]).airspeed[1]),
        )
        truth = generator_changes(gen, states, float(jcfg["step"]))
    for tname in ("airflow (paper box)", "body (envelope)"):
        if "jump" in steps:
            sur = surrogates[(ecfg["model"], tname)]
            jumps[tname] = jump(sur, states, group, float(jcfg["step"]), truth)
            report(f"jump {tname}: {jumps[tname]}")
        if "env" in steps:
            envs[tname] = env_in_domain(surrogates[(ecfg["model"], tname)], vehicle, ecfg)
            for r in envs[tname]:
                share = 100 * r["in_domain"]
                report(f"env {tname} {r['task']} wind {r['wind_max']:g}: in domain {share:.1f} %")
    sym = None
    if "symmetry" in steps:
        sym = symmetry_rows(cfg["symmetry"], env_train, env_test, vehicle)
    vrs = {
        name: float(np.mean(vortex_ring_state(vehicle, ds.x, ds.y_aero[:, :3])))
        for name, ds in (("train", env_train), ("test", env_test))
    }
    report(f"envelope cases in the vortex-ring state (not to be trusted): {vrs}")
    cols = [
        ("model", "model", ""),
        ("training", "training data", ""),
        ("test", "test set", ""),
        ("Fx_mae", "Fx MAE (N)", ".4f"),
        ("Mx_mae", "Mx MAE (N·m)", ".5f"),
        ("L1_mae", "L1 MAE (dB)", ".3f"),
        ("in_domain", "in domain", ".3f"),
    ]
    summary = table(rows, cols)
    report("\n" + summary)
    out = {
        "machine": machine(),
        "accuracy": rows,
        "jump": jumps,
        "env": envs,
        "symmetry": sym,
        "vortex_ring_share": vrs,
        "same_cases_generation_s": gen_s,
        "summary": summary,
        "config": cfg,
    }
    outdir.mkdir(parents=True, exist_ok=True)
    write_json(outdir / "results.json", out)
    return out
