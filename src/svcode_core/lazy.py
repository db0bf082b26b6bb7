"""Names a package exports from its submodules, each imported on first use (PEP 562), so
that importing the package (and the ``svcode`` command's help) loads no torch."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, exports: dict[str, str], namespace: dict[str, Any]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package``, whose name ``name``
    is defined in the submodule ``exports[name]`` (relative, e.g. ``".config"``);
    ``namespace`` is the package's ``globals()``.

    Examples
    --------
    >>> get, names = lazy_exports("svcode_core", {"SystemConfig": ".config"}, {})
    >>> get("SystemConfig").__name__, names()
    ('SystemConfig', ['SystemConfig'])
    """

    def __getattr__(name: str) -> Any:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(exports[name], package), name)

    def __dir__() -> list[str]:
        return sorted([*namespace, *exports])

    return __getattr__, __dir__
