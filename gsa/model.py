"""The 3D Gaussian Splatting model as plain arrays.

Storage follows the INRIA conventions so that files round-trip losslessly:
quaternions are w,x,y,z, scales are logs, opacities are logits, and the
spherical-harmonic coefficients are kept per Gaussian as (K, 3) with
K = (degree + 1)**2 and coefficient 0 the DC term.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from gsa.colour import linear_to_srgb, srgb_to_linear
from gsa.errors import GSAError
from gsa.geometry import normalize_quats, quat_multiply, quat_to_rotation, rotation_to_quat
from gsa.render import steps
from gsa.sh import rgb_to_sh_dc, rotate_sh, sh_dc_to_rgb

# Rows per block where whole-model work is done block by block to bound its temporaries.
ROW_BLOCK = 1 << 18


def _bad_rows(block: np.ndarray) -> int:
    finite = np.isfinite(block)
    return 0 if finite.all() else int((~finite).reshape(len(block), -1).any(axis=1).sum())


class ModelError(GSAError, ValueError):
    """A GaussianModel whose arrays are inconsistent or not finite."""


def sh_coeff_count(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_count(count: int) -> int:
    degree = int(round(np.sqrt(count))) - 1
    if degree < 0 or (degree + 1) ** 2 != count or degree > 3:
        raise ModelError(f"{count} SH coefficients per channel is not a degree 0..3 layout")
    return degree


# Feature provenances (metadata["features"], PLY comment "gsa_features") whose values are
# coordinates in the model's own canonical frame rather than properties of the surface.
FRAME_RELATIVE_FEATURES = ("canonical", "lifted:canonical")


# Gaussians per block of surface_normals' rotation pass (a progress report between blocks).
NORMALS_BLOCK = 500_000


@dataclass
class GaussianModel:
    """N Gaussians.

    means: (N, 3) float32; quats: (N, 4) float32 unit w,x,y,z;
    log_scales: (N, 3) float32; opacity_logits: (N,) float32;
    sh: (N, K, 3) float32 with K in {1, 4, 9, 16};
    features: optional (N, D) float32 per-Gaussian feature vectors (GSA uses D = 3).
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray
    features: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)

    @property
    def features_frame_relative(self) -> bool:
        """True when the features are canonical coordinates in this model's own frame
        (metadata "features" = "canonical" or "lifted:canonical", as written by
        `gsa.features` and `gsa reconstruct`): two such models' features are not comparable
        point for point, because each frame carries its own axis labelling and error."""
        return self.metadata.get("features") in FRAME_RELATIVE_FEATURES

    def __post_init__(self) -> None:
        self.means = np.ascontiguousarray(self.means, dtype=np.float32)
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32)
        self.opacity_logits = np.ascontiguousarray(self.opacity_logits, dtype=np.float32).reshape(-1)
        self.sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        if self.features is not None:
            self.features = np.ascontiguousarray(self.features, dtype=np.float32)
            if self.features.ndim == 1:
                self.features = self.features[:, None]
        self._check_shapes()

    def _check_shapes(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "log_scales": (self.log_scales, (n, 3)),
            "opacity_logits": (self.opacity_logits, (n,)),
        }
        for name, (arr, shape) in expected.items():
            if arr.shape != shape:
                raise ModelError(f"{name} has shape {arr.shape}, expected {shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ModelError(f"sh has shape {self.sh.shape}, expected ({n}, K, 3)")
        sh_degree_from_count(self.sh.shape[1])
        if self.features is not None and (self.features.ndim != 2 or self.features.shape[0] != n):
            raise ModelError(f"features has shape {self.features.shape}, expected ({n}, D)")

    # ------------------------------------------------------------------ views
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_count(self.sh.shape[1])

    @property
    def feature_dim(self) -> int:
        return 0 if self.features is None else int(self.features.shape[1])

    @property
    def opacities(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))

    @property
    def scales(self) -> np.ndarray:
        return np.exp(self.log_scales.astype(np.float64))

    @property
    def base_colors(self) -> np.ndarray:
        """(N, 3) view-independent RGB from the DC coefficient, clipped to [0, 1]."""
        return np.clip(sh_dc_to_rgb(self.sh[:, 0, :]), 0.0, 1.0)

    def surface_normals(self, rows: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) unit normals, (N,) flatness in [0, 1]) of the Gaussians at `rows`: a
        3DGS surface Gaussian is a flat disc whose shortest axis is the surface normal;
        flatness = 1 − shortest/middle scale says how far that axis can be trusted
        (0 for a ball, whose shortest axis is arbitrary)."""
        scales = self.log_scales[rows].astype(np.float64)
        order = np.argsort(scales, axis=1)
        quats = self.quats[rows]
        # In blocks, a due progress report (gsa.align.pair._Repeater) before each: on 3M
        # Gaussians the whole pass ran 2 s without one, an embedded cancel's wait.
        normals = np.empty((len(quats), 3))
        for start in range(0, len(quats), NORMALS_BLOCK):
            block = slice(start, start + NORMALS_BLOCK)
            steps.step()
            rot = quat_to_rotation(normalize_quats(quats[block].astype(np.float64)))
            normals[block] = np.take_along_axis(rot, order[block, None, :1], axis=2)[:, :, 0]
        steps.step()
        ranked = np.take_along_axis(scales, order, axis=1)
        flatness = 1.0 - np.exp(ranked[:, 0] - ranked[:, 1])
        return normals, flatness

    # ------------------------------------------------------------ constructors
    @classmethod
    def from_colors(
        cls,
        means: np.ndarray,
        colors: np.ndarray,
        *,
        quats: np.ndarray | None = None,
        scales: np.ndarray | None = None,
        opacities: np.ndarray | float = 0.9,
        sh_degree: int = 0,
        features: np.ndarray | None = None,
    ) -> GaussianModel:
        """Build a model from RGB colours in [0, 1] and linear scales/opacities."""
        n = len(means)
        if quats is None:
            quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1))
        if scales is None:
            scales = np.full((n, 3), 0.01, np.float32)
        op = np.clip(np.broadcast_to(np.asarray(opacities, np.float64), (n,)), 1e-6, 1 - 1e-6)
        sh = np.zeros((n, sh_coeff_count(sh_degree), 3), np.float32)
        sh[:, 0, :] = rgb_to_sh_dc(np.asarray(colors, np.float64))
        return cls(
            means=means,
            quats=normalize_quats(quats),
            log_scales=np.log(np.maximum(np.asarray(scales, np.float64), 1e-12)),
            opacity_logits=np.log(op / (1 - op)),
            sh=sh,
            features=features,
        )

    # ------------------------------------------------------------- operations
    def validate(self, source: str = "model") -> None:
        """Raise ModelError if the model is empty or holds NaN/Inf."""
        if len(self) == 0:
            raise ModelError(f"{source}: the model has zero Gaussians")
        # In blocks of rows: whole-array temporaries (a mask as large as the SH, the squares
        # of every quaternion) would add a fifth of a large model to the peak memory.
        blocks = range(0, len(self), ROW_BLOCK)
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh", "features"):
            arr = getattr(self, name)
            if arr is None:
                continue
            bad = sum(_bad_rows(arr[lo : lo + ROW_BLOCK]) for lo in blocks)
            if bad:
                raise ModelError(f"{source}: {name} holds NaN or Inf in {bad} Gaussian(s)")
        zero = sum(int((np.linalg.norm(self.quats[lo : lo + ROW_BLOCK], axis=1) < 1e-12).sum()) for lo in blocks)
        if zero:
            raise ModelError(f"{source}: {zero} Gaussian(s) have a zero quaternion")

    def subset(self, index: np.ndarray) -> GaussianModel:
        """The Gaussians selected by a boolean mask or an index array."""
        return GaussianModel(
            means=self.means[index],
            quats=self.quats[index],
            log_scales=self.log_scales[index],
            opacity_logits=self.opacity_logits[index],
            sh=self.sh[index],
            features=None if self.features is None else self.features[index],
            metadata=dict(self.metadata),
        )

    def with_features(self, features: np.ndarray | None) -> GaussianModel:
        # The old features' provenance does not describe the new ones; the caller sets it.
        meta = {k: v for k, v in self.metadata.items() if k != "features"}
        return replace(self, features=features, metadata=meta)

    def with_exposure(self, gain) -> GaussianModel:
        """The model as a camera with other exposure and white balance would record it:
        base colours (SH DC, taken as sRGB) multiplied by `gain` per channel in linear RGB
        and clipped at white, as a sensor saturates; the view-dependent SH bands scaled by
        each Gaussian's DC ratio per channel. metadata gains `exposure_gain`."""
        gain = np.broadcast_to(np.asarray(gain, np.float64), (3,))
        if not np.all(gain > 0):
            raise ValueError("exposure gains must be positive")
        old = self.base_colors.astype(np.float64)
        new = linear_to_srgb(srgb_to_linear(old) * gain)
        sh = self.sh.copy()
        sh[:, 0, :] = rgb_to_sh_dc(new)
        if sh.shape[1] > 1:
            ratio = np.where(old > 1e-3, new / np.maximum(old, 1e-3), 1.0)
            sh[:, 1:, :] *= ratio[:, None, :].astype(sh.dtype)
        return replace(self, sh=sh, metadata=dict(self.metadata) | {"exposure_gain": gain.tolist()})

    def with_sh_degree(self, degree: int) -> GaussianModel:
        """Truncate or zero-pad the SH coefficients to `degree`."""
        k = sh_coeff_count(degree)
        sh = np.zeros((len(self), k, 3), np.float32)
        keep = min(k, self.sh.shape[1])
        sh[:, :keep] = self.sh[:, :keep]
        return replace(self, sh=sh, metadata=dict(self.metadata))

    def transformed(self, sim3) -> GaussianModel:
        """This model mapped by a similarity transform x -> s R x + t.

        Means, log-scales (+ log s), rotations (q_R ⊗ q) and SH bands 1..3
        (rotated exactly) change; opacities, DC colours and features do not.
        """
        rot = np.asarray(sim3.rotation, np.float64)
        q_r = rotation_to_quat(rot)
        log_s = np.log(sim3.scale)
        n = len(self)
        means = np.empty((n, 3), np.float32)
        quats = np.empty((n, 4), np.float32)
        log_scales = np.empty((n, 3), np.float32)
        sh = np.empty(self.sh.shape, np.float32)
        # Block by block: the float64 intermediates (the SH bands above all) of a whole
        # 2M-Gaussian SH-3 model would be about twice the model again.
        for lo in range(0, n, ROW_BLOCK):
            hi = min(n, lo + ROW_BLOCK)
            means[lo:hi] = sim3.apply(self.means[lo:hi].astype(np.float64))
            q = quat_multiply(np.broadcast_to(q_r, (hi - lo, 4)), self.quats[lo:hi].astype(np.float64))
            quats[lo:hi] = normalize_quats(q)
            log_scales[lo:hi] = self.log_scales[lo:hi].astype(np.float64) + log_s
            sh[lo:hi] = rotate_sh(self.sh[lo:hi], rot)
        meta = dict(self.metadata)
        if hasattr(meta.get("photo_anchors"), "transformed"):  # they lie in the model's frame
            meta["photo_anchors"] = meta["photo_anchors"].transformed(sim3)
        return GaussianModel(
            means=means,
            quats=quats,
            log_scales=log_scales,
            opacity_logits=self.opacity_logits,
            sh=sh,
            features=self.features,
            metadata=meta,
        )


def merge_models(*models: GaussianModel, keep: tuple[np.ndarray | None, ...] | None = None) -> GaussianModel:
    """Concatenate models. SH is padded to the highest degree; features are kept
    when every model has them with one dimension, else dropped for all. `keep` (one
    boolean mask or index array per model, None for all) selects the rows taken from each.

    The result's arrays are allocated once and filled block by block, so merging two
    scene-size models holds the result and no concatenated or padded intermediates."""
    if not models:
        raise ModelError("merge needs at least one model")
    keep = keep or (None,) * len(models)
    if len(keep) != len(models):
        raise ModelError(f"{len(keep)} row selections for {len(models)} models")
    # Whole models are copied by slices (no index arrays, no gathered temporaries).
    rows = [None if sel is None else np.asarray(sel) for sel in keep]
    rows = [r if r is None or r.dtype != bool else np.flatnonzero(r) for r in rows]
    k = sh_coeff_count(max(m.sh_degree for m in models))
    dims = {m.feature_dim for m in models}
    keep_features = len(dims) == 1 and 0 not in dims
    counts = [len(m) if r is None else len(r) for m, r in zip(models, rows)]
    n = sum(counts)
    out = {
        "means": np.empty((n, 3), np.float32),
        "quats": np.empty((n, 4), np.float32),
        "log_scales": np.empty((n, 3), np.float32),
        "opacity_logits": np.empty(n, np.float32),
    }
    sh = np.zeros((n, k, 3), np.float32)  # bands a model lacks stay zero
    features = np.empty((n, dims.pop()), np.float32) if keep_features else None
    lo = 0
    for m, idx, count in zip(models, rows, counts):
        mk = m.sh.shape[1]
        for a in range(0, count, ROW_BLOCK):
            block = slice(a, min(count, a + ROW_BLOCK)) if idx is None else idx[a : a + ROW_BLOCK]
            at = slice(lo + a, lo + min(count, a + ROW_BLOCK))
            for name, arr in out.items():
                arr[at] = getattr(m, name)[block]
            sh[at, : min(k, mk)] = m.sh[block, : min(k, mk)]
            if features is not None:
                features[at] = m.features[block]
        lo += count
    return GaussianModel(sh=sh, features=features, **out)
