"""Which simulator cases to run next: ``python -m experiments.design step=ask|tell`` for an
external solver, ``+experiment=active`` for the whole loop against Latin hypercubes."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import design


@hydra.main(config_path="../conf", config_name="design", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: design.run(values, run_dir()))


if __name__ == "__main__":
    main()
