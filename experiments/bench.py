"""Speed measurements: ``python -m experiments.bench [suites=[exact_gp]]``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import bench


@hydra.main(config_path="../conf", config_name="bench", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: bench.run(values, run_dir()))


if __name__ == "__main__":
    main()
