"""Learned surrogates of the seed paper: POD layer, sample-time selectors, differentiable gappy POD,
FDI network (Levenberg-Marquardt or Adam, optionally end to end), health classifiers, metrics, and
the :class:`SurrogateBundle` that the online pipeline loads.

The Lightning training module lives in :mod:`phm_torch.surrogates.lightning_fdi` and is not imported
here, so that loading and running a bundle needs torch only."""

from .augment import SignalAugment, add_noise, drop_samples, noise_level, rms
from .bundle import SurrogateBundle
from .classifiers import CLASSIFIERS, RBFSVM, HealthClassifier, PolynomialSVM, build_classifier
from .fdi_ensemble import FDIEnsemble, build_fdi_network
from .fdi_mlp import FDIMLP
from .gappy_pod import GappyPOD
from .metrics import confusion, err_alpha, err_k, err_k_interval, err_k_per_signal, err_k_weights, fdi_mae
from .pod import POD
from .selectors import SELECTORS, Selector, build_selector
from .trainlm import TrainLM

__all__ = [
    "CLASSIFIERS",
    "FDIMLP",
    "POD",
    "RBFSVM",
    "SELECTORS",
    "FDIEnsemble",
    "GappyPOD",
    "HealthClassifier",
    "PolynomialSVM",
    "Selector",
    "SignalAugment",
    "SurrogateBundle",
    "TrainLM",
    "add_noise",
    "build_classifier",
    "build_fdi_network",
    "build_selector",
    "confusion",
    "drop_samples",
    "err_alpha",
    "err_k",
    "err_k_interval",
    "err_k_per_signal",
    "err_k_weights",
    "fdi_mae",
    "noise_level",
    "rms",
]
