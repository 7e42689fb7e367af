"""What the experiments print: results to the console (and the run's log under Hydra), and
Markdown tables."""

from __future__ import annotations

import logging
from typing import Any

_log = logging.getLogger("experiments.runs")


def report(text: str) -> None:
    """A result for the console and, under Hydra, the run's log file (``<job>.log``): logged
    at INFO when logging is configured, printed otherwise."""
    if logging.getLogger().hasHandlers():
        _log.info(text)
    else:
        print(text)


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
