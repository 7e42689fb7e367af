"""Datasets: schema and files, sampling, preprocessing."""

from gpg.data.bounds import Bounds
from gpg.data.dataset import Dataset, from_csv
from gpg.data.preprocess import Normalizer, Training, prepare, restore
from gpg.data.sampling import FDSteps, generate, latin_hypercube

__all__ = [
    "Bounds",
    "Dataset",
    "FDSteps",
    "Normalizer",
    "Training",
    "from_csv",
    "generate",
    "latin_hypercube",
    "prepare",
    "restore",
]
