"""The paper's comparison: ``python -m experiments.compare [+model=<name>] [data=<scale>]``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from gpg.models import NAMES
from gpg.runs import compare
from gpg.runs.common import conf


def model_configs(cfg: dict) -> dict[str, dict]:
    """The model(s) to run: ``+model=<name>`` or every name in ``models`` (conf/model/)."""
    if "model" in cfg:
        return {cfg["model"]["name"]: cfg["model"]}
    out = {}
    for name in cfg["models"]:
        if name not in NAMES:
            raise ValueError(f"unknown model {name!r} in models; valid: {list(NAMES)}")
        out[name] = conf(name, "model")  # a known name without a file: conf lists the files
    return out


@hydra.main(config_path="../conf", config_name="compare", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: compare.run(values, run_dir(), model_configs(values)))


if __name__ == "__main__":
    main()
