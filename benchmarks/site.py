"""The `site` protocol (scenes that are not rooms): two partial captures of an
outdoor site - generated (gsa.synth.sites.make_site: hilly terrain, trees, rocks,
benches, a shed, vehicles) and, where SfM point files are found, real geometry
(gsa.synth.sites.PointSite: Gaussians around the points, e.g. the Mip-NeRF 360 garden's).

Captures as the scene protocol's (gsa.synth.scene_captures with SCENE_HARD less the
ceiling: 50-80 % overlap, exposure and white balance, density falling off from each
capture's scanner, wavy cut, holes, floaters, each under its own Sim(3) of scale 0.2-5).
Judged as rooms are (benchmarks.scene.scene_judge: RRE < 2 deg and translation error < 2 %
of the site's extent; a point site's extent is its 1st-99th percentile box's diagonal, so
far background points do not loosen the tolerance).

A second generator, written apart from make_site (gsa.synth.terrain: rolling plane-wave
hills, primitive props, Y up, each capture 60-80 % of the scene), deals the 'terrain-i'
pairs, so the site path is measured on scenes it was not designed on.

Full: SITE_FULL generated pairs, SITE_TERRAIN terrain pairs, then SITE_REAL_PAIRS per SfM
point file, 1-2M Gaussians per capture (terrain: 1M sampled, 60-80 % kept); --quick: 3 pairs
of ~100k (one of them real when a point file is found).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.pairs import SCENE_HARD
from benchmarks.records import Pair
from gsa.synth.scenes import scene_captures
from gsa.synth.sites import PointSite, make_site, resample_site
from gsa.synth.terrain import terrain_captures

# (generated pairs, capture size range) for quick and full; real pairs per point file.
SITE_QUICK = (2, (80_000, 120_000))
SITE_FULL = (12, (1_000_000, 2_000_000))
SITE_TERRAIN = (0, 8, 1_000_000)  # terrain pairs quick, full; Gaussians sampled per capture
SITE_REAL_PAIRS = (1, 8)  # quick, full: a real site is the hard case, 8 pairs tell more than 4
SITE_HARD = {k: v for k, v in SCENE_HARD.items() if k != "no_ceiling"}
# Where the project's development data lives (../shared/data/real-dev beside the checkout).
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real-dev"


def point_files(data: str | Path | None) -> list[Path]:
    """SfM point files (.npz with means3d and colors) in `data` (a file or a folder);
    DEFAULT_DATA when None and present; none otherwise."""
    root = Path(data) if data is not None else DEFAULT_DATA
    if data is None and not root.exists():
        return []
    if not root.exists():
        raise ValueError(f"site: --data {root} does not exist")
    files = [root] if root.is_file() else sorted(root.glob("*.npz"))
    out = []
    for f in files:
        with np.load(f) as z:
            if {"means3d", "colors"} <= set(z.files):
                out.append(f)
    return out


def site_pairs(quick: bool, seed: int, data: str | Path | None = None, count: int | None = None) -> list[Pair]:
    """Generated site pairs ('site-i') then real point-site pairs ('<file stem>-j'). Each
    pair is built when its turn comes (make()), so one pair is in memory at a time."""
    n_gen, size_range = SITE_QUICK if quick else SITE_FULL
    n_real = SITE_REAL_PAIRS[0 if quick else 1]
    files = point_files(data)
    if quick and not files:
        n_gen += n_real  # three pairs either way
    if count is not None:
        n_gen = count
    pairs: list[Pair] = []

    def build(model_of, i: int, label: str, resample=None):
        rng = np.random.default_rng([seed, 26, i])
        sizes = tuple(int(x) for x in rng.integers(*size_range, 2))
        site = model_of(int(max(sizes) / 0.6) + 1, i)  # each side keeps ≥ 60 % of the site
        cap = scene_captures(site, rng, sizes=sizes, resample=resample, **SITE_HARD)
        cap.target.metadata.update(pair_overlap=cap.overlap, site=label)
        return cap.source, cap.target, cap.truth

    for i in range(n_gen):
        pairs.append(
            (
                f"site-{i}",
                lambda i=i: build(lambda n, i: make_site(seed=2600 + i, n_gaussians=n), i, "gen", resample_site),
            )
        )
    for i in range(SITE_TERRAIN[1 if not quick and count is None else 0]):

        def terrain(i=i):
            cap = terrain_captures(2700 + i, SITE_TERRAIN[2], np.random.default_rng([seed, 27, i]))
            cap.target.metadata.update(scene_extent=cap.extent * cap.truth.scale, site="terrain")
            return cap.source, cap.target, cap.truth

        pairs.append((f"terrain-{i}", terrain))
    for f in files:
        cache: dict = {}

        def point_site(f=f, cache=cache) -> PointSite:
            if "site" not in cache:  # the neighbourhoods once per file, when its first pair is built
                cache["site"] = PointSite.from_file(f)
            return cache["site"]

        for j in range(n_real):

            def make(j=j, f=f, point_site=point_site):
                ps = point_site()
                return build(lambda n, j: ps.sample(n, 1000 + j), 1000 + j, f.stem, ps.resampler())

            pairs.append((f"{f.stem}-{j}", make))
    return pairs


def site_of(label: str) -> dict:
    """The record's `site`: "generated", or the point file's stem."""
    return {"site": "generated" if label.startswith("site-") else label.rsplit("-", 1)[0]}
