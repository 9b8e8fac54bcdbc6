"""Structure from motion with pycolmap on CPU: SIFT -> matching -> incremental mapping.

One shared PINHOLE camera is estimated per camera size (object captures usually come from one
camera; a phone set's portrait and landscape shots share theirs, gsa.recon.photos; the
rasterizer is a pinhole renderer, so no distortion model is fitted).
Poses are returned as OpenCV world-to-camera matrices, the convention of
gsa.render.cameras (COLMAP's cam_from_world is already x right, y down, z forward).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gsa.errors import GSAError
from gsa.recon.anchors import MAX_PER_POINT, PhotoAnchors
from gsa.recon.images import ImageSet
from gsa.render.cameras import Cameras
from gsa.sim3 import solve_sim3

Progress = Callable[[str, float], None]


class SfMError(GSAError, RuntimeError):
    """SfM could not register enough images."""


@dataclass
class SfMResult:
    """cameras: registered views (C); names: their file names (C); points (P,3), colors (P,3) in [0,1];
    errors (P,) mean reprojection error (px); n_images: images given; timings: seconds per step."""

    cameras: Cameras
    names: list[str]
    points: np.ndarray
    colors: np.ndarray
    errors: np.ndarray
    n_images: int
    unregistered: list[str] = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    sparse_dir: Path | None = None
    mapping_attempts: int = 1
    anchors: PhotoAnchors | None = None  # descriptors under the points (gsa.recon.anchors)

    @property
    def n_registered(self) -> int:
        return len(self.names)


def _pycolmap():
    # pycolmap's extension carries its own zlib and exports its symbols: Python's zlib module
    # loaded AFTER it mixes the two and aborts the process in free() on the first compress
    # (pycolmap 4.2, seen in a script that imported pycolmap first). This module's own imports
    # load zlib already (zipfile); the import here keeps that true whatever they become.
    import zlib  # noqa: F401

    try:
        import pycolmap
    except ImportError as exc:  # the recon extra is optional
        raise SfMError("reconstruction needs pycolmap: pip install 'gsa[recon]'") from exc
    return pycolmap


def _mapping_options(pycolmap, seed: int, fixed_intrinsics: bool = False):
    opts = pycolmap.IncrementalPipelineOptions()
    if fixed_intrinsics:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
    opts.random_seed = seed
    opts.mapper.random_seed = seed
    opts.triangulation.random_seed = seed
    opts.min_model_size = 3
    # Small object sets have fewer matches than scene captures.
    opts.mapper.init_min_num_inliers = 50
    opts.mapper.abs_pose_min_num_inliers = 15
    opts.mapper.abs_pose_min_inlier_ratio = 0.2
    opts.min_num_matches = 15
    opts.mapper.filter_max_reproj_error = 2.0  # renders/photos of objects: tighter than 4 px
    # One thread: multi-threaded bundle adjustment sums in a timing-dependent order, and under
    # load the same set registered 18 instead of 21 of 24 views (a test failed on a busy
    # machine). Object sets map in seconds on one thread; the same seed now gives the same model.
    opts.num_threads = 1
    return opts


def run_sfm(
    images: ImageSet,
    work_dir: str | Path,
    *,
    matching: str = "exhaustive",
    min_registered: int | float = 0.5,
    max_features: int = 8192,
    peak_threshold: float = 0.002,
    progress: Progress | None = None,
    seed: int = 0,
    verbose: bool = False,
    mapping_attempts: int = 3,
    fixed_intrinsics: tuple[float, float, float, float] | None = None,
) -> SfMResult:
    """Run SIFT + matching + incremental mapping; keep the largest model.

    matching: "exhaustive" (best for <~100 unordered images) or "sequential" (video order).
    min_registered: an int count or a fraction of the images that must register,
    else SfMError says how many did. mapping_attempts: mapping runs (seeds seed, seed+1, ...)
    until every image registers; the most complete model is kept.
    """
    pycolmap = _pycolmap()
    if not verbose:
        pycolmap.logging.minloglevel = 2  # glog INFO/WARNING per image drown real messages
    if matching not in ("exhaustive", "sequential"):
        raise ValueError(f"matching must be exhaustive or sequential, got {matching!r}")
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    if db.exists():
        db.unlink()
    report = progress or (lambda stage, frac: None)
    timings = {}

    t = time.perf_counter()
    report("sfm:features", 0.0)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    if fixed_intrinsics is not None:
        reader.camera_params = ",".join(f"{v:.6f}" for v in fixed_intrinsics)
    ext = pycolmap.FeatureExtractionOptions()
    ext.sift.max_num_features = max_features
    ext.use_gpu = False
    # Object captures are small in frame: a lower contrast threshold and upsampled
    # first octave find enough keypoints on a few-hundred-pixel object.
    ext.sift.peak_threshold = peak_threshold
    ext.sift.first_octave = -1
    # One camera per camera size (gsa.recon.photos groups them; one group when all share one):
    # each extraction run in SINGLE mode adds its own camera.
    groups = images.camera_groups or [0] * len(images)
    for group in sorted(set(groups)):
        pycolmap.extract_features(
            db,
            images.directory,
            image_names=[n for n, g in zip(images.names, groups) if g == group],
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=ext,
            device=pycolmap.Device.cpu,
        )
    timings["features"] = time.perf_counter() - t

    t = time.perf_counter()
    report("sfm:matching", 0.3)
    mopts = pycolmap.FeatureMatchingOptions()
    mopts.use_gpu = False
    # The two-view verification's RANSAC draws from an unseeded generator by default (seed -1):
    # the verified matches, and so the model, changed from run to run (a test saw 18 instead of
    # 20+ of 24 views registered). Seeded, the same photos give the same matches.
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    match = pycolmap.match_exhaustive if matching == "exhaustive" else pycolmap.match_sequential
    match(db, matching_options=mopts, verification_options=verification, device=pycolmap.Device.cpu)
    timings["matching"] = time.perf_counter() - t

    t = time.perf_counter()
    report("sfm:mapping", 0.6)
    sparse = work_dir / "sparse"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir()
    # A seed can leave a view or two out of a set that registers fully with another: mapping
    # is seconds, so other seeds are tried and the most complete model is kept.
    rec = None
    for attempt in range(mapping_attempts):
        attempt_dir = sparse / f"attempt{attempt}"
        attempt_dir.mkdir()
        recs = pycolmap.incremental_mapping(
            db,
            images.directory,
            attempt_dir,
            options=_mapping_options(pycolmap, seed + attempt, fixed_intrinsics is not None),
        )
        if recs:
            best = max(recs.values(), key=lambda r: r.num_reg_images())
            if rec is None or best.num_reg_images() > rec.num_reg_images():
                rec = best
        if rec is not None and rec.num_reg_images() == len(images):
            break
    timings["mapping"] = time.perf_counter() - t
    need = int(np.ceil(min_registered * len(images))) if isinstance(min_registered, float) else int(min_registered)
    need = max(need, 2)
    if rec is None:
        raise SfMError(
            f"0 of {len(images)} images registered (no initial pair with enough matches); "
            f"the set needs more overlap or texture"
        )
    result = _from_reconstruction(rec, images, timings)
    result.mapping_attempts = attempt + 1
    if result.n_registered < need:
        raise SfMError(
            f"only {result.n_registered} of {len(images)} images registered (need {need}); "
            f"unregistered: {', '.join(result.unregistered[:10])}"
        )
    out = sparse / "model"
    out.mkdir(exist_ok=True)
    rec.write_text(str(out))  # COLMAP text model: cameras.txt, images.txt, points3D.txt
    result.sparse_dir = out
    result.anchors = photo_anchors(rec, db)
    report("sfm:done", 1.0)
    return result


def _from_reconstruction(rec, images: ImageSet, timings: dict) -> SfMResult:
    by_name = {}
    for img in rec.images.values():
        if not img.has_pose:
            continue
        cam = rec.cameras[img.camera_id]
        fx, fy, cx, cy = (float(v) for v in cam.params[:4])
        m = np.eye(4)
        m[:3, :] = np.asarray(img.cam_from_world().matrix())
        by_name[img.name] = (m, fx, fy, cx, cy)
    names = [n for n in images.names if n in by_name]
    unregistered = [n for n in images.names if n not in by_name]
    if len(names) == 0:
        raise SfMError(f"0 of {len(images)} images registered")
    vm = np.stack([by_name[n][0] for n in names])
    intr = np.array([by_name[n][1:] for n in names])
    cams = Cameras(vm, intr[:, 0], intr[:, 1], intr[:, 2], intr[:, 3], images.width, images.height)
    pts, cols, errs = [], [], []
    for p in rec.points3D.values():
        pts.append(p.xyz)
        cols.append(p.color)
        errs.append(p.error)
    pts = np.asarray(pts, np.float64).reshape(-1, 3)
    cols = np.asarray(cols, np.float64).reshape(-1, 3) / 255.0
    return SfMResult(cams, names, pts, cols, np.asarray(errs, np.float64), len(images), unregistered, timings)


def photo_anchors(rec, database_path: str | Path, max_per_point: int = MAX_PER_POINT) -> PhotoAnchors:
    """The photo anchors (gsa.recon.anchors) of a pycolmap Reconstruction whose features are in the COLMAP database at
    `database_path` (a point2D's index is its keypoint's, and so its descriptor's, row)."""
    pycolmap = _pycolmap()
    ids = list(rec.points3D.keys())
    row_of = {pid: i for i, pid in enumerate(ids)}
    points = np.array([rec.points3D[pid].xyz for pid in ids], np.float64).reshape(-1, 3)
    taken = np.zeros(len(ids), np.int64)
    descriptors, point_index = [], []
    db = pycolmap.Database.open(str(database_path))
    try:
        for image_id in sorted(rec.images):
            image = rec.images[image_id]
            if not image.has_pose:
                continue
            table = db.read_descriptors(image_id)
            table = np.asarray(getattr(table, "data", table))
            for k, p2 in enumerate(image.points2D):
                if not p2.has_point3D():
                    continue
                row = row_of[p2.point3D_id]
                if taken[row] >= max_per_point or k >= len(table):
                    continue
                taken[row] += 1
                descriptors.append(table[k])
                point_index.append(row)
    finally:
        db.close()
    desc = np.asarray(descriptors, np.uint8).reshape(-1, 128)
    return PhotoAnchors(points, desc, np.asarray(point_index, np.int64))


def centre_error(est: Cameras, true: Cameras) -> tuple[float, object]:
    """Fit a Sim(3) taking estimated camera centres onto true ones; returns (RMS residual in
    true units, the Sim3). est and true must list the same images in the same order."""
    a, b = est.centers(), true.centers()
    t = solve_sim3(a, b)
    res = np.linalg.norm(t.apply(a) - b, axis=1)
    return float(np.sqrt(np.mean(res**2))), t


def trimmed_centre_fit(est: Cameras, true: Cameras, factor: float = 3.0, rounds: int = 5) -> tuple[object, int]:
    """The Sim(3) of centre_error refitted on the cameras within `factor` × the median residual
    (at least half of them), until they settle: a few views SfM placed off (a registration that
    failed quietly) otherwise tilt a truth fitted on all of them. Returns (Sim3, cameras kept)."""
    a, b = est.centers(), true.centers()
    keep = np.ones(len(a), bool)
    t = solve_sim3(a, b)
    for _ in range(rounds):
        res = np.linalg.norm(t.apply(a) - b, axis=1)
        now = res <= max(factor * np.median(res), np.sort(res)[(len(res) - 1) // 2])
        if (now == keep).all():
            break
        keep = now
        t = solve_sim3(a[keep], b[keep])
    return t, int(keep.sum())
