"""Library side of the experiments: each module has ``run(cfg, outdir)`` taking plain values.

The Hydra entry points in ``experiments/`` only compose the config, turn it into a plain
``dict`` and call these; no ``DictConfig`` reaches the numerics.
"""
