"""Every 3DGS format: round trips within each format's quantisation, sniffing from the bytes,
axis conventions as the reference readers see them, and bad files as one error line."""

from __future__ import annotations

import gzip
import json
import struct

import numpy as np
import pytest

from benchmarks.formats_io import attribute_errors
from gsa.cli import FORMAT_CHOICES, main
from gsa.geometry import quat_multiply
from gsa.io.formats import EXTENSIONS, FORMATS, MAX_SH_DEGREE, ROUNDTRIP_BOUNDS, FormatError, read_model, write_model
from gsa.io.frames import RDF_TO_RUB
from gsa.io.ply import PlyError
from gsa.synth import make_object


@pytest.fixture(scope="module")
def model():
    return make_object("car", seed=3, n_gaussians=3000, sh_degree=3)


@pytest.fixture(scope="module")
def written(model, tmp_path_factory):
    d = tmp_path_factory.mktemp("formats")
    return {fmt: write_model(model, d / f"m{EXTENSIONS[fmt]}", fmt) for fmt in FORMATS}


def test_cli_format_choices_match_the_library():
    assert tuple(FORMAT_CHOICES) == FORMATS


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_stays_within_the_formats_quantisation(model, written, fmt):
    back = read_model(written[fmt])
    assert back.metadata["format"] == fmt
    assert len(back) == len(model)
    assert back.sh_degree == min(3, MAX_SH_DEGREE[fmt])
    errors = attribute_errors(model, back, fmt)
    bounds = ROUNDTRIP_BOUNDS[fmt]
    assert set(bounds) == set(errors) - {"position"}
    for name, bound in bounds.items():
        assert errors[name]["max"] <= bound, (fmt, name, errors[name])


@pytest.mark.parametrize("fmt", FORMATS)
def test_format_is_sniffed_from_the_bytes_not_the_name(written, tmp_path, fmt):
    misnamed = tmp_path / "model.ply" if fmt != "ply" else tmp_path / "model.spz"
    misnamed.write_bytes(written[fmt].read_bytes())
    assert read_model(misnamed).metadata["format"] == fmt


def test_spz_is_rub_as_niantics_reader_sees_it(model, written):
    gsply = pytest.importorskip("gsply")  # the dev extra installs it
    ref = gsply.read_spz(str(written["spz"]))
    expected = model.means @ RDF_TO_RUB.T  # x right, y up, z back
    assert np.abs(np.asarray(ref.means) - expected).max() < 5e-4
    back = read_model(written["spz"])
    assert np.abs(back.means - model.means).max() < 5e-4


def test_compressed_ply_opens_in_gsply(model, written):
    gsply = pytest.importorskip("gsply")
    ref = gsply.decompress_from_bytes(written["compressed-ply"].read_bytes())
    assert np.abs(np.asarray(ref.means) - model.means).max() < 2e-3 * np.ptp(model.means)
    assert np.abs(np.asarray(ref.shN) - model.sh[:, 1:]).max() < 0.017


def test_glb_opens_in_pygltflib_with_gltf_axes_and_xyzw(model, written):
    pygltflib = pytest.importorskip("pygltflib")
    gltf = pygltflib.GLTF2().load(str(written["glb"]))
    assert "KHR_gaussian_splatting" in gltf.extensionsUsed
    prim = gltf.meshes[0].primitives[0]
    assert prim.mode == 0 and prim.extensions["KHR_gaussian_splatting"]["kernel"] == "ellipse"
    blob = gltf.binary_blob()
    attrs = vars(prim.attributes)  # pygltflib keeps extension semantics as extra attributes

    def column(index, width):
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
        assert acc.count == len(model) and acc.componentType == pygltflib.FLOAT
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        return np.frombuffer(blob, "<f4", acc.count * width, start).reshape(-1, width)

    assert np.allclose(column(attrs["POSITION"], 3), model.means @ RDF_TO_RUB.T, atol=1e-6)
    # each Gaussian turned by the axis change, 180° about x: q' = (0, 1, 0, 0) ⊗ q (w, x, y, z)
    turned = quat_multiply(np.broadcast_to([0.0, 1.0, 0.0, 0.0], model.quats.shape), model.quats.astype(float))
    rot = column(attrs["KHR_gaussian_splatting:ROTATION"], 4)
    expected = turned[:, [1, 2, 3, 0]]  # glTF order: x, y, z, w
    assert np.allclose(np.abs((rot * expected).sum(1)), 1.0, atol=1e-5)


def test_ksplat_and_sog_open_in_gaussforges_own_reader(model, written):
    import gaussforge

    forge = gaussforge.GaussForge()
    for fmt, name in (("ksplat", "ksplat"), ("sog", "sog"), ("compressed-ply", "compressed.ply"), ("spz", "spz")):
        result = forge.read(written[fmt].read_bytes(), name)
        assert result.get("data", {}).get("numPoints") == len(model), (fmt, result.get("error"))


def test_splat_follows_the_antimatter15_layout(model, written):
    raw = written["splat"].read_bytes()
    assert len(raw) == 32 * len(model)
    x, y, z, sx, sy, sz = struct.unpack_from("<6f", raw, 0)
    r, g, b, a, qw, qx, qy, qz = struct.unpack_from("<8B", raw, 24)
    assert np.allclose([x, y, z], model.means[0], atol=1e-6)
    assert np.allclose([sx, sy, sz], np.exp(model.log_scales[0]), rtol=1e-5)
    assert abs(a / 255 - model.opacities[0]) <= 1 / 255
    assert np.allclose((np.array([qw, qx, qy, qz]) - 128) / 128, model.quats[0], atol=1 / 128)


def _truncate(path, dst, keep=0.5):
    data = path.read_bytes()
    dst.write_bytes(data[: max(1, int(len(data) * keep) - 7)])  # .splat has no header: cut mid-record


def _lie_about_count(fmt, path, dst):
    """The same file with a header that claims far more Gaussians than it holds."""
    data = bytearray(path.read_bytes())
    if fmt in ("ply", "compressed-ply"):
        head = bytes(data[:4096])
        dst.write_bytes(data.replace(b"element vertex 3000\n", b"element vertex 3000000\n", 1))
        assert head != bytes(dst.read_bytes()[:4096])
        return
    if fmt == "spz":
        raw = bytearray(gzip.decompress(bytes(data)))
        struct.pack_into("<I", raw, 8, 3_000_000)
        dst.write_bytes(gzip.compress(bytes(raw)))
        return
    if fmt == "ksplat":
        struct.pack_into("<II", data, 12, 3_000_000, 3_000_000)
    elif fmt == "glb":
        js_len = struct.unpack_from("<I", data, 12)[0]
        doc = bytes(data[20 : 20 + js_len]).replace(b'"count":3000', b'"count":9000')
        data[20 : 20 + js_len] = doc.ljust(js_len)[:js_len]
    elif fmt == "sog":
        data = data[: len(data) - 100]
    elif fmt == "splat":
        data = data[:-5]
    dst.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["truncated", "lying-header", "garbage-body"])
@pytest.mark.parametrize("fmt", FORMATS)
def test_bad_files_are_one_error_line(written, tmp_path, capsys, fmt, damage):
    bad = tmp_path / f"bad{EXTENSIONS[fmt]}"
    if damage == "truncated":
        _truncate(written[fmt], bad)
    elif damage == "lying-header":
        _lie_about_count(fmt, written[fmt], bad)
    else:
        data = bytearray(written[fmt].read_bytes())
        data[64:] = np.random.default_rng(0).integers(0, 256, len(data) - 64, dtype=np.uint8).tobytes()
        bad.write_bytes(bytes(data))
    with pytest.raises(PlyError):  # FormatError is a PlyError
        read_model(bad, max_gaussians=1_000_000)
    code = main(["convert", str(bad), str(tmp_path / "out.ply")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert len(err) == 1 and err[0].startswith("gsa: error: ") and str(bad) in err[0], err
    assert not (tmp_path / "out.ply").exists()


def test_convert_cli_chain_and_sh_degree(model, written, tmp_path, capsys):
    assert main(["convert", str(written["ply"]), str(tmp_path / "a.spz")]) == 0
    assert main(["convert", str(tmp_path / "a.spz"), str(tmp_path / "b.glb"), "--sh-degree", "1"]) == 0
    assert main(["convert", str(tmp_path / "b.glb"), str(tmp_path / "c.out"), "--format", "ply"]) == 0
    back = read_model(tmp_path / "c.out")
    assert back.metadata["format"] == "ply" and back.sh_degree == 1
    assert np.abs(back.means - model.means).max() < 5e-4
    assert main(["convert", str(written["ply"]), str(tmp_path / "c.unknown")]) == 1
    assert "--format" in capsys.readouterr().err


def test_empty_and_unknown_files(tmp_path):
    (tmp_path / "empty").write_bytes(b"")
    (tmp_path / "odd").write_bytes(b"\x07" * 33)
    with pytest.raises(FormatError, match="empty"):
        read_model(tmp_path / "empty")
    with pytest.raises(FormatError, match="not a PLY nor any other"):
        read_model(tmp_path / "odd")


def test_glb_node_transform_is_applied(model, written, tmp_path):
    data = bytearray(written["glb"].read_bytes())
    js_len = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(bytes(data[20 : 20 + js_len]))
    doc["nodes"][0]["translation"] = [1.0, 2.0, 3.0]
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    rest = bytes(data[20 + js_len :])
    out = (
        struct.pack("<4sII", b"glTF", 2, 20 + len(js) + len(rest)) + struct.pack("<II", len(js), 0x4E4F534A) + js + rest
    )
    (tmp_path / "moved.glb").write_bytes(out)
    back = read_model(tmp_path / "moved.glb")
    # +2 in glTF's y is -2 in the internal y (RDF), +3 in glTF's z is -3 internally
    assert np.allclose(back.means - model.means, [1.0, -2.0, -3.0], atol=1e-5)


@pytest.mark.parametrize("degree", [0, 1])
def test_low_sh_degrees_read_back_in_every_format(tmp_path, degree):
    """gaussforge 0.6.0's `read` fails on every SH-degree-0 model: decoded through its converter."""
    small = make_object("chair", seed=1, n_gaussians=500, sh_degree=degree)
    for fmt in FORMATS:
        back = read_model(write_model(small, tmp_path / f"m{EXTENSIONS[fmt]}", fmt))
        assert len(back) == len(small) and back.sh_degree == min(degree, MAX_SH_DEGREE[fmt]), fmt
        assert attribute_errors(small, back, fmt)["colour"]["max"] <= ROUNDTRIP_BOUNDS[fmt]["colour"], fmt


def test_arbitrary_bytes_of_a_multiple_of_32_are_not_a_splat(tmp_path):
    rng = np.random.default_rng(0)
    for i, junk in enumerate([b"\1" * (2 << 20), bytes(4096), rng.integers(0, 256, 1 << 16, dtype=np.uint8).tobytes()]):
        (tmp_path / f"junk{i}").write_bytes(junk)
        with pytest.raises(FormatError, match="not a PLY nor any other"):
            read_model(tmp_path / f"junk{i}")


def test_axis_flip_is_the_exact_rotation_by_180_degrees_about_x():
    from gsa.io.frames import flip_yz
    from gsa.sim3 import Sim3

    m = make_object("car", seed=1, n_gaussians=500, sh_degree=3)
    fast, general = flip_yz(m), m.transformed(Sim3(1.0, RDF_TO_RUB, np.zeros(3)))
    assert np.allclose(fast.means, general.means, atol=1e-6)
    assert np.allclose(np.abs((fast.quats * general.quats).sum(axis=1)), 1.0, atol=1e-6)
    assert np.allclose(fast.sh, general.sh, atol=1e-5)  # every SH band's signs
    assert np.array_equal(flip_yz(fast).means, m.means)  # its own inverse


@pytest.mark.parametrize("fmt", [f for f in FORMATS if f != "ply"])
def test_mutated_files_read_or_fail_with_one_format_error(written, tmp_path, fmt):
    """Random bit flips, cuts, insertions and header edits: a model or a PlyError, nothing else."""
    rng = np.random.default_rng(abs(hash(fmt)) % 2**32)
    original = written[fmt].read_bytes()
    for trial in range(25):
        data = bytearray(original)
        kind = trial % 4
        if kind == 0:
            for i in rng.integers(0, len(data), 20):
                data[i] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:
            data = data[: int(rng.integers(1, len(data)))]
        elif kind == 2:
            at = int(rng.integers(0, min(len(data), 4096)))
            data[at:at] = rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes()
        else:
            for i in rng.integers(0, min(len(data), 2048), 8):  # the header region
                data[i] = int(rng.integers(0, 256))
        path = tmp_path / f"m{trial}"
        path.write_bytes(bytes(data))
        try:
            model = read_model(path, max_gaussians=100_000)
        except PlyError:
            continue
        assert len(model) > 0 and np.isfinite(model.means).all()
