"""The service and 3DGS formats: uploads of every format (sniffed), the transform contract in
the job result and the gRPC message, artifacts in a requested format, bad files as 4xx."""

from __future__ import annotations

import io
import json

import grpc
import httpx
import numpy as np
import pytest

from gsa.io.formats import EXTENSIONS, FORMATS, read_model, write_model
from gsa.io.frames import RDF_TO_RUB
from gsa.sim3 import Sim3
from tests.service.conftest import ALICE, assert_problem, wait_job

pytestmark = pytest.mark.slow  # starts servers and worker processes


@pytest.fixture(scope="module")
def formatted(pair, tmp_path_factory):
    """The session pair's source as SPZ and its target as GLB."""
    d = tmp_path_factory.mktemp("formatted")
    src, tgt = read_model(pair["source"]), read_model(pair["target"])
    return {
        "source": write_model(src, d / "source.spz", "spz"),
        "target": write_model(tgt, d / "target.glb", "glb"),
        "dir": d,
        "model": src,
    }


@pytest.fixture(scope="module")
def done_job(stack, formatted):
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        with open(formatted["source"], "rb") as s, open(formatted["target"], "rb") as t:
            r = c.post(
                "/v1/jobs",
                files=[("source", ("scan.spz", s)), ("target", ("scene.glb", t))],
                data={"options": json.dumps({"outputs": ["result", "aligned"]})},
            )
        assert r.status_code in (200, 201, 202), r.text
        done = wait_job(c, r.json()["id"], timeout=120)
    assert done["state"] == "succeeded", done
    return done


@pytest.mark.parametrize("fmt", [f for f in FORMATS if f != "ply"])
def test_every_format_uploads_as_a_model(http, formatted, fmt):
    path = write_model(formatted["model"], formatted["dir"] / f"up{EXTENSIONS[fmt]}", fmt)
    with open(path, "rb") as fh:  # a name without the format's extension: the bytes decide
        r = http.post("/v1/assets", files={"file": ("upload.bin", fh)})
    assert r.status_code in (200, 201), r.text
    body = r.json()
    assert body["kind"] == "ply" and body["n_gaussians"] == len(formatted["model"])


@pytest.mark.parametrize("fmt", ["spz", "glb", "compressed-ply", "ksplat", "sog"])
def test_truncated_uploads_are_one_problem(http, formatted, fmt):
    data = write_model(formatted["model"], formatted["dir"] / f"cut{EXTENSIONS[fmt]}", fmt).read_bytes()
    r = http.post("/v1/assets", files={"file": ("cut", io.BytesIO(data[: len(data) // 2 - 7]))})
    body = assert_problem(r, 422)
    assert "cut" in body["detail"]


def test_job_result_carries_the_contract_in_file_coordinates(done_job, pair):
    result = done_job["result"]
    assert result["frames"]["source"]["format"] == "spz" and result["frames"]["target"]["format"] == "glb"
    assert result["frames"]["source"]["convention"] == result["frames"]["target"]["convention"] == "RUB"
    gt = pair["gt"]
    expected = Sim3(gt.scale, RDF_TO_RUB @ gt.rotation @ RDF_TO_RUB, RDF_TO_RUB @ gt.translation)
    assert np.allclose(result["transform"], expected.matrix(), atol=1e-3)
    q = result["quaternion"]
    assert result["quaternion_xyzw"] == [q[1], q[2], q[3], q[0]]
    assert np.allclose(np.array(result["inverse_transform"]) @ np.array(result["transform"]), np.eye(4), atol=1e-9)


def test_aligned_artifact_in_a_requested_format(http, done_job, tmp_path):
    aligned = next(a for a in done_job["artifacts"] if a["name"].startswith("aligned"))
    r = http.get(aligned["href"], params={"format": "spz"})
    assert r.status_code == 200, r.text
    assert r.headers["content-disposition"].endswith('.spz"')
    (tmp_path / "a").write_bytes(r.content)
    model = read_model(tmp_path / "a")
    assert model.metadata["format"] == "spz"
    as_stored = http.get(aligned["href"])
    (tmp_path / "b").write_bytes(as_stored.content)
    assert np.abs(read_model(tmp_path / "b").means - model.means).max() < 1e-3
    assert_problem(http.get(aligned["href"], params={"format": "obj"}), 422)
    result_json = next(a for a in done_job["artifacts"] if a["name"] == "result.json")
    assert_problem(http.get(result_json["href"], params={"format": "spz"}), 422)


def test_grpc_transform_carries_the_contract(stack, done_job):
    from service.rpc.generated import alignment_pb2 as pb
    from service.rpc.generated import alignment_pb2_grpc as pbg

    with grpc.insecure_channel(stack["grpc"]) as ch:
        stub = pbg.AlignmentServiceStub(ch)
        job = stub.GetJob(pb.JobRef(job_id=done_job["id"]), metadata=(("authorization", ALICE["Authorization"]),))
    t = job.transform
    assert len(t.quaternion_xyzw) == 4 and len(t.gltf_node_matrix) == 16 and len(t.inverse_matrix) == 16
    assert t.source_frame.format == "spz" and t.target_frame.convention == "RUB"


def test_a_header_claiming_too_many_gaussians_is_413(http, formatted):
    import gzip
    import struct

    raw = bytearray(gzip.decompress(formatted["source"].read_bytes()))
    struct.pack_into("<I", raw, 8, 6_000_000)  # the SPZ header's count, over GSA_MAX_GAUSSIANS (5M)
    r = http.post("/v1/assets", files={"file": ("huge.spz", gzip.compress(bytes(raw)))})
    body = assert_problem(r, 413)
    assert "6000000 Gaussians exceeds the limit" in body["detail"]


def _ascii(header: bytes, body: bytes, count: int) -> bytes:
    """The same rows as an ASCII PLY (write_ply writes every property as a float)."""
    names = [ln.split()[2] for ln in header.decode().splitlines() if ln.startswith("property ")]
    rows = np.frombuffer(body, "<f4").reshape(-1, len(names))
    head = f"ply\nformat ascii 1.0\nelement vertex {count}\n" + "".join(f"property float {n}\n" for n in names)
    return (head + "end_header\n" + "\n".join(" ".join(f"{v:.9g}" for v in r) for r in rows) + "\n").encode()


def test_a_ply_whose_header_count_disagrees_with_its_body_is_refused_at_upload(http, formatted):
    """A header that says 100 Gaussians over a body of 3,000 (binary, ASCII, compressed PLY), or a
    body shorter than the header says: 422 at upload naming the mismatch, on POST /v1/assets and
    on a multipart job, not 201 and a job failed later; the file as written still uploads."""
    model = formatted["model"]
    n = len(model)
    data = write_model(model, formatted["dir"] / "whole.ply", "ply").read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header, body = data[:end], data[end:]
    fewer = header.replace(f"element vertex {n}\n".encode(), b"element vertex 100\n")
    packed = write_model(model, formatted["dir"] / "whole.compressed.ply", "compressed-ply").read_bytes()
    cases = {
        "more-rows.ply": (fewer + body, f"declares 100 Gaussians ({100 * (len(body) // n)} bytes in all)"),
        "short-body.ply": (header + body[: len(body) // 2], "truncated: the header declares"),
        "ascii-more-rows.ply": (_ascii(header, body, 100), "the header declares 100 Gaussians"),
        "packed-more.ply": (packed + bytes(4096), "a count in the header is wrong"),
    }
    for name, (content, said) in cases.items():
        r = http.post("/v1/assets", files={"file": (name, content)})
        detail = assert_problem(r, 422, "invalid-input")["detail"]
        assert detail.startswith(f"{name}: ") and said in detail, detail
    assert f"{n} Gaussians' worth" in http.post("/v1/assets", files={"file": ("x.ply", fewer + body)}).json()["detail"]
    r = http.post(
        "/v1/jobs",
        files=[("source", ("more-rows.ply", fewer + body)), ("target", ("whole.ply", data))],
        data={"options": json.dumps({"stages": ["coarse"]})},
    )
    assert "count in the header is wrong" in assert_problem(r, 422)["detail"]
    for content in (data, _ascii(header, body, n), packed):
        r = http.post("/v1/assets", files={"file": ("fine.ply", content)})
        assert r.status_code == 201 and r.json()["n_gaussians"] == n, r.text


def test_a_sog_whose_local_headers_disagree_with_its_directory_is_422(http, formatted):
    """A SOG model is a zip: its entries' local headers are held to its central directory as an
    image set's are (zipfile reads by the directory, the decoder need not)."""
    from tests.zip_defects import set_local

    data = write_model(formatted["model"], formatted["dir"] / "m.sog", "sog").read_bytes()
    for which, value in (("usize", 7), ("crc", 0x12345678)):
        r = http.post("/v1/assets", files={"file": ("m.sog", set_local(data, which, value, nth=1))})
        detail = assert_problem(r, 422, "invalid-input")["detail"]
        assert "its local header says" in detail and "the central directory" in detail, detail
    r = http.post("/v1/assets", files={"file": ("m.sog", data)})
    assert r.status_code == 201 and r.json()["n_gaussians"] == len(formatted["model"]), r.text
