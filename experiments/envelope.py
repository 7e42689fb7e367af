"""The whole flight envelope, body frame against the paper's airflow frame:
``python -m experiments.envelope [data=envelope] [airflow_data=default]``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import envelope


@hydra.main(config_path="../conf", config_name="envelope", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: envelope.run(values, run_dir()))


if __name__ == "__main__":
    main()
