"""The generation pipeline (``phm-generate``): the dataset store of the surrogates, resumable and shardable, and
the life split beside it.

:func:`generate` (:mod:`.pipeline`) runs the steps; its settings are :mod:`.settings`'s; what a store records
about itself (the fingerprint of its config) is :mod:`.records`'s; the life split is :mod:`.life`'s.
"""

from .life import write_life
from .pipeline import generate
from .records import DATA_NODES, NOT_FINGERPRINTED, fingerprint, git_revision
from .settings import STAGES, GenerateSettings

__all__ = [
    "DATA_NODES",
    "NOT_FINGERPRINTED",
    "STAGES",
    "GenerateSettings",
    "fingerprint",
    "generate",
    "git_revision",
    "write_life",
]
