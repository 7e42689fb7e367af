"""A policy learned on the surrogate environment against the geometric controller:
``python -m experiments.learn``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import learn


@hydra.main(config_path="../conf", config_name="learn", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: learn.run(values, run_dir()))


if __name__ == "__main__":
    main()
