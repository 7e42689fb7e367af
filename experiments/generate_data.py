"""Generate a dataset: ``python -m experiments.generate_data data=smoke|default|paper|large``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import generate_data


@hydra.main(config_path="../conf", config_name="generate_data", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: generate_data.run(values, run_dir()))


if __name__ == "__main__":
    main()
