"""Shared glue for the Hydra entry points: plain values in, the run directory out, and one
clear message (no traceback) for a bad input, a lack of memory or a Ctrl-C.

The entry points compute in float64 throughout (the library fits in float64 whatever the
setting; this also makes their predictions float64): the process-wide choice is theirs to make,
not the library's (docs/design.md, "Dtype policy").
"""

from __future__ import annotations

import os
import shutil
import sys
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from gpg.checkpoint import CheckpointError
from gpg.linalg.memory import InsufficientMemory
from gpg.runtime import deferred_interrupt

jax.config.update("jax_enable_x64", True)


def _run_id() -> str:
    """A suffix that tells apart runs started in the same second (process id and a random
    part): every run gets its own directory, ``outputs/<date>/<time>-<id>``; the dataset cache
    stays shared. Cached per config, so the run directory is resolved once."""
    return f"{os.getpid()}-{uuid.uuid4().hex[:6]}"


if not OmegaConf.has_resolver("gpg_run_id"):
    OmegaConf.register_new_resolver("gpg_run_id", _run_id, use_cache=True)


def plain(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as plain Python containers (no DictConfig past this point)."""
    return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)


def run_dir() -> Path:
    """The Hydra run directory of the current job."""
    return Path(HydraConfig.get().runtime.output_dir)


def guarded(work: Callable[[], Any]) -> None:
    """Run an entry point's ``work`` with Ctrl-C taken at safe points
    (:func:`gpg.runtime.deferred_interrupt`): a bad input or too little memory prints
    ``error: ...`` and exits 2, a Ctrl-C prints that nothing was kept and exits 130. A failed
    run removes its run directory when it holds nothing but Hydra's own files (its config and
    a log of the failure)."""
    out = run_dir()
    try:
        with deferred_interrupt():
            work()
    except KeyboardInterrupt:
        print(
            "interrupted: stopped cleanly, no partial dataset or result was kept", file=sys.stderr
        )
        _remove_if_empty(out)
        sys.exit(130)
    except (ValueError, InsufficientMemory, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        _remove_if_empty(out)
        sys.exit(2)


def _remove_if_empty(out: Path) -> None:
    """Delete a run directory that holds only Hydra's ``.hydra/`` and ``*.log`` files."""
    if not out.is_dir():
        return
    own = [p for p in out.iterdir() if not (p.name == ".hydra" or p.suffix == ".log")]
    if not own:
        shutil.rmtree(out, ignore_errors=True)
