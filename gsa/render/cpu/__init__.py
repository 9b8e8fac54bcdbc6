"""Native CPU compositing with numba: tile binning, front-to-back forward and a
hand-written back-to-front backward (the scheme of the CUDA 3DGS rasterizer).

Work is parallel over (camera, 16x16 tile) with prange. Inside a tile, Gaussians
are visited in depth order and each one only touches the pixels of its own
bounding box (3σ ellipse shrunk by the 1/255 opacity cutoff), keeping per-pixel
transmittance, so the cost is the true overlap rather than pixels x list length.
The backward pass recovers each pixel's transmittance from the saved final value
(T / (1 - alpha)) and the saved contributor count. Gradients are written per
(tile, Gaussian) pair, never shared between threads, then reduced per camera,
so results are deterministic and race-free.

Projection (means, covariances, SH) happens in torch (gsa.render.projection);
`composite_cpu` is a torch.autograd.Function over its outputs, so autograd chains
the kernel gradients to means, quaternions, log-scales, opacities, SH and features.
Kernels are compiled for float32 (speed) and float64 (gradient checks).

Modules: common (tile size, numba threading layer, kernel lock), binning (footprints, depth
order, tile lists, record packing, Morton order), composite (forward/backward compositing),
project (projection), covariance (3D covariances).
"""

from gsa.render.cpu.binning import locality_order
from gsa.render.cpu.common import TILE
from gsa.render.cpu.composite import composite_cpu
from gsa.render.cpu.covariance import covariance_cpu
from gsa.render.cpu.project import project_cpu

__all__ = ["TILE", "composite_cpu", "covariance_cpu", "locality_order", "project_cpu"]
