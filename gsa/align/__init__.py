"""Alignment of two 3DGS models: the pipeline and its stages.

    from gsa.align import align, AlignOptions
    result = align(source, target, AlignOptions(search="auto"))

`gsa.align` is this package and also callable: `gsa.align(source, target, ...)`
runs gsa.align.pipeline.align. (A package attribute named like a subpackage is
replaced by the subpackage as soon as anything imports it, so `from gsa import
align` could otherwise give a function or a module depending on import order.)
"""

from __future__ import annotations

import importlib
import sys
import types

_LAZY = dict.fromkeys(("align", "AlignOptions", "AlignmentResult", "AlignmentError"), "gsa.align.pipeline")
__all__ = list(_LAZY)


def __getattr__(name: str):
    # Loaded on first use: the pipeline pulls in scipy and numba (~1 s), which
    # commands that never align (the service client) should not pay.
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'gsa.align' has no attribute {name!r}")


class _CallablePackage(types.ModuleType):
    def __call__(self, *args, **kwargs):
        from gsa.align.pipeline import align as run

        return run(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage
