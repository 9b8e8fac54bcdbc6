"""Names a package exports but loads on first use, so that importing the package stays cheap.

    __getattr__, __dir__ = lazy_exports(__name__, {"render_model": "gsa.render.rasterizer"})

Each name is looked up in its home module whenever it is asked for (PEP 562 module
`__getattr__`), so the package never holds a stale copy of a name the home module rebinds.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping


def lazy_exports(package: str, homes: Mapping[str, str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """(__getattr__, __dir__) for `package`: each name of `homes` read from its module, by name."""
    homes = dict(homes)

    def __getattr__(name: str):
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(home), name)

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(homes))

    return __getattr__, __dir__
