import numpy as np
import pytest

from gsa.io.ply import PlyError, ply_property_names, read_ply, write_ply
from gsa.model import GaussianModel
from gsa.sim3 import Sim3


def _assert_same(a: GaussianModel, b: GaussianModel):
    assert np.allclose(a.means, b.means)
    assert np.allclose(a.quats, b.quats, atol=1e-6)
    assert np.allclose(a.log_scales, b.log_scales)
    assert np.allclose(a.opacity_logits, b.opacity_logits)
    assert np.allclose(a.sh, b.sh)
    assert (a.features is None) == (b.features is None)
    if a.features is not None:
        assert np.allclose(a.features, b.features)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_any_degree_with_features(tmp_path, car_model, degree):
    m = car_model.with_sh_degree(degree).with_features(np.random.default_rng(0).random((len(car_model), 3)))
    _assert_same(m, read_ply(write_ply(m, tmp_path / "m.ply")))


def test_feature_provenance_round_trips_as_a_header_comment(tmp_path, car_model):
    m = car_model.with_features(np.zeros((len(car_model), 3)))
    m.metadata["features"] = "lifted:spheremap"
    back = read_ply(write_ply(m, tmp_path / "m.ply"))
    assert back.metadata["features"] == "lifted:spheremap"
    assert not back.features_frame_relative
    assert "features" not in back.with_features(np.ones((len(m), 3))).metadata  # stale provenance dropped
    plain = read_ply(write_ply(car_model, tmp_path / "plain.ply"))
    assert "features" not in plain.metadata


def test_header_uses_inria_names_and_order(tmp_path, car_model):
    path = write_ply(car_model, tmp_path / "m.ply")
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(45)]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert props == expected == ply_property_names(3, 0)
    assert "format binary_little_endian 1.0" in header


def _write_custom(path, model, fmt):
    names = ply_property_names(model.sh_degree, model.feature_dim)
    table = np.zeros((len(model), len(names)))
    table[:, 0:3] = model.means
    table[:, 6:9] = model.sh[:, 0]
    k = model.sh.shape[1]
    table[:, 9 : 9 + 3 * (k - 1)] = model.sh[:, 1:].transpose(0, 2, 1).reshape(len(model), -1)
    c = 9 + 3 * (k - 1)
    table[:, c] = model.opacity_logits
    table[:, c + 1 : c + 4] = model.log_scales
    table[:, c + 4 : c + 8] = model.quats * 3.0  # unnormalised, as trainers store them
    head = f"ply\nformat {fmt} 1.0\ncomment written by a test\nelement vertex {len(model)}\n"
    if fmt == "binary_big_endian":
        head += "".join(f"property double {n}\n" for n in names) + "end_header\n"
        path.write_bytes(head.encode() + table.astype(">f8").tobytes())
    else:
        head += "".join(f"property float {n}\n" for n in names) + "end_header\n"
        body = "\n".join(" ".join(f"{v:.9g}" for v in row) for row in table)
        path.write_text(head + body + "\n")


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
def test_reads_ascii_and_big_endian(tmp_path, car_model, fmt):
    m = car_model.subset(np.arange(50)).with_sh_degree(1)
    _write_custom(tmp_path / "m.ply", m, fmt)
    _assert_same(m, read_ply(tmp_path / "m.ply"))


@pytest.fixture
def good_bytes(tmp_path, car_model):
    return write_ply(car_model.subset(np.arange(100)), tmp_path / "good.ply").read_bytes()


def _bad(tmp_path, data: bytes):
    p = tmp_path / "bad.ply"
    p.write_bytes(data)
    return p


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda b: b"hello world", "not a PLY"),
        (lambda b: b[: len(b) // 2], "truncated"),
        (lambda b: b.replace(b"element vertex 100", b"element vertex 99"), "count in the header is wrong"),
        (lambda b: b.replace(b"element vertex 100", b"element vertex 101"), "truncated"),
        (lambda b: b.replace(b"element vertex 100", b"element vertex 0"), "zero Gaussians"),
        (lambda b: b.replace(b"property float opacity", b"property float opacty"), "missing properties opacity"),
        (lambda b: b.replace(b"end_header", b"end_headr"), "end_header"),
        (lambda b: b.replace(b"binary_little_endian", b"binary_middle_endian"), "unknown format"),
        (lambda b: b.replace(b"element vertex 100", b"element vertex 99999999999"), "exceeds the limit"),
        (lambda b: b.replace(b"property float f_rest_44\n", b""), "f_rest"),
        # a bare 'property' line (the service fuzzer's; it used to escape as IndexError)
        (lambda b: b.replace(b"property float nz", b"property\nfloat nz"), "unknown property type"),
    ],
    ids=[
        "not-ply",
        "truncated",
        "count-too-small",
        "count-too-large",
        "zero",
        "misnamed",
        "no-end",
        "format",
        "absurd-count",
        "sh-layout",
        "bare-property",
    ],
)
def test_bad_files_get_one_clear_error(tmp_path, car_model, mutate, message):
    data = write_ply(car_model.subset(np.arange(100)), tmp_path / "good.ply").read_bytes()
    path = _bad(tmp_path, mutate(data))
    with pytest.raises(PlyError, match=message) as info:
        read_ply(path)
    assert str(path) in str(info.value)


def test_a_body_longer_than_every_element_needs_is_refused(tmp_path, car_model):
    """Counted over all the header's elements when none has a list property: a scalar element
    after the vertices does not hide extra rows (binary), and an ASCII body with more rows than
    the count is refused as a binary one is; a list element leaves the length unknown."""
    m = car_model.subset(np.arange(50)).with_sh_degree(1)
    _write_custom(tmp_path / "a.ply", m, "ascii")
    data = (tmp_path / "a.ply").read_bytes()
    p = _bad(tmp_path, data.replace(b"element vertex 50", b"element vertex 40"))
    with pytest.raises(PlyError, match="declares 40 Gaussians but the ASCII body holds .*count in the header is wrong"):
        read_ply(p)
    data = write_ply(m, tmp_path / "good.ply").read_bytes()
    two = data.replace(b"end_header\n", b"element extra 2\nproperty uchar flag\nend_header\n") + b"\x01\x02"
    assert len(read_ply(_bad(tmp_path, two))) == 50
    p = _bad(tmp_path, two + bytes(64))
    with pytest.raises(PlyError, match="count in the header is wrong"):
        read_ply(p)
    listed = data.replace(b"end_header\n", b"element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    assert len(read_ply(_bad(tmp_path, listed + b"\x03" + bytes(12)))) == 50


def test_nan_values_are_rejected(tmp_path, car_model):
    m = car_model.subset(np.arange(10))
    m.means[3, 1] = np.inf
    with pytest.raises(PlyError, match="NaN or Inf in 1 Gaussian"):
        read_ply(write_ply(m, tmp_path / "nan.ply"))


def test_missing_file_is_a_ply_error(tmp_path):
    with pytest.raises(PlyError, match="cannot open"):
        read_ply(tmp_path / "nope.ply")


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian"])
def test_bodies_are_read_and_written_in_chunks(tmp_path, car_model, monkeypatch, fmt):
    """Chunk boundaries fall mid-model (chunks of 7 rows, not dividing 200): nothing lost or shifted."""
    import gsa.io.ply as plymod
    import gsa.model as modelmod

    m = car_model.subset(np.arange(200)).with_features(np.random.default_rng(1).random((200, 3)))
    whole = read_ply(write_ply(m, tmp_path / "whole.ply"))
    monkeypatch.setattr(plymod, "CHUNK_BYTES", 7 * 4 * len(ply_property_names(m.sh_degree, 3)))
    monkeypatch.setattr(plymod, "ROW_BLOCK", 9)
    monkeypatch.setattr(modelmod, "ROW_BLOCK", 9)
    if fmt == "binary_big_endian":
        _write_custom(tmp_path / "m.ply", m.with_features(None), fmt)
        _assert_same(m.with_features(None), read_ply(tmp_path / "m.ply"))
        return
    path = write_ply(m, tmp_path / "m.ply")
    assert path.read_bytes() == (tmp_path / "whole.ply").read_bytes()
    _assert_same(whole, read_ply(path))
    bad = m.subset(np.arange(200))
    bad.sh[150, 2, 1] = np.nan  # in a later chunk
    with pytest.raises(PlyError, match="sh holds NaN or Inf in 1 Gaussian"):
        read_ply(write_ply(bad, tmp_path / "bad.ply"))


def _peak_growth_mb(fn) -> float:
    """Peak resident memory of fn() above the level before it (VmHWM, reset first)."""

    def status(field):
        with open("/proc/self/status") as fh:
            return next(int(line.split()[1]) / 1024 for line in fh if line.startswith(field + ":"))

    before = status("VmRSS")
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")  # VmHWM := VmRSS
    fn()
    return status("VmHWM") - before


def test_large_files_are_held_once_in_memory(tmp_path):
    """Reading holds the model's arrays plus a chunk, writing the model plus a chunk
    (no second copy of the data: scene-size 5M-Gaussian files; python -m benchmarks.ply_memory)."""
    import gsa.io.ply as plymod

    n = 300_000
    rng = np.random.default_rng(0)
    m = GaussianModel(
        means=rng.standard_normal((n, 3), dtype=np.float32),
        quats=rng.standard_normal((n, 4), dtype=np.float32) + np.float32(2),
        log_scales=rng.standard_normal((n, 3), dtype=np.float32),
        opacity_logits=rng.standard_normal(n, dtype=np.float32),
        sh=rng.standard_normal((n, 16, 3), dtype=np.float32),
    )
    model_mb = n * (3 + 4 + 3 + 1 + 48) * 4 / 2**20  # 67.5 MB
    chunk_mb = plymod.CHUNK_BYTES / 2**20
    path = tmp_path / "big.ply"
    assert _peak_growth_mb(lambda m=m: write_ply(m, path)) < 2 * chunk_mb + 8
    del m
    assert _peak_growth_mb(lambda: read_ply(path)) < model_mb + 2 * chunk_mb + 8


def test_parts_are_written_as_their_merge_without_building_it(tmp_path, car_model, monkeypatch):
    """write_ply(models, keep=...) gives the bytes of write_ply(merge_models(models, keep=...)):
    SH padded to the highest degree, features only when all have them, chunks across parts."""
    import gsa.io.ply as plymod
    from gsa.merge import merge_plan
    from gsa.model import merge_models

    a = car_model.subset(np.arange(60)).with_features(np.random.default_rng(2).random((60, 3)))
    b = car_model.subset(np.arange(60, 100)).with_sh_degree(1).with_features(np.ones((40, 3)))
    c = car_model.subset(np.arange(100, 130)).with_sh_degree(0)
    monkeypatch.setattr(plymod, "CHUNK_BYTES", 11 * 4 * len(ply_property_names(3, 3)))
    mask = np.random.default_rng(3).random(60) < 0.5
    for parts, keep in (((a, b), (mask, np.array([39, 0, 7]))), ((b, a), None), ((c, b, a), (None, None, mask))):
        whole = write_ply(merge_models(*parts, keep=keep), tmp_path / "whole.ply").read_bytes()
        assert write_ply(parts, tmp_path / "parts.ply", keep=keep).read_bytes() == whole
    keep, removed = merge_plan(a, a.transformed(Sim3.identity()), "dedup")
    assert removed == 60 and write_ply((a, a), tmp_path / "dedup.ply", keep=keep)
    assert len(read_ply(tmp_path / "dedup.ply")) == 60
