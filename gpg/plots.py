"""Figures (matplotlib, no display needed): dataset sanity checks and model comparisons."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gpg.quadrotor.generator import INPUT_NAMES, OUTPUT_NAMES, evaluate_batch  # noqa: E402

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
    plt.close(fig)
    return out


def data_sanity(gen, simple, check: dict[str, Any], outdir: Path) -> list[Path]:
    """Thrust vs rpm, wrench vs airspeed, OASPL vs rpm, FD vs exact gradients."""
    from gpg.runs.generate_data import hover_sweep

    paths: list[Path] = []
    rpm = np.linspace(0, 7000, 29)
    T, Q = hover_sweep(gen, rpm)
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ax[0].plot(rpm, T, "o", ms=3, label="generator (per rotor)")
    ax[0].plot(rpm, float(simple.P_F) * rpm**2, "-", label=r"$P_F\,r^2$ (fit)")
    ax[0].set(xlabel="rpm", ylabel="thrust [N]", title="Hover thrust")
    ax[1].plot(rpm, Q, "o", ms=3, label="generator")
    ax[1].plot(rpm, float(simple.T_z) * rpm**2, "-", label=r"$T_z\,r^2$ (fit)")
    ax[1].set(xlabel="rpm", ylabel="torque [N m]", title="Hover rotor torque")
    for a in ax:
        a.legend()
        a.grid(alpha=0.3)
    paths += save(fig, outdir / "thrust_vs_rpm")

    hover = float(simple.hover_rpm(float(gen.vehicle.weight)))
    V = np.linspace(0, 20, 21)
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.5))
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
                label=f"{OUTPUT_NAMES[j]}, pitch {pitch_deg:g}°",
            )
            ax[1].plot(
                V,
                Y[:, 3 + j],
                c,
                ls="-" if pitch_deg == 0 else "--",
                label=f"{OUTPUT_NAMES[3 + j]}, pitch {pitch_deg:g}°",
            )
            ax[2].plot(
                V,
                Y[:, 6 + j],
                c,
                ls="-" if pitch_deg == 0 else "--",
                label=f"{OUTPUT_NAMES[6 + j]}, pitch {pitch_deg:g}°",
            )
    ax[0].set(xlabel="airspeed [m/s]", ylabel="force [N]", title=f"Forces at {hover:.0f} rpm")
    ax[1].set(xlabel="airspeed [m/s]", ylabel="moment [N m]", title="Moments")
    ax[2].set(xlabel="airspeed [m/s]", ylabel="OASPL [dB]", title="Noise")
    for a in ax:
        a.legend(fontsize=6)
        a.grid(alpha=0.3)
    paths += save(fig, outdir / "wrench_vs_airspeed")

    X = np.zeros((rpm.size, 8))
    X[:, :4] = rpm[:, None]
    Y0 = evaluate_batch(gen, X, chunk=SANITY_CHUNK)
    X[:, 7] = 10.0
    Y10 = evaluate_batch(gen, X, chunk=SANITY_CHUNK)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for j, c in zip(range(3), "rgb", strict=True):
        ax.plot(rpm, Y0[:, 6 + j], c, label=f"{OUTPUT_NAMES[6 + j]} hover")
        ax.plot(rpm, Y10[:, 6 + j], c, ls="--", label=f"{OUTPUT_NAMES[6 + j]} 10 m/s")
    ax.set(xlabel="rpm", ylabel="OASPL [dB re 20 µPa]", title="Tonal noise at 20 R", ylim=(0, None))
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    paths += save(fig, outdir / "oaspl_vs_rpm")

    if check:
        err = check["scaled_error"]  # (n, M, 7)
        fig, ax = plt.subplots(figsize=(7, 3.5))
        data = [err[:, :, j].ravel() for j in range(err.shape[2])]
        ax.boxplot(data, showfliers=False)
        ax.set_xticks(range(1, err.shape[2] + 1), INPUT_NAMES[: err.shape[2]])
        ax.set(
            ylabel="|FD − exact| / std(exact)",
            yscale="log",
            title=f"Finite-difference gradient error ({err.shape[0]} points, all outputs)",
        )
        ax.grid(alpha=0.3)
        paths += save(fig, outdir / "fd_vs_exact_gradients")
    return paths


__all__ = ["data_sanity", "save", "jnp"]
