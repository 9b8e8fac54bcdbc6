"""Harder variants of generated 3DGS data, for the robustness benchmarks
(benchmarks.protocols: partial, noisy, symmetric, deform).

cut_by_plane           a capture that missed one side: a half-space removed
add_floaters           faint, brightly coloured floaters around the object
make_symmetric_object  k-fold rotationally symmetric geometry (k = 4..8) whose
                       colours break the symmetry on one sector
deform                 a cross-instance proxy: stretch, taper and bend
shift_exposure         the colours another camera or day would record: an exposure
                       and white-balance gain per channel in linear RGB

Everything is deterministic given the numpy Generator (or seed) passed in.
"""

from __future__ import annotations

import colorsys

import numpy as np

from gsa.geometry import axis_rotation, normalize_quats, rotation_distance_deg
from gsa.model import GaussianModel, merge_models
from gsa.sim3 import Sim3, solve_sim3
from gsa.synth.objects import _quats_from_normals
from gsa.synth.shapes import Cylinder, Primitive, RegularPrism, Torus, _frame

SYMMETRIC_FAMILIES = ("prism", "wheel", "bottle")


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ---------------------------------------------------------------- partial capture


def cut_by_plane(
    model: GaussianModel, rng: np.random.Generator, keep: tuple[float, float] = (0.6, 0.8)
) -> GaussianModel:
    """The model with the Gaussians on one side of a random plane removed.

    The plane's unit normal n is uniformly random; its offset is the quantile of
    the projections n·x that leaves a fraction, drawn uniformly in `keep`, of the
    Gaussians. Kept: n·x <= offset. metadata gains `cut_keep` (the drawn
    fraction), `cut_kept` (the fraction actually kept), `cut_normal` and
    `cut_offset` (the plane n·x = offset in the model's coordinates).
    """
    lo, hi = keep
    if not 0.0 < lo <= hi <= 1.0:
        raise ValueError(f"keep must be a range inside (0, 1], got {keep}")
    if len(model) == 0:
        raise ValueError("cannot cut an empty model")
    fraction = float(rng.uniform(lo, hi))
    normal = _unit(rng.normal(size=3))
    proj = model.means.astype(np.float64) @ normal
    offset = float(np.quantile(proj, fraction))
    mask = proj <= offset
    out = model.subset(mask)
    out.metadata.update(cut_keep=fraction, cut_kept=float(mask.mean()), cut_normal=normal.tolist(), cut_offset=offset)
    return out


# ---------------------------------------------------------------- floaters


def _bright_colors(rng: np.random.Generator, n: int, min_luminance: float = 0.5) -> np.ndarray:
    """Saturated colours of random hue, lifted towards white where needed so that
    every one has Rec. 709 luminance of at least `min_luminance`."""
    hue = rng.uniform(0, 1, n)
    sat = rng.uniform(0.6, 0.95, n)
    val = rng.uniform(0.9, 1.0, n)
    rgb = np.array([colorsys.hsv_to_rgb(h, s, v) for h, s, v in zip(hue, sat, val)]).reshape(n, 3)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    lift = np.clip((min_luminance - lum) / np.maximum(1 - lum, 1e-9), 0, 1)
    return rgb + lift[:, None] * (1 - rgb)


def add_floaters(
    model: GaussianModel,
    rng: np.random.Generator,
    fraction: float = 0.2,
    opacity: tuple[float, float] = (0.1, 0.3),
    box_scale: float = 1.5,
) -> GaussianModel:
    """The model plus round(fraction·len(model)) floaters, appended at the end.

    Floaters are uniform over the model's axis-aligned bounding box scaled by
    `box_scale` about its centre, with bright saturated colours, opacities
    uniform in `opacity`, random rotations, and sizes of the model's median
    Gaussian (its largest axis) times 0.5..2 (each axis 0.6..1 of that). The SH
    degree is the model's (floaters' higher SH rows are zero); if the model has
    features, each floater copies a random Gaussian's. metadata gains
    `floaters` (count), `floater_fraction` and `floater_box` (lo, hi corners).
    """
    if fraction < 0 or box_scale <= 0:
        raise ValueError("fraction must be >= 0 and box_scale > 0")
    n = round(fraction * len(model))
    means = model.means.astype(np.float64)
    lo, hi = means.min(0), means.max(0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * box_scale
    box = (centre - half, centre + half)
    meta = dict(model.metadata)
    meta.update(floaters=n, floater_fraction=float(fraction), floater_box=[box[0].tolist(), box[1].tolist()])
    if n == 0:
        out = model.subset(np.arange(len(model)))
        out.metadata = meta
        return out
    pos = rng.uniform(box[0], box[1], (n, 3))
    colors = _bright_colors(rng, n)
    size = float(np.median(model.scales.max(axis=1)))
    scales = size * rng.uniform(0.5, 2.0, (n, 1)) * rng.uniform(0.6, 1.0, (n, 3))
    quats = normalize_quats(rng.normal(size=(n, 4)))
    opac = rng.uniform(opacity[0], opacity[1], n)
    features = None if model.features is None else model.features[rng.integers(0, len(model), n)]
    floaters = GaussianModel.from_colors(
        pos, colors, quats=quats, scales=scales, opacities=opac, sh_degree=model.sh_degree, features=features
    )
    out = merge_models(model, floaters)
    out.metadata = meta
    return out


# ---------------------------------------------------------------- symmetric objects


def _hsv(h, s, v) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, s, v))


def symmetric_spec(seed: int) -> tuple[str, int]:
    """(family, k) of the symmetric instance `seed`: the family cycles with the
    seed (prism, wheel, bottle), k in 4..8 is drawn from it."""
    rng = np.random.default_rng([seed, 4271])
    return SYMMETRIC_FAMILIES[seed % len(SYMMETRIC_FAMILIES)], int(rng.integers(4, 9))


def _axis_angle_world(prim: RegularPrism, angle: float) -> float:
    """World angle about z of the direction at `angle` in the primitive's frame."""
    f = _frame(prim.axis)
    d = np.cos(angle) * f[0] + np.sin(angle) * f[1]
    return float(np.arctan2(d[1], d[0]))


def _symmetric_parts(seed: int) -> tuple[str, int, list[Primitive], float, np.ndarray]:
    """(family, k, parts, marked-sector angle, marker colour); axis z through the origin."""
    family, k = symmetric_spec(seed)
    rng = np.random.default_rng([seed, 4271, 1])
    hue = rng.uniform(0, 1)
    main = _hsv(hue, rng.uniform(0.35, 0.7), rng.uniform(0.55, 0.8))
    # The marker: a far hue, fully saturated, and a different brightness.
    marker = _hsv(hue + rng.uniform(0.35, 0.65), rng.uniform(0.85, 1.0), rng.uniform(0.85, 1.0))
    if np.linalg.norm(marker - main) < 0.45:
        marker = np.clip(1.0 - main, 0.02, 0.98)
    z = (0.0, 0.0, 1.0)
    parts: list[Primitive]
    if family == "prism":
        # A k-gon prism with a bevelled top (so no flip turns it onto itself:
        # the rotations about z are its only symmetries).
        r = rng.uniform(0.6, 1.2)
        height = 2 * r * (rng.uniform(0.3, 0.6) if rng.uniform() < 0.5 else rng.uniform(1.6, 2.4))
        bevel_h = height * rng.uniform(0.12, 0.25)
        top_r = r * rng.uniform(0.45, 0.75)
        body = RegularPrism((0, 0, 0), z, r, height, k, tuple(main), caps=(True, False))
        lid = RegularPrism(
            (0, 0, 0.5 * (height + bevel_h)), z, r, bevel_h, k, tuple(main * 0.85), top_radius=top_r, caps=(False, True)
        )
        parts = [body, lid]
        mark_angle = _axis_angle_world(body, body.face_angle(0))
    elif family == "wheel":
        # Tyre, k spokes and a hub that sticks out on one side (a dished wheel).
        big_r = rng.uniform(0.8, 1.2)
        tube = big_r * rng.uniform(0.08, 0.16)
        hub_r = big_r * rng.uniform(0.15, 0.25)
        hub_len = big_r * rng.uniform(0.25, 0.45)
        spoke_r = big_r * rng.uniform(0.025, 0.05)
        tyre_color = np.clip(_hsv(hue, 0.2, 0.15) + 0.05, 0, 1)
        hub = RegularPrism((0, 0, 0.35 * hub_len), z, hub_r, hub_len, k, tuple(main * 0.8))
        parts = [Torus((0, 0, 0), z, big_r, tube, tuple(tyre_color)), hub]
        inner, outer = hub_r * np.cos(np.pi / k) * 0.9, big_r - tube * 0.5
        for j in range(k):
            a = 2 * np.pi * j / k
            d = np.array([np.cos(a), np.sin(a), 0.0])
            parts.append(Cylinder(tuple(d * 0.5 * (inner + outer)), tuple(d), spoke_r, outer - inner, tuple(main)))
        mark_angle = 0.0  # spoke 0
    elif family == "bottle":
        body_r = rng.uniform(0.35, 0.6)
        body_h = rng.uniform(1.0, 1.8)
        shoulder_h = rng.uniform(0.2, 0.4)
        neck_r = body_r * rng.uniform(0.25, 0.4)
        neck_h = rng.uniform(0.2, 0.45)
        cap_h = rng.uniform(0.08, 0.15)
        zb = 0.0
        zs = zb + 0.5 * (body_h + shoulder_h)
        zn = zb + 0.5 * body_h + shoulder_h + 0.5 * neck_h
        zc = zb + 0.5 * body_h + shoulder_h + neck_h + 0.5 * cap_h
        cap_color = _hsv(hue + 0.5, 0.3, 0.35)
        body = RegularPrism((0, 0, zb), z, body_r, body_h, k, tuple(main), caps=(True, False))
        parts = [
            body,
            RegularPrism((0, 0, zs), z, body_r, shoulder_h, k, tuple(main), top_radius=neck_r, caps=(False, False)),
            RegularPrism((0, 0, zn), z, neck_r, neck_h, k, tuple(main), caps=(False, False)),
            Cylinder((0, 0, zc), z, neck_r * 1.15, cap_h, tuple(cap_color)),
        ]
        mark_angle = _axis_angle_world(body, body.face_angle(0))  # the label's face
    else:  # pragma: no cover - symmetric_spec only returns the families above
        raise ValueError(family)
    return family, k, parts, mark_angle, marker


def make_symmetric_object(
    seed: int = 0, n_gaussians: int = 20_000, sample_seed: int | None = None, sh_degree: int = 0
) -> GaussianModel:
    """A 3DGS model of an object with k-fold rotational symmetry (k = 4..8)
    about the z axis through the origin.

    seed fixes the instance: the family (prism, wheel or bottle, cycling with
    the seed), k and the proportions. The geometry is exactly k-fold symmetric;
    the colours are not: one angular sector of width 2π/k about the axis (a
    face of the prism, a spoke with its stretch of tyre, a bottle face as a
    label, each with everything else in that sector: 1/k of the surface) has a
    marker colour far from the rest. The shading pattern is itself k-fold
    symmetric, so the marker is the one cue that tells the k poses apart.

    Like make_object: uniform by area; sample_seed (defaults to seed) fixes
    where the Gaussians fall; the model is centred by the instance's shape, so
    two samplings of one instance share one frame (true relative pose identity).
    metadata: symmetry_axis, symmetry_center, symmetry_order (k), family,
    mark_angle (the marked sector's central angle about the axis, radians from
    +x towards +y), seed, sample_seed.
    """
    if n_gaussians < 1:
        raise ValueError("n_gaussians must be at least 1")
    family, k, parts, mark_angle, marker = _symmetric_parts(seed)
    rng = np.random.default_rng([seed if sample_seed is None else sample_seed, 7919, 4271])
    areas = np.array([p.area() for p in parts])
    counts = rng.multinomial(n_gaussians, areas / areas.sum())
    pts, nrm, col = [], [], []
    for part, c in zip(parts, counts):
        if c == 0:
            continue
        p, nr = part.sample(int(c), rng)
        pts.append(p)
        nrm.append(nr)
        col.append(np.broadcast_to(np.asarray(part.color, np.float64), (int(c), 3)))
    means, normals, colors = np.concatenate(pts), np.concatenate(nrm), np.concatenate(col)
    # Shape-based centre: on the axis by symmetry; along it, the area-weighted part centres.
    centers = np.array([np.asarray(p.center, np.float64) for p in parts])
    z0 = float((areas @ centers[:, 2]) / areas.sum())
    means = means - np.array([0.0, 0.0, z0])
    theta = np.arctan2(means[:, 1], means[:, 0])
    in_sector = np.abs(np.angle(np.exp(1j * (theta - mark_angle)))) < np.pi / k
    colors = np.where(in_sector[:, None], marker, colors)
    # k-fold symmetric shading (radius, height, cos kθ), so only the marker breaks the symmetry.
    radius = np.hypot(means[:, 0], means[:, 1])
    pattern = 0.06 * np.sin(5.3 * radius + 4.1 * means[:, 2]) + 0.04 * np.cos(k * theta)
    colors = np.clip(colors + pattern[:, None] + rng.normal(0, 0.02, colors.shape), 0, 1)
    spacing = np.sqrt(areas.sum() / n_gaussians)
    tangent = spacing * rng.uniform(0.6, 1.0, n_gaussians)
    scales = np.stack([tangent, tangent * rng.uniform(0.7, 1.0, n_gaussians), tangent * 0.08], axis=1)
    quats = _quats_from_normals(normals, rng)
    opac = rng.uniform(0.7, 0.99, n_gaussians)
    model = GaussianModel.from_colors(means, colors, quats=quats, scales=scales, opacities=opac, sh_degree=sh_degree)
    if sh_degree > 0:
        model.sh[:, 1:, :] = rng.normal(0, 0.05, model.sh[:, 1:, :].shape)
    model.metadata.update(
        category=f"symmetric-{family}",
        family=family,
        seed=seed,
        sample_seed=sample_seed,
        symmetry_axis=[0.0, 0.0, 1.0],
        symmetry_center=[0.0, 0.0, 0.0],
        symmetry_order=k,
        mark_angle=float(mark_angle),
    )
    return model


def symmetry_rotations(model: GaussianModel) -> list[np.ndarray]:
    """The k rotations about the model's symmetry axis (metadata of
    make_symmetric_object), identity first; [identity] without that metadata."""
    k = int(model.metadata.get("symmetry_order") or 1)
    axis = model.metadata.get("symmetry_axis", (0.0, 0.0, 1.0))
    return [axis_rotation(axis, 2 * np.pi * j / k) for j in range(k)]


# ---------------------------------------------------------------- deformation


def deform(
    model: GaussianModel, rng: np.random.Generator, stretch: float = 0.25, taper: float = 0.2, bend: float = 0.15
) -> GaussianModel:
    """A smoothly deformed copy, as a proxy for another instance of the category.

    About the centroid c of the means, in order:
    1. stretch: along the model's principal axes by factors with product 1
       (volume-preserving), each in [1/(1+stretch), 1+stretch];
    2. taper: along a random principal-ish axis a (a principal axis, tilted a
       little at random), the cross-section is scaled linearly from 1−taper at
       one end to 1+taper at the other;
    3. bend: one coordinate perpendicular to a is displaced by
       bend·extent·(2τ−1)², τ∈[0, 1] the position along a (extent: a's span);
    then the similarity that best maps the model onto its deformed copy (least
    squares over corresponding Gaussians) is undone, so that the identity is the
    natural alignment to the undeformed model: a taper or bend of an off-centre
    mass turns and scales the copy as a whole (up to 11° on a motorcycle), and a
    protocol judged against the identity would mark the best alignment wrong.

    Only positions change: quaternions, scales, opacities, SH and features are
    kept as they are (Gaussians are not re-oriented to the deformed surface).
    metadata gains `deform`: the factors, axes and amounts used.
    """
    if not (stretch >= 0 and 0 <= taper < 1 and bend >= 0):
        raise ValueError("need stretch >= 0, 0 <= taper < 1, bend >= 0")
    x = model.means.astype(np.float64)
    c = x.mean(0)
    x = x - c
    # principal axes (rows), largest variance first
    _, _, vt = np.linalg.svd(x - x.mean(0), full_matrices=False)
    axes = vt if len(x) >= 3 else np.eye(3)
    lim = np.log1p(stretch)
    while True:
        logs = rng.uniform(-lim, lim, 2)
        if abs(logs.sum()) <= lim:
            break
    factors = np.exp(rng.permutation(np.append(logs, -logs.sum())))
    x = ((x @ axes.T) * factors) @ axes
    # taper
    which = int(rng.integers(0, 3))
    a = _unit(axes[which] + rng.normal(0, 0.1, 3))
    if rng.uniform() < 0.5:
        a = -a
    t = x @ a
    span = max(float(t.max() - t.min()), 1e-12)
    tau = (t - t.min()) / span
    scale = (1 - taper) + 2 * taper * tau
    along = t[:, None] * a
    x = along + scale[:, None] * (x - along)
    # bend: a direction perpendicular to a
    b = rng.normal(size=3)
    b = _unit(b - (b @ a) * a)
    t = x @ a
    span = max(float(t.max() - t.min()), 1e-12)
    tau = (t - t.min()) / span
    x = x + (bend * span * (2 * tau - 1) ** 2)[:, None] * b
    original = model.means.astype(np.float64) - c
    implied = solve_sim3(original, x) if len(x) >= 3 else Sim3.identity()
    x = implied.inverse().apply(x) + c
    out = model.subset(np.arange(len(model)))
    out.means = np.ascontiguousarray(x, dtype=np.float32)
    out.metadata["deform"] = {
        "stretch_factors": factors.tolist(),
        "stretch_axes": axes.tolist(),
        "taper": float(taper),
        "taper_axis": a.tolist(),
        "bend": float(bend),
        "bend_direction": b.tolist(),
        "undone_rotation_deg": rotation_distance_deg(implied.rotation, np.eye(3)),
        "undone_scale": implied.scale,
    }
    return out


def random_exposure(rng: np.random.Generator, stops: float = 1.0, white_balance: float = 0.2) -> np.ndarray:
    """Per-channel linear-RGB gains of another capture: an exposure change of up to
    ±`stops` and a white-balance tilt of up to ±`white_balance` (log gain) per channel."""
    return 2.0 ** rng.uniform(-stops, stops) * np.exp(rng.uniform(-white_balance, white_balance, 3))


def shift_exposure(model: GaussianModel, gain) -> GaussianModel:
    """The model under another exposure and white balance (GaussianModel.with_exposure)."""
    return model.with_exposure(gain)
