"""Every name a package exports in ``__all__`` exists (``from phm_torch.x import *`` works)."""

from __future__ import annotations

import importlib
import pkgutil

import pytest

import phm_torch

PACKAGES = sorted(m.name for m in pkgutil.walk_packages(phm_torch.__path__, "phm_torch.") if m.ispkg)


@pytest.mark.parametrize("name", ["phm_torch", *PACKAGES])
def test_all_names_exist(name):
    module = importlib.import_module(name)
    missing = [n for n in getattr(module, "__all__", []) if not hasattr(module, n)]
    assert not missing, f"{name}.__all__ names what it does not define: {missing}"
