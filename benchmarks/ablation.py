"""The ablation protocol's runner (paper Table 4 / Sec. 4.5): coarse iterations, the
features switched off, and the fine stage from a fixed coarse result over different
camera sets and on colours.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.records import QUICK_FINE, Runner
from gsa.align.coarse import CoarseOptions, icp_refine
from gsa.align.pipeline import AlignOptions, align
from gsa.canonical import canonical_features, model_frame
from gsa.render.cameras import cameras_around
from gsa.sim3 import Sim3

ABLATION_COARSE = [
    # refine="off": the feature stage (Alg. 3) alone, as the paper's rows; our
    # default pipeline follows it with nearest-neighbour refinement (last row).
    # hypothesis_iterations too: each frame hypothesis is first run that many
    # feature-stage iterations on a subsample, which would otherwise hide the count.
    ("coarse, 1 iteration", dict(coarse_iterations=1, hypothesis_iterations=1, refine="off")),
    ("coarse, 3 iterations", dict(coarse_iterations=3, hypothesis_iterations=3, refine="off")),
    ("coarse, until convergence", dict(coarse_iterations=200, refine="off")),
    (ABLATION_REFERENCE := "coarse (default: feature stage + NN refinement)", dict()),
]
# the paper's "coarse 3 iterations + fine"
FINE_BASE = dict(coarse_iterations=3, hypothesis_iterations=3, refine="off")


def similar_cameras(target, n: int = 3, pool: int = 60, image_size: int = 128, seed: int = 0):
    """n mutually close orbit cameras: the first of a dense orbit and its n-1 nearest."""
    cams = cameras_around(target.means, pool, image_size, seed=seed)
    centers = cams.centers() - target.means.astype(np.float64).mean(0)
    dirs = centers / np.linalg.norm(centers, axis=1, keepdims=True)
    order = np.argsort(-(dirs @ dirs[0]))[:n]
    return cams[np.sort(order)]


def _fine_from(source, target, coarse_result, cameras, on: str, views: int, seed: int, quick: bool = False) -> Sim3:
    """The pipeline's fine stage (gsa.align.pair._Refinement.fine) from a given coarse
    result with an explicit camera set: canonical features from the frames the
    coarse stage chose, as align() builds them."""
    from gsa.align.fine import FineOptions, fine_align  # lazy: loads torch and the renderer

    if coarse_result.features == "canonical":
        source = source.with_features(canonical_features(source.means.astype(np.float64), coarse_result.source_frame))
        target = target.with_features(canonical_features(target.means.astype(np.float64), coarse_result.target_frame))
    defaults = AlignOptions(**(QUICK_FINE if quick else {}))
    opts = FineOptions(
        iterations=defaults.fine_iterations,
        lr=defaults.fine_lr,
        views=views,
        image_size=defaults.fine_image_size,
        loss=defaults.fine_loss,
        on=on,
        seed=seed,
    )
    return fine_align(source, target, coarse_result.coarse.transform, opts, cameras=cameras).transform


def ablation_runner(seed: int, quick: bool = False, fine: bool = True) -> Runner:
    """All configurations on one pair; `fine` False skips the rendering (fine-stage) rows."""

    def run(source, target):
        out = {}
        for label, opts in ABLATION_COARSE:
            t0 = time.perf_counter()
            res = align(source, target, AlignOptions(**opts))
            out[label] = (res.transform, time.perf_counter() - t0)

        # Features off: our closed-form ICP on spatial nearest neighbours only,
        # from the authors' centroid start plus the RMS-radius scale ratio.
        t0 = time.perf_counter()
        sf, df = model_frame(source), model_frame(target)
        s = df.radius / sf.radius
        init = Sim3(s, np.eye(3), df.center - s * sf.center)
        dst = target.means.astype(np.float64)
        rows = np.random.default_rng(seed).permutation(len(source))[:20_000]
        res = icp_refine(
            source.means.astype(np.float64)[rows], dst, cKDTree(dst), init, CoarseOptions(max_iterations=200)
        )
        out["features off (plain ICP, centroid/RMS start)"] = (res.transform, time.perf_counter() - t0)

        if not fine:
            return out
        t0 = time.perf_counter()
        base = align(source, target, AlignOptions(**FINE_BASE))
        coarse_s = time.perf_counter() - t0
        size = AlignOptions(**(QUICK_FINE if quick else {})).fine_image_size
        variants = [
            ("coarse 3 + fine, 3 similar views", similar_cameras(target, 3, image_size=size, seed=seed), "features", 3),
            ("coarse 3 + fine, 3 diverse views", cameras_around(target.means, 3, size, seed=seed), "features", 3),
            ("coarse 3 + fine, 30 views", cameras_around(target.means, 30, size, seed=seed), "features", 30),
            (
                "coarse 3 + fine on colours, 3 diverse views",
                cameras_around(target.means, 3, size, seed=seed),
                "colors",
                3,
            ),
        ]
        for label, cams, on, views in variants:
            t0 = time.perf_counter()
            try:
                est = _fine_from(source, target, base, cams, on, views, seed, quick)
            except Exception as exc:  # noqa: BLE001 -- a variant failing is a row of the table, not a crash
                est = exc
            out[label] = (est, coarse_s + time.perf_counter() - t0)
        return out

    return run
