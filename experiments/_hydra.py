"""Shared glue for the Hydra entry points: plain values in, the run directory out."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf


def plain(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config as plain Python containers (no DictConfig past this point)."""
    return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)


def run_dir() -> Path:
    """The Hydra run directory of the current job."""
    return Path(HydraConfig.get().runtime.output_dir)
