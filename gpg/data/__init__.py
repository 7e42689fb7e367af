"""Datasets: schema and files, sampling, preprocessing.

The file format and CSV import are :mod:`gpg.data.dataset`; sampling and the finite
differences :mod:`gpg.data.sampling`; the GP's targets :mod:`gpg.data.preprocess`; generated
train/test pairs and their cache :mod:`gpg.data.cache`; airflow-frame data in the body frame
:mod:`gpg.data.convert`; mirror images of body-frame cases :mod:`gpg.data.symmetry`.
"""

from gpg.data import bounds, cache, convert, dataset, preprocess, sampling, symmetry
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
    "bounds",
    "cache",
    "convert",
    "dataset",
    "from_csv",
    "generate",
    "latin_hypercube",
    "prepare",
    "preprocess",
    "restore",
    "sampling",
    "symmetry",
]
