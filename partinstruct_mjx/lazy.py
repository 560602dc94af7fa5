"""Lazy public names for a package: each is imported from its module on first use (keeps imports cheap)."""

from __future__ import annotations

import importlib


def lazy_getattr(package: str, public: dict[str, str]):
    """A module-level `__getattr__` for `package` that imports `name` from `public[name]` when first asked for."""

    def __getattr__(name: str):
        if name in public:
            return getattr(importlib.import_module(public[name]), name)
        raise AttributeError(f"module '{package}' has no attribute '{name}'")

    return __getattr__
