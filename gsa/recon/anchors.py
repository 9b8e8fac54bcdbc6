"""Photo anchors: the SIFT descriptors under each point a reconstruction's SfM triangulated.

Two reconstructions of one object made from different photos share no Gaussian, and at the CPU
preset's resolution their surfaces agree only to a few per cent of the size (docs/benchmarks.md,
"Two halves of a real photo set"). Their photos, though, show the same texture: a SIFT feature
seen in a photo of one set matches the same feature in a photo of the other, and each side's SfM
already placed that feature in 3D. Those 3D–3D pairs fix the Sim(3) as precisely as the SfM
points themselves (gsa.align.photo). `reconstruct()` keeps them beside the model (anchors.npz)
and in `model.metadata["photo_anchors"]`, in the model's own frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

ANCHORS_FILE = "anchors.npz"
# A point seen in many photos carries many near-identical descriptors; a few spread along its
# track describe it from its different viewpoints without growing the matching quadratically.
MAX_PER_POINT = 4  # gsa.recon.sfm.photo_anchors takes this many at most


@dataclass(frozen=True)
class PhotoAnchors:
    """points (P, 3) float64 in the model's frame; descriptors (N, 128) uint8, each of the point
    point_index[i] (N,), as seen in one photo."""

    points: np.ndarray
    descriptors: np.ndarray
    point_index: np.ndarray

    def __post_init__(self) -> None:
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points must be (P, 3), got {self.points.shape}")
        if self.descriptors.ndim != 2 or len(self.descriptors) != len(self.point_index):
            raise ValueError("one point index per descriptor")
        if len(self.point_index) and not (0 <= self.point_index.min() and self.point_index.max() < len(self.points)):
            raise ValueError("point_index out of range")

    def __len__(self) -> int:
        return len(self.descriptors)

    def subset(self, keep: np.ndarray) -> PhotoAnchors:
        """The anchors of the points where `keep` (P,) is true, renumbered."""
        keep = np.asarray(keep, bool)
        new_index = np.cumsum(keep) - 1
        rows = keep[self.point_index]
        return PhotoAnchors(self.points[keep], self.descriptors[rows], new_index[self.point_index[rows]])

    def transformed(self, sim3) -> PhotoAnchors:
        """The same anchors with their points mapped by a Sim(3) (the model moved with them)."""
        return PhotoAnchors(sim3.apply(self.points), self.descriptors, self.point_index)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        # uncompressed: SIFT descriptors hardly compress
        np.savez(path, points=self.points, descriptors=self.descriptors, point_index=self.point_index)
        return path

    @classmethod
    def load(cls, path: str | Path) -> PhotoAnchors:
        with np.load(path) as z:
            return cls(
                np.asarray(z["points"], np.float64),
                np.asarray(z["descriptors"], np.uint8),
                np.asarray(z["point_index"], np.int64),
            )
