"""Procedural furnished rooms as 3DGS, and two partial "captures" of one room
(scene-scale registration).

make_scene       a room (floor of planks, four walls with recessed windows and a door,
                 optional ceiling), objects of the gsa.synth categories scaled to furniture
                 size and stood on the floor at random poses, and clutter boxes
scene_captures   two captures of a scene: each keeps its own half-space of the room (the
                 shared slab holds 50–80 % of their union), its own density, its own
                 floaters, and its own random Sim(3) (scale 0.2–5); the truths are returned

Both are deterministic by seed / Generator. Built for millions of Gaussians: every
component is sampled vectorised and stored as float32 at once, so the float64
temporaries are one component's, never the whole scene's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from gsa.colour import linear_to_srgb, srgb_to_linear
from gsa.geometry import axis_rotation
from gsa.model import GaussianModel, sh_coeff_count
from gsa.sh import rgb_to_sh_dc, sh_dc_to_rgb
from gsa.sim3 import Sim3
from gsa.synth.objects import CATEGORIES, _quats_from_normals, make_object
from gsa.synth.perturb import random_sim3
from gsa.synth.shapes import Box
from gsa.synth.variants import add_floaters

# Sampling density per unit area relative to the room's surfaces: furniture carries
# the detail a capture resolves best.
OBJECT_DENSITY = 3.0
CLUTTER_DENSITY = 2.0


@dataclass
class _Piece:
    """One sampled component, already float32."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    dc: np.ndarray  # (n, 3) SH DC coefficients


def _hash01(i: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random value in [0, 1) per integer cell (texture, not randomness)."""
    return np.modf(np.abs(np.sin(i * 12.9898 + 78.233)) * 43758.5453)[0]


def _surface_piece(
    points: np.ndarray, normals: np.ndarray, colors: np.ndarray, area: float, rng: np.random.Generator
) -> _Piece:
    """Flat Gaussians on a surface: discs of the local sample spacing, normal axis thin."""
    n = len(points)
    spacing = np.sqrt(area / max(n, 1))
    tangent = spacing * rng.uniform(0.6, 1.0, n)
    scales = np.stack([tangent, tangent * rng.uniform(0.7, 1.0, n), tangent * 0.08], axis=1)
    opac = rng.uniform(0.7, 0.99, n)
    return _Piece(
        means=points.astype(np.float32),
        quats=_quats_from_normals(normals, rng).astype(np.float32),
        log_scales=np.log(scales).astype(np.float32),
        opacity_logits=np.log(opac / (1 - opac)).astype(np.float32),
        dc=rgb_to_sh_dc(np.clip(colors, 0.0, 1.0)).astype(np.float32),
    )


def _rect(origin, u, v, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Uniform points on the parallelogram origin + a·u + b·v (a, b in [0, 1]), and (a, b)."""
    ab = rng.uniform(0.0, 1.0, (count, 2))
    return np.asarray(origin, np.float64) + ab[:, :1] * np.asarray(u) + ab[:, 1:] * np.asarray(v), ab


def _floor(w: float, d: float, count: int, rng: np.random.Generator) -> _Piece:
    pts, _ = _rect((0, 0, 0), (w, 0, 0), (0, d, 0), count, rng)
    plank = np.floor(pts[:, 1] / 0.18)
    shade = 0.12 * (_hash01(plank) - 0.5) + 0.03 * np.sin(pts[:, 0] * 40.0 + 10 * _hash01(plank + 7))
    colors = np.array([0.55, 0.38, 0.22]) + shade[:, None] + rng.normal(0, 0.02, (count, 3))
    seams = np.abs(pts[:, 1] / 0.18 - np.round(pts[:, 1] / 0.18)) < 0.04
    colors[seams] *= 0.6
    return _surface_piece(pts, np.tile([0.0, 0.0, 1.0], (count, 1)), colors, w * d, rng)


def _ceiling(w: float, d: float, h: float, count: int, rng: np.random.Generator) -> _Piece:
    pts, _ = _rect((0, 0, h), (w, 0, 0), (0, d, 0), count, rng)
    colors = np.array([0.92, 0.92, 0.9]) + rng.normal(0, 0.015, (count, 3))
    lamp = np.hypot(pts[:, 0] - w / 2, pts[:, 1] - d / 2) < 0.3  # a ceiling lamp marks the middle
    colors[lamp] = (1.0, 0.95, 0.7)
    return _surface_piece(pts, np.tile([0.0, 0.0, -1.0], (count, 1)), colors, w * d, rng)


def _walls(
    w: float, d: float, h: float, count: int, rng: np.random.Generator, layout: np.random.Generator
) -> tuple[_Piece, list[dict]]:
    """Four walls, their counts by area; windows are recessed glass panels in white
    frames, one door is a dark panel. Wall colours and wallpaper differ per wall."""
    walls = [  # origin, along-wall unit, inward normal, length
        ((0, 0, 0), (1, 0, 0), (0, 1, 0), w),
        ((w, d, 0), (-1, 0, 0), (0, -1, 0), w),
        ((w, 0, 0), (0, 1, 0), (-1, 0, 0), d),
        ((0, d, 0), (0, -1, 0), (1, 0, 0), d),
    ]
    lengths = np.array([x[3] for x in walls])
    counts = rng.multinomial(count, lengths / lengths.sum())
    door_wall = int(layout.integers(4))
    pts_all, nrm_all, col_all, openings = [], [], [], []
    for k, ((origin, along, inward, length), c) in enumerate(zip(walls, counts)):
        along, inward = np.asarray(along, np.float64), np.asarray(inward, np.float64)
        pts, ab = _rect(origin, along * length, (0, 0, h), int(c), rng)
        s, z = ab[:, 0] * length, ab[:, 1] * h  # position along the wall, height
        base = np.clip(layout.uniform(0.45, 0.9, 3), 0, 1)
        stripes = 0.06 * np.sign(np.sin(s * np.pi / layout.uniform(0.1, 0.4))) if k % 2 else 0.03 * np.sin(3 * s)
        colors = base + stripes[:, None] + rng.normal(0, 0.015, (len(pts), 3))
        colors[z < 0.1] = (0.95, 0.95, 0.95)  # skirting board
        normals = np.tile(inward, (len(pts), 1))
        n_windows = int(layout.integers(1, 3)) if k != door_wall else 0
        for j in range(n_windows):
            ww, wh = layout.uniform(0.8, 1.6), layout.uniform(0.9, 1.4)
            centre = length * (j + 1) / (n_windows + 1) + layout.uniform(-0.2, 0.2)
            lo, hi = (centre - ww / 2, 0.9), (centre + ww / 2, 0.9 + wh)
            inside = (s > lo[0]) & (s < hi[0]) & (z > lo[1]) & (z < min(hi[1], h - 0.1))
            frame = inside & ((s < lo[0] + 0.06) | (s > hi[0] - 0.06) | (z < lo[1] + 0.06) | (z > hi[1] - 0.06))
            glass = inside & ~frame
            pts[glass] -= 0.12 * inward  # recessed: the window sits in the wall's depth
            colors[glass] = np.array([0.65, 0.8, 0.95]) + 0.1 * (z[glass, None] - 0.9) / wh
            colors[frame] = (0.97, 0.97, 0.97)
            openings.append({"wall": k, "kind": "window", "along": [lo[0], hi[0]], "height": [lo[1], hi[1]]})
        if k == door_wall:
            centre = layout.uniform(0.8, length - 0.8)
            door = (np.abs(s - centre) < 0.45) & (z < 2.05)
            colors[door] = np.array([0.35, 0.2, 0.12]) + 0.04 * np.sin(z[door, None] * 25)
            openings.append({"wall": k, "kind": "door", "along": [centre - 0.45, centre + 0.45], "height": [0, 2.05]})
        pts_all.append(pts)
        nrm_all.append(normals)
        col_all.append(colors)
    area = 2 * (w + d) * h
    piece = _surface_piece(np.concatenate(pts_all), np.concatenate(nrm_all), np.concatenate(col_all), area, rng)
    return piece, openings


def _furniture(category: str, seed: int, count: int, size: float, yaw: float, xy, rng) -> _Piece:
    """A gsa.synth object scaled so its largest side is `size`, turned by `yaw` about
    the vertical and stood on the floor at `xy`. The placement comes from a fixed
    reference sampling of the instance, so every sampling of the room puts it in one place."""
    reference = make_object(category, seed=seed, n_gaussians=4000, sample_seed=0).means
    scale = size / float(np.ptp(reference, axis=0).max())
    rot = axis_rotation((0, 0, 1), yaw)
    ref = reference @ (scale * rot).T.astype(np.float32)
    lo, hi = ref.min(0), ref.max(0)
    shift = np.array([xy[0] - 0.5 * (lo[0] + hi[0]), xy[1] - 0.5 * (lo[1] + hi[1]), -lo[2]])
    model = make_object(category, seed=seed, n_gaussians=count, sample_seed=int(rng.integers(1 << 30)))
    placed = model.transformed(Sim3(scale, rot, shift))
    return _Piece(placed.means, placed.quats, placed.log_scales, placed.opacity_logits, placed.sh[:, 0, :])


def _clutter_box(half, yaw, centre, base, count: int, rng: np.random.Generator) -> _Piece:
    box = Box((0, 0, 0), tuple(half), (0, 0, 0))
    pts, nrm = box.sample(count, rng)
    rot = axis_rotation((0, 0, 1), yaw)
    band = 0.15 * (np.sin(pts[:, 2] * np.pi / max(half[2], 1e-3) * 2) > 0.6)  # a label stripe
    colors = base + band[:, None] + rng.normal(0, 0.02, (count, 3))
    return _surface_piece(pts @ rot.T + centre, nrm @ rot.T, colors, box.area(), rng)


def _place(footprints: list, radius: float, w: float, d: float, layout, tries: int = 60) -> np.ndarray:
    """A floor position whose circle of `radius` clears the walls and, if it can, the
    earlier footprints (the last try is kept when the room is full)."""
    for _ in range(tries):
        xy = layout.uniform([radius + 0.1, radius + 0.1], [w - radius - 0.1, d - radius - 0.1])
        if all(np.hypot(*(xy - c)) > radius + r for c, r in footprints):
            break
    footprints.append((xy, radius))
    return xy


def make_scene(
    seed: int = 0,
    n_gaussians: int = 1_000_000,
    sample_seed: int | None = None,
    objects: int = 6,
    clutter: int = 12,
    ceiling: bool = True,
    sh_degree: int = 0,
) -> GaussianModel:
    """A furnished room of exactly `n_gaussians` Gaussians (float32 arrays).

    seed fixes the room (size, furniture, windows, colours); sample_seed (default: seed)
    where the Gaussians fall, so two sample seeds give two independent 3DGS models of one
    room in one frame.

    The room is 5–9 × 4–7 m, 2.6–3.2 m high, with corner (0, 0, 0) and z up. `objects`
    are gsa.synth category instances (categories in turn) scaled to 0.5–1.6 m and
    `clutter` boxes 0.1–0.5 m, all at random floor positions and yaws. Gaussians are
    split by area: room surfaces 1×, objects 3×, clutter 2× the density.
    metadata: seed, room size, `extent` (room diagonal), objects, clutter and openings.
    """
    if n_gaussians < 1000:
        raise ValueError("a scene needs at least 1000 Gaussians")
    layout = np.random.default_rng([seed, 18, 1])  # what the room is
    rng = np.random.default_rng([seed if sample_seed is None else sample_seed, 18, 2])  # where its Gaussians fall
    w, d, h = layout.uniform(5.0, 9.0), layout.uniform(4.0, 7.0), layout.uniform(2.6, 3.2)
    footprints: list = []
    furniture = []
    for i in range(objects):
        cat = CATEGORIES[(seed + i) % len(CATEGORIES)]
        size = float(layout.uniform(0.5, 1.6))
        xy = _place(footprints, 0.5 * size, w, d, layout)
        furniture.append(
            dict(category=cat, seed=int(layout.integers(10_000)), size=size, yaw=float(layout.uniform(0, 2 * np.pi)))
        )
        furniture[-1]["xy"] = xy.tolist()
    boxes = []
    for _ in range(clutter):
        half = layout.uniform(0.05, 0.25, 3)
        xy = _place(footprints, float(np.hypot(half[0], half[1])), w, d, layout)
        yaw, color = float(layout.uniform(0, 2 * np.pi)), layout.uniform(0.1, 0.95, 3)
        boxes.append(dict(half=half, yaw=yaw, centre=np.array([*xy, half[2]]), color=color))
    # Areas: an object's surface is about 2·size² (its parts' areas scale with size²).
    areas = [w * d, 2 * (w + d) * h, w * d if ceiling else 0.0]
    areas += [OBJECT_DENSITY * 2.0 * f["size"] ** 2 for f in furniture]
    areas += [CLUTTER_DENSITY * Box((0, 0, 0), tuple(b["half"]), (0, 0, 0)).area() for b in boxes]
    counts = rng.multinomial(n_gaussians, np.array(areas) / np.sum(areas))
    counts[0] += sum(int(c) for c in counts[3:] if c < 10)  # too few to sample a shape: give them to the floor
    counts[3:] = np.where(counts[3:] < 10, 0, counts[3:])
    pieces = [_floor(w, d, int(counts[0]), rng)]
    wall_piece, openings = _walls(w, d, h, int(counts[1]), rng, layout)
    pieces.append(wall_piece)
    if ceiling and counts[2]:
        pieces.append(_ceiling(w, d, h, int(counts[2]), rng))
    for f, c in zip(furniture, counts[3 : 3 + objects]):
        if c:
            pieces.append(_furniture(f["category"], f["seed"], int(c), f["size"], f["yaw"], f["xy"], rng))
    for b, c in zip(boxes, counts[3 + objects :]):
        if c:
            pieces.append(_clutter_box(b["half"], b["yaw"], b["centre"], b["color"], int(c), rng))
    sh = np.zeros((n_gaussians, sh_coeff_count(sh_degree), 3), np.float32)
    sh[:, 0, :] = np.concatenate([p.dc for p in pieces])
    model = GaussianModel(
        means=np.concatenate([p.means for p in pieces]),
        quats=np.concatenate([p.quats for p in pieces]),
        log_scales=np.concatenate([p.log_scales for p in pieces]),
        opacity_logits=np.concatenate([p.opacity_logits for p in pieces]),
        sh=sh,
    )
    model.metadata.update(
        kind="scene",
        seed=seed,
        sample_seed=sample_seed,
        scene_args=dict(objects=objects, clutter=clutter, ceiling=ceiling, sh_degree=sh_degree),
        room=[float(w), float(d), float(h)],
        extent=float(np.linalg.norm([w, d, h])),
        objects=[dict(f) for f in furniture],
        clutter=len(boxes),
        openings=openings,
    )
    return model


@dataclass
class SceneCaptures:
    """Two captures of one scene. `source` = pose_source(the Gaussians source_index of
    `scene`, then floaters appended); `target` = pose_target(the Gaussians target_index of
    `target_sampling`, then floaters) — an independent sampling of the same room, or
    `scene` itself when the captures were made with independent=False. `truth` maps the
    source into the target (target ≈ truth(source)): pose_target ∘ pose_source⁻¹.

    The sub-volumes are half-spaces along the horizontal unit `direction` (scene frame):
    the source keeps d·x ≥ cuts[0], the target d·x ≤ cuts[1]. `overlap` is
    |S ∩ T| / |S ∪ T| over `scene`'s Gaussians in those half-spaces (before the density
    subsampling); `overlap_of_source` / `overlap_of_target` are |S ∩ T| / |S|, / |T|.
    `extent_source` / `extent_target`: the room's diagonal in each capture's units.
    """

    source: GaussianModel
    target: GaussianModel
    target_sampling: GaussianModel
    truth: Sim3
    pose_source: Sim3
    pose_target: Sim3
    source_index: np.ndarray
    target_index: np.ndarray
    direction: np.ndarray
    cuts: tuple[float, float]
    overlap: float
    overlap_of_source: float
    overlap_of_target: float
    floaters: tuple[int, int]
    extent_source: float
    extent_target: float
    # What scene_captures' harder options did (all empty/1 when they are off): the cut's
    # wave (amplitude, wavelength, phase; scene units) and, per capture, its linear RGB
    # gains (exposure x white balance), Gaussians removed by holes, whether it lost the
    # ceiling, and its scanner position (scene frame; density falls off from it).
    wave: tuple[float, float, float] | None = None
    gains: tuple[tuple[float, float, float], tuple[float, float, float]] = ((1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    holed: tuple[int, int] = (0, 0)
    no_ceiling: tuple[bool, bool] = (False, False)
    scanners: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None


def scene_captures(
    scene: GaussianModel,
    rng: np.random.Generator,
    overlap: tuple[float, float] = (0.5, 0.8),
    density: tuple[float, float] = (0.5, 1.0),
    sizes: tuple[int, int] | None = None,
    floaters: tuple[float, float] = (0.01, 0.05),
    scale_range: tuple[float, float] = (0.2, 5.0),
    independent: bool = True,
    exposure: float = 0.0,
    white_balance: float = 0.0,
    falloff: float = 0.0,
    wavy: float = 0.0,
    holes: int = 0,
    no_ceiling: float = 0.0,
    resample: Callable[[GaussianModel, int], GaussianModel] | None = None,
) -> SceneCaptures:
    """Two partial, differently dense, noisy captures of `scene`, each under its own Sim(3).

    The overlap (Jaccard of the two half-spaces' Gaussians) is drawn in `overlap` and
    placed by quantiles, so it is met to within ties; the non-shared rest is split
    30–70 % between the two sides. Each capture keeps a fraction drawn in `density` of
    its half-space's Gaussians (or exactly `sizes[i]` of them, all when fewer), gets
    floaters (a fraction drawn in `floaters` of its size, inside its own bounding box,
    gsa.synth.add_floaters) and then its own random Sim(3): any rotation, scale
    log-uniform in `scale_range`, translation within ± the room's diagonal.

    independent: the target comes from a second sampling of the room (make_scene with a
    new sample_seed; real captures never share Gaussians), cut by the same half-space;
    False: both from `scene` (their overlap then holds identical Gaussians). A make_site
    model is resampled by make_site; any other by resample(scene, sample_seed).

    Harder captures (each off at its default, and then no random number is drawn for it,
    so seeds keep their captures):
    - exposure: each capture's exposure is 2^u stops, u uniform in ±exposure, and
      white_balance its red and blue gains 1 ± white_balance (linear RGB, on SH DC);
    - falloff: density falls with the distance d from the capture's scanner (1.5 m above
      the centroid of the outer 30 % of its part of the room, the part the other capture
      lacks): Gaussians are kept with weight (1 + d / (0.1·extent))^-falloff;
    - wavy: the cut is not a plane: its offset along `direction` varies as
      wavy·extent·sin(2π s/λ + φ) along the horizontal s across it (λ 0.5-1 extent);
    - holes: each capture misses that many surface patches (balls of 4-10 % of the extent
      around random Gaussians of it: occluded or unscanned surfaces);
    - no_ceiling: the probability that a capture misses the ceiling altogether.
    """
    lo_o, hi_o = overlap
    if not 0.0 < lo_o <= hi_o < 1.0:
        raise ValueError(f"overlap must be a range inside (0, 1), got {overlap}")
    extent = float(scene.metadata.get("extent") or np.linalg.norm(np.ptp(scene.means, axis=0)))
    angle = rng.uniform(0, 2 * np.pi)
    direction = np.array([np.cos(angle), np.sin(angle), 0.0])
    wave = None
    if wavy > 0:
        wave = (wavy * extent, float(rng.uniform(0.5, 1.0)) * extent, float(rng.uniform(0, 2 * np.pi)))
    across = np.array([-direction[1], direction[0], 0.0])

    def project(means: np.ndarray) -> np.ndarray:
        """Where a Gaussian lies along the cut's direction (a wavy cut: offset by the wave)."""
        out = means @ direction.astype(np.float32)
        if wave is not None:
            amp, wavelength, phase = wave
            out = out + (amp * np.sin(2 * np.pi * (means @ across.astype(np.float32)) / wavelength + phase)).astype(
                np.float32
            )
        return out

    proj = project(scene.means)
    target_overlap = float(rng.uniform(lo_o, hi_o))
    only_target = (1.0 - target_overlap) * float(rng.uniform(0.3, 0.7))  # lowest projections
    cut_src, cut_dst = (float(q) for q in np.quantile(proj, [only_target, only_target + target_overlap]))
    in_src, in_dst = proj >= cut_src, proj <= cut_dst
    both = int(np.count_nonzero(in_src & in_dst))
    n_src, n_dst = int(np.count_nonzero(in_src)), int(np.count_nonzero(in_dst))
    union = n_src + n_dst - both
    del proj
    second = scene
    if independent:
        second = _second_sampling(scene, rng, resample)
        in_dst = project(second.means) <= cut_dst
    captures, poses, indices, n_floaters = [], [], [], []
    gains, holed, ceilingless, scanners = [], [], [], []
    for side, (base, mask) in enumerate(((scene, in_src), (second, in_dst))):
        index = np.flatnonzero(mask)
        n_before = len(index)
        if holes > 0:
            index = _punch_holes(base.means, index, holes, extent, rng)
        holed.append(n_before - len(index))
        drop_ceiling = bool(no_ceiling > 0 and rng.random() < no_ceiling)
        if drop_ceiling:
            index = index[base.means[index, 2] < np.float32(base.metadata["room"][2] - 1e-3)]
        ceilingless.append(drop_ceiling)
        weight = None
        if falloff > 0:
            # The scanner stands in the part only this capture holds (the two captures' scanners
            # were in different places): the centroid of its outer 30 % along the cut direction.
            along = project(base.means[index]) * (1.0 if side == 0 else -1.0)
            outer = index[along >= np.quantile(along, 0.7)]
            scanner = np.append(base.means[outer, :2].mean(axis=0, dtype=np.float64), 1.5)
            scanners.append(tuple(float(v) for v in scanner))
            d = np.linalg.norm(base.means[index].astype(np.float64) - scanner, axis=1)
            weight = (1.0 + d / (0.1 * extent)) ** -falloff
        index = _thin(index, weight, None if sizes is None else int(sizes[side]), density, rng)
        capture = base.subset(index)
        capture = add_floaters(capture, rng, fraction=float(rng.uniform(*floaters)), box_scale=1.0)
        gain = _colour_gain(capture, exposure, white_balance, rng)
        gains.append(tuple(float(g) for g in gain))
        pose = random_sim3(rng, scale_range=scale_range, translation=extent)
        captures.append(capture.transformed(pose))
        poses.append(pose)
        indices.append(index)
        n_floaters.append(len(capture) - len(index))
    for k, (capture, pose, n_float) in enumerate(zip(captures, poses, n_floaters)):
        capture.metadata.update(kind="scene-capture", scene_extent=extent * pose.scale, floaters=n_float)
        capture.metadata.update(colour_gains=list(gains[k]), holed=holed[k], no_ceiling=ceilingless[k])
    return SceneCaptures(
        source=captures[0],
        target=captures[1],
        target_sampling=second,
        truth=poses[1] @ poses[0].inverse(),
        pose_source=poses[0],
        pose_target=poses[1],
        source_index=indices[0],
        target_index=indices[1],
        direction=direction,
        cuts=(cut_src, cut_dst),
        overlap=both / union,
        overlap_of_source=both / n_src,
        overlap_of_target=both / n_dst,
        floaters=(n_floaters[0], n_floaters[1]),
        extent_source=extent * poses[0].scale,
        extent_target=extent * poses[1].scale,
        wave=wave,
        gains=(gains[0], gains[1]),
        holed=(holed[0], holed[1]),
        no_ceiling=(ceilingless[0], ceilingless[1]),
        scanners=(scanners[0], scanners[1]) if scanners else None,
    )


def _second_sampling(
    scene: GaussianModel, rng: np.random.Generator, resample: Callable[[GaussianModel, int], GaussianModel] | None
) -> GaussianModel:
    """A second, independent sampling of the room: resample(scene, sample_seed), or make_scene
    again from a make_scene model's metadata."""
    meta = scene.metadata
    sample_seed = int(rng.integers(1 << 30))
    if resample is not None:
        return resample(scene, sample_seed)
    if meta.get("kind") == "scene":
        return make_scene(meta["seed"], len(scene), sample_seed=sample_seed, **meta["scene_args"])
    raise ValueError(
        "independent captures need a make_scene model (its metadata says how to resample it) or resample= "
        "(gsa.synth.sites.resample_site for make_site models)"
    )


def _thin(
    index: np.ndarray,
    weight: np.ndarray | None,
    size: int | None,
    density: tuple[float, float],
    rng: np.random.Generator,
) -> np.ndarray:
    """The Gaussians a capture keeps of index: exactly `size` of them (all when fewer) or a
    fraction drawn in `density`; uniformly, or with probability weighted by `weight`."""
    if weight is None:
        if size is not None:
            keep = min(size, len(index))
            return np.sort(rng.choice(index, keep, replace=False))
        return index[rng.random(len(index)) < rng.uniform(*density)]
    if size is not None:
        keep = min(size, len(index))
    else:
        keep = round(rng.uniform(*density) * len(index))
    # Weighted sampling without replacement in O(n): the k smallest Exp(1)/w keys.
    keys = rng.exponential(size=len(index)) / weight
    if keep < len(index):
        index = np.sort(index[np.argpartition(keys, max(keep - 1, 0))[:keep]])
    return index


def _colour_gain(capture: GaussianModel, exposure: float, white_balance: float, rng: np.random.Generator) -> np.ndarray:
    """A capture's exposure and white-balance gains (linear RGB), applied to its SH DC in place;
    ones, with no random number drawn, when both are off."""
    gain = np.ones(3)
    if exposure > 0 or white_balance > 0:
        gain = 2.0 ** rng.uniform(-exposure, exposure) * np.array(
            [
                1.0 + rng.uniform(-white_balance, white_balance),
                1.0,
                1.0 + rng.uniform(-white_balance, white_balance),
            ]
        )
        capture.sh[:, 0, :] = _gained_dc(capture.sh[:, 0, :], gain)
    return gain


def _punch_holes(means: np.ndarray, index: np.ndarray, holes: int, extent: float, rng: np.random.Generator):
    """`index` less the Gaussians within `holes` balls (radius 4-10 % of the extent)
    centred on random Gaussians of it."""
    keep = np.ones(len(index), bool)
    for _ in range(holes):
        centre = means[index[rng.integers(len(index))]].astype(np.float64)
        radius = rng.uniform(0.04, 0.1) * extent
        keep &= np.sum((means[index].astype(np.float64) - centre) ** 2, axis=1) > radius**2
    return index[keep]


def _gained_dc(dc: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """SH DC coefficients of the colours under a linear-RGB gain (exposure, white balance)."""
    c = np.clip(sh_dc_to_rgb(dc.astype(np.float64)), 0.0, 1.0)
    return rgb_to_sh_dc(linear_to_srgb(srgb_to_linear(c) * gain)).astype(np.float32)
