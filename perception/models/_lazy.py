"""Packages whose public names load on first use: ``import perception`` loads nothing heavy.

A package's ``__init__`` maps each public name to the module that defines it and takes
``__getattr__`` and ``__dir__`` from :func:`lazy_exports` (PEP 562). ``from perception import
PinholeCamera`` then imports ``perception.models.cameras`` at that moment, and a tool that needs
only a small part of the package (``perception.models.validation``) does not pay for SciPy and
OpenCV at start-up.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(
    package: str, names: Mapping[str, str], namespace: dict[str, Any]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` of ``package`` that import each of ``names`` from its module on first use.

    Args:
        package: The package's name (``__name__``).
        names: Public name -> the module that defines it.
        namespace: The package's ``globals()`` (a name is cached there once loaded).
    """

    def __getattr__(name: str) -> Any:
        module = names.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*namespace, *names})

    return __getattr__, __dir__
