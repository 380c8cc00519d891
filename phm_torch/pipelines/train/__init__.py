"""The training pipeline (``phm-train``): every surrogate from a dataset store, evaluated on its validation split.

:func:`train_surrogates` (:mod:`.pipeline`) runs the steps: the data and its reduction (:mod:`.data`), the FDI
network (:mod:`.fdi`), the classifiers (:mod:`.classifiers`), the evaluation; its settings are
:mod:`.settings`'s (:class:`FDIModel` is the ``_target_`` of the ``model`` config node).
"""

from .classifiers import classifier_set, fit_health_classifier, store_labeller
from .fdi import monitor_rows
from .pipeline import train_surrogates
from .settings import EvalSettings, FDIModel, FitSettings, GappySettings, TrainSettings

__all__ = [
    "EvalSettings",
    "FDIModel",
    "FitSettings",
    "GappySettings",
    "TrainSettings",
    "classifier_set",
    "fit_health_classifier",
    "monitor_rows",
    "store_labeller",
    "train_surrogates",
]
