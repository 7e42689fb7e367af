"""The work of the experiments: each module has ``run(cfg, outdir)`` taking plain values.

The Hydra entry points in ``experiments/`` only compose the config, turn it into a plain
``dict`` and call these; no ``DictConfig`` reaches the numerics. This package lives in the
repository beside ``gpg`` and is not installed with it: it imports gpg's public API only, as a
user's script would (tests/test_architecture.py). It was ``gpg.runs`` up to gpg 0.2.0, which
forwards to it, with a DeprecationWarning, until the next release.
"""
