"""Thin Hydra entry points; the work is done by ``gpg.runs``."""
