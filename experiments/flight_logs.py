"""The sim-to-real benchmark with known truth: ``python -m experiments.flight_logs``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import flight_logs


@hydra.main(config_path="../conf", config_name="flight_logs", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: flight_logs.run(values, run_dir()))


if __name__ == "__main__":
    main()
