"""A directory of flight logs read and labelled across processes: on this machine's cores, or on
a Dask cluster when a client is given.

Each log is read (:func:`~gpg.flight.read_csv` by its ``.csv`` suffix,
:func:`~gpg.flight.read_ulog` by ``.ulg``) and labelled (:func:`~gpg.flight.label`) in a worker
of its own, independently of the others, so the labels do not depend on how many workers there
are or which one took a log: each is the same function of the same file. A log that fails is
reported by name with its error, and the others are labelled; the warnings each log raised are
kept with it and raised again in the caller, prefixed with the log's name, so nothing a worker
said is lost.

The workers are this process and others started with ``spawn``, not ``fork``: JAX's runtime
runs threads that a forked child would inherit in whatever state they were. This process labels
from the end of the list while the others start (each imports gpg once, in seconds) and take
logs from its front. Each worker labels many logs, with the caller's JAX precision
(``jax_enable_x64``; the vehicle's and the reference model's arrays travel as NumPy and become
JAX arrays after it is set). As everywhere with ``spawn``, a script that calls
:func:`label_logs` with more than one worker must guard its entry point with
``if __name__ == "__main__":``.
"""

from __future__ import annotations

import inspect
import os
import warnings
from collections import deque
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from functools import partial
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from gpg.flight.labels import Labels, check_label_arguments, label
from gpg.flight.log import CsvFormat, FlightLog
from gpg.quadrotor.vehicle import Vehicle

__all__ = ["LOG_SUFFIXES", "LabelledLogs", "label_logs"]

LOG_SUFFIXES = (".csv", ".ulg")
"""The files :func:`label_logs` reads, by suffix (case-insensitive)."""

# label's keywords and their defaults, read off its signature (one place says them).
_LABEL_DEFAULTS = {
    k: p.default for k, p in inspect.signature(label).parameters.items() if p.kind == p.KEYWORD_ONLY
}


@dataclass(frozen=True)
class LabelledLogs:
    """What :func:`label_logs` gives back.

    Attributes:
        labels: each labelled log's :class:`~gpg.flight.Labels`, by path, in the order the
            logs were given (the failed ones absent).
        failed: each log that failed, by path: its error as ``"ErrorType: message"``.
        warned: each log's warnings, by path, as ``"WarningType: message"`` (raised again in
            the caller, prefixed with the path).
    """

    labels: dict[str, Labels]
    failed: dict[str, str] = field(default_factory=dict)
    warned: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def parts(self) -> list[Labels]:
        """The labels as a list, one part per log (what :func:`~gpg.flight.correct` takes).

        Returns:
            The labelled logs' :class:`~gpg.flight.Labels`, in the order given.
        """
        return list(self.labels.values())

    def report(self) -> str:
        """A text report: how many logs were labelled, and each failure with its error.

        Returns:
            One line for the count and one per failed log.
        """
        n = len(self.labels) + len(self.failed)
        lines = [f"{len(self.labels)} of {n} logs labelled, {len(self.failed)} failed"]
        lines += [f"  {path}: {err}" for path, err in self.failed.items()]
        return "\n".join(lines)


def _log_paths(logs: str | Path | Sequence[str | Path]) -> list[Path]:
    """The log files: a directory's ``.csv`` and ``.ulg`` files sorted by name, or the paths
    given, each checked to exist with a suffix it can be read by."""
    if isinstance(logs, (str, Path)):
        root = Path(logs)
        if not root.is_dir():
            raise ValueError(f"logs: {str(root)!r} is not a directory (give a list of files)")
        paths = sorted(p for p in root.iterdir() if p.suffix.lower() in LOG_SUFFIXES)
        if not paths:
            raise ValueError(f"logs: no {' or '.join(LOG_SUFFIXES)} files in {str(root)!r}")
        return paths
    if not isinstance(logs, Sequence) or not logs:
        raise ValueError("logs must be a directory or a non-empty list of log files")
    paths = [Path(p) for p in logs]
    for p in paths:
        if p.suffix.lower() not in LOG_SUFFIXES:
            raise ValueError(f"logs: {str(p)!r} is neither {' nor '.join(LOG_SUFFIXES)}")
        if not p.is_file():
            raise ValueError(f"logs: {str(p)!r} does not exist or is not a file")
    if len({p.resolve() for p in paths}) != len(paths):
        raise ValueError("logs: a file is given twice")
    return paths


def _read(path: Path, csv_format: CsvFormat | None, ulog_options: Mapping[str, Any]) -> FlightLog:
    if path.suffix.lower() == ".ulg":
        from gpg.flight.ulog import read_ulog

        return read_ulog(path, **ulog_options)
    from gpg.flight.log import read_csv

    return read_csv(path, csv_format)


class _Host:
    """A JAX array's values in transit to a worker, as NumPy: a JAX array unpickled before the
    worker has the caller's precision would be made float32 there."""

    def __init__(self, value):
        self.value = np.asarray(value)


def _to_host(tree):
    return jax.tree.map(lambda x: _Host(x) if isinstance(x, jax.Array) else x, tree)


def _from_host(tree):
    return jax.tree.map(lambda x: jnp.asarray(x.value) if isinstance(x, _Host) else x, tree,
                        is_leaf=lambda x: isinstance(x, _Host))  # fmt: skip


def _label_one(path: str, vehicle: Vehicle, csv_format, ulog_options, label_options, x64: bool):
    """One log read and labelled, in whichever process runs it: ``(labels or None, error or
    None, warnings)``. Never raises for a log's own fault: the caller reports it by name.
    ``vehicle`` and ``label_options`` come with their arrays as :class:`_Host`: made JAX
    arrays again after the caller's precision is set."""
    jax.config.update("jax_enable_x64", x64)
    vehicle, label_options = _from_host((vehicle, label_options))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        try:
            lab = label(_read(Path(path), csv_format, ulog_options), vehicle, **label_options)
            err = None
        except Exception as e:  # noqa: BLE001 - every failure of one log is reported, by name
            lab, err = None, f"{type(e).__name__}: {e}"
    said = tuple((w.category, str(w.message)) for w in seen)
    return lab, err, said


def label_logs(
    logs: str | Path | Sequence[str | Path],
    vehicle: Vehicle,
    *,
    csv_format: CsvFormat | None = None,
    ulog_options: Mapping[str, Any] | None = None,
    workers: int | None = None,
    client: Any = None,
    progress: bool = True,
    **label_options: Any,
) -> LabelledLogs:
    """Read and label many flight logs in parallel, on processes or a Dask cluster (module
    docstring).

    Args:
        logs: a directory (its ``.csv`` and ``.ulg`` files, by name) or a list of log files.
        vehicle: the vehicle every log flew (:func:`~gpg.flight.label`'s ``vehicle``).
        csv_format: how the CSV logs differ from gpg's conventions
            (:func:`~gpg.flight.read_csv`); None: its defaults.
        ulog_options: keywords of :func:`~gpg.flight.read_ulog` (``rate``, ``rotor_order``...).
        workers: processes on this machine: this one and ``workers − 1`` spawned ones
            (default: one per core, at most one per log; 1: this process alone). Ignored with
            ``client``.
        client: a ``dask.distributed.Client``: the logs are labelled on its cluster instead
            (the workers must see the files at the same paths).
        progress: a progress bar over the logs.
        **label_options: :func:`~gpg.flight.label`'s keywords (``reference``, ``rate``,
            ``source``, ``curve``...), the same for every log.

    Returns:
        The :class:`LabelledLogs`: labels by path, failures by path with their errors, and
        each log's warnings.

    Raises:
        ValueError: no logs, a file that does not exist or has another suffix, a file given
            twice, an unknown or bad label option, a ``workers`` that is not a positive
            integer, or a ``client`` without ``map``.
    """
    paths = _log_paths(logs)
    unknown = sorted(set(label_options) - _LABEL_DEFAULTS.keys())
    if unknown:
        raise ValueError(
            f"unknown label option(s) {unknown}; label takes {sorted(_LABEL_DEFAULTS)}"
        )
    _check_options(vehicle, label_options)
    if csv_format is not None and not isinstance(csv_format, CsvFormat):
        raise ValueError(f"csv_format must be a CsvFormat, got {type(csv_format).__name__}")
    ulog_options = dict(ulog_options or {})
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or workers < 1):  # fmt: skip
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    if client is not None and not callable(getattr(client, "map", None)):
        raise ValueError(f"client must be a dask.distributed.Client, got {type(client).__name__}")
    one = partial(_label_one, vehicle=_to_host(vehicle), csv_format=csv_format,
                  ulog_options=ulog_options, label_options=_to_host(dict(label_options)),
                  x64=bool(jax.config.jax_enable_x64))  # fmt: skip
    names = [str(p) for p in paths]
    bar = tqdm(total=len(names), desc="labelling logs", unit="log", disable=not progress)
    try:
        if client is not None:
            results = _on_dask(client, one, names, bar)
        else:
            n = min(len(names), os.cpu_count() or 1) if workers is None else workers
            results = _in_processes(one, names, n, bar)
    finally:
        bar.close()
    return _collected(names, results)


def _check_options(vehicle: Vehicle, label_options: Mapping[str, Any]) -> None:
    """The label options checked once, here, before any worker starts (a mistake in them is
    every log's, not one log's)."""
    o = {**_LABEL_DEFAULTS, **label_options}
    check_label_arguments(vehicle, o["reference"], o["rate"], o["source"], o["delay"],
                          o["max_delay"], o["curve"])  # fmt: skip


def _in_processes(one, names: list[str], n: int, bar) -> dict[str, tuple]:
    """The logs on this process and ``n − 1`` spawned ones. This process labels too, from the
    end of the list while the others take it from the front: it is warm (gpg imported, the
    labelling compiled) while a spawned worker takes seconds to start, and it would idle
    otherwise."""
    pending = deque(names)
    out: dict[str, tuple] = {}

    def here() -> None:
        name = pending.pop()
        out[name] = one(name)
        bar.update()

    if n == 1:
        while pending:
            here()
        return out
    running: dict[Any, str] = {}
    with ProcessPoolExecutor(max_workers=n - 1, mp_context=get_context("spawn")) as pool:

        def top_up() -> None:  # two queued a worker: none idles between two logs
            while len(pending) > 1 and len(running) < 2 * (n - 1):
                name = pending.popleft()
                running[pool.submit(one, name)] = name

        def collect(futures) -> None:
            for fut in futures:
                out[running.pop(fut)] = _result(fut)
                bar.update()

        top_up()
        while pending:
            here()
            collect([f for f in running if f.done()])
            top_up()
        collect(list(as_completed(running)))
    return out


def _on_dask(client, one, names: list[str], bar) -> dict[str, tuple]:
    from distributed import as_completed as dask_completed

    futures = client.map(one, names, pure=False)
    which = {f.key: name for f, name in zip(futures, names, strict=True)}
    out: dict[str, tuple] = {}
    for fut in dask_completed(futures):
        out[which[fut.key]] = _result(fut)
        bar.update()
    return out


def _result(fut) -> tuple:
    """A worker's result, or the failure of the worker itself (a process that died) as the
    log's error."""
    try:
        return fut.result()
    except Exception as e:  # noqa: BLE001 - a dead worker fails its log, not the batch
        return None, f"{type(e).__name__} in the worker: {e}", ()


def _collected(names: list[str], results: Mapping[str, tuple]) -> LabelledLogs:
    labels, failed, warned = {}, {}, {}
    for name in names:
        lab, err, said = results[name]
        if err is None:
            labels[name] = lab
        else:
            failed[name] = err
        if said:
            warned[name] = tuple(f"{cat.__name__}: {msg}" for cat, msg in said)
        for cat, msg in said:
            warnings.warn(f"{name}: {msg}", cat if issubclass(cat, Warning) else UserWarning,
                          stacklevel=3)  # fmt: skip
    return LabelledLogs(labels, failed, warned)
