"""The online flow: raw envelope current -> k_hat, health score, RUL 5/50/95 and an OOD flag."""

from .pipeline import OnlinePipeline

__all__ = ["OnlinePipeline"]
