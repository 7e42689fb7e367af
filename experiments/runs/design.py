"""Which cases to run next (``python -m experiments.design``).

``step: ask``: fit the surrogate on the training data, propose the next ``batch`` cases
(:func:`gpg.design.propose`) and write ``ask.csv`` (one row per simulator run, in the
configured columns and units) for an external solver.
``step: tell``: read the solver's answered file (``tell.results``) through
:func:`gpg.design.cases.read_tell`, condition the surrogate on it, and write the grown
dataset and the surrogate's checkpoint.
``step: active`` (``+experiment=active``): the whole loop unattended, with the built-in
generator standing in for the solver and the ask/tell files written and read every round,
against Latin hypercubes of the same cost, over several seeds; writes the learning curves
(test MAE per output against simulator runs) and the figure.
``step: merge``: the curves of several such runs (``merge.runs``: seeds or arms run apart, in
parallel or longer) joined into one ``curves.json``, its figure and ``summary.md``, the table
of medians and ranges over the seeds at each budget of ``merge.budgets``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from experiments.runs.config import check_options
from experiments.runs.output import report
from experiments.runs.timing import machine
from gpg.data.cache import build_generator, load_data
from gpg.data.dataset import Dataset
from gpg.data.sampling import FDSteps, generate
from gpg.design import cases, merge_datasets, propose
from gpg.quadrotor.generator import evaluate_batch
from gpg.runtime import float64, write_json
from gpg.surrogate import Surrogate

OPTIONS = {
    "cache_dir": "path",
    "progress": "bool",
    "figures": "bool",
}  # the run's own keys besides its groups and sections (runs.common.check_options)
DESIGN_OPTIONS = {"batch": "count", "candidates": "count", "reference": "count", "seed": "index"}
STEPS = ("ask", "tell", "active", "merge")
ARMS = ("lhs_gradients", "lhs_values", "active_gradients", "active_choose")


def test_mae(sur: Surrogate, test: Dataset) -> dict[str, float]:
    """Test MAE per output of the surrogate's mean, in the data's units."""
    from gpg.data.preprocess import residuals

    X = np.asarray(sur.normalizer.x(test.x))
    mean = np.asarray(sur.normalizer.y_inv(sur.model.predict_mean(X)))
    y, _, _ = residuals(test, sur.simple, sur.noise_model)
    err = np.mean(np.abs(mean - y), axis=0)
    return dict(zip(sur.output_names, err.tolist(), strict=True))


def _design_kw(d: dict[str, Any]) -> dict[str, Any]:
    return {
        "candidates": int(d["candidates"]),
        "reference": int(d["reference"]),
        "keep": d.get("keep"),
        "weights": d.get("weights") or None,
    }


def answer(gen, ask_path: Path, out_path: Path, columns=None, units=None) -> Path:
    """The built-in generator as the solver: read an ask file, run every row, write the
    answered file (the ask columns plus the outputs) in the same units."""
    import csv

    from gpg.data.dataset import unit_factor
    from gpg.names import AERO, INPUTS, NOISE

    columns, units = dict(columns or {}), dict(units or {})
    with ask_path.open(newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    idx = [header.index(columns.get(k, k)) for k in INPUTS]
    scale = np.array([unit_factor(k, units.get(k)) for k in INPUTS])
    x = np.array([[float(r[i]) for i in idx] for r in body]) * scale
    y = evaluate_batch(gen, x)
    names = AERO + NOISE
    out_scale = np.array([unit_factor(k, units.get(k)) for k in names])
    with out_path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(header + [columns.get(k, k) for k in names])
        for r, yy in zip(body, y / out_scale, strict=True):
            w.writerow(r + [repr(float(v)) for v in yy])
    return out_path


@float64
def run(cfg: dict[str, Any], outdir: Path) -> dict[str, Any]:
    """The configured step (module docstring); results and the resolved config in ``outdir``."""
    outdir = Path(outdir)
    check_options(cfg, OPTIONS)
    check_options(cfg["design"], DESIGN_OPTIONS)
    step = cfg["step"]
    if step not in STEPS:
        raise ValueError(f"step must be one of {STEPS}, got {step!r}")
    outdir.mkdir(parents=True, exist_ok=True)
    out = {"ask": _ask, "tell": _tell, "active": _active, "merge": _merge}[step](cfg, outdir)
    out.update(machine=machine(), config=cfg)
    write_json(outdir / "results.json", out)
    return out


VALUES_MODEL = "gp_values"  # the exact kind on values alone, for designs without gradients


def _fit(cfg, train: Dataset) -> Surrogate:
    model = dict(cfg["model"])
    name = model.pop("name")
    if train.jac_aero is None:
        from gpg import models
        from gpg.kinds import KINDS

        if VALUES_MODEL not in models.SPECS:
            models.register(VALUES_MODEL, KINDS["exact"], "values", "GP on values")
        name, model = VALUES_MODEL, models.restrict(VALUES_MODEL, model)
    return Surrogate.fit(train.without("raw samples") if train.has_raw else train, name, model)


def _train(cfg) -> Dataset:
    path = (cfg.get("dataset") or {}).get("train")
    return Dataset.load(path) if path else load_data(cfg)[0]


def _ask(cfg, outdir: Path) -> dict[str, Any]:
    d, c = cfg["design"], cfg["csv"]
    train = _train(cfg)
    sur = _fit(cfg, train)
    t0 = time.perf_counter()
    p = propose(sur, train, int(d["batch"]), gradients=d["gradients"], seed=int(d["seed"]),
                **_design_kw(d))  # fmt: skip
    seconds = time.perf_counter() - t0
    path = cases.write_ask(outdir / "ask.csv", p.x, p.gradients, fd=FDSteps(**cfg["fd"]),
                           columns=c["columns"], units=c["units"])  # fmt: skip
    report(f"{p.batch.index.size} cases, {p.runs} runs -> {path} ({seconds:.1f} s)")
    return {"ask": str(path), "cases": int(p.x.shape[0]), "runs": p.runs, "propose_s": seconds}


def _tell(cfg, outdir: Path) -> dict[str, Any]:
    from gpg import checkpoint

    c = cfg["csv"]
    if not cfg["tell"].get("results"):
        raise ValueError("step=tell needs tell.results: the answered ask file")
    new = cases.read_tell(cfg["tell"]["results"], c["columns"] or None, units=c["units"])
    train = _train(cfg)
    sur = _fit(cfg, train)
    t0 = time.perf_counter()
    grown = sur.condition(new)
    seconds = time.perf_counter() - t0
    merged = merge_datasets(train.without("raw samples") if train.has_raw else train, new)
    merged.save(outdir / "dataset")
    checkpoint.save(outdir / "surrogate", grown)
    report(f"conditioned on {new.n} cases ({new.runs} runs) in {seconds:.1f} s")
    where = {"dataset": str(outdir / "dataset"), "checkpoint": str(outdir / "surrogate")}
    return {"cases": new.n, "runs": new.runs, "condition_s": seconds, **where}


# Long by design: one arm of the study, its rounds in order (ask, answer, tell, refit rule,
# measure); split, the round's state would travel through half a dozen arguments.
def _active_arm(cfg, gen, test, gradients: str, seed: int, outdir: Path, bar, meta) -> list[dict]:
    a, d = cfg["active"], cfg["design"]
    fd = FDSteps(**cfg["fd"])
    data = generate(gen, int(a["initial"]), seed=1000 + seed, keep_raw=False, fd=fd,
                    bounds=_bounds(cfg), meta=meta)  # fmt: skip
    sur = _fit(cfg, data)
    fitted_at = data.n
    curve = [{"runs": data.runs, "cases": data.n, **test_mae(sur, test)}]
    rnd = 0
    while data.runs < int(a["budget"]):
        rnd += 1
        t0 = time.perf_counter()
        p = propose(sur, data, int(d["batch"]), gradients=gradients, seed=seed * 1000 + rnd,
                    **_design_kw(d))  # fmt: skip
        t_propose = time.perf_counter() - t0
        folder = outdir / f"seed{seed}" / f"{gradients}" / f"round{rnd:02d}"
        ask = cases.write_ask(folder / "ask.csv", p.x, p.gradients, fd=fd)
        new = cases.read_tell(answer(gen, ask, folder / "answered.csv"), meta=meta)
        data = merge_datasets(data, new)
        t0 = time.perf_counter()
        if data.n >= float(a["refit_growth"]) * fitted_at:
            sur, fitted_at, how = _fit(cfg, data), data.n, "refit"
        else:
            sur, how = sur.condition(new), "condition"
        curve.append({"runs": data.runs, "cases": data.n, "round": rnd, "update": how,
                      "propose_s": t_propose, "update_s": time.perf_counter() - t0,
                      "gradient_runs": int(p.gradients.sum()), **test_mae(sur, test)})  # fmt: skip
        bar.update(1)
        release_memory()
    return curve


def release_memory() -> None:
    """Between rounds: every round's model has new shapes, so JAX compiles new programs and
    keeps the old ones (about 0.2 GB a round at a few hundred cases, measured); drop them and
    give the freed heap back (glibc keeps it otherwise). Without, a run of the loop grew past
    10 GB by its 38th round."""
    import ctypes
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to trim
        pass


def _bounds(cfg):
    from gpg.data.bounds import Bounds

    return Bounds.from_config(cfg["data"]["bounds"])


def _lhs_arm(cfg, gen, test, gradients: bool, seed: int, bar, meta) -> list[dict]:
    fd = FDSteps(**cfg["fd"])
    curve = []
    for runs in cfg["active"]["lhs_runs"]:
        n = int(runs) // (8 if gradients else 1)
        ds = generate(gen, n, seed=2000 + seed, keep_raw=False, fd=fd, bounds=_bounds(cfg),
                      gradients="fd" if gradients else "none", meta=meta)  # fmt: skip
        sur = _fit(cfg, ds)
        curve.append({"runs": ds.runs, "cases": ds.n, **test_mae(sur, test)})
        bar.update(1)
    return curve


def _active(cfg, outdir: Path) -> dict[str, Any]:
    a = cfg["active"]
    train, test, _ = load_data(cfg)
    # M's coefficients as the generated data record them, so every arm subtracts the same M
    meta = {k: train.meta[k] for k in ("simple_model",) if k in train.meta}
    gen = build_generator(cfg["data"], cfg["vehicle"])
    seeds = [int(s) for s in a["seeds"]]
    arms = list(a["arms"])
    bad = sorted(set(arms) - set(ARMS))
    if bad:
        raise ValueError(f"active.arms has unknown arms {bad}; valid: {list(ARMS)}")
    curves: dict[str, dict[str, list]] = {arm: {} for arm in arms}
    # One tick per fitted Latin hypercube and per active round (their count is the budget's).
    with tqdm(desc="design rounds", unit="round", disable=not cfg.get("progress", True)) as bar:
        for seed in seeds:
            for arm in arms:
                if arm.startswith("lhs"):
                    c = _lhs_arm(cfg, gen, test, arm == "lhs_gradients", seed, bar, meta)
                else:
                    g = "all" if arm == "active_gradients" else "choose"
                    c = _active_arm(cfg, gen, test, g, seed, outdir, bar, meta)
                curves[arm][str(seed)] = c
                write_json(outdir / "curves.json", curves)  # nothing lost if a later arm fails
    figures = _figure(curves, outdir / "figures") if cfg.get("figures", True) else []
    return {"curves": curves, "figures": [str(f.relative_to(outdir)) for f in figures]}


def merge_curves(paths: list[str | Path]) -> dict[str, dict[str, list]]:
    """The ``curves.json`` of several runs (a run directory or the file itself) joined: arm by
    arm and seed by seed, a later run's curve replaces an earlier one's (a seed run again
    with a larger budget replaces its shorter curve)."""
    import json

    out: dict[str, dict[str, list]] = {}
    for path in paths:
        f = Path(path)
        f = f / "curves.json" if f.is_dir() else f
        if not f.is_file():
            raise ValueError(f"merge.runs: no curves.json at {path}")
        curves = json.loads(f.read_text())
        bad = sorted(set(curves) - set(ARMS))
        if bad:
            raise ValueError(f"{f} has unknown arms {bad}; valid: {list(ARMS)}")
        for arm, per_seed in curves.items():
            out.setdefault(arm, {}).update(per_seed)
    return {arm: out[arm] for arm in ARMS if arm in out}


def summary(curves, budgets, outputs=("Fx", "Mx", "L1")) -> list[dict[str, Any]]:
    """Per arm and budget ``b``: each seed's error after its last point with at most ``b``
    runs, among the seeds whose curve went on to ``b`` runs or more; the median over those
    seeds and the range (a budget that adds no point to the one before is left out)."""
    rows = []
    for arm, per_seed in curves.items():
        last: list = []
        for b in budgets:
            spent = [c for c in per_seed.values() if c and c[0]["runs"] <= b <= c[-1]["runs"]]
            pts = [max((p for p in c if p["runs"] <= b), key=lambda p: p["runs"]) for c in spent]
            if not pts or pts == last:  # nothing, or the same points as the budget before
                continue
            last = pts
            row: dict[str, Any] = {"design": arm, "budget": int(b), "seeds": len(pts),
                                   "runs": sorted({int(p["runs"]) for p in pts})}  # fmt: skip
            for o in outputs:
                v = np.array([p[o] for p in pts])
                row[o] = (float(np.median(v)), float(v.min()), float(v.max()))
            rows.append(row)
    return rows


def summary_markdown(rows, outputs=("Fx", "Mx", "L1")) -> str:
    units = {"F": "N", "M": "N·m", "L": "dB"}
    head = ["design", "runs", "seeds"] + [f"MAE {o} {units[o[0]]}" for o in outputs]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        runs = "/".join(str(x) for x in r["runs"])
        cells = [r["design"], runs, str(r["seeds"])]
        for o in outputs:
            med, lo, hi = r[o]
            cells.append(f"{med:.3g}" if r["seeds"] == 1 else f"{med:.3g} ({lo:.3g}-{hi:.3g})")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _merge(cfg, outdir: Path) -> dict[str, Any]:
    m = cfg.get("merge") or {}
    runs, budgets = list(m.get("runs") or []), [int(b) for b in m.get("budgets") or []]
    if not runs:
        raise ValueError("step=merge needs merge.runs: the run directories of step=active")
    if not budgets or min(budgets) < 1:
        raise ValueError(f"merge.budgets must be simulator runs >= 1, got {m.get('budgets')}")
    curves = merge_curves(runs)
    write_json(outdir / "curves.json", curves)
    rows = summary(curves, sorted(budgets))
    (outdir / "summary.md").write_text(summary_markdown(rows))
    figures = _figure(curves, outdir / "figures") if cfg.get("figures", True) else []
    report(f"{sum(len(v) for v in curves.values())} curves -> {outdir / 'summary.md'}")
    return {"summary": rows, "figures": [str(f.relative_to(outdir)) for f in figures]}


def _figure(curves, folder: Path) -> list[Path]:
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter

    folder.mkdir(parents=True, exist_ok=True)
    outputs = ("Fx", "Mx", "L1")
    fig = Figure(figsize=(12, 3.6))
    axes = fig.subplots(1, len(outputs))
    labels = {
        "lhs_gradients": "(a) LHS, all gradients",
        "lhs_values": "(b) LHS, no gradients",
        "active_gradients": "(c) active, all gradients",
        "active_choose": "(d) active, chosen gradients",
    }
    for ax, o in zip(axes, outputs, strict=True):
        for arm, per_seed in curves.items():
            for k, c in enumerate(per_seed.values()):
                if not c or o not in c[0]:
                    continue
                runs = [p["runs"] for p in c]
                mae = [p[o] for p in c]
                ax.plot(runs, mae, "-o", ms=2.5, color=f"C{list(labels).index(arm)}", alpha=0.8,
                        label=labels[arm] if k == 0 else None)  # fmt: skip
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())  # minor labels overlap on a log axis
        ax.set_xticks([200, 500, 1000, 2000, 4000, 8000], ["200", "500", "1k", "2k", "4k", "8k"])
        ax.set_xlabel("simulator runs")
        ax.set_ylabel(f"test MAE {o}")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    path = folder / "learning_curves.png"
    fig.savefig(path, dpi=120)
    return [path]
