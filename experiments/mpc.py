"""Cautious MPC against the geometric controller in gusts: ``python -m experiments.mpc``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import mpc


@hydra.main(config_path="../conf", config_name="mpc", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: mpc.run(values, run_dir()))


if __name__ == "__main__":
    main()
