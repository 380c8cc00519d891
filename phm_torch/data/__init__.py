"""Training data: importance sampling, the dataset store, its generation and its LightningDataModule."""

from .sampling import ImportanceSampler
from .store import DatasetStore, read_labelled

__all__ = ["DatasetStore", "ImportanceSampler", "read_labelled"]
