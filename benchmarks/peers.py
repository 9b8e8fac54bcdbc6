"""Peer registration methods, run in the same loop as GSA on the same pairs.

Each peer maps a (source, target) GaussianModel pair to a Sim3 with
target ≈ T(source), like `gsa.align.pipeline.align`. A peer whose optional
package is missing reports why through `unavailable()` and is skipped with a
printed note by the protocols, never a crash.

  icp       plain trimmed nearest-neighbour ICP with Umeyama scale, started from
            the centroids and the RMS-radius ratio; no features. Self-contained
            (scipy only), deliberately independent of gsa.align so a bug there
            cannot hide in the comparison.
  open3d    Open3D FPFH + RANSAC + point-to-plane ICP. FPFH radii are metric and
            the scale is unknown, so each cloud is first normalised by its own
            centroid and RMS radius; the Sim(3) is the two normalisations
            composed with the rigid result.
  splatreg  splatreg.register(target, source, transform="sim3", init="global"):
            its SO(3)-sweep global initialiser, then LM over its default ICP +
            Gaussian-SDF residuals (with its default init, identity, it only refines).
            Note its argument order: target first. Opt-in and run on a 300-Gaussian
            subsample: about 20 s per pair on 2 CPU cores (see SplatReg).
"""

from __future__ import annotations

import functools
import importlib.util
import subprocess
import sys
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from gsa.geometry import nearest_rotation
from gsa.model import GaussianModel
from gsa.sim3 import Sim3


class Peer(ABC):
    name: str = ""
    label: str = ""  # what the tables print

    def unavailable(self) -> str | None:
        """None when the peer can run, else a one-line reason."""
        return None

    @abstractmethod
    def register(self, source: GaussianModel, target: GaussianModel, seed: int = 0) -> Sim3:
        """Implemented by each subclass."""


def _normalisation(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid and RMS radius: the only scale cue a feature-free method has."""
    c = points.mean(axis=0)
    r = float(np.sqrt(np.mean(np.sum((points - c) ** 2, axis=1))))
    return c, r if r > 0 else 1.0


def umeyama(src: np.ndarray, dst: np.ndarray) -> Sim3:
    """Umeyama (1991) least-squares similarity dst ≈ s R src + t."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    e = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2] = -1.0
    r = u @ np.diag(e) @ vt
    var_s = float(np.mean(np.sum(xs**2, axis=1)))
    s = float(np.sum(d * e) / var_s) if var_s > 0 else 1.0
    s = s if s > 0 else 1.0
    return Sim3(s, r, mu_d - s * r @ mu_s)


@dataclass
class PlainICP(Peer):
    """Trimmed point-to-point ICP with scale (no features)."""

    max_iterations: int = 100
    max_points: int = 20_000  # source sample, as GSA's refinement uses
    trim: float = 3.0  # drop pairs beyond trim × median distance
    tolerance: float = 1e-6  # relative change in mean residual that counts as converged
    name: str = "icp"
    label: str = "plain ICP + scale (centroid/RMS init)"

    def register(self, source: GaussianModel, target: GaussianModel, seed: int = 0) -> Sim3:
        rng = np.random.default_rng(seed)
        p = source.means.astype(np.float64)
        if len(p) > self.max_points:
            p = p[np.sort(rng.choice(len(p), self.max_points, replace=False))]
        q = target.means.astype(np.float64)
        tree = cKDTree(q)
        cs, rs = _normalisation(source.means.astype(np.float64))
        cd, rd = _normalisation(q)
        s = rd / rs
        transform = Sim3(s, np.eye(3), cd - s * cs)
        previous = np.inf
        for _ in range(self.max_iterations):
            d, idx = tree.query(transform.apply(p), k=1)
            keep = d <= self.trim * max(float(np.median(d)), 1e-12)
            transform = umeyama(p[keep], q[idx[keep]])
            err = float(d[keep].mean())
            if abs(previous - err) <= self.tolerance * max(err, 1e-12):
                break
            previous = err
        return transform


@dataclass
class Open3DFPFH(Peer):
    """FPFH + RANSAC + point-to-plane ICP on RMS-normalised clouds."""

    voxel: float = 0.05  # in units of each cloud's RMS radius
    ransac_iterations: int = 100_000
    ransac_confidence: float = 0.999
    name: str = "open3d"
    label: str = "Open3D FPFH + RANSAC + ICP (RMS-normalised)"

    def unavailable(self) -> str | None:
        if importlib.util.find_spec("open3d") is None:
            return "open3d is not installed (pip install 'gsa[peers]')"
        return _import_error("open3d")

    def register(self, source: GaussianModel, target: GaussianModel, seed: int = 0) -> Sim3:
        import open3d as o3d

        reg = o3d.pipelines.registration
        o3d.utility.random.seed(int(seed))
        src = source.means.astype(np.float64)
        dst = target.means.astype(np.float64)
        cs, rs = _normalisation(src)
        cd, rd = _normalisation(dst)

        def prepare(points):
            pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
            down = pc.voxel_down_sample(self.voxel)
            for cloud in (pc, down):
                cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * self.voxel, max_nn=30))
            fpfh = reg.compute_fpfh_feature(
                down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.voxel, max_nn=100)
            )
            return pc, down, fpfh

        src_pc, src_down, src_fpfh = prepare((src - cs) / rs)
        dst_pc, dst_down, dst_fpfh = prepare((dst - cd) / rd)
        distance = 1.5 * self.voxel
        ransac = reg.registration_ransac_based_on_feature_matching(
            src_down,
            dst_down,
            src_fpfh,
            dst_fpfh,
            True,
            distance,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
            reg.RANSACConvergenceCriteria(self.ransac_iterations, self.ransac_confidence),
        )
        icp = reg.registration_icp(
            src_pc,
            dst_pc,
            0.4 * self.voxel,
            ransac.transformation,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=60),
        )
        m = np.asarray(icp.transformation, np.float64)
        rigid = Sim3(1.0, nearest_rotation(m[:3, :3]), m[:3, 3])
        # x_t = c_d + r_d · rigid((x_s − c_s) / r_s)
        to_unit = Sim3(1.0 / rs, np.eye(3), -cs / rs)
        from_unit = Sim3(rd, np.eye(3), cd)
        return from_unit @ rigid @ to_unit


@dataclass
class SplatReg(Peer):
    """splatreg (PyPI) in its Sim(3) mode, with its own defaults."""

    # splatreg's default residuals include a Gaussian-SDF term whose Sim(3)
    # Jacobian is autodiffed over n_points × M target anchors: on 2 CPU cores
    # 500 Gaussians per model took ~37 s and 1,000 took ~140 s per pair at
    # quality="low" (its "full" default does not finish in minutes at 30k). So
    # both models are randomly subsampled to max_points first, and the table
    # label says so.
    quality: str = "low"
    max_points: int = 300
    # Its documented global initialiser (SO(3) sweep + trimmed ICP, full overlap assumed);
    # the default (identity) only refines and cannot undo this benchmark's large rotations.
    init: str = "global"
    name: str = "splatreg"
    label: str = "splatreg register(sim3, init=global), 300-Gaussian subsample"

    def unavailable(self) -> str | None:
        if importlib.util.find_spec("splatreg") is None:
            return "splatreg is not installed (pip install 'gsa[peers]')"
        try:
            from splatreg import register  # noqa: F401
        # installed with --no-deps against our torch: a broken install can fail in any way on
        # import, and that only makes this peer unavailable (the reason is reported)
        except Exception as exc:  # noqa: BLE001
            return f"splatreg does not import: {exc}"
        return None

    def register(self, source: GaussianModel, target: GaussianModel, seed: int = 0) -> Sim3:
        import torch
        from splatreg import Gaussians, register

        torch.manual_seed(seed)
        rng = np.random.default_rng(seed)

        def sample(model):
            if len(model) <= self.max_points:
                return model
            return model.subset(np.sort(rng.choice(len(model), self.max_points, replace=False)))

        result = register(
            _to_splatreg(sample(target), Gaussians),
            _to_splatreg(sample(source), Gaussians),
            transform="sim3",
            quality=self.quality,
            init=self.init,
        )
        # result.T maps source into target: [[s R, t], [0, 1]].
        return Sim3.from_matrix(result.T.detach().cpu().double().numpy())


@functools.cache
def _import_error(module: str) -> str | None:
    """Import check in a child process: open3d ships its own TBB, and loading it
    before numba has started its threads makes numba drop its TBB layer with a
    warning; it also fails on a missing system library (libusb-1.0)."""
    proc = subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True, text=True)
    if proc.returncode == 0:
        return None
    return f"{module} does not import: " + ((proc.stderr.strip().splitlines() or ["?"])[-1])


def _to_splatreg(model: GaussianModel, gaussians_type):
    import torch

    return gaussians_type(
        means=torch.as_tensor(model.means, dtype=torch.float32),
        quats=torch.as_tensor(model.quats, dtype=torch.float32),
        scales=torch.as_tensor(model.log_scales, dtype=torch.float32),
        opacities=torch.as_tensor(model.opacities, dtype=torch.float32),
        colors=torch.as_tensor(model.base_colors, dtype=torch.float32),
        log_scales=True,
    )


PEERS: dict[str, type[Peer]] = {"icp": PlainICP, "open3d": Open3DFPFH, "splatreg": SplatReg}
# splatreg is opt-in (--peers all / --peers splatreg): at CPU speed it needs minutes per
# pair even on a 300-Gaussian subsample (see SplatReg), more than a whole protocol of GSA.
DEFAULT_PEERS = ["icp", "open3d"]


def available_peers(names: list[str] | None = None, note=print) -> list[Peer]:
    """Instantiated peers that can run; a printed note for each that cannot."""
    out = []
    names = DEFAULT_PEERS if names is None else names
    unknown = [n for n in names if n not in PEERS]
    if unknown:
        raise ValueError(f"unknown peer(s) {', '.join(unknown)}; choose from {', '.join(PEERS)}")
    for name in names:
        peer = PEERS[name]()
        reason = peer.unavailable()
        if reason:
            note(f"note: peer {name} skipped: {reason}")
            continue
        out.append(peer)
    return out
