"""GSA: Gaussian Splatting Alignment (CVPR 2026) — the library.

Importable and testable without any web framework; `service/` builds on it.
"""

from gsa.model import GaussianModel, merge_models
from gsa.sim3 import Sim3, solve_sim3

__all__ = ["GaussianModel", "Sim3", "merge_models", "solve_sim3"]
__version__ = "0.1.0"
