"""GSA: Gaussian Splatting Alignment (CVPR 2026) — the library.

Importable and testable without any web framework; `service/` builds on it.

    from gsa import read_ply
    from gsa.align import AlignOptions, align
    result = align(read_ply("a.ply"), read_ply("b.ply"), AlignOptions())
    result.transform.matrix()  # 4×4 with target ≈ T(source)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from gsa.lazy import lazy_exports
from gsa.model import GaussianModel, merge_models
from gsa.sim3 import Sim3, solve_sim3

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from gsa.align.pipeline import AlignmentError, AlignmentResult, AlignOptions  # noqa: F401
    from gsa.io.formats import read_model, write_model  # noqa: F401
    from gsa.io.ply import read_ply, write_ply  # noqa: F401

# The alignment API pulls in scipy and numba; it loads on first use so that
# `import gsa` (and the CLI's start-up) stays cheap. `align` itself is gsa.align.align:
# here `gsa.align` is the subpackage.
_HOMES = {
    "AlignOptions": "gsa.align.pipeline",
    "AlignmentResult": "gsa.align.pipeline",
    "AlignmentError": "gsa.align.pipeline",
    "read_ply": "gsa.io.ply",
    "write_ply": "gsa.io.ply",
    "read_model": "gsa.io.formats",  # any 3DGS format, sniffed (docs/formats.md)
    "write_model": "gsa.io.formats",
}

__all__ = ["GaussianModel", "Sim3", "merge_models", "solve_sim3", *_HOMES]
__version__ = "0.1.0"
__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
