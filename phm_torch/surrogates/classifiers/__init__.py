"""Health classifiers: smooth scores f(k) > 0 for a healthy actuator (surrogates of phi_a(k))."""

from .base import HealthClassifier
from .mlp import MLPClassifier
from .polynomial_svm import PolynomialSVM
from .rbf_svm import RBFSVM
from .registry import CLASSIFIERS, build_classifier

__all__ = ["CLASSIFIERS", "RBFSVM", "HealthClassifier", "MLPClassifier", "PolynomialSVM", "build_classifier"]
