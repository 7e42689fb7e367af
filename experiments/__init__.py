"""The repository's experiments, outside the installed library: the thin Hydra entry points
(``python -m experiments.<name>``) and, in ``experiments.runs``, the work they do. Neither is
installed by ``pip install gpg``; both use only gpg's public API (docs/design.md, "Layout")."""
