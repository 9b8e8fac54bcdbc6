"""Object masks for image sets (Alg. 1 preprocessing), offline by default.

Backends:
  "key"     background keying: the border's median colour is the background; a pixel
            is foreground when its colour differs from it (uniform studio/turntable
            backgrounds). Weight-free and exact on plain backgrounds.
  "grabcut" OpenCV GrabCut seeded with the projected SfM points (probable/definite
            foreground) and the image border (definite background). Weight-free; for
            cluttered but object-centric captures.
  "auto"    "key" when the border looks uniform, else "grabcut".
  "sam"     Segment Anything exported to ONNX (encoder + decoder files), run with
            onnxruntime and prompted with the projected SfM points. Needs a local
            checkpoint; nothing is downloaded.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from gsa.errors import GSAError

METHODS = ("auto", "key", "grabcut", "sam", "none")


class MaskError(GSAError, RuntimeError):
    """The chosen mask backend cannot run (its checkpoints or runtime missing)."""


def border_pixels(image: np.ndarray, width: int = 4) -> np.ndarray:
    """(M, 3) pixels from a `width`-pixel frame around (H, W, 3) image."""
    return np.concatenate(
        [
            image[:width].reshape(-1, 3),
            image[-width:].reshape(-1, 3),
            image[:, :width].reshape(-1, 3),
            image[:, -width:].reshape(-1, 3),
        ]
    )


def border_is_uniform(image: np.ndarray, tol: float = 0.03) -> bool:
    """True when 95% of border pixels lie within `tol` (RGB distance) of their median."""
    b = border_pixels(image)
    d = np.linalg.norm(b - np.median(b, axis=0), axis=1)
    return bool(np.percentile(d, 95) < tol)


def _clean(mask: np.ndarray, min_fraction: float = 0.02) -> np.ndarray:
    """Open/close, fill holes, drop components smaller than min_fraction of the largest."""
    m = mask.astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, k)
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, k, iterations=2)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n > 1:
        areas = stats[1:, cv2.CC_STAT_AREA]
        keep = np.flatnonzero(areas >= min_fraction * areas.max()) + 1
        m = np.isin(lab, keep).astype(np.uint8)
    # Fill holes: background is what the border reaches through non-object pixels.
    inv = (1 - m).astype(np.uint8)
    n, lab = cv2.connectedComponents(inv, connectivity=4)
    edge = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    holes = (inv == 1) & ~np.isin(lab, edge)
    return m.astype(bool) | holes


def key_mask(image: np.ndarray, threshold: float = 0.06) -> np.ndarray:
    """(H, W) bool foreground by distance from the border's median colour."""
    bg = np.median(border_pixels(image), axis=0)
    d = np.linalg.norm(image - bg, axis=2)
    return _clean(d > threshold)


def grabcut_mask(
    image: np.ndarray, points2d: np.ndarray | None = None, border: int = 4, iterations: int = 5
) -> np.ndarray:
    """(H, W) bool GrabCut mask. points2d (K, 2) pixel x, y of object points (e.g. the
    SfM points seen in this image): their disks are definite foreground and their
    dilated convex hull probable foreground; the border strip is definite background."""
    h, w = image.shape[:2]
    gc = np.full((h, w), cv2.GC_PR_BGD, np.uint8)
    if points2d is not None and len(points2d) >= 3:
        p = np.round(points2d).astype(np.int32)
        p = p[(p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)]
    else:
        p = np.zeros((0, 2), np.int32)
    if len(p) >= 3:
        hull = cv2.convexHull(p)
        hull_img = np.zeros((h, w), np.uint8)
        cv2.fillConvexPoly(hull_img, hull, 1)
        hull_img = cv2.dilate(hull_img, np.ones((9, 9), np.uint8))
        gc[hull_img > 0] = cv2.GC_PR_FGD
        for x, y in p:
            cv2.circle(gc, (int(x), int(y)), 1, cv2.GC_FGD, -1)
    else:  # no seeds: assume an object-centric frame
        gc[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4] = cv2.GC_PR_FGD
    gc[:border], gc[-border:], gc[:, :border], gc[:, -border:] = (cv2.GC_BGD,) * 4
    img8 = (np.clip(image, 0, 1) * 255).astype(np.uint8)[..., ::-1].copy()
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(img8, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    return _clean((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD))


class SamOnnxMasker:
    """SAM (ONNX export: an image encoder taking a (1,3,1024,1024) normalised image and the
    official prompt decoder export) run with onnxruntime; prompts are object points.

    encoder_path, decoder_path: local .onnx files (`gsa reconstruct` also reads them from
    GSA_SAM_ENCODER / GSA_SAM_DECODER, see gsa.settings_env).
    """

    MEAN = np.array([123.675, 116.28, 103.53], np.float32)
    STD = np.array([58.395, 57.12, 57.375], np.float32)

    def __init__(self, encoder_path: str | None = None, decoder_path: str | None = None):
        if not encoder_path or not decoder_path:
            raise MaskError(
                "the SAM mask backend needs local ONNX files: pass sam_encoder/sam_decoder "
                "(gsa reconstruct: --sam-encoder/--sam-decoder or GSA_SAM_ENCODER and "
                "GSA_SAM_DECODER; nothing is downloaded)"
            )
        for p in (encoder_path, decoder_path):
            if not Path(p).is_file():
                raise MaskError(f"SAM checkpoint not found: {p}")
        try:
            import onnxruntime as ort
        except ImportError as exc:
            raise MaskError("the SAM mask backend needs onnxruntime (pip install onnxruntime)") from exc
        self.encoder = ort.InferenceSession(str(encoder_path), providers=["CPUExecutionProvider"])
        self.decoder = ort.InferenceSession(str(decoder_path), providers=["CPUExecutionProvider"])

    def __call__(self, image: np.ndarray, points2d: np.ndarray) -> np.ndarray:
        h, w = image.shape[:2]
        s = 1024.0 / max(h, w)
        nh, nw = int(round(h * s)), int(round(w * s))
        x = cv2.resize((image * 255).astype(np.float32), (nw, nh), interpolation=cv2.INTER_LINEAR)
        x = (x - self.MEAN) / self.STD
        pad = np.zeros((1024, 1024, 3), np.float32)
        pad[:nh, :nw] = x
        emb = self.encoder.run(None, {self.encoder.get_inputs()[0].name: pad.transpose(2, 0, 1)[None]})[0]
        pts = np.asarray(points2d, np.float32)
        if len(pts) > 16:  # a spread subset is a better prompt than hundreds of points
            pts = pts[np.linspace(0, len(pts) - 1, 16).astype(int)]
        coords = np.concatenate([pts, np.zeros((1, 2), np.float32)])[None] * s
        labels = np.concatenate([np.ones(len(pts), np.float32), -np.ones(1, np.float32)])[None]
        masks = self.decoder.run(
            None,
            {
                "image_embeddings": emb,
                "point_coords": coords.astype(np.float32),
                "point_labels": labels,
                "mask_input": np.zeros((1, 1, 256, 256), np.float32),
                "has_mask_input": np.zeros(1, np.float32),
                "orig_im_size": np.array([h, w], np.float32),
            },
        )[0]
        return _clean(masks[0, 0] > 0.0)


def project_points(points: np.ndarray, viewmat: np.ndarray, fx, fy, cx, cy, width, height) -> np.ndarray:
    """(P,3) world points -> (K,2) pixel coordinates of those in front and inside the image."""
    pc = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    ok = pc[:, 2] > 1e-6
    uv = np.stack([fx * pc[ok, 0] / pc[ok, 2] + cx, fy * pc[ok, 1] / pc[ok, 2] + cy], axis=1)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
    return uv[inside] - 0.5  # pixel centres at i + 0.5 -> array index coordinates


def compute_masks(
    images: np.ndarray,
    method: str = "auto",
    cameras=None,
    points: np.ndarray | None = None,
    sam: SamOnnxMasker | None = None,
) -> tuple[np.ndarray, list[str]]:
    """(C, H, W, 3) images -> (C, H, W) bool masks and the method used per image.

    cameras (gsa.render.Cameras) and points (P, 3) seed GrabCut/SAM with projected SfM points.
    """
    if method not in METHODS:
        raise ValueError(f"mask method must be one of {METHODS}, got {method!r}")
    if method == "sam" and sam is None:
        sam = SamOnnxMasker()
    out, used = [], []
    for i, img in enumerate(images):
        m = method
        if m == "auto":
            m = "key" if border_is_uniform(img) else "grabcut"
        pts = None
        if cameras is not None and points is not None and len(points):
            pts = project_points(
                points,
                cameras.viewmats[i],
                cameras.fx[i],
                cameras.fy[i],
                cameras.cx[i],
                cameras.cy[i],
                cameras.width,
                cameras.height,
            )
        if m == "none":
            mask = np.ones(img.shape[:2], bool)
        elif m == "key":
            mask = key_mask(img)
        elif m == "grabcut":
            mask = grabcut_mask(img, pts)
        else:
            if pts is None or len(pts) == 0:
                raise MaskError("the SAM backend needs SfM points to prompt with")
            mask = sam(img, pts)
        if mask.mean() < 1e-3:
            raise MaskError(f"image {i}: the {m} mask is empty; try another --masks method")
        out.append(mask)
        used.append(m)
    return np.stack(out), used
