"""INRIA 3DGS PLY files, optionally with Feature-3DGS `semantic_*` properties.

Reading fills the model's arrays from the binary body in chunks of rows (one reused buffer of
CHUNK_BYTES), and writing builds the file's rows chunk by chunk, so a 5M-Gaussian file is held
once in memory (the model's arrays), never twice (python -m benchmarks.ply_memory). ASCII and big-endian bodies
are read too, extra properties (normals, colours, ...) are ignored, and Mip-Splatting's `filter_3D`
is folded into the scales and opacities. Every problem is raised as one `PlyError` naming the file.

What real exporters write but the model cannot hold is changed on read and said in one
`ReaderWarning` per file (the CLI prints it as one `gsa: warning:` line): an infinite opacity
logit (alpha stored as exactly 1 or 0) becomes ±MAX_OPACITY_LOGIT, an infinite log-scale (a
scale of 0, or one past float range) ±LOG_SCALE_BOUND (`clamp_infinite`, used by every reader).
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gsa.errors import GSAError
from gsa.io.atomic import mkstemp_for
from gsa.model import ROW_BLOCK, GaussianModel, ModelError, sh_coeff_count

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
MAX_HEADER_BYTES = 1 << 16
# Header comment recording where the semantic_* features came from (GaussianModel.metadata["features"]).
FEATURES_COMMENT = "gsa_features"
DEFAULT_MAX_GAUSSIANS = 50_000_000
# Bodies are read and written in chunks of rows of about this size, so a model of millions of
# Gaussians is held once (its arrays) plus one chunk, never a whole second copy.
CHUNK_BYTES = 16 << 20
# Alpha is read within [ALPHA_EPS, 1 − ALPHA_EPS]: exporters store exactly 0 and 1, whose logit
# is infinite. The bound is float32-safe (its logit, ±13.8, and back round-trip) and below any
# 8-bit format's step, so a clamped Gaussian still writes as alpha 0 or 255.
ALPHA_EPS = 1e-6
MAX_OPACITY_LOGIT = float(np.log((1.0 - ALPHA_EPS) / ALPHA_EPS))
# An infinite log-scale is read as ±LOG_SCALE_BOUND (scales e^±30: their squares, the
# covariances, stay normal float32 numbers). Finite values are kept as the file has them.
LOG_SCALE_BOUND = 30.0
REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip


class ReaderWarning(UserWarning):
    """A model file read with values changed so that the model can hold them; the message
    names the file and says what changed (one line)."""


class PlyError(GSAError, ValueError):
    """A file that is not a readable 3DGS PLY; the message names file and problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def _clamp_infinite(model: GaussianModel, name: str, bound: float) -> int:
    """±Inf in the array `name` of `model` become ±bound (block by block, copying a read-only
    memory map first); returns how many Gaussians (rows) held one."""
    count = 0
    for lo in range(0, len(model), ROW_BLOCK):
        block = getattr(model, name)[lo : lo + ROW_BLOCK]
        inf = np.isinf(block)
        if inf.any():
            if not getattr(model, name).flags.writeable:
                setattr(model, name, getattr(model, name).copy())
                block = getattr(model, name)[lo : lo + ROW_BLOCK]
            block[inf] = np.copysign(bound, block[inf])
            count += int(inf.reshape(len(block), -1).any(axis=1).sum())
    return count


def clamp_infinite(model: GaussianModel, path: str | os.PathLike, *, clamped_opacity: int = 0) -> dict[str, int]:
    """Make infinite opacity logits and log-scales finite, in place, and warn once.

    ±Inf opacity logits (alpha exactly 1 or 0) become ±MAX_OPACITY_LOGIT and ±Inf log-scales
    ±LOG_SCALE_BOUND; NaN stays (validate refuses it). `clamped_opacity`: Gaussians whose alpha
    a decoder already clamped (formats that store alpha, not its logit). Returns the counts
    ({"opacity": n, "scale": m}, Gaussians), also kept in metadata["clamped"] when not zero."""
    n_opacity = int(clamped_opacity) + _clamp_infinite(model, "opacity_logits", MAX_OPACITY_LOGIT)
    n_scale = _clamp_infinite(model, "log_scales", LOG_SCALE_BOUND)
    counts = {"opacity": n_opacity, "scale": n_scale}
    if n_opacity or n_scale:
        model.metadata["clamped"] = counts
        parts = []
        if n_opacity:
            parts.append(
                f"{n_opacity} Gaussian(s) with opacity 0 or 1 (an infinite logit) read as "
                f"{ALPHA_EPS:g} or 1 - {ALPHA_EPS:g}"
            )
        if n_scale:
            parts.append(
                f"{n_scale} Gaussian(s) with a scale of 0 or past float range read as "
                f"e^-{LOG_SCALE_BOUND:g} or e^{LOG_SCALE_BOUND:g}"
            )
        warnings.warn(f"{path}: {'; '.join(parts)}", ReaderWarning, stacklevel=2)
    return counts


def _parse_header(
    path: Path, fh, comments: list[str] | None = None
) -> tuple[str, int, list[tuple[str, int, list[tuple[str, str]]]]]:
    lines, header_len = _header_lines(path, fh)
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for lineno, line in enumerate(lines[1:-1], start=2):
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            if comments is not None and tok and tok[0] == "comment":
                comments.append(line[len("comment") :].strip())
            continue
        if tok[0] == "format":
            if len(tok) != 3 or tok[1] not in FORMATS:
                raise PlyError(path, f"header line {lineno}: unknown format {line!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise PlyError(path, f"header line {lineno}: malformed element line {line!r}")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            _add_property(path, lineno, line, tok, elements)
        else:
            raise PlyError(path, f"header line {lineno}: unexpected keyword {tok[0]!r}")
    if fmt is None:
        raise PlyError(path, "the header has no 'format' line")
    return fmt, header_len, elements


def _header_lines(path: Path, fh) -> tuple[list[str], int]:
    """The header's lines ('ply' to 'end_header') and its length in bytes."""
    head = fh.read(MAX_HEADER_BYTES)
    if not head.startswith(b"ply"):
        raise PlyError(path, "not a PLY file (it does not start with 'ply')")
    end = re.search(rb"end_header\r?\n", head)
    if end is None:
        raise PlyError(path, f"no 'end_header' line within the first {MAX_HEADER_BYTES} bytes")
    header_len = end.end()
    try:
        lines = head[:header_len].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise PlyError(path, "the header is not ASCII text") from None
    return lines, header_len


def _add_property(
    path: Path, lineno: int, line: str, tok: list[str], elements: list[tuple[str, int, list[tuple[str, str]]]]
) -> None:
    """A 'property' header line, added to the last element (a list property as type "list")."""
    if not elements:
        raise PlyError(path, f"header line {lineno}: property before any element")
    if len(tok) > 1 and tok[1] == "list":
        if len(tok) != 5:
            raise PlyError(path, f"header line {lineno}: malformed list property {line!r}")
        elements[-1][2].append((tok[4], "list"))
        return
    if len(tok) != 3 or tok[1] not in PLY_TYPES:
        raise PlyError(path, f"header line {lineno}: unknown property type in {line!r}")
    elements[-1][2].append((tok[2], PLY_TYPES[tok[1]]))


def _sh_and_feature_layout(path: Path, names: list[str]) -> tuple[int, int]:
    present = set(names)
    missing = [n for n in REQUIRED if n not in present]
    if missing:
        known = set(REQUIRED) | {"nx", "ny", "nz", "filter_3D"}
        unknown = [n for n in names if n not in known and not re.fullmatch(r"(f_rest|semantic)_\d+", n)]
        hint = f"; unrecognised properties: {', '.join(unknown[:8])}" if unknown else ""
        raise PlyError(path, f"not a 3DGS PLY: missing properties {', '.join(missing)}{hint}")
    rest = sorted(int(n[7:]) for n in names if re.fullmatch(r"f_rest_\d+", n))
    if rest != list(range(len(rest))):
        raise PlyError(path, "f_rest_* properties are not numbered 0..n-1 without gaps")
    degree = next((d for d in range(4) if 3 * (sh_coeff_count(d) - 1) == len(rest)), None)
    if degree is None:
        raise PlyError(path, f"{len(rest)} f_rest_* properties match no SH degree 0..3 (0, 9, 24 or 45)")
    sem = sorted(int(n[9:]) for n in names if re.fullmatch(r"semantic_\d+", n))
    if sem != list(range(len(sem))):
        raise PlyError(path, "semantic_* properties are not numbered 0..D-1 without gaps")
    return degree, len(sem)


def read_ply(path: str | os.PathLike, *, max_gaussians: int = DEFAULT_MAX_GAUSSIANS) -> GaussianModel:
    """Read a 3DGS PLY (binary little/big endian or ASCII) into a GaussianModel."""
    path = Path(path)
    try:
        file_size = path.stat().st_size
        fh = open(path, "rb")
    except OSError as exc:
        raise PlyError(path, f"cannot open: {exc.strerror or exc}") from None
    comments: list[str] = []
    with fh:
        fmt, header_len, elements = _parse_header(path, fh, comments)
    count, props, degree, feat_dim = _vertex_layout(path, elements, max_gaussians)
    names = [n for n, _ in props]
    k = sh_coeff_count(degree)
    index = {n: i for i, n in enumerate(names)}
    chunks = _data_chunks(path, fmt, header_len, file_size - header_len, elements, index)

    # The model's arrays are allocated once and filled chunk by chunk (assignment converts
    # double / big-endian columns in place), so reading holds one copy of the data plus a chunk.
    means = np.empty((count, 3), np.float32)
    quats = np.empty((count, 4), np.float32)
    log_scales = np.empty((count, 3), np.float32)
    opacity = np.empty(count, np.float32)
    sh = np.empty((count, k, 3), np.float32)
    features = np.empty((count, feat_dim), np.float32) if feat_dim else None
    rest_keys = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    feat_keys = [f"semantic_{i}" for i in range(feat_dim)]
    filter_3d = np.empty(count, np.float32) if "filter_3D" in index else None
    for lo, hi, cols in chunks:
        means[lo:hi] = cols(["x", "y", "z"])
        quats[lo:hi] = cols(["rot_0", "rot_1", "rot_2", "rot_3"])
        log_scales[lo:hi] = cols(["scale_0", "scale_1", "scale_2"])
        opacity[lo:hi] = cols(["opacity"])[:, 0]
        sh[lo:hi, 0, :] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
        if k > 1:  # channel-major in the file
            sh[lo:hi, 1:, :] = cols(rest_keys).reshape(hi - lo, 3, k - 1).transpose(0, 2, 1)
        if features is not None:
            features[lo:hi] = cols(feat_keys)
        if filter_3d is not None:
            filter_3d[lo:hi] = cols(["filter_3D"])[:, 0]
    try:
        model = GaussianModel(
            means=means, quats=quats, log_scales=log_scales, opacity_logits=opacity, sh=sh, features=features
        )
        clamp_infinite(model, path)
        if filter_3d is not None:
            _apply_3d_filter(path, model, filter_3d)
        model.validate(source="data")
    except ModelError as exc:
        raise PlyError(path, str(exc)) from None
    # Stored quaternions are unnormalised by convention; normalise once here (in place).
    for lo in range(0, count, ROW_BLOCK):
        q = model.quats[lo : lo + ROW_BLOCK]
        q /= np.linalg.norm(q, axis=1, keepdims=True)
    model.metadata["source_path"] = str(path)
    provenance = next((c.split()[1] for c in comments if c.startswith(FEATURES_COMMENT + " ")), None)
    if provenance and feat_dim:
        model.metadata["features"] = provenance
    return model


def _vertex_layout(
    path: Path, elements: list[tuple[str, int, list[tuple[str, str]]]], max_gaussians: int
) -> tuple[int, list[tuple[str, str]], int, int]:
    """The vertex element checked as 3DGS: (count, properties, SH degree, feature dim)."""
    if not elements or elements[0][0] != "vertex":
        raise PlyError(path, "the first element must be 'vertex' (the Gaussians)")
    _, count, props = elements[0]
    names = [n for n, _ in props]
    if any(t == "list" for _, t in props):
        raise PlyError(path, "the vertex element has list properties; 3DGS vertices are scalar")
    if len(set(names)) != len(names):
        raise PlyError(path, "the vertex element repeats a property name")
    degree, feat_dim = _sh_and_feature_layout(path, names)
    if count == 0:
        raise PlyError(path, "the file holds zero Gaussians")
    if count > max_gaussians:
        raise PlyError(path, f"{count} Gaussians exceeds the limit of {max_gaussians}")
    return count, props, degree, feat_dim


def _data_chunks(
    path: Path,
    fmt: str,
    header_len: int,
    body: int,
    elements: list[tuple[str, int, list[tuple[str, str]]]],
    index: dict[str, int],
):
    """The vertex data as (lo, hi, cols) chunks; cols(keys) -> the rows' columns named keys.
    body: the bytes after the header, checked against the count for binary files."""
    _, count, props = elements[0]
    if FORMATS[fmt] is None:
        table = _read_ascii(path, header_len, count, len(props), _scalar_values(elements))
        return iter([(0, count, lambda keys: table[:, [index[key] for key in keys]])])
    dtype = np.dtype([(n, FORMATS[fmt] + t) for n, t in props])
    check_body_length(path, body, elements)
    return _binary_chunks(path, header_len, dtype, count, props, index)


def _scalar_values(elements: list[tuple[str, int, list[tuple[str, str]]]]) -> int | None:
    """Values (ASCII) the header's elements hold in all, or None when one has a list property
    (its rows' lengths are in the body)."""
    if any(t == "list" for _, _, props in elements for _, t in props):
        return None
    return sum(n * len(props) for _, n, props in elements)


def check_body_length(path: Path, body: int, elements: list[tuple[str, int, list[tuple[str, str]]]]) -> None:
    """A binary body's length against the header's counts (the reader's rule, and the service's at
    upload): fewer bytes than the vertex rows need is truncated; more than every element needs
    (known when none has a list property) means a count in the header is wrong. Either way the
    header and the body disagree on how many Gaussians there are: refused, never read in part."""
    _, count, props = elements[0]
    row = sum(np.dtype(t).itemsize for _, t in props)
    need = count * row
    if body < need:
        raise PlyError(
            path,
            f"truncated: the header declares {count} Gaussians ({need} bytes) but only {body} bytes of data "
            f"follow ({body // row} Gaussians' worth)",
        )
    if any(t == "list" for _, _, p in elements for _, t in p):
        return
    total = sum(n * sum(np.dtype(t).itemsize for _, t in p) for _, n, p in elements)
    if body > total:
        held = f" ({body // row} Gaussians' worth)" if len(elements) == 1 else ""
        raise PlyError(
            path,
            f"the header declares {count} Gaussians ({total} bytes in all) but {body} bytes of "
            f"data follow{held}; the count in the header is wrong",
        )


def _apply_3d_filter(path: Path, model: GaussianModel, filter_3d: np.ndarray) -> None:
    """Fold Mip-Splatting's 3D smoothing filter into the model, in place, as its renderer
    does: scales s → √(s² + f²), alpha × √(Π s² / Π (s² + f²)). The result is a plain 3DGS."""
    if not np.isfinite(filter_3d).all() or (filter_3d < 0).any():
        raise PlyError(path, "filter_3D holds negative, NaN or Inf values")
    for lo in range(0, len(model), ROW_BLOCK):
        rows = slice(lo, lo + ROW_BLOCK)
        s2 = np.exp(2.0 * model.log_scales[rows].astype(np.float64))
        f2 = np.square(filter_3d[rows].astype(np.float64))[:, None]
        filtered = s2 + f2
        with np.errstate(divide="ignore", invalid="ignore"):
            coef = np.sqrt(np.prod(s2 / filtered, axis=1))
        alpha = coef / (1.0 + np.exp(-model.opacity_logits[rows].astype(np.float64)))
        alpha = np.clip(np.nan_to_num(alpha), ALPHA_EPS, 1.0 - ALPHA_EPS)
        model.opacity_logits[rows] = np.log(alpha / (1.0 - alpha))
        model.log_scales[rows] = 0.5 * np.log(filtered)
    model.metadata["filter_3D"] = "applied"
    warnings.warn(
        f"{path}: Mip-Splatting's filter_3D folded into the scales and opacities of {len(model)} Gaussians",
        ReaderWarning,
        stacklevel=3,
    )


def _binary_chunks(path: Path, header_len: int, dtype: np.dtype, count: int, props, index: dict[str, int]):
    """(first row, end row, columns getter) per chunk of about CHUNK_BYTES of the body, read
    into one reused buffer: no memory map, whose touched pages would count as a second copy."""
    rows = max(1, min(count, CHUNK_BYTES // dtype.itemsize))
    buf = np.empty(rows, dtype)
    raw = buf.view(np.uint8)
    uniform = all(t == props[0][1] for _, t in props)
    with open(path, "rb") as fh:
        fh.seek(header_len)
        for lo in range(0, count, rows):
            hi = min(count, lo + rows)
            nbytes = (hi - lo) * dtype.itemsize
            if fh.readinto(raw[:nbytes]) != nbytes:  # the file shrank after its size was checked
                raise PlyError(path, f"truncated: the body ended within the last {count - lo} Gaussians")
            part = buf[: hi - lo]
            if uniform:
                # The usual all-float file: a 2-D view; a run of properties is a slice, not a copy.
                flat = part.view(dtype[0]).reshape(hi - lo, len(props))
                yield lo, hi, lambda keys, flat=flat: _slice(flat, [index[key] for key in keys])
            else:
                yield lo, hi, lambda keys, part=part: np.stack([part[key] for key in keys], axis=1)


def _slice(flat: np.ndarray, idx: list[int]) -> np.ndarray:
    if idx == list(range(idx[0], idx[0] + len(idx))):
        return flat[:, idx[0] : idx[0] + len(idx)]
    return flat[:, idx]


def _read_ascii(path: Path, header_len: int, count: int, nprops: int, total: int | None) -> np.ndarray:
    """The vertex rows of an ASCII body; `total`: the values every element holds, when known
    (more values than that mean the header's count is wrong)."""
    with open(path, "rb") as fh:
        fh.seek(header_len)
        text = fh.read()
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise PlyError(path, "the ASCII body holds a value that is not a number") from None
    need = count * nprops
    if values.size < need:
        raise PlyError(
            path,
            f"truncated: the header declares {count} Gaussians but the ASCII body holds "
            f"only {values.size // nprops} complete rows",
        )
    if total is not None and values.size > total:
        raise PlyError(
            path,
            f"the header declares {count} Gaussians but the ASCII body holds {values.size} values "
            f"({values.size // nprops} rows' worth); the count in the header is wrong",
        )
    return values[:need].reshape(count, nprops)


def ply_property_names(degree: int, feature_dim: int) -> list[str]:
    """Vertex properties in the order INRIA's trainer writes them (+ semantic_*)."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (sh_coeff_count(degree) - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    names += [f"semantic_{i}" for i in range(feature_dim)]
    return names


def write_ply(
    model: GaussianModel | Sequence[GaussianModel],
    path: str | os.PathLike,
    *,
    keep: tuple[np.ndarray | None, ...] | None = None,
) -> Path:
    """Write a binary little-endian INRIA PLY atomically (temp file + rename).

    A sequence of models is written as their concatenation under gsa.model.merge_models's
    rules (SH padded to the highest degree; features kept when all have one dimension;
    `keep` selects each model's rows) without building it: a merged scene model is written
    from its parts, chunk by chunk, holding no copy of them (gsa.merge.merge_plan)."""
    path = Path(path)
    models = [model] if isinstance(model, GaussianModel) else list(model)
    if not models:
        raise ValueError("write_ply needs at least one model")
    keep = keep or (None,) * len(models)
    if len(keep) != len(models):
        raise ValueError(f"{len(keep)} row selections for {len(models)} models")
    rows_of = [None if sel is None else np.asarray(sel) for sel in keep]
    rows_of = [r if r is None or r.dtype != bool else np.flatnonzero(r) for r in rows_of]
    counts = [len(m) if r is None else len(r) for m, r in zip(models, rows_of)]
    degree = max(m.sh_degree for m in models)
    dims = {m.feature_dim for m in models}
    feature_dim = dims.pop() if len(dims) == 1 else 0
    names = ply_property_names(degree, feature_dim)
    header = "ply\nformat binary_little_endian 1.0\n"
    provenances = {m.metadata.get("features") for m in models}
    provenance = provenances.pop() if len(provenances) == 1 else None
    if feature_dim and isinstance(provenance, str) and re.fullmatch(r"[\w:.\-]+", provenance):
        header += f"comment {FEATURES_COMMENT} {provenance}\n"
    header += f"element vertex {sum(counts)}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = mkstemp_for(path)  # 0666 & ~umask, not mkstemp's 0600
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(header.encode("ascii"))
            rows = max(1, CHUNK_BYTES // (4 * len(names)))
            table = np.zeros((min(rows, max(counts)), len(names)), "<f4")  # normals stay 0
            for m, idx, count in zip(models, rows_of, counts):
                for lo in range(0, count, rows):
                    hi = min(count, lo + rows)
                    sel = slice(lo, hi) if idx is None else idx[lo:hi]
                    part = _rows(m, sel, hi - lo, degree, feature_dim, table)
                    fh.write(memoryview(part).cast("B"))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _rows(model: GaussianModel, sel, n: int, degree: int, feature_dim: int, table: np.ndarray) -> np.ndarray:
    """The model's Gaussians `sel` (a slice or indices, n of them) as the file's rows with SH
    padded to `degree`, in (the first n rows of) the reused `table`."""
    k, km = sh_coeff_count(degree), model.sh.shape[1]
    out = table[:n]
    out[:, 0:3] = model.means[sel]
    out[:, 6:9] = model.sh[sel, 0, :]
    col = 9
    if k > 1:  # channel-major in the file: f_rest_{c·(k-1) + j-1} is channel c, coefficient j
        if km < k:
            out[:, col : col + 3 * (k - 1)] = 0  # bands this model lacks (the table is reused)
        for c in range(3):
            out[:, col + c * (k - 1) : col + c * (k - 1) + km - 1] = model.sh[sel, 1:, c]
        col += 3 * (k - 1)
    out[:, col] = model.opacity_logits[sel]
    out[:, col + 1 : col + 4] = model.log_scales[sel]
    out[:, col + 4 : col + 8] = model.quats[sel]
    if feature_dim:
        out[:, col + 8 :] = model.features[sel]
    return out
