"""Compare the numbers of two ``results.json`` files, timings and machine facts excluded:
``python -m experiments.diff_results A/results.json B/results.json [--rtol 0]``.

Prints every number that differs (by more than ``--rtol`` relative) with its path, and exits 1
when any does: the check behind "every number of ``make compare`` identical before and after".
Keys that measure time or memory (``*_s``, ``*_ms*``, latencies, peaks, bytes of the run's
process) and the ``machine``/``config``/``figures`` records are left out.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

SKIP_KEYS = {"machine", "config", "figures", "dataset", "cache", "generate_s"}
TIMING = re.compile(r"(_s$|_ms|_s_|latency|per_s|seconds|peak|rss|^t_|time|_ratio_to_)")


def numbers(obj: Any, path: str = "") -> dict[str, float]:
    """Every number of a JSON tree, by its path, timings and run records left out."""
    out: dict[str, float] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k in SKIP_KEYS or TIMING.search(str(k)):
                continue
            out.update(numbers(v, f"{path}.{k}" if path else str(k)))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.update(numbers(v, f"{path}[{i}]"))
    elif isinstance(obj, bool):
        out[path] = float(obj)
    elif isinstance(obj, int | float):
        out[path] = float(obj)
    return out


def differences(a: dict[str, float], b: dict[str, float], rtol: float) -> list[str]:
    rows = []
    for k in sorted(set(a) | set(b)):
        if k not in a or k not in b:
            rows.append(f"{k}: only in {'the first' if k in a else 'the second'}")
            continue
        x, y = a[k], b[k]
        same = (math.isnan(x) and math.isnan(y)) or x == y
        if not same and not (rtol > 0 and abs(x - y) <= rtol * max(abs(x), abs(y))):
            rows.append(f"{k}: {x!r} -> {y!r}")
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("first", type=Path)
    p.add_argument("second", type=Path)
    p.add_argument("--rtol", type=float, default=0.0, help="relative tolerance (default: exact)")
    args = p.parse_args(argv)
    a, b = (numbers(json.loads(f.read_text())) for f in (args.first, args.second))
    rows = differences(a, b, args.rtol)
    print(f"{len(a)} numbers compared; {len(rows)} differ")
    for r in rows:
        print("  " + r)
    return 1 if rows else 0


if __name__ == "__main__":
    sys.exit(main())
