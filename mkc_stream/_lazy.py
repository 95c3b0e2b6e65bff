"""Lazy exports of a package (PEP 562): names resolved from their module on first use, then cached.

Keeps `import mkc_stream` (and its subpackages) light: numba, scipy and matplotlib load only when a
name that needs them is first used.
"""
from __future__ import annotations

import importlib


def lazy_exports(package: str, names: dict, subpackages: tuple = ()):
    """The module-level (__getattr__, __dir__) of `package` for `names` ({name: module}) and its
    `subpackages` (exported by name as the subpackage itself)."""
    def __getattr__(name):
        if name in names:
            value = getattr(importlib.import_module(names[name]), name)
        elif name in subpackages:
            value = importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        vars(importlib.import_module(package))[name] = value      # later look-ups skip __getattr__
        return value

    def __dir__():
        module = importlib.import_module(package)
        return sorted(set(vars(module)) | set(getattr(module, "__all__", ())))

    return __getattr__, __dir__
