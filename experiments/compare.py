"""The paper's comparison: ``python -m experiments.compare [+model=<name>] [data=<scale>]``."""

import hydra
from omegaconf import DictConfig

from experiments._hydra import guarded, plain, run_dir
from experiments.runs import compare
from experiments.runs.config import conf
from gpg import conf as gpg_conf
from gpg import models


def model_configs(cfg: dict) -> dict[str, dict]:
    """The model(s) to run: ``+model=<name>`` or every name in ``models`` (conf/model/)."""
    if "model" in cfg:
        return {cfg["model"]["name"]: cfg["model"]}
    out = {}
    for name in cfg["models"]:
        if name not in models.SPECS:
            raise ValueError(f"unknown model {name!r} in models; valid: {list(models.SPECS)}")
        # A built-in name has its gpg/conf/model file; one registered in code, its defaults.
        has_file = name in gpg_conf.names("model")
        out[name] = conf(name, "model") if has_file else models.model_defaults(name)
    return out


@hydra.main(config_path="../conf", config_name="compare", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = plain(cfg)
    guarded(lambda: compare.run(values, run_dir(), model_configs(values)))


if __name__ == "__main__":
    main()
