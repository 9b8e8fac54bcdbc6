"""What real tools write: alpha exactly 0 or 1 (an infinite logit), scales of 0 or past float
range, PLY variants (no normals, extra properties, Mip-Splatting's filter_3D, big-endian, ASCII,
doubles, SH degree 0-3), SPZ v2/v3 with and without gzip, and the real captures in
../shared/data/real-dev/ (skipped only where that folder is absent)."""

from __future__ import annotations

import gzip
import math
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from benchmarks.formats_io import REORDERING
from gsa.cli import main
from gsa.io.formats import EXTENSIONS, FORMATS, read_model, write_model
from gsa.io.ply import ALPHA_EPS, LOG_SCALE_BOUND, PlyError, ReaderWarning, ply_property_names, read_ply
from gsa.model import GaussianModel
from gsa.synth import make_object

# CI and the development machines keep the shared data beside the repository (../shared/data).
REAL_DEV = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real-dev"
REAL_FILES = {"biker.spz": 152_746, "biker.compressed.ply": 152_746, "guitar.compressed.ply": 90_854}


def _read(path, **kw) -> tuple[GaussianModel, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = read_model(path, **kw)
    return model, [str(w.message) for w in caught if issubclass(w.category, ReaderWarning)]


# ------------------------------------------------------------------ extremes, every format
OPAQUE, CLEAR, HUGE, TINY, ZERO, PAST = (
    slice(0, 40),
    slice(40, 80),
    slice(80, 100),
    slice(100, 120),
    slice(120, 130),
    slice(130, 140),
)


@pytest.fixture(scope="module")
def extreme():
    """A model as exporters leave it: alpha exactly 1 and 0 (±Inf logits), huge and tiny
    scales, scales of exactly 0 on one axis (flat 2D splats), and scales past float range."""
    m = make_object("car", seed=5, n_gaussians=600, sh_degree=3)
    rng = np.random.default_rng(0)
    m = m.subset(rng.permutation(len(m)))  # extremes spread over the file, not only its first records
    op, ls = m.opacity_logits.copy(), m.log_scales.copy()
    op[OPAQUE], op[CLEAR] = np.inf, -np.inf
    ls[HUGE], ls[TINY] = 25.0, -25.0
    ls[ZERO, 2] = -np.inf
    ls[PAST] = 100.0
    m.opacity_logits, m.log_scales = op, ls
    return m


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_format_reads_back_at_extreme_values(extreme, tmp_path, fmt):
    path = write_model(extreme, tmp_path / f"m{EXTENSIONS[fmt]}", fmt)
    back, said = _read(path)
    assert len(back) == len(extreme)
    back.validate()  # finite everywhere
    # each read-back row's original index (SOG reorders the Gaussians)
    if fmt in REORDERING:  # by position (600 Gaussians lie far apart beside SOG's quantisation)
        dist, origin = cKDTree(extreme.means).query(back.means)
        assert len(set(origin)) == len(origin)
    else:
        origin = np.arange(len(extreme))
    alpha, log_s = back.opacities, back.log_scales.astype(np.float64)
    rows = lambda sel: np.isin(origin, np.arange(len(extreme))[sel])  # noqa: E731
    normal = ~(rows(OPAQUE) | rows(CLEAR) | rows(HUGE) | rows(TINY) | rows(ZERO) | rows(PAST))
    # Exactly 1 reads as 1 - 1e-6 wherever the format keeps it (SOG writes opacity ≥ 1/255)
    assert np.allclose(alpha[rows(OPAQUE)], 1 - ALPHA_EPS, atol=1e-6), fmt
    assert alpha[rows(CLEAR)].max() <= (1.01 / 255 if fmt == "sog" else ALPHA_EPS * 1.01), fmt
    assert said and "with opacity 0 or 1" in said[0], (fmt, said)
    assert len(said) == 1  # one warning line per file
    n_alpha = int(said[0].split(": ")[1].split()[0])
    assert n_alpha >= OPAQUE.stop - OPAQUE.start, said  # every fully opaque one counted
    # Huge stay bigger and tiny smaller than every ordinary Gaussian (formats clamp their range:
    # SPZ keeps log-scales in [-10, 6], compressed PLY in [-20, 20]).
    assert log_s[rows(HUGE)].min() > log_s[normal].max() and log_s[rows(TINY)].max() < log_s[normal].min(), fmt
    assert log_s.max() <= max(LOG_SCALE_BOUND, 100.0 if fmt == "ply" else 0) and log_s.min() >= -LOG_SCALE_BOUND
    # what was read writes and reads again the same way (no drift, no new warning about scales)
    again, _ = _read(write_model(back, tmp_path / f"again{EXTENSIONS[fmt]}", fmt))
    again.validate()
    assert np.allclose(np.sort(again.opacities), np.sort(alpha), atol=2 / 255)


def test_cli_reads_alpha_one_with_one_warning_line(extreme, tmp_path, capsys):
    src = write_model(extreme, tmp_path / "m.spz")
    assert main(["convert", str(src), str(tmp_path / "out.ply")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gsa: warning: ") and "opacity 0 or 1" in err[0], err
    assert main(["convert", str(tmp_path / "out.ply"), str(tmp_path / "out.glb")]) == 0
    assert capsys.readouterr().err == ""  # the PLY holds the clamped (finite) values


# ------------------------------------------------------------------ PLY variants
def _write_ply(path: Path, columns: dict[str, np.ndarray], *, fmt="binary_little_endian", types=None, crlf=False):
    """A PLY with exactly these vertex properties (float unless `types` says otherwise)."""
    types = types or {}
    n = len(next(iter(columns.values())))
    nl = "\r\n" if crlf else "\n"
    head = ["ply", f"format {fmt} 1.0", "comment written by a test", f"element vertex {n}"]
    head += [f"property {types.get(k, 'float')} {k}" for k in columns]
    head += ["end_header"]
    header = nl.join(head) + nl
    np_types = {"float": "f4", "double": "f8", "uchar": "u1"}
    if fmt == "ascii":
        body = "\n".join(" ".join(repr(float(columns[k][i])) for k in columns) for i in range(n)) + "\n"
        path.write_bytes(header.encode() + body.encode())
        return path
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(k, order + np_types[types.get(k, "float")]) for k in columns])
    table = np.empty(n, dtype)
    for k, v in columns.items():
        table[k] = v
    path.write_bytes(header.encode() + table.tobytes())
    return path


def _columns(m: GaussianModel, names: list[str]) -> dict[str, np.ndarray]:
    k = m.sh.shape[1]
    cols = {
        "x": m.means[:, 0],
        "y": m.means[:, 1],
        "z": m.means[:, 2],
        "nx": np.zeros(len(m)),
        "ny": np.zeros(len(m)),
        "nz": np.zeros(len(m)),
        "opacity": m.opacity_logits,
    }
    cols.update({f"f_dc_{c}": m.sh[:, 0, c] for c in range(3)})
    cols.update({f"f_rest_{c * (k - 1) + j - 1}": m.sh[:, j, c] for c in range(3) for j in range(1, k)})
    cols.update({f"scale_{i}": m.log_scales[:, i] for i in range(3)})
    cols.update({f"rot_{i}": m.quats[:, i] for i in range(4)})
    return {n: cols[n] for n in names}


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("variant", ["big-endian-doubles", "ascii-crlf", "no-normals-extra-colours"])
def test_ply_variants_read_like_the_inria_layout(tmp_path, degree, variant):
    m = make_object("chair", seed=2, n_gaussians=200, sh_degree=degree)
    names = ply_property_names(degree, 0)
    if variant == "big-endian-doubles":
        path = _write_ply(
            tmp_path / "m.ply",
            _columns(m, names),
            fmt="binary_big_endian",
            types={n: "double" for n in names if n.startswith(("x", "y", "z", "f_dc"))},
        )
    elif variant == "ascii-crlf":
        path = _write_ply(tmp_path / "m.ply", _columns(m, names), fmt="ascii", crlf=True)
    else:
        cols = _columns(m, [n for n in names if n not in ("nx", "ny", "nz")])
        rgb = (np.clip(m.base_colors, 0, 1) * 255).astype(np.uint8)
        cols.update({"red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]})
        path = _write_ply(tmp_path / "m.ply", cols, types={"red": "uchar", "green": "uchar", "blue": "uchar"})
    back, said = _read(path)
    assert said == [] and back.sh_degree == degree and len(back) == len(m)
    assert np.allclose(back.means, m.means, atol=1e-5) and np.allclose(back.sh, m.sh, atol=1e-5)
    assert np.allclose(back.opacity_logits, m.opacity_logits, atol=1e-5)
    assert np.allclose(np.abs((back.quats * m.quats).sum(1)), 1, atol=1e-5)


def test_ply_filter_3d_is_folded_in_as_mip_splatting_renders_it(tmp_path):
    m = make_object("chair", seed=2, n_gaussians=200, sh_degree=1)
    cols = _columns(m, ply_property_names(1, 0))
    filt = np.full(len(m), 0.01, np.float32)
    cols["filter_3D"] = filt
    back, said = _read(_write_ply(tmp_path / "mip.ply", cols))
    assert len(said) == 1 and "filter_3D" in said[0]
    s2 = m.scales**2
    assert np.allclose(back.scales, np.sqrt(s2 + 0.01**2), rtol=1e-5)
    coef = np.sqrt(np.prod(s2 / (s2 + 0.01**2), axis=1))
    assert np.allclose(back.opacities, m.opacities * coef, atol=1e-6)


def test_ply_infinite_values_are_clamped_and_nan_is_refused(tmp_path):
    m = make_object("chair", seed=2, n_gaussians=100, sh_degree=0)
    cols = _columns(m, ply_property_names(0, 0))
    cols["opacity"] = cols["opacity"].copy()
    cols["opacity"][:3] = [np.inf, -np.inf, np.inf]
    cols["scale_2"] = cols["scale_2"].copy()
    cols["scale_2"][5] = -np.inf
    back, said = _read(_write_ply(tmp_path / "inf.ply", cols))
    assert "3 Gaussian(s) with opacity 0 or 1" in said[0] and "1 Gaussian(s) with a scale of 0" in said[0]
    assert back.metadata["clamped"] == {"opacity": 3, "scale": 1}
    assert np.allclose(back.opacities[:3], [1 - ALPHA_EPS, ALPHA_EPS, 1 - ALPHA_EPS])
    assert back.log_scales[5, 2] == -LOG_SCALE_BOUND
    cols["opacity"][7] = np.nan
    with pytest.raises(PlyError, match="NaN or Inf in 1 Gaussian"):
        read_ply(_write_ply(tmp_path / "nan.ply", cols))


@pytest.mark.parametrize(
    "drop, message",
    [
        (["opacity"], "missing properties opacity"),
        (["rot_0", "rot_1", "rot_2", "rot_3"], "missing properties rot_0"),
        (["f_rest_5"], "f_rest_"),
    ],
)
def test_ply_without_3dgs_properties_is_one_clear_error(tmp_path, capsys, drop, message):
    m = make_object("chair", seed=2, n_gaussians=50, sh_degree=1)
    names = [n for n in ply_property_names(1, 0) if n not in drop]
    path = _write_ply(tmp_path / "bad.ply", _columns(m, names))
    with pytest.raises(PlyError, match=message):
        read_ply(path)
    assert main(["convert", str(path), str(tmp_path / "o.spz")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gsa: error: ") and message in err[0]


# ------------------------------------------------------------------ SPZ v2 and v3, gzipped or not
def _v3_to_v2(stream: bytes) -> bytes:
    """An SPZ v3 stream (inflated) as v2: rotations as 3 bytes of x, y, z (w ≥ 0) instead of
    v3's smallest-three 4 bytes; the rest of the layout is the same."""
    magic, version, n, degree, frac, flags, _ = struct.unpack_from("<IIIBBBB", stream, 0)
    assert version == 3
    rot_at = 16 + n * (9 + 1 + 3 + 3)
    packed = np.frombuffer(stream, "<u4", n, rot_at).astype(np.int64)
    quats = np.zeros((n, 4))  # x, y, z, w
    largest = packed >> 30
    rest = packed.copy()
    mask = (1 << 9) - 1
    for i in (3, 2, 1, 0):
        skip = largest == i
        mag = (rest & mask) / mask * math.sqrt(0.5)
        neg = (rest >> 9) & 1
        quats[~skip, i] = np.where(neg[~skip] == 1, -mag[~skip], mag[~skip])
        rest = np.where(skip, rest, rest >> 10)
    quats[np.arange(n), largest] = np.sqrt(np.clip(1 - (quats**2).sum(1), 0, 1))
    quats *= np.where(quats[:, 3] < 0, -1.0, 1.0)[:, None]
    xyz = np.clip(np.rint(quats[:, :3] * 127.5 + 127.5), 0, 255).astype(np.uint8)
    head = struct.pack("<IIIBBBB", magic, 2, n, degree, frac, flags, 0)
    return head + stream[16:rot_at] + xyz.tobytes() + stream[rot_at + 4 * n :]


def test_spz_v2_and_v3_read_with_or_without_gzip(tmp_path):
    m = make_object("car", seed=4, n_gaussians=500, sh_degree=2)
    m.opacity_logits[:5] = np.inf
    v3_gz = write_model(m, tmp_path / "v3.spz").read_bytes()
    v3 = gzip.decompress(v3_gz)
    assert struct.unpack_from("<I", v3, 4)[0] == 3
    v2 = _v3_to_v2(v3)
    reference, _ = _read(tmp_path / "v3.spz")
    for name, data in {"v3.raw.spz": v3, "v2.spz": gzip.compress(v2), "v2.raw.spz": v2}.items():
        (tmp_path / name).write_bytes(data)
        back, said = _read(tmp_path / name)
        assert back.metadata["format"] == "spz" and len(back) == len(m), name
        assert "5 Gaussian(s) with opacity 0 or 1" in said[0], (name, said)
        assert np.array_equal(back.means, reference.means) and np.array_equal(back.sh, reference.sh), name
        turn = np.degrees(2 * np.arccos(np.clip(np.abs((back.quats * reference.quats).sum(1, dtype=np.float64)), 0, 1)))
        if "v3" in name:
            assert turn.max() < 0.1, (name, turn.max())
        else:  # v2: x, y, z in 8 bits and w = √(1 − |xyz|²), coarse where w is near 0
            assert np.median(turn) < 1.0 and turn.max() < 15.0, (name, np.median(turn), turn.max())
    (tmp_path / "cut.spz").write_bytes(v3[: len(v3) // 2])
    with pytest.raises(PlyError, match="truncated"):
        read_model(tmp_path / "cut.spz")


# ------------------------------------------------------------------ real captures
def _real(name: str) -> Path:
    if not REAL_DEV.is_dir():
        pytest.skip(f"the shared real-capture folder {REAL_DEV} is absent (CI has it at ../shared/data)")
    return REAL_DEV / name


@pytest.mark.parametrize("name", sorted(REAL_FILES))
def test_real_captures_read_convert_and_read_back(name, tmp_path):
    model, said = _read(_real(name))
    assert len(model) == REAL_FILES[name] and model.sh_degree == 0
    model.validate()
    if name == "biker.spz":  # SPZ v4 (zstd, no gzip) with 198 Gaussians at alpha 255
        assert model.metadata["format"] == "spz" and "198 Gaussian(s) with opacity 0 or 1" in said[0]
    for fmt in ("ply", "spz", "glb"):
        back, _ = _read(write_model(model, tmp_path / f"out{EXTENSIONS[fmt]}", fmt))
        back.validate()
        assert len(back) == len(model)


def test_real_capture_in_two_formats_is_one_model():
    """biker.spz and biker.compressed.ply are one capture: same Gaussians, in their own axes
    (SPZ RUB, PLY RDF), both read into the internal frame, within both formats' quantisation."""
    spz, _ = _read(_real("biker.spz"))
    ply, _ = _read(_real("biker.compressed.ply"))
    dist, _ = cKDTree(ply.means).query(spz.means)
    diag = float(np.linalg.norm(np.ptp(ply.means, axis=0)))
    assert np.median(dist) / diag < 1e-3, np.median(dist) / diag
