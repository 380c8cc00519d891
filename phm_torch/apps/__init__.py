"""Hydra command-line entry points (``phm-simulate``, ``phm-run``)."""

from .schema import register_commands

register_commands()  # conf/command/*.yaml compose their class's defaults in (apps/schema.py)
