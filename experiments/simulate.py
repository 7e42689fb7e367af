"""Closed-loop flights: ``python -m experiments.simulate [data=<scale>]``."""

import sys

import hydra
from omegaconf import DictConfig

import gpg  # noqa: F401  (float64)
from experiments._hydra import plain, run_dir
from gpg.memory import InsufficientMemory
from gpg.runs import simulate


@hydra.main(config_path="../conf", config_name="simulate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    try:
        simulate.run(plain(cfg), run_dir())
    except (ValueError, InsufficientMemory) as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
