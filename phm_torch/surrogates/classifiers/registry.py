"""Health-classifier registry: config names to classes."""

from __future__ import annotations

from typing import Any

from .base import HealthClassifier
from .mlp import MLPClassifier
from .polynomial_svm import PolynomialSVM
from .rbf_svm import RBFSVM

CLASSIFIERS: dict[str, type[HealthClassifier]] = {cls.name: cls for cls in (PolynomialSVM, RBFSVM, MLPClassifier)}


def build_classifier(name: str, **params: Any) -> HealthClassifier:
    """The classifier registered as ``name``, constructed with ``params``."""
    if name not in CLASSIFIERS:
        raise ValueError(f"classifier: unknown name {name!r}; known: {sorted(CLASSIFIERS)}")
    return CLASSIFIERS[name](**params)
