"""Pinhole cameras (OpenCV convention: x right, y down, z forward).

A `Cameras` batch holds C world-to-camera 4x4 matrices and intrinsics sharing one
image size. The view matrix may be a similarity [[sR, t], [0, 1]] rather than a
rigid transform: rendering a transformed model T·G from a camera with view matrix
W equals rendering G with view matrix W·T (Rend(T·G, C) = Rend(G, T^-1·C)), which
is how the fine stage differentiates through a Sim(3) without touching the model.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsa.geometry import rotation_to_quat
from gsa.sim3 import Sim3


@dataclass
class Cameras:
    """C pinhole cameras.

    viewmats: (C, 4, 4) float64 world-to-camera; fx, fy, cx, cy: (C,) float64 pixels
    (pixel (i, j) has its centre at (i + 0.5, j + 0.5)); width, height: ints.
    """

    viewmats: np.ndarray
    fx: np.ndarray
    fy: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        self.viewmats = np.asarray(self.viewmats, np.float64).reshape(-1, 4, 4)
        c = self.viewmats.shape[0]
        for name in ("fx", "fy", "cx", "cy"):
            arr = np.broadcast_to(np.asarray(getattr(self, name), np.float64).reshape(-1), (c,)).copy()
            setattr(self, name, arr)
        self.width, self.height = int(self.width), int(self.height)
        if c == 0:
            raise ValueError("Cameras needs at least one camera")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not (np.all(self.fx > 0) and np.all(self.fy > 0)):
            raise ValueError("focal lengths must be positive")
        if not np.isfinite(self.viewmats).all():
            raise ValueError("view matrices hold NaN or Inf")

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    def __getitem__(self, index) -> Cameras:
        idx = np.atleast_1d(np.arange(len(self))[index])
        return Cameras(
            self.viewmats[idx], self.fx[idx], self.fy[idx], self.cx[idx], self.cy[idx], self.width, self.height
        )

    @property
    def intrinsics(self) -> np.ndarray:
        """(C, 4) rows fx, fy, cx, cy."""
        return np.stack([self.fx, self.fy, self.cx, self.cy], axis=1)

    def centers(self) -> np.ndarray:
        """(C, 3) camera centres in world coordinates (valid for similarity view matrices too)."""
        a = self.viewmats[:, :3, :3]
        b = self.viewmats[:, :3, 3]
        return -np.linalg.solve(a, b[..., None])[..., 0]

    def resized(self, width: int, height: int) -> Cameras:
        """Same poses, intrinsics rescaled to a new image size."""
        sx, sy = width / self.width, height / self.height
        return Cameras(self.viewmats, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    def for_transformed_model(self, sim3: Sim3) -> Cameras:
        """Cameras that see the untransformed model G as these cameras see sim3·G."""
        return Cameras(self.viewmats @ sim3.matrix()[None], self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    @classmethod
    def concat(cls, items: list[Cameras]) -> Cameras:
        if not items:
            raise ValueError("nothing to concatenate")
        w, h = items[0].width, items[0].height
        if any(c.width != w or c.height != h for c in items):
            raise ValueError("all cameras in a batch must share one image size")
        return cls(
            np.concatenate([c.viewmats for c in items]),
            np.concatenate([c.fx for c in items]),
            np.concatenate([c.fy for c in items]),
            np.concatenate([c.cx for c in items]),
            np.concatenate([c.cy for c in items]),
            w,
            h,
        )


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) OpenCV world-to-camera matrix for a camera at `eye` looking at `target`."""
    eye = np.asarray(eye, np.float64)
    f = np.asarray(target, np.float64) - eye
    norm = np.linalg.norm(f)
    if norm < 1e-12:
        raise ValueError("camera eye and target coincide")
    f /= norm
    up = np.asarray(up, np.float64)
    right = np.cross(f, up)
    if np.linalg.norm(right) < 1e-6:  # looking along `up`: any perpendicular will do
        right = np.cross(f, np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    rot = np.stack([right, down, f])  # rows: camera axes in world coordinates
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = -rot @ eye
    return m


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) near-uniform unit vectors on the sphere."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def orbit_cameras(
    center,
    radius: float,
    n: int,
    width: int = 128,
    height: int | None = None,
    fov: float = 50.0,
    seed: int | None = 0,
    elevations=None,
) -> Cameras:
    """n cameras on a sphere of `radius` around `center`, all looking at it.

    Directions are a Fibonacci lattice (evenly spread, so views are diverse),
    randomly rotated by `seed` (None keeps the lattice as is). If `elevations`
    (degrees, length n) is given, cameras are instead evenly spaced in azimuth at
    those elevations. fov: horizontal field of view in degrees.
    """
    if n <= 0:
        raise ValueError("need at least one camera")
    if not radius > 0:
        raise ValueError(f"orbit radius must be positive, got {radius}")
    height = width if height is None else height
    center = np.asarray(center, np.float64).reshape(3)
    if elevations is not None:
        el = np.radians(np.asarray(elevations, np.float64).reshape(-1))
        if el.size != n:
            raise ValueError("need one elevation per camera")
        az = 2 * np.pi * np.arange(n) / n
        dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    else:
        dirs = fibonacci_directions(n)
        if seed is not None:
            from scipy.spatial.transform import Rotation

            dirs = dirs @ Rotation.random(random_state=seed).as_matrix().T
    views = np.stack([look_at(center + radius * d, center) for d in dirs])
    f = 0.5 * width / np.tan(np.radians(fov) / 2)
    return Cameras(views, f, f, width / 2, height / 2, width, height)


def cameras_around(
    means: np.ndarray,
    n: int,
    width: int = 128,
    height: int | None = None,
    fov: float = 50.0,
    seed: int | None = 0,
    margin: float = 1.15,
) -> Cameras:
    """Orbit cameras framing a point cloud: centre = centroid, radius so that the
    bounding sphere (robust 99th-percentile extent) fits the field of view."""
    means = np.asarray(means, np.float64)
    if means.ndim != 2 or len(means) == 0:
        raise ValueError("need a non-empty (N, 3) point set to place cameras")
    center = means.mean(axis=0)
    extent = float(np.percentile(np.linalg.norm(means - center, axis=1), 99)) or 1.0
    dist = margin * extent / np.sin(np.radians(fov) / 2)
    return orbit_cameras(center, dist, n, width, height, fov, seed)


# ----------------------------------------------------------------------------- cameras.json
def cameras_json(cameras: Cameras, names: list[str]) -> dict:
    """COLMAP-compatible camera description: PINHOLE params and per-image qvec (w,x,y,z
    cam_from_world) / tvec, plus the 4x4 world-to-camera matrix for convenience."""
    out = {
        "camera_model": "PINHOLE",
        "convention": "OpenCV world-to-camera (COLMAP cam_from_world)",
        "width": cameras.width,
        "height": cameras.height,
        "images": [],
    }
    for i, n in enumerate(names):
        m = cameras.viewmats[i]
        out["images"].append(
            {
                "image_id": i + 1,
                "name": n,
                "camera_id": 1,
                "params": [float(cameras.fx[i]), float(cameras.fy[i]), float(cameras.cx[i]), float(cameras.cy[i])],
                "qvec": [float(v) for v in rotation_to_quat(m[:3, :3])],
                "tvec": [float(v) for v in m[:3, 3]],
                "world_to_camera": m.tolist(),
            }
        )
    return out


def write_cameras_json(path: str | Path, cameras: Cameras, names: list[str]) -> Path:
    path = Path(path)
    path.write_text(json.dumps(cameras_json(cameras, names), indent=1))
    return path


def read_cameras_json(path: str | Path) -> tuple[Cameras, list[str]]:
    """Cameras and image names from a file written by write_cameras_json (e.g. a
    reconstruction's cameras.json); ValueError naming the file when it is not one."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        images = data["images"]
        cams = Cameras(
            np.array([im["world_to_camera"] for im in images], np.float64),
            [im["params"][0] for im in images],
            [im["params"][1] for im in images],
            [im["params"][2] for im in images],
            [im["params"][3] for im in images],
            data["width"],
            data["height"],
        )
        return cams, [str(im["name"]) for im in images]
    except (OSError, ValueError, KeyError, IndexError, TypeError) as exc:
        raise ValueError(f"{path}: not a cameras.json written by gsa reconstruct ({exc})") from None
