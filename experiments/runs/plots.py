"""Figures: dataset sanity checks, model comparisons and flights.

Drawn with matplotlib's object API (``Figure``), so no backend is chosen and no pyplot state
is kept: importing or calling this module changes nothing for the caller's own plots.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from gpg import models
from gpg.names import INPUTS, OUTPUTS
from gpg.quadrotor.generator import evaluate_batch
from gpg.quadrotor.simple_model import hover_sweep


def _subplots(*args, figsize, **kw):
    """A figure without pyplot: no backend is chosen and no global figure list is kept, so
    plotting changes no matplotlib state of the caller."""
    fig = Figure(figsize=figsize)
    return fig, fig.subplots(*args, **kw)


# One padded batch size for every sanity curve: one compilation of the generator serves all.
SANITY_CHUNK = 32


def save(fig, path: Path, formats=("png", "pdf")) -> list[Path]:
    """Save ``fig`` as ``path.<fmt>`` for each format and close it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    out = []
    for fmt in formats:
        p = path.with_suffix(f".{fmt}")
        fig.savefig(
            p,
            dpi=150,
            bbox_inches="tight",
            metadata={"CreationDate": None} if fmt == "pdf" else None,
        )
        out.append(p)
    return out


def data_sanity(gen, simple, check: dict[str, Any], outdir: Path) -> list[Path]:
    """Thrust vs rpm, wrench vs airspeed, OASPL vs rpm, FD vs exact gradients."""
    rpm = np.linspace(0, 7000, 29)
    paths = _thrust_figure(gen, simple, rpm, outdir)
    paths += _wrench_figure(gen, simple, outdir)
    paths += _levels_figure(gen, rpm, outdir)
    if check:
        paths += _gradient_figure(check["scaled_error"], outdir)
    return paths


def _thrust_figure(gen, simple, rpm: np.ndarray, outdir: Path) -> list[Path]:
    T, Q = hover_sweep(gen, rpm)
    T, Q = T[:, 0], Q[:, 0]  # one rotor: at hover all four carry the same load
    fig, ax = _subplots(1, 2, figsize=(9, 3.5))
    ax[0].plot(rpm, T, "o", ms=3, label="generator (per rotor)")
    ax[0].plot(rpm, float(simple.P_F) * rpm**2, "-", label=r"$P_F\,r^2$ (fit)")
    ax[0].set(xlabel="rpm", ylabel="thrust [N]", title="Hover thrust")
    ax[1].plot(rpm, Q, "o", ms=3, label="generator")
    ax[1].plot(rpm, float(simple.T_z) * rpm**2, "-", label=r"$T_z\,r^2$ (fit)")
    ax[1].set(xlabel="rpm", ylabel="torque [N m]", title="Hover rotor torque")
    for a in ax:
        a.legend()
        a.grid(alpha=0.3)
    return save(fig, outdir / "thrust_vs_rpm")


def _wrench_figure(gen, simple, outdir: Path) -> list[Path]:
    hover = float(simple.hover_rpm(float(gen.vehicle.weight)))
    V = np.linspace(0, 20, 21)
    fig, ax = _subplots(1, 3, figsize=(13, 3.5))
    for pitch_deg in (0.0, -10.0):
        X = np.zeros((V.size, 8))
        X[:, :4] = hover
        X[:, 5] = np.deg2rad(pitch_deg)
        X[:, 7] = V
        Y = evaluate_batch(gen, X, chunk=SANITY_CHUNK)
        for j, c in zip(range(3), "rgb", strict=True):
            ax[0].plot(
                V,
                Y[:, j],
                c,
                ls="-" if pitch_deg == 0 else "--",
                label=f"{OUTPUTS[j]}, pitch {pitch_deg:g}°",
            )
            ax[1].plot(
                V,
                Y[:, 3 + j],
                c,
                ls="-" if pitch_deg == 0 else "--",
                label=f"{OUTPUTS[3 + j]}, pitch {pitch_deg:g}°",
            )
            ax[2].plot(
                V,
                Y[:, 6 + j],
                c,
                ls="-" if pitch_deg == 0 else "--",
                label=f"{OUTPUTS[6 + j]}, pitch {pitch_deg:g}°",
            )
    ax[0].set(xlabel="airspeed [m/s]", ylabel="force [N]", title=f"Forces at {hover:.0f} rpm")
    ax[1].set(xlabel="airspeed [m/s]", ylabel="moment [N m]", title="Moments")
    ax[2].set(xlabel="airspeed [m/s]", ylabel="OASPL [dB]", title="Noise")
    for a in ax:
        a.legend(fontsize=6)
        a.grid(alpha=0.3)
    return save(fig, outdir / "wrench_vs_airspeed")


def _levels_figure(gen, rpm: np.ndarray, outdir: Path) -> list[Path]:
    X = np.zeros((rpm.size, 8))
    X[:, :4] = rpm[:, None]
    Y0 = evaluate_batch(gen, X, chunk=SANITY_CHUNK)
    X[:, 7] = 10.0
    Y10 = evaluate_batch(gen, X, chunk=SANITY_CHUNK)
    fig, ax = _subplots(figsize=(5, 3.5))
    for j, c in zip(range(3), "rgb", strict=True):
        ax.plot(rpm, Y0[:, 6 + j], c, label=f"{OUTPUTS[6 + j]} hover")
        ax.plot(rpm, Y10[:, 6 + j], c, ls="--", label=f"{OUTPUTS[6 + j]} 10 m/s")
    ax.set(xlabel="rpm", ylabel="OASPL [dB re 20 µPa]", title="Tonal noise at 20 R", ylim=(0, None))
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    return save(fig, outdir / "oaspl_vs_rpm")


def _gradient_figure(err: np.ndarray, outdir: Path) -> list[Path]:
    """Finite-difference against exact gradients, ``err`` (n, M, 7) scaled by their spread."""
    fig, ax = _subplots(figsize=(7, 3.5))
    data = [err[:, :, j].ravel() for j in range(err.shape[2])]
    ax.boxplot(data, showfliers=False)
    ax.set_xticks(range(1, err.shape[2] + 1), INPUTS[: err.shape[2]])
    ax.set(
        ylabel="|FD − exact| / std(exact)",
        yscale="log",
        title=f"Finite-difference gradient error ({err.shape[0]} points, all outputs)",
    )
    ax.grid(alpha=0.3)
    return save(fig, outdir / "fd_vs_exact_gradients")


def _boxes(ax, data, labels, title, ylabel):
    ax.boxplot(data, showfliers=False, whis=(5, 95))
    ax.set_xticks(range(1, len(labels) + 1), labels, rotation=30, ha="right", fontsize=8)
    ax.set_yscale("log")
    ax.set_title(title)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, axis="y")


UNITS = {"F": "N", "M": "N m", "L": "dB"}
# A model whose median error on an output is this many times the best model's is "failing"
# there: it is drawn apart, so that it does not squash the axis the working models share.
FAILING = 10.0


def _split(labels, err, n):
    med = {lab: float(np.median(err(lab, n))) for lab in labels}
    best = min(med.values())
    failing = [lab for lab in labels if med[lab] > FAILING * max(best, 1e-300)]
    return [lab for lab in labels if lab not in failing], failing, med


def _compare_panels(axes, labels, err, outputs):
    """One box panel per output of the working models; failing ones noted under it."""
    for ax, n in zip(np.ravel(axes), outputs, strict=False):
        good, bad, med = _split(labels, err, n)
        _boxes(ax, [err(lab, n) for lab in good], good, n, f"|error| [{UNITS[n[0]]}]")
        if bad:
            note = "not shown (median ≥ 10x best): " + ", ".join(
                f"{lab} {med[lab]:.3g}" for lab in bad
            )
            ax.text(0.0, -0.42, note, transform=ax.transAxes, fontsize=7, va="top", wrap=True)


def compare_figures(
    results: dict[str, Any], errors: dict[str, np.ndarray], names: list[str], outdir: Path
) -> list[Path]:
    """Error distributions (paper Fig. model comparison), all outputs, the Schur model against
    its no-Schur counterpart, error vs airspeed, and every mean form of the Schur model.
    ``results`` are the runs by label (:class:`gpg.results.ModelRun`, others skipped) and
    ``errors`` their absolute test errors (Q, M). Models that fail on an output are listed under
    its panel instead of stretching its axis (their own figures show them)."""
    ok = {k: v for k, v in results.items() if k in errors}
    labels = list(ok)
    paths: list[Path] = []
    key = [n for n in ("Fx", "Mx", "L1") if n in names]

    def err(label, n):
        return errors[label][:, names.index(n)]

    fig, axes = _subplots(1, len(key), figsize=(4.6 * len(key), 4.4))
    _compare_panels(axes, labels, err, key)
    fig.suptitle("Model comparison on the test set (boxes: quartiles, whiskers: 5-95 %)")
    fig.tight_layout()
    paths += save(fig, outdir / "model_compare")

    cols = 3
    rows = -(-len(names) // cols)
    fig, axes = _subplots(rows, cols, figsize=(14, 4.4 * rows))
    _compare_panels(axes, labels, err, names)
    for ax in np.ravel(axes)[len(names) :]:
        ax.axis("off")
    fig.tight_layout()
    paths += save(fig, outdir / "model_compare_all_outputs")

    paths += _schur_figures(ok, err, key, outdir)
    paths += _airspeed_figure(ok, err, names, key, outdir)
    return paths


def _schur_figures(ok, err, key, outdir: Path) -> list[Path]:
    """The Schur model against its no-Schur counterpart, and its mean forms side by side."""
    paths: list[Path] = []
    pair = _schur_pair(ok)
    if pair:
        fig, axes = _subplots(1, len(key), figsize=(4.2 * len(key), 3.8))
        for ax, n in zip(np.atleast_1d(axes), key, strict=True):
            _boxes(
                ax,
                [err(lab, n) for lab in pair],
                [f"no Schur ({pair[0]})", f"Schur ({pair[1]})"],
                n,
                f"|error| [{UNITS[n[0]]}]",
            )
        fig.suptitle("Schur complement comparison")
        fig.tight_layout()
        paths += save(fig, outdir / "schur_compare")

    forms = [lab for lab, r in ok.items() if models.SPECS[r.model].schur]
    if len(forms) >= 2:
        fig, axes = _subplots(1, len(key), figsize=(4.2 * len(key), 3.8))
        for ax, n in zip(np.atleast_1d(axes), key, strict=True):
            _boxes(ax, [err(lab, n) for lab in forms], forms, n, f"|error| [{UNITS[n[0]]}]")
        fig.suptitle(
            r"Schur model: mean forms (exact = $k_{qn}^\top \alpha_n$, "
            r"paper = $k_{qn}^\top S^{-1} \bar{Y}_n$)"
        )
        fig.tight_layout()
        paths += save(fig, outdir / "schur_mean_forms")
    return paths


def _airspeed_figure(ok, err, names, key, outdir: Path) -> list[Path]:
    labels = list(ok)
    fig, axes = _subplots(1, len(key), figsize=(4.6 * len(key), 3.8))
    for ax, n in zip(np.atleast_1d(axes), key, strict=True):
        j = names.index(n)
        good, bad, _ = _split(labels, err, n)
        for lab in good:
            ev = ok[lab].error_vs_airspeed
            mid = 0.5 * (np.array(ev["edges"][1:]) + np.array(ev["edges"][:-1]))
            vals = [np.nan if row is None else row[j] for row in ev["mean_abs_error"]]
            ax.plot(mid, vals, marker="o", ms=3, label=lab)
        ax.set(
            xlabel="airspeed [m/s]", ylabel=f"mean |error| [{UNITS[n[0]]}]", title=n, yscale="log"
        )
        if bad:
            ax.set_title(f"{n} (not shown: {', '.join(bad)})", fontsize=8)
        ax.grid(alpha=0.3)
    handles, lbls = np.atleast_1d(axes)[0].get_legend_handles_labels()
    fig.legend(handles, lbls, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=8)
    fig.suptitle("Prediction error vs airspeed")
    fig.tight_layout()
    return save(fig, outdir / "error_vs_airspeed")


def _schur_pair(runs: dict[str, Any]) -> tuple[str, str] | None:
    """The plain runs (no variant label) of a Schur model and of the local model on the same
    data, if the comparison has both: what the Schur correction adds."""
    plain = {r.model: lab for lab, r in runs.items() if lab == r.model}
    schur = [n for n in plain if models.SPECS[n].schur]
    for s in schur:
        data = models.SPECS[s].data
        local = [
            n
            for n in plain
            if models.SPECS[n].kind.name == "local" and models.SPECS[n].data == data
        ]
        if local:
            return plain[local[0]], plain[s]
    return None


def flight_figures(traces: dict, noise_simple: np.ndarray, plan, outdir: Path) -> list[Path]:
    """Path in the y-z plane, tracking error, mean rotor speed, microphone levels."""
    paths: list[Path] = []
    style = {"simplified": ("tab:blue", "-"), "surrogate": ("tab:red", "-")}
    wp = np.asarray(plan.waypoints)

    fig, ax = _subplots(figsize=(6, 3.6))
    for name, tr in traces.items():
        p = np.asarray(tr.p)
        ax.plot(p[:, 1], -p[:, 2], color=style[name][0], label=f"{name} dynamics")
    ref = np.asarray(next(iter(traces.values())).ref_p)
    ax.plot(ref[:, 1], -ref[:, 2], "k--", lw=0.8, label="reference")
    ax.plot(wp[:, 1], -wp[:, 2], "ks", ms=6, label="waypoints")
    ax.set(xlabel="y [m]", ylabel="altitude −z [m]", title="Flight path, y-z plane")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    paths += save(fig, outdir / "path_yz")

    fig, ax = _subplots(figsize=(6, 3.4))
    for name, tr in traces.items():
        err = np.linalg.norm(np.asarray(tr.p) - np.asarray(tr.ref_p), axis=1)
        ax.plot(np.asarray(tr.t), err, color=style[name][0], label=name)
    ax.set(xlabel="time [s]", ylabel="|p − p_ref| [m]", title="Tracking error")
    ax.legend()
    ax.grid(alpha=0.3)
    paths += save(fig, outdir / "tracking_error")

    fig, ax = _subplots(figsize=(6, 3.4))
    for name, tr in traces.items():
        ax.plot(np.asarray(tr.t), np.asarray(tr.rpm).mean(1), color=style[name][0], label=name)
    ax.set(xlabel="time [s]", ylabel="mean rotor speed [rpm]", title="Average rpm")
    ax.legend()
    ax.grid(alpha=0.3)
    paths += save(fig, outdir / "average_rpm")

    sur = traces["surrogate"]
    noise = np.asarray(sur.levels)
    if noise.shape[-1]:
        fig, ax = _subplots(figsize=(6, 3.4))
        t = np.asarray(sur.t)
        for j, c in zip(range(noise.shape[1]), ("tab:red", "tab:green", "tab:blue"), strict=False):
            ax.plot(t, noise[:, j], color=c, label=f"L{j + 1}, surrogate flight")
            ax.plot(
                np.asarray(traces["simplified"].t),
                noise_simple[:, j],
                color=c,
                ls=":",
                label=f"L{j + 1}, simplified flight",
            )
        ax.set(xlabel="time [s]", ylabel="OASPL [dB]", title="Microphone levels (surrogate)")
        ax.legend(fontsize=6, ncol=2)
        ax.grid(alpha=0.3)
        paths += save(fig, outdir / "microphone_levels")
    return paths


__all__ = ["compare_figures", "data_sanity", "flight_figures", "save"]
