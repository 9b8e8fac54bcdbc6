"""Compressed PLY, .ksplat, SPZ and SOG through gaussforge (C++), with our own checks first;
SOG is written by our own encoder (gsa/io/sog.py), gaussforge's being superlinear.

gaussforge 0.6.0 reads and writes all four from and to bytes, 10-100× faster than gsply's
numba code on first use (no JIT). It reports most bad input as an error, but trusts the
counts in a header and crashes (SIGSEGV) on some corrupt SOG archives: each reader here
checks counts and sizes against the file and the caller's Gaussian limit first, and the
decode itself runs in a child process (gsa/io/packed_child.py), which also keeps its SPZ
debug line off our stdout.
"""

from __future__ import annotations

import gzip
import io
import json
import struct
import subprocess
import sys
import zipfile
import zlib

import numpy as np

from gsa.errors import GSAError
from gsa.model import GaussianModel, sh_coeff_count

GAUSSFORGE_NAMES = {"compressed-ply": "compressed.ply", "ksplat": "ksplat", "spz": "spz", "sog": "sog"}
SPZ_MAGIC = 0x5053474E  # "NGSP"
DECODE_TIMEOUT_S = 600


class PackedError(GSAError, ValueError):
    """A packed file gaussforge or our checks refuse."""


def _forge():
    import gaussforge  # lazy: a compiled extension only these formats need

    return gaussforge.GaussForge()


def check_header(fmt: str, data: bytes, max_gaussians: int) -> None:
    """Refuse counts beyond the limit and bodies shorter than their header says."""
    if fmt == "spz":
        _check_spz(data, max_gaussians)
    elif fmt == "ksplat":
        if len(data) < 4096:
            raise PackedError(f"truncated: a .ksplat header is 4096 bytes, the file has {len(data)}")
        max_sections, _, max_splats, splats = struct.unpack_from("<IIII", data, 4)
        if max(max_splats, splats) > max_gaussians:
            raise PackedError(f"{max(max_splats, splats)} Gaussians exceeds the limit of {max_gaussians}")
        if 4096 + max_sections * 1024 > len(data):
            raise PackedError(f"truncated: {max_sections} section headers declared, the file is too short")
    elif fmt == "sog":
        _check_sog(data, max_gaussians)
    elif fmt == "compressed-ply":
        _check_compressed_ply(data, max_gaussians)


def _check_spz(data: bytes, max_gaussians: int) -> None:
    gz = data[:4] != b"NGSP"  # SPZ v4 has a plain header and zstd sections
    try:
        head = zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(data, 16) if gz else data[:16]
    except zlib.error as exc:
        raise PackedError(f"the gzip stream is corrupt ({exc})") from None
    if len(head) < 16:
        raise PackedError("truncated: no complete SPZ header")
    magic, version, count, degree = struct.unpack_from("<IIIB", head, 0)
    if magic != SPZ_MAGIC:
        raise PackedError("not an SPZ stream (no NGSP magic)")
    if version not in (1, 2, 3, 4):
        raise PackedError(f"unsupported SPZ version {version}")
    if count > max_gaussians:
        raise PackedError(f"{count} Gaussians exceeds the limit of {max_gaussians}")
    if degree > 3:
        raise PackedError(f"SH degree {degree} in the header (0..3 exist)")
    per = 9 + 1 + 3 + 3 + (4 if version == 3 else 3) + 3 * (sh_coeff_count(degree) - 1)
    need = 16 + count * per
    if not gz and version <= 3 and len(data) < need:
        raise PackedError(
            f"truncated: the header declares {count} Gaussians ({need} bytes), the stream holds {len(data)}"
        )
    if gz and version <= 3:
        # The whole stream, at most one byte past what the header implies: a truncated or
        # corrupt stream is named here (gaussforge says only "std::bad_cast"), and a stream
        # that would inflate far beyond its header's count is never inflated.
        inflater = zlib.decompressobj(16 + zlib.MAX_WBITS)
        try:
            got = len(inflater.decompress(data, need + (1 << 20)))
        except zlib.error as exc:
            raise PackedError(f"the gzip stream is corrupt ({exc})") from None
        if got < need:
            raise PackedError(
                f"truncated: the header declares {count} Gaussians ({need} bytes), the stream holds {got}"
            )
        if not inflater.eof and inflater.unconsumed_tail:
            raise PackedError(f"the stream inflates beyond the {need} bytes its header declares")


def _check_sog(data: bytes, max_gaussians: int) -> None:
    from gsa.ziparchive import ZipArchiveError, check_local_headers

    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            meta = json.loads(zf.read("meta.json"))
            unpacked = sum(i.file_size for i in zf.infolist())
            # gaussforge may read by the local headers where zipfile reads by the directory
            check_local_headers(io.BytesIO(data), [i for i in zf.infolist() if not i.is_dir()], "the archive")
    except ZipArchiveError as exc:
        raise PackedError(str(exc).removeprefix("the archive: ")) from None
    except (zipfile.BadZipFile, KeyError, OSError, ValueError, EOFError) as exc:
        raise PackedError(f"not a readable SOG archive ({exc})") from None
    count = meta.get("count", meta.get("means", {}).get("shape", [0])[0]) if isinstance(meta, dict) else 0
    if not isinstance(count, int) or count > max_gaussians:
        raise PackedError(f"meta.json declares {count!r} Gaussians (limit {max_gaussians})")
    if unpacked > (4 << 20) + 200 * max(count, 1):  # images of ≤ 4 bytes per texel per property, codebooks
        raise PackedError(f"the archive unpacks to {unpacked} bytes, far more than {count} Gaussians need")


def _check_compressed_ply(data: bytes, max_gaussians: int) -> None:
    from gsa.io.ply import MAX_HEADER_BYTES, PLY_TYPES

    end = data.find(b"end_header\n", 0, MAX_HEADER_BYTES)
    if end < 0:
        raise PackedError("no 'end_header' line")
    need, vertices = end + len(b"end_header\n"), 0
    size = current = 0
    lists = False  # a list property's rows have their lengths in the body: the total is not known
    for line in data[:end].decode("ascii", "replace").splitlines():
        tok = line.split()
        lists |= tok[:2] == ["property", "list"]
        if tok[:1] == ["element"] and len(tok) == 3 and tok[2].isdigit():
            count = int(tok[2])
            vertices = count if tok[1] == "vertex" else vertices
            need += size
            size = 0
            current = count
        elif tok[:1] == ["property"] and len(tok) == 3 and tok[1] in PLY_TYPES:
            size += current * np.dtype(PLY_TYPES[tok[1]]).itemsize
    need += size
    if vertices > max_gaussians:
        raise PackedError(f"{vertices} Gaussians exceeds the limit of {max_gaussians}")
    if len(data) < need:
        raise PackedError(f"truncated: the header declares {need} bytes, the file has {len(data)}")
    if len(data) > need and not lists:
        raise PackedError(
            f"the header declares {need} bytes ({vertices} Gaussians) but the file has {len(data)}; "
            "a count in the header is wrong"
        )


def decode(fmt: str, data: bytes) -> GaussianModel:
    """Decoded by gaussforge's converter to an INRIA PLY, in a child process, then parsed here
    (values still unchecked). Its `read` returns a dict of arrays but fails with std::bad_cast
    on every SH-degree-0 model (0.6.0); `convert` has no such gap. The child: some corrupt SOG
    archives crash gaussforge (SIGSEGV) — tests/test_formats.py mutates files of every format."""
    if fmt == "spz" and data[:4] == b"NGSP" and struct.unpack_from("<I", data, 4)[0] <= 3:
        # An SPZ v1-v3 stream saved without its gzip wrapper (v4 has none): gaussforge reads
        # v1-v3 only gzipped, so wrap it (level 1: seconds at most).
        data = gzip.compress(data, compresslevel=1)
    proc = subprocess.run(
        [sys.executable, "-m", "gsa.io.packed_child", GAUSSFORGE_NAMES[fmt]],
        input=data,
        capture_output=True,
        timeout=DECODE_TIMEOUT_S,
    )
    if proc.returncode < 0:
        raise PackedError(f"the decoder crashed on this file (signal {-proc.returncode}): corrupt data")
    if proc.returncode != 0:
        message = proc.stderr.decode("utf-8", "replace").strip().splitlines()
        raise PackedError(message[-1] if message else f"the decoder failed (exit {proc.returncode})")
    return parse_float_ply(proc.stdout)


def parse_float_ply(ply: bytes) -> GaussianModel:
    """An all-float binary little-endian 3DGS PLY held in memory (gaussforge's output)."""
    from gsa.io.ply import REQUIRED

    end = ply.find(b"end_header\n")
    if not ply.startswith(b"ply\n") or end < 0:
        raise PackedError("the decoder produced no PLY header")
    lines = ply[:end].decode("ascii", "replace").splitlines()
    count = next((int(ln.split()[2]) for ln in lines if ln.startswith("element vertex ")), 0)
    names = [ln.split()[2] for ln in lines if ln.startswith("property float ")]
    if count <= 0:
        raise PackedError("the file holds zero Gaussians")
    if any(n not in names for n in REQUIRED):
        raise PackedError("the decoder's output lacks 3DGS properties")
    body = end + len(b"end_header\n")
    if len(ply) - body < count * len(names) * 4:
        raise PackedError("the decoder's output is shorter than its header")
    table = np.frombuffer(ply, "<f4", count * len(names), body).reshape(count, len(names))
    index = {n: i for i, n in enumerate(names)}

    def cols(keys: list[str]) -> np.ndarray:
        return table[:, [index[k] for k in keys]]

    rest = sum(1 for n in names if n.startswith("f_rest_"))
    k = 1 + rest // 3
    if k not in (1, 4, 9, 16):
        raise PackedError(f"{rest} SH coefficients match no degree 0..3")
    sh = np.empty((count, k, 3), np.float32)
    sh[:, 0] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:  # channel-major in a PLY
        sh[:, 1:] = cols([f"f_rest_{i}" for i in range(rest)]).reshape(count, 3, k - 1).transpose(0, 2, 1)
    return GaussianModel(
        means=cols(["x", "y", "z"]),
        quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]),
        log_scales=cols(["scale_0", "scale_1", "scale_2"]),
        opacity_logits=cols(["opacity"])[:, 0],
        sh=sh,
    )


def encode(fmt: str, model: GaussianModel) -> bytes:
    if fmt == "sog":  # gaussforge's SOG writer is superlinear (200 s for 100k Gaussians)
        from gsa.io.sog import encode_sog

        return encode_sog(model)
    n = len(model)
    sh_rest = model.sh[:, 1:]
    if fmt == "compressed-ply":
        # gaussforge 0.6.0 writes compressed PLY from channel-major SH while its other writers
        # and all its readers use coefficient-major (checked against gsply's reader).
        sh_rest = sh_rest.transpose(0, 2, 1)
    ir = {
        "numPoints": n,
        "positions": model.means.astype("<f4").tobytes(),
        "scales": model.log_scales.astype("<f4").tobytes(),
        "rotations": (model.quats / np.linalg.norm(model.quats, axis=1, keepdims=True)).astype("<f4").tobytes(),
        "alphas": model.opacity_logits.astype("<f4").tobytes(),
        "colors": np.ascontiguousarray(model.sh[:, 0]).astype("<f4").tobytes(),
        "sh": np.ascontiguousarray(sh_rest).astype("<f4").tobytes(),
        "extras": {},
        "meta": {"shDegree": model.sh_degree, "sourceFormat": "ply"},
    }
    result = _forge().write(ir, GAUSSFORGE_NAMES[fmt])
    if "error" in result:
        raise PackedError(f"gaussforge cannot write {fmt}: {result['error']}")
    return result["data"]
