"""Surrogate bundles named on a command line: ``[name=]path`` specs (the comparison scripts' ``--bundle``)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from .bundle import SurrogateBundle


def load_named_bundles(specs: Sequence[str]) -> dict[str, SurrogateBundle]:
    """Bundles from command-line specs ``[name=]path`` (the comparison scripts' ``--bundle``), in order.

    The name ends at the first ``=`` and holds no path separator, so a path from a Hydra sweep
    (``multirun/.../n_hidden=20/surrogates.pt``) stays whole, named or not. A spec without a name is called
    ``bundle<i>`` (``bundle`` when it is the only one)."""
    out = {}
    for i, spec in enumerate(specs):
        name, sep, path = spec.partition("=")
        if not sep or "/" in name or os.sep in name or Path(spec).is_file():
            name, path = "", spec
        name = name or (f"bundle{i}" if len(specs) > 1 else "bundle")
        if name in out:
            raise ValueError(f"--bundle name {name!r} is given twice")
        out[name] = SurrogateBundle.load(path)
    return out
