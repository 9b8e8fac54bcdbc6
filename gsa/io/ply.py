"""INRIA 3DGS PLY files, optionally with Feature-3DGS `semantic_*` properties.

Reading memory-maps binary bodies and copies each column once into the model's
arrays, so a file is never held twice in memory. ASCII and big-endian bodies
are read too. Every problem is raised as one `PlyError` naming the file.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

import numpy as np

from gsa.model import GaussianModel, ModelError, sh_coeff_count

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
REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]  # fmt: skip


class PlyError(ValueError):
    """A file that is not a readable 3DGS PLY; the message names file and problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def _parse_header(
    path: Path, fh, comments: list[str] | None = None
) -> tuple[str, int, list[tuple[str, int, list[tuple[str, str]]]]]:
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
            if not elements:
                raise PlyError(path, f"header line {lineno}: property before any element")
            if tok[1] == "list":
                if len(tok) != 5:
                    raise PlyError(path, f"header line {lineno}: malformed list property {line!r}")
                elements[-1][2].append((tok[4], "list"))
                continue
            if len(tok) != 3 or tok[1] not in PLY_TYPES:
                raise PlyError(path, f"header line {lineno}: unknown property type in {line!r}")
            elements[-1][2].append((tok[2], PLY_TYPES[tok[1]]))
        else:
            raise PlyError(path, f"header line {lineno}: unexpected keyword {tok[0]!r}")
    if fmt is None:
        raise PlyError(path, "the header has no 'format' line")
    return fmt, header_len, elements


def _sh_and_feature_layout(path: Path, names: list[str]) -> tuple[int, int]:
    present = set(names)
    missing = [n for n in REQUIRED if n not in present]
    if missing:
        known = set(REQUIRED) | {"nx", "ny", "nz"}
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

    body = file_size - header_len
    if FORMATS[fmt] is not None:
        dtype = np.dtype([(n, FORMATS[fmt] + t) for n, t in props])
        need = count * dtype.itemsize
        if body < need:
            raise PlyError(
                path,
                f"truncated: the header declares {count} Gaussians ({need} bytes) but only {body} bytes of data follow",
            )
        if body > need and len(elements) == 1:
            raise PlyError(
                path,
                f"the header declares {count} Gaussians ({need} bytes) but {body} bytes of "
                f"data follow; the count in the header is wrong",
            )
        data = np.memmap(path, dtype=dtype, mode="r", offset=header_len, shape=(count,))
        uniform = all(t == props[0][1] for _, t in props)
        if uniform:
            # Fast path (the usual all-float file): a 2-D view, no per-field strides.
            flat = data.view(np.dtype(FORMATS[fmt] + props[0][1])).reshape(count, len(props))
            index = {n: i for i, n in enumerate(names)}

            def cols(keys: list[str]) -> np.ndarray:
                idx = [index[k] for k in keys]
                if idx == list(range(idx[0], idx[0] + len(idx))):
                    return flat[:, idx[0] : idx[0] + len(idx)].astype(np.float32)
                return flat[:, idx].astype(np.float32)
        else:

            def cols(keys: list[str]) -> np.ndarray:
                return np.stack([data[k].astype(np.float32) for k in keys], axis=1)
    else:
        table = _read_ascii(path, header_len, count, len(props))
        index = {n: i for i, n in enumerate(names)}

        def cols(keys: list[str]) -> np.ndarray:
            return table[:, [index[k] for k in keys]].astype(np.float32)

    k = sh_coeff_count(degree)
    sh = np.empty((count, k, 3), np.float32)
    sh[:, 0, :] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:
        rest = cols([f"f_rest_{i}" for i in range(3 * (k - 1))])
        sh[:, 1:, :] = rest.reshape(count, 3, k - 1).transpose(0, 2, 1)  # channel-major in file
    try:
        model = GaussianModel(
            means=cols(["x", "y", "z"]),
            quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
            log_scales=cols(["scale_0", "scale_1", "scale_2"]),
            opacity_logits=cols(["opacity"])[:, 0],
            sh=sh,
            features=cols([f"semantic_{i}" for i in range(feat_dim)]) if feat_dim else None,
        )
        model.validate(source="data")
    except ModelError as exc:
        raise PlyError(path, str(exc)) from None
    # Stored quaternions are unnormalised by convention; normalise once here.
    model.quats /= np.linalg.norm(model.quats, axis=1, keepdims=True)
    model.metadata["source_path"] = str(path)
    provenance = next((c.split()[1] for c in comments if c.startswith(FEATURES_COMMENT + " ")), None)
    if provenance and feat_dim:
        model.metadata["features"] = provenance
    return model


def _read_ascii(path: Path, header_len: int, count: int, nprops: int) -> np.ndarray:
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
    return values[:need].reshape(count, nprops)


def ply_property_names(degree: int, feature_dim: int) -> list[str]:
    """Vertex properties in the order INRIA's trainer writes them (+ semantic_*)."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (sh_coeff_count(degree) - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    names += [f"semantic_{i}" for i in range(feature_dim)]
    return names


def write_ply(model: GaussianModel, path: str | os.PathLike) -> Path:
    """Write a binary little-endian INRIA PLY atomically (temp file + rename)."""
    path = Path(path)
    n = len(model)
    k = model.sh.shape[1]
    names = ply_property_names(model.sh_degree, model.feature_dim)
    table = np.zeros((n, len(names)), np.float32)
    table[:, 0:3] = model.means
    table[:, 6:9] = model.sh[:, 0, :]
    col = 9
    if k > 1:
        table[:, col : col + 3 * (k - 1)] = model.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)
        col += 3 * (k - 1)
    table[:, col] = model.opacity_logits
    table[:, col + 1 : col + 4] = model.log_scales
    table[:, col + 4 : col + 8] = model.quats
    if model.feature_dim:
        table[:, col + 8 :] = model.features
    header = "ply\nformat binary_little_endian 1.0\n"
    provenance = model.metadata.get("features")
    if model.feature_dim and isinstance(provenance, str) and re.fullmatch(r"[\w:.\-]+", provenance):
        header += f"comment {FEATURES_COMMENT} {provenance}\n"
    header += f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(header.encode("ascii"))
            table.astype("<f4", copy=False).tofile(fh)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
