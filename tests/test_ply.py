import numpy as np
import pytest

from gsa.io.ply import PlyError, ply_property_names, read_ply, write_ply
from gsa.model import GaussianModel


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
    ],
)
def test_bad_files_get_one_clear_error(tmp_path, car_model, mutate, message):
    data = write_ply(car_model.subset(np.arange(100)), tmp_path / "good.ply").read_bytes()
    path = _bad(tmp_path, mutate(data))
    with pytest.raises(PlyError, match=message) as info:
        read_ply(path)
    assert str(path) in str(info.value)


def test_nan_values_are_rejected(tmp_path, car_model):
    m = car_model.subset(np.arange(10))
    m.means[3, 1] = np.inf
    with pytest.raises(PlyError, match="NaN or Inf in 1 Gaussian"):
        read_ply(write_ply(m, tmp_path / "nan.ply"))


def test_missing_file_is_a_ply_error(tmp_path):
    with pytest.raises(PlyError, match="cannot open"):
        read_ply(tmp_path / "nope.ply")
