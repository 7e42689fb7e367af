"""Small helpers shared by the experiment runners: timing, JSON output, tables."""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def conf(name: str, group: str | None = None) -> dict[str, Any]:
    """A config file of ``conf/`` as plain values, without Hydra (for notebooks and scripts):
    ``conf("smoke", "data")`` reads ``conf/data/smoke.yaml``. Defaults lists are not composed."""
    import yaml

    path = CONF_DIR / (group or "") / f"{name}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ValueError(f"no config {path}; known: {known}")
    with open(path) as f:
        return yaml.safe_load(f)


def block(x):
    """Wait for every array in ``x`` (JAX dispatch is asynchronous)."""
    return jax.block_until_ready(x)


def time_calls(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> np.ndarray:
    """Wall-clock seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed calls."""
    for _ in range(warmup):
        block(fn())
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        block(fn())
        out[i] = time.perf_counter() - t0
    return out


def stats(seconds: np.ndarray) -> dict[str, float]:
    """Median, 5th and 95th percentile and mean, in seconds."""
    return {
        "median_s": float(np.median(seconds)),
        "p05_s": float(np.percentile(seconds, 5)),
        "p95_s": float(np.percentile(seconds, 95)),
        "mean_s": float(np.mean(seconds)),
        "n": int(seconds.size),
    }


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
    }


def _default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray | jax.Array):
        return np.asarray(o).tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(obj, f, indent=2, sort_keys=False, default=_default)
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    """A Markdown table: ``columns`` are (key, header, format spec)."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    lines = [head, sep]
    for r in rows:
        cells = []
        for key, _, spec in columns:
            v = r.get(key)
            cells.append("—" if v is None else format(v, spec) if spec else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
