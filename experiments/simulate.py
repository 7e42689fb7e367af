"""Closed-loop flights: ``python -m experiments.simulate [data=<scale>]``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import simulate


@hydra.main(config_path="../conf", config_name="simulate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: simulate.run(values, run_dir()))


if __name__ == "__main__":
    main()
