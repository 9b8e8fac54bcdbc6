"""Alignment of two 3DGS models: the pipeline and its stages.

    from gsa.align import align, AlignOptions
    result = align(source, target, AlignOptions(search="auto"))

The names load gsa.align.pipeline on first use: it pulls in scipy and numba (~1 s), which
commands that never align (the service client) should not pay.
"""

from __future__ import annotations

from gsa.lazy import lazy_exports

_HOMES = dict.fromkeys(("align", "AlignOptions", "AlignmentResult", "AlignmentError"), "gsa.align.pipeline")
_HOMES |= dict.fromkeys(("Verdict", "Alternative"), "gsa.align.verdict")
__all__ = list(_HOMES)
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
