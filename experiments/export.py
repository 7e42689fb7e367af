"""The surrogate as C, CasADi and ONNX, checked and timed:
``python -m experiments.export [data=<scale>] [surrogate_checkpoint=<path>]``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import export


@hydra.main(config_path="../conf", config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: export.run(values, run_dir()))


if __name__ == "__main__":
    main()
