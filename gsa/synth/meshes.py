"""Triangle meshes -> 3DGS models: surface Gaussians sampled by area, as the procedural
objects are, for benchmarks on real shapes (ShapeNet-style category meshes).

The meshes are read from a folder the user names (`<category>_<i>.npz` with `V` float
vertices, `F` int triangles and optional `C`, per-face RGB in [0, 1] with NaN where the
mesh has no colour); nothing here ships meshes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsa.model import GaussianModel
from gsa.synth.objects import surface_gaussians

# Uncoloured meshes get one grey: a real capture of an unpainted object has one albedo.
UNCOLOURED_RGB = (0.62, 0.62, 0.6)


@dataclass(frozen=True)
class Mesh:
    name: str
    category: str
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    face_rgb: np.ndarray  # (F, 3) in [0, 1]


def load_mesh(path: str | Path) -> Mesh:
    """One `<category>_<i>.npz` mesh; faces indexing outside the vertices or
    degenerate arrays raise ValueError naming the file."""
    path = Path(path)
    with np.load(path) as data:
        if "V" not in data or "F" not in data:
            raise ValueError(f"{path}: needs arrays V (vertices) and F (triangles)")
        vertices = np.asarray(data["V"], np.float64)
        faces = np.asarray(data["F"], np.int64)
        colours = np.asarray(data["C"], np.float64) if "C" in data else np.full((len(faces), 3), np.nan)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"{path}: V must be (N, 3) and F (M, 3) with M > 0")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"{path}: F indexes vertices outside V")
    if colours.shape != faces.shape:
        colours = np.full(faces.shape, np.nan)
    colours = np.where(np.isnan(colours), np.asarray(UNCOLOURED_RGB), np.clip(colours, 0, 1))
    category = path.stem.rsplit("_", 1)[0]
    return Mesh(path.stem, category, vertices, faces, colours)


def find_meshes(folder: str | Path) -> dict[str, list[Path]]:
    """`<category>_<i>.npz` files of a folder, grouped by category (sorted)."""
    groups: dict[str, list[Path]] = {}
    for path in sorted(Path(folder).glob("*.npz")):
        category, _, index = path.stem.rpartition("_")
        if category and index.isdigit():
            groups.setdefault(category, []).append(path)
    return groups


def mesh_to_gaussians(
    mesh: Mesh,
    n_gaussians: int,
    rng: np.random.Generator,
    floaters: float = 0.0,
    normalise: bool = True,
) -> GaussianModel:
    """Surface Gaussians on `mesh`, area-weighted, flat along the face normal, with the
    face colours (plus a little noise); `floaters` adds that fraction of faint Gaussians
    in the padded bounding box, as real captures have. normalise: centre the mesh's
    bounding box and scale its diagonal to 1 (ShapeNet's convention), so every instance
    of a category shares one frame up to its own proportions."""
    v = mesh.vertices
    if normalise:
        lo, hi = v.min(0), v.max(0)
        v = (v - 0.5 * (lo + hi)) / max(np.linalg.norm(hi - lo), 1e-12)
    tri = v[mesh.faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    if not np.isfinite(area2).all() or area2.sum() <= 0:
        raise ValueError(f"{mesh.name}: the mesh has no surface area")
    n_floaters = int(round(n_gaussians * floaters))
    n_surface = n_gaussians - n_floaters
    face = rng.choice(len(tri), n_surface, p=area2 / area2.sum())
    r1, r2 = rng.uniform(size=(2, n_surface))
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
    means = np.einsum("nk,nkd->nd", bary, tri[face])
    normals = cross[face] / np.maximum(area2[face], 1e-30)[:, None]
    degenerate = area2[face] <= 1e-30
    normals[degenerate] = (0.0, 0.0, 1.0)
    colours = np.clip(mesh.face_rgb[face] + rng.normal(0, 0.02, (n_surface, 3)), 0, 1)
    spacing = np.sqrt(0.5 * area2.sum() / max(n_surface, 1))
    means, colours, scales, quats, opacity = surface_gaussians(means, normals, colours, spacing, n_floaters, rng)
    model = GaussianModel.from_colors(means, colours, quats=quats, scales=scales, opacities=opacity)
    model.metadata.update(category=mesh.category, mesh=mesh.name)
    return model
