"""Hydra command-line entry points (``phm-simulate``, ``phm-run``)."""
