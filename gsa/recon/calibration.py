"""One camera's intrinsics carried from one reconstruction to another.

Two photo sets of one object taken with one camera, reconstructed apart, each let SfM estimate
their own focal length, and the estimates differ by ~1 % (the halves of a real phone set:
425.8 vs 422.6 px). A focal length too long makes an object look smaller from its cameras, so
the two models come out sized differently relative to their cameras, and no similarity overlays
both their objects and their cameras: the scale one registration finds is ~0.7 % from the one
the cameras say (docs/benchmarks.md, "Photo matches"). The second set reconstructed with the
first's intrinsics, held fixed, shares its lens: 0.70 % -> 0.09 %.

Whether two sets share a camera is what their EXIF says (gsa.recon.photos.exif_camera: make,
model, lens, focal length, 35 mm equivalent, digital zoom; every photo of each set the same);
a set without EXIF is never assumed to share one. A user who knows better passes the
intrinsics on (`gsa reconstruct --intrinsics-from DIR`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Two image sizes are one camera's when their aspect ratios agree to this (a 4032 x 3024 photo
# stored at 512 x 384 keeps its aspect to well under this; 4:3 against 16:9 does not).
ASPECT_TOLERANCE = 0.005


@dataclass(frozen=True)
class Calibration:
    """Pinhole intrinsics (pixels) for images of width x height; camera: the EXIF identity of
    the photos they were estimated from (None: unknown)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    camera: tuple | None = None

    @classmethod
    def of_cameras(cls, cameras, camera: tuple | None = None) -> Calibration | None:
        """The one camera every view of `cameras` (gsa.render.cameras.Cameras) shares; None when
        the views have different intrinsics (a set from several cameras)."""
        params = np.stack([cameras.fx, cameras.fy, cameras.cx, cameras.cy], axis=1)
        if np.ptp(params, axis=0).max() > 1e-6 * max(1.0, float(np.abs(params).max())):
            return None
        fx, fy, cx, cy = (float(v) for v in params[0])
        return cls(fx, fy, cx, cy, int(cameras.width), int(cameras.height), _as_camera(camera))

    @classmethod
    def of_model(cls, model) -> Calibration | None:
        """The intrinsics a reconstructed model was trained with (its metadata's
        training_cameras and exif_camera), None for a model that was not reconstructed here."""
        cameras = model.metadata.get("training_cameras")
        return None if cameras is None else cls.of_cameras(cameras, model.metadata.get("exif_camera"))

    def for_size(self, width: int, height: int) -> tuple[float, float, float, float] | None:
        """(fx, fy, cx, cy) for images of width x height of the same camera: scaled to another
        size, turned for the other orientation; None when the aspect differs (another crop)."""
        for w, h, fx, fy, cx, cy in (
            (self.width, self.height, self.fx, self.fy, self.cx, self.cy),
            (self.height, self.width, self.fy, self.fx, self.cy, self.cx),  # turned by 90°
        ):
            sx, sy = width / w, height / h
            if abs(sx / sy - 1) <= ASPECT_TOLERANCE:
                return fx * sx, fy * sy, cx * sx, cy * sy
        return None


def _as_camera(camera) -> tuple | None:
    # report.json stores the identity as a JSON list: compare it as the tuple exif_camera gives
    return tuple(camera) if camera else None


def same_camera(a, b) -> bool:
    """Whether two EXIF identities (exif_camera, or their JSON lists) name one camera; unknown
    identities never do."""
    a, b = _as_camera(a), _as_camera(b)
    return a is not None and a == b
