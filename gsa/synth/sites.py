"""Outdoor sites as 3DGS (scenes that are not rooms): no walls, a ground.

make_site          a generated site: a terrain heightfield with hills, a textured ground
                   (grass patches, dirt paths, tiles of varied tone), trees, rocks,
                   benches, a shed and parked vehicles standing on it, and faint sky
                   floaters above it
site_from_points   a site from real geometry: Gaussians around an SfM point cloud (e.g.
                   the Mip-NeRF 360 garden's), drawn at random points, jittered within
                   each point's local spacing on its local surface, to any count

Two captures of either are made by gsa.synth.scene_captures (pass `resample=` for a
site_from_points model). Both are deterministic by seed / sample seed; every component
is sampled vectorised and stored as float32 at once, as make_scene does.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from gsa.model import GaussianModel, sh_coeff_count
from gsa.sh import rgb_to_sh_dc
from gsa.synth.objects import _quats_from_normals
from gsa.synth.scenes import _furniture, _hash01, _Piece, _surface_piece
from gsa.synth.shapes import Box

# Sampling density per unit area relative to the ground: what stands on a site carries
# the detail a capture resolves best (as make_scene's furniture).
OBJECT_DENSITY = 3.0
SKY_FLOATERS = 0.003  # share of a site's Gaussians that are sky/background floaters


class _Terrain:
    """A heightfield: a sum of Gaussian hills and hollows plus a gentle tilt."""

    def __init__(self, w: float, d: float, layout: np.random.Generator):
        k = int(layout.integers(4, 8))
        self.centres = layout.uniform([0, 0], [w, d], (k, 2))
        self.sigma = layout.uniform(0.08, 0.25, k) * max(w, d)
        self.amp = layout.uniform(0.5, 3.5, k) * layout.choice([-1.0, 1.0, 1.0], k)  # more hills than hollows
        self.tilt = layout.uniform(-0.03, 0.03, 2)

    def height(self, xy: np.ndarray) -> np.ndarray:
        d2 = np.sum((xy[:, None, :] - self.centres[None]) ** 2, axis=-1)
        return np.exp(-0.5 * d2 / self.sigma**2) @ self.amp + xy @ self.tilt

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        diff = xy[:, None, :] - self.centres[None]
        g = np.exp(-0.5 * np.sum(diff**2, axis=-1) / self.sigma**2) * self.amp / self.sigma**2
        return -np.einsum("nk,nkj->nj", g, diff) + self.tilt


def _ground(terrain: _Terrain, w: float, d: float, count: int, paths, rng, layout_seed: int) -> _Piece:
    """The terrain's surface: grass whose tone varies in patches and 0.7 m tiles, dirt
    paths along polylines, gravel specks; the texture is fixed by the layout, not by
    where the Gaussians fall."""
    xy = rng.uniform([0, 0], [w, d], (count, 2))
    z = terrain.height(xy)
    g = terrain.gradient(xy)
    normals = np.concatenate([-g, np.ones((count, 1))], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    ph = np.random.default_rng([layout_seed, 26, 3]).uniform(0, 2 * np.pi, 6)
    patch = np.sin(xy[:, 0] / 3.1 + ph[0]) * np.sin(xy[:, 1] / 2.3 + ph[1]) + 0.5 * np.sin(
        (xy[:, 0] + xy[:, 1]) / 1.7 + ph[2]
    )
    tile = _hash01(np.floor(xy[:, 0] / 0.7) * 131.0 + np.floor(xy[:, 1] / 0.7) + 17.0 * layout_seed)
    grass = np.array([0.25, 0.45, 0.15]) + 0.08 * patch[:, None] * np.array([0.6, 1.0, 0.3])
    colors = grass + 0.1 * (tile[:, None] - 0.5) * np.array([0.8, 1.0, 0.4])
    dry = patch > 0.9  # dry, yellowed grass where the patch field peaks
    colors[dry] = np.array([0.55, 0.5, 0.25]) + 0.05 * (tile[dry, None] - 0.5)
    for path in paths:
        dist = _polyline_distance(xy, path["points"])
        on = dist < path["width"] / 2
        colors[on] = np.array([0.55, 0.42, 0.3]) + 0.08 * (tile[on, None] - 0.5)
        edge = on & (dist > 0.4 * path["width"])
        colors[edge] *= 0.75
    colors += rng.normal(0, 0.02, colors.shape)
    pts = np.concatenate([xy, z[:, None]], axis=1)
    return _surface_piece(pts, normals, colors, w * d, rng)


def _polyline_distance(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    best = np.full(len(xy), np.inf)
    for a, b in zip(poly[:-1], poly[1:]):
        ab = b - a
        t = np.clip(((xy - a) @ ab) / max(ab @ ab, 1e-12), 0, 1)
        best = np.minimum(best, np.linalg.norm(xy - (a + t[:, None] * ab), axis=1))
    return best


def _bumpy_ellipsoid(radii, bumps: np.ndarray, count: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, normals and a bump value on an ellipsoid whose radius is modulated by a
    few fixed lobes (`bumps`: rows of direction and amplitude): tree crowns, rocks."""
    u = rng.normal(size=(count, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    lobe = np.maximum(u @ bumps[:, :3].T, 0) ** 4 @ bumps[:, 3]
    pts = u * np.asarray(radii) * (1.0 + lobe)[:, None]
    normals = u / np.asarray(radii)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return pts, normals, lobe


def _lobes(layout: np.random.Generator, k: int, amp: float) -> np.ndarray:
    d = layout.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.concatenate([d, layout.uniform(0.1, amp, (k, 1))], axis=1)


def _tree(spec: dict, base: np.ndarray, count: int, rng) -> _Piece:
    r_t, h_t, crown = spec["trunk_radius"], spec["trunk_height"], np.asarray(spec["crown"])
    trunk_area = 2 * np.pi * r_t * h_t
    crown_area = 4 * np.pi * float(np.mean(crown)) ** 2
    n_trunk = max(int(count * trunk_area / (trunk_area + crown_area)), 1)
    theta = rng.uniform(0, 2 * np.pi, n_trunk)
    radial = np.stack([np.cos(theta), np.sin(theta), np.zeros(n_trunk)], 1)
    trunk = radial * r_t + np.outer(rng.uniform(0, h_t, n_trunk), [0, 0, 1])
    trunk_col = np.array([0.35, 0.25, 0.15]) + 0.05 * np.sin(trunk[:, 2:3] * 9.0) + rng.normal(0, 0.02, (n_trunk, 3))
    pts, nrm, lobe = _bumpy_ellipsoid(crown, np.asarray(spec["lobes"]), count - n_trunk, rng)
    pts[:, 2] += h_t + 0.8 * crown[2]
    shade = np.clip(pts[:, 2:3] - h_t, 0, None) / (2 * crown[2])  # lighter towards the top (sunlit)
    crown_col = np.asarray(spec["leaf"]) * (0.8 + 0.4 * shade) + 0.15 * lobe[:, None] * np.array([0.3, 0.5, 0.1])
    crown_col += rng.normal(0, 0.03, crown_col.shape)
    p = _surface_piece(
        np.concatenate([trunk, pts]) + base,
        np.concatenate([radial, nrm]),
        np.concatenate([trunk_col, crown_col]),
        trunk_area + crown_area,
        rng,
    )
    return p


def _rock(spec: dict, base: np.ndarray, count: int, rng) -> _Piece:
    radii = np.asarray(spec["radii"])
    pts, nrm, lobe = _bumpy_ellipsoid(radii, np.asarray(spec["lobes"]), 2 * count, rng)
    keep = np.flatnonzero(pts[:, 2] > -0.3 * radii[2])[:count]  # half-buried: only what is above ground
    pts, nrm, lobe = pts[keep], nrm[keep], lobe[keep]
    col = np.asarray(spec["tone"]) + 0.1 * lobe[:, None] + rng.normal(0, 0.03, (len(pts), 3))
    lichen = _hash01(np.floor(pts[:, 0] * 5) * 31 + np.floor(pts[:, 1] * 5) + np.floor(pts[:, 2] * 5) * 7) > 0.85
    col[lichen] = (0.6, 0.65, 0.3)
    pts[:, 2] += 0.3 * radii[2]
    area = 4 * np.pi * float(np.mean(radii)) ** 2 * 0.8
    return _surface_piece(pts + base, nrm, col, area, rng)


def _boxes(boxes: list[tuple], yaw: float, base: np.ndarray, count: int, rng) -> _Piece:
    """Axis boxes (centre, half extents, colour) in a local frame turned by `yaw` and
    placed at `base`: benches and sheds. Counts by area."""
    areas = np.array([Box((0, 0, 0), tuple(h), (0, 0, 0)).area() for _, h, _ in boxes])
    counts = rng.multinomial(count, areas / areas.sum())
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    pts, nrm, col = [], [], []
    for (centre, half, colour), k in zip(boxes, counts):
        p, n = Box(tuple(centre), tuple(half), (0, 0, 0)).sample(int(k), rng)
        stripe = 0.06 * np.sin(p[:, 0] * 20.0)[:, None]  # wood grain / siding
        pts.append(p)
        nrm.append(n)
        col.append(np.asarray(colour) + stripe + rng.normal(0, 0.02, (int(k), 3)))
    return _surface_piece(
        np.concatenate(pts) @ rot.T + base, np.concatenate(nrm) @ rot.T, np.concatenate(col), areas.sum(), rng
    )


def _bench_boxes(length: float, colour) -> list[tuple]:
    legs = [((x, 0.0, 0.22), (0.04, 0.2, 0.22), (0.2, 0.2, 0.2)) for x in (-0.4 * length, 0.4 * length)]
    return [
        ((0, 0, 0.46), (length / 2, 0.22, 0.03), colour),  # seat
        ((0, 0.2, 0.75), (length / 2, 0.03, 0.25), colour),  # back
        *legs,
    ]


def _shed_boxes(w: float, d: float, h: float, colour) -> list[tuple]:
    return [
        ((0, 0, h / 2), (w / 2, d / 2, h / 2), colour),
        ((0, 0, h + 0.1), (w / 2 + 0.3, d / 2 + 0.3, 0.1), (0.45, 0.2, 0.15)),  # roof, overhanging
        ((w / 2 + 0.01, 0, 0.95), (0.01, 0.45, 0.95), (0.3, 0.2, 0.12)),  # door on one side
    ]


def make_site(
    seed: int = 0,
    n_gaussians: int = 1_000_000,
    sample_seed: int | None = None,
    trees: int | None = None,
    rocks: int | None = None,
    benches: int | None = None,
    vehicles: int | None = None,
    shed: bool | None = None,
    sh_degree: int = 0,
) -> GaussianModel:
    """An outdoor site of exactly `n_gaussians` Gaussians (float32 arrays), z up.

    seed fixes the site (size, terrain, paths, what stands where, colours); sample_seed
    (default: seed) where the Gaussians fall, so two sample seeds give two independent
    3DGS models of one site in one frame. The site is 30–60 × 25–45 m of hilly terrain
    (4–7 hills or hollows of 0.5–3.5 m, a gentle tilt), 1–2 dirt paths, 5–12 trees
    (2–6 m), 4–10 rocks (0.3–1.2 m), 1–4 benches, 0–2 vehicles (gsa.synth cars and
    buses at 4–9 m) and, at random, a shed (2–4 m); object counts left None are drawn.
    Gaussians are split by area: ground 1×, objects 3× the density; SKY_FLOATERS of
    them are faint sky floaters 5–20 m above the ground.
    metadata: kind "site", seed, sample_seed, site_args, size, extent (the diagonal of
    the site's box, terrain and objects included), objects.
    """
    if n_gaussians < 2000:
        raise ValueError("a site needs at least 2000 Gaussians")
    layout = np.random.default_rng([seed, 26, 1])  # what the site is
    rng = np.random.default_rng([seed if sample_seed is None else sample_seed, 26, 2])  # where its Gaussians fall
    w, d = layout.uniform(30.0, 60.0), layout.uniform(25.0, 45.0)
    terrain = _Terrain(w, d, layout)
    paths = _paths(layout, w, d)
    # Drawn whether given or not, so that giving the drawn counts (a resampling from
    # metadata["site_args"]) leaves the layout's stream, and so the site, as it was.
    drawn = (int(layout.integers(5, 13)), int(layout.integers(4, 11)), int(layout.integers(1, 5)))
    drawn += (int(layout.integers(0, 3)), bool(layout.random() < 0.6))
    given = (trees, rocks, benches, vehicles, shed)
    n_trees, n_rocks, n_benches, n_vehicles, has_shed = (d if g is None else g for d, g in zip(drawn, given))
    objects = _site_objects(layout, w, d, n_trees, n_rocks, n_benches, n_vehicles, has_shed)
    areas = [w * d] + [OBJECT_DENSITY * _object_area(o) for o in objects]
    n_sky = int(round(SKY_FLOATERS * n_gaussians))
    counts = rng.multinomial(n_gaussians - n_sky, np.array(areas) / np.sum(areas))
    small = counts[1:] < 20  # too few to sample a shape: give them to the ground
    counts[0] += int(counts[1:][small].sum())
    counts[1:][small] = 0
    pieces = [_ground(terrain, w, d, int(counts[0]), paths, rng, seed)]
    pieces += [_object_piece(o, terrain, int(c), rng) for o, c in zip(objects, counts[1:]) if c]
    if n_sky:
        pieces.append(_sky(terrain, w, d, n_sky, rng))
    model = _assemble(pieces, n_gaussians, sh_degree)
    z = model.means[: n_gaussians - n_sky, 2]
    model.metadata.update(
        kind="site",
        seed=seed,
        sample_seed=sample_seed,
        site_args=dict(
            trees=n_trees, rocks=n_rocks, benches=n_benches, vehicles=n_vehicles, shed=has_shed, sh_degree=sh_degree
        ),
        size=[float(w), float(d)],
        extent=float(np.linalg.norm([w, d, float(z.max() - z.min())])),
        objects=[{k: v for k, v in o.items() if k not in ("lobes", "boxes")} for o in objects],
    )
    return model


def _paths(layout: np.random.Generator, w: float, d: float) -> list[dict]:
    """1-2 dirt paths across the site, each a polyline of 3-5 points and a width."""
    paths = []
    for _ in range(int(layout.integers(1, 3))):
        k = int(layout.integers(3, 6))
        pts = np.stack([np.linspace(0, w, k), layout.uniform(0.2 * d, 0.8 * d, k)], 1)
        if layout.random() < 0.5:
            pts = np.stack([layout.uniform(0.2 * w, 0.8 * w, k), np.linspace(0, d, k)], 1)
        paths.append({"points": pts, "width": float(layout.uniform(1.0, 2.5))})
    return paths


def _site_objects(
    layout: np.random.Generator,
    w: float,
    d: float,
    n_trees: int,
    n_rocks: int,
    n_benches: int,
    n_vehicles: int,
    has_shed: bool,
) -> list[dict]:
    """The specs of what stands on the site (trees, rocks, benches, a shed, vehicles), each
    placed at "xy"."""
    footprints: list = []

    def place(radius: float) -> np.ndarray:
        for _ in range(60):  # clear of the edges and, when there is room, of earlier things
            xy = layout.uniform([radius + 1, radius + 1], [w - radius - 1, d - radius - 1])
            if all(np.hypot(*(xy - c)) > radius + r for c, r in footprints):
                break
        footprints.append((xy, radius))
        return xy

    objects: list[dict] = []
    for _ in range(n_trees):
        crown = layout.uniform([1.0, 1.0, 1.0], [2.5, 2.5, 3.0])
        crown[1] = crown[0] * layout.uniform(0.8, 1.2)
        spec = dict(
            kind="tree",
            trunk_radius=float(layout.uniform(0.12, 0.35)),
            trunk_height=float(layout.uniform(1.0, 3.0)),
            crown=crown.tolist(),
            lobes=_lobes(layout, 6, 0.35).tolist(),
            leaf=(np.array([0.2, 0.42, 0.15]) * layout.uniform(0.7, 1.3, 3)).tolist(),
        )
        spec["xy"] = place(float(crown[0])).tolist()
        objects.append(spec)
    for _ in range(n_rocks):
        radii = layout.uniform(0.3, 1.2) * layout.uniform([0.8, 0.8, 0.5], [1.2, 1.2, 0.9])
        spec = dict(kind="rock", radii=radii.tolist(), lobes=_lobes(layout, 5, 0.25).tolist())
        spec["tone"] = (np.full(3, layout.uniform(0.35, 0.6)) + layout.uniform(-0.05, 0.05, 3)).tolist()
        spec["xy"] = place(float(radii[0])).tolist()
        objects.append(spec)
    for _ in range(n_benches):
        length = float(layout.uniform(1.2, 2.0))
        colour = (np.array([0.5, 0.33, 0.18]) * layout.uniform(0.7, 1.3)).tolist()
        objects.append(dict(kind="bench", boxes=_bench_boxes(length, colour), yaw=float(layout.uniform(0, 2 * np.pi))))
        objects[-1]["xy"] = place(0.6 * length).tolist()
    if has_shed:
        sw, sd, sh_ = layout.uniform(2.0, 4.0), layout.uniform(2.0, 3.5), layout.uniform(2.2, 3.0)
        colour = layout.uniform(0.3, 0.8, 3).tolist()
        objects.append(
            dict(kind="shed", boxes=_shed_boxes(sw, sd, sh_, colour), yaw=float(layout.uniform(0, 2 * np.pi)))
        )
        objects[-1]["xy"] = place(0.6 * float(np.hypot(sw, sd))).tolist()
    for i in range(n_vehicles):
        cat = ("car", "bus")[i % 2]
        size = float(layout.uniform(4.0, 5.0) if cat == "car" else layout.uniform(7.0, 9.0))
        spec = dict(kind=cat, seed=int(layout.integers(10_000)), size=size, yaw=float(layout.uniform(0, 2 * np.pi)))
        spec["xy"] = place(0.5 * size).tolist()
        objects.append(spec)
    return objects


def _object_area(o: dict) -> float:
    """An object's surface area (m²), which sets its share of the Gaussians."""
    if o["kind"] == "tree":
        return 2 * np.pi * o["trunk_radius"] * o["trunk_height"] + 4 * np.pi * float(np.mean(o["crown"])) ** 2
    if o["kind"] == "rock":
        return 4 * np.pi * float(np.mean(o["radii"])) ** 2
    if o["kind"] in ("bench", "shed"):
        return sum(Box((0, 0, 0), tuple(h), (0, 0, 0)).area() for _, h, _ in o["boxes"])
    return 2.0 * o["size"] ** 2  # as make_scene's furniture


def _object_piece(o: dict, terrain: _Terrain, count: int, rng: np.random.Generator) -> _Piece:
    """`count` Gaussians on an object's surface, standing on the terrain at its "xy"."""
    xy = np.asarray(o["xy"])
    base = np.array([*xy, terrain.height(xy[None])[0]])
    if o["kind"] == "tree":
        return _tree(o, base, count, rng)
    if o["kind"] == "rock":
        return _rock(o, base, count, rng)
    if o["kind"] in ("bench", "shed"):
        return _boxes(o["boxes"], o["yaw"], base, count, rng)
    p = _furniture(o["kind"], o["seed"], count, o["size"], o["yaw"], xy, rng)
    p.means[:, 2] += np.float32(base[2])
    return p


def _sky(terrain: _Terrain, w: float, d: float, count: int, rng) -> _Piece:
    """Faint, large floaters 5–20 m above the ground: what optimisation leaves in the sky."""
    xy = rng.uniform([-0.1 * w, -0.1 * d], [1.1 * w, 1.1 * d], (count, 2))
    z = terrain.height(xy) + rng.uniform(5.0, 20.0, count)
    scales = np.exp(rng.uniform(np.log(0.3), np.log(1.5), (count, 3)))
    opac = rng.uniform(0.05, 0.3, count)
    colors = np.array([0.65, 0.78, 0.95]) + rng.normal(0, 0.05, (count, 3))
    quats = rng.normal(size=(count, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return _Piece(
        means=np.concatenate([xy, z[:, None]], axis=1).astype(np.float32),
        quats=quats.astype(np.float32),
        log_scales=np.log(scales).astype(np.float32),
        opacity_logits=np.log(opac / (1 - opac)).astype(np.float32),
        dc=rgb_to_sh_dc(np.clip(colors, 0, 1)).astype(np.float32),
    )


def _assemble(pieces: list[_Piece], n: int, sh_degree: int) -> GaussianModel:
    sh = np.zeros((n, sh_coeff_count(sh_degree), 3), np.float32)
    sh[:, 0, :] = np.concatenate([p.dc for p in pieces])
    return GaussianModel(
        means=np.concatenate([p.means for p in pieces]),
        quats=np.concatenate([p.quats for p in pieces]),
        log_scales=np.concatenate([p.log_scales for p in pieces]),
        opacity_logits=np.concatenate([p.opacity_logits for p in pieces]),
        sh=sh,
    )


# --- sites from real SfM points --------------------------------------------------------------


def load_sfm_points(path) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float64, colours (n, 3) in [0, 1]) from an .npz holding `means3d` and
    `colors` (uint8 0–255 or floats in [0, 1]), as gsplat's test_garden.npz."""
    with np.load(path) as data:
        missing = {"means3d", "colors"} - set(data.files)
        if missing:
            raise ValueError(f"{path}: no {', '.join(sorted(missing))} array (an SfM point file needs means3d, colors)")
        pts = np.asarray(data["means3d"], np.float64)
        col = np.asarray(data["colors"], np.float64)
    if col.max(initial=0.0) > 1.0:
        col = col / 255.0
    ok = np.isfinite(pts).all(axis=1) & np.isfinite(col).all(axis=1)
    return pts[ok], np.clip(col[ok], 0.0, 1.0)


def robust_extent(points: np.ndarray) -> float:
    """The diagonal of the 1st–99th percentile box: an SfM cloud's far background points
    (a few distant trees or buildings) would otherwise set the scale of every tolerance."""
    lo, hi = np.percentile(points, [1, 99], axis=0)
    return float(np.linalg.norm(hi - lo))


class PointSite:
    """Gaussians around real SfM points: `sample(n, seed)` draws n Gaussians, each at a
    random point (uniformly over the points, so dense parts stay dense), moved within the
    point's local spacing along its local surface (and a tenth of it across), shaped as a
    flat disc on that surface with the point's colour. The neighbourhoods (k nearest
    points) are computed once; each seed is an independent sampling of one geometry."""

    K = 8

    def __init__(self, points: np.ndarray, colors: np.ndarray, name: str = "sfm"):
        if len(points) < 100:
            raise ValueError(f"{name}: {len(points)} points; a site needs at least 100")
        self.points, self.colors, self.name = points, colors, name
        dist, nn = cKDTree(points).query(points, k=self.K + 1, workers=-1)
        # Spacing: the median distance to the k nearest (robust to one duplicate point).
        self.spacing = np.maximum(np.median(dist[:, 1:], axis=1), 1e-9)
        nb = points[nn] - points[nn].mean(axis=1, keepdims=True)
        _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
        self.frames = vecs  # columns: normal (least variance), then the two tangents
        self.extent = robust_extent(points)

    @classmethod
    def from_file(cls, path) -> PointSite:
        pts, col = load_sfm_points(path)
        return cls(pts, col, name=str(path))

    def sample(self, n_gaussians: int, seed: int = 0) -> GaussianModel:
        rng = np.random.default_rng([seed, 26, 4])
        idx = rng.integers(0, len(self.points), n_gaussians)
        per_point = max(n_gaussians / len(self.points), 1.0)
        sp = self.spacing[idx]
        f = self.frames[idx]
        # Uniform on a disc of the spacing's radius in the tangent plane, thin across it.
        r = 0.5 * sp * np.sqrt(rng.random(n_gaussians))
        th = rng.uniform(0, 2 * np.pi, n_gaussians)
        off = (r * np.cos(th))[:, None] * f[:, :, 1] + (r * np.sin(th))[:, None] * f[:, :, 2]
        off += (0.05 * sp * rng.normal(size=n_gaussians))[:, None] * f[:, :, 0]
        means = self.points[idx] + off
        tangent = sp / np.sqrt(per_point) * rng.uniform(0.5, 1.0, n_gaussians)
        scales = np.stack([tangent, tangent * rng.uniform(0.7, 1.0, n_gaussians), 0.1 * tangent], 1)
        colors = self.colors[idx] + rng.normal(0, 0.02, (n_gaussians, 3))
        opac = rng.uniform(0.6, 0.99, n_gaussians)
        piece = _Piece(
            means=means.astype(np.float32),
            quats=_quats_from_normals(f[:, :, 0], rng).astype(np.float32),
            log_scales=np.log(scales).astype(np.float32),
            opacity_logits=np.log(opac / (1 - opac)).astype(np.float32),
            dc=rgb_to_sh_dc(np.clip(colors, 0, 1)).astype(np.float32),
        )
        model = _assemble([piece], n_gaussians, 0)
        model.metadata.update(kind="site-points", source=self.name, points=len(self.points), extent=self.extent)
        return model

    def resampler(self) -> Callable[[GaussianModel, int], GaussianModel]:
        """For gsa.synth.scene_captures(resample=...): another sampling of the same points."""
        return lambda model, sample_seed: self.sample(len(model), sample_seed)


def resample_site(site: GaussianModel, sample_seed: int) -> GaussianModel:
    """For gsa.synth.scene_captures(resample=...): another sampling of a make_site model, from
    its metadata."""
    meta = site.metadata
    return make_site(meta["seed"], len(site), sample_seed=sample_seed, **meta["site_args"])


def site_from_points(points: np.ndarray, colors: np.ndarray, n_gaussians: int, seed: int = 0) -> GaussianModel:
    """`n_gaussians` Gaussians around SfM points (PointSite.sample)."""
    return PointSite(np.asarray(points, np.float64), np.asarray(colors, np.float64)).sample(n_gaussians, seed)


__all__ = ["PointSite", "load_sfm_points", "make_site", "resample_site", "robust_extent", "site_from_points"]
