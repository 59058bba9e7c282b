"""PEP 562-style lazy package attributes: nothing heavy (torch, numba) is imported until a name
that needs it is first used.

``lazy_package(__name__, {"name": ".submodule", ...})`` in a package ``__init__`` makes each
name resolve on first access (then cached). No listed name may be a submodule's name
(``tests/test_public_api.py`` checks it): importing that submodule would rebind the attribute,
so ``pkg.name`` would mean the function or the module depending on import order.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any


class _LazyPackage(types.ModuleType):
    def __getattr__(self, name: str) -> Any:
        lazy = self.__dict__.get("_LAZY", {})
        if name not in lazy:
            raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(lazy[name], self.__name__), name)
        types.ModuleType.__setattr__(self, name, value)
        return value

    def __dir__(self) -> list[str]:
        return sorted(set(self.__dict__) | set(self.__dict__.get("_LAZY", {})))


def lazy_package(package: str, names: dict[str, str]) -> None:
    """Make ``package`` (its ``__init__`` calling this) resolve ``names`` (name -> relative
    submodule) on first use."""
    mod = sys.modules[package]
    mod._LAZY = dict(names)
    mod.__class__ = _LazyPackage
