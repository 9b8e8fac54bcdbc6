"""Generated HTTP requests for fuzzing the service (hypothesis strategies), a raw
HTTP/1.1 sender and the per-response checks.

Requests go over a plain socket, not httpx: the fuzzer must be able to send what
a well-behaved client library refuses to build (bytes in paths and headers,
broken multipart framing, wrong Content-Length), and it must see exactly what
the server did (an answer, a reset connection, or silence)."""

from __future__ import annotations

import http.client
import json
import select
import socket
import time
import zipfile
from dataclasses import dataclass, field
from urllib.parse import quote

import numpy as np
from hypothesis import strategies as st

from tests.zip_defects import build as zip_of
from tests.zip_defects import png as png_bytes

CRLF = b"\r\n"


def one_in(draw, n: int) -> bool:
    """True about once in n draws (hypothesis' integers lean towards their bounds)."""
    return draw(st.sampled_from([True] + [False] * (n - 1)))


@dataclass
class Req:
    kind: str
    method: str
    target: bytes  # request target: path and query, sent as is
    headers: list[tuple[bytes, bytes]] = field(default_factory=list)
    body: bytes = b""


@dataclass
class Resp:
    status: int  # 0: no answer (reset, closed or timed out)
    headers: dict[str, str]
    body: bytes
    elapsed: float
    error: str | None = None


def send(host: str, port: int, req: Req, timeout: float) -> Resp:
    """One request on a fresh connection. A large body goes in chunks, and sending
    stops once the server has answered (a 413 comes before the body is read)."""
    t = time.monotonic()
    head = [req.method.encode() + b" " + req.target + b" HTTP/1.1", b"Host: " + f"{host}:{port}".encode()]
    names = {k.lower() for k, _ in req.headers}
    head += [k + b": " + v for k, v in req.headers]
    if b"content-length" not in names and b"transfer-encoding" not in names and req.body:
        head.append(b"Content-Length: " + str(len(req.body)).encode())
    head.append(b"Connection: close")
    data = CRLF.join(head) + CRLF + CRLF + req.body
    sock = socket.create_connection((host, port), timeout=timeout)
    send_error = None
    try:
        for i in range(0, len(data), 1 << 16):
            if select.select([sock], [], [], 0)[0]:
                break  # the server answered early
            try:
                sock.sendall(data[i : i + (1 << 16)])
            except OSError as exc:
                send_error = exc
                break
        resp = http.client.HTTPResponse(sock, method=req.method)
        try:
            resp.begin()
            body = resp.read()
        except (OSError, http.client.HTTPException) as exc:
            why = f"{type(exc).__name__}: {exc}" + (f" (while sending: {send_error})" if send_error else "")
            return Resp(0, {}, b"", time.monotonic() - t, why)
        return Resp(resp.status, {k.lower(): v for k, v in resp.getheaders()}, body, time.monotonic() - t)
    finally:
        sock.close()


# ---- stored failing requests (tests/service/corpus/*.http) -------------------------------------
# One request per file, as it goes on the wire minus what `send` adds (Host, Connection and,
# when the request has none, Content-Length): "METHOD TARGET", header lines, an empty line,
# the body bytes. Leading "# key: value" lines are notes; "# expect: 4xx" (the default) is
# what the server must answer. benchmarks/service/fuzz_service.py --save writes what it finds this way.


def dump_http(req: Req, notes: dict[str, str] | None = None) -> bytes:
    head = [f"# {k}: {v}".encode() for k, v in (notes or {}).items()]
    head.append(req.method.encode() + b" " + req.target)
    head += [k + b": " + v for k, v in req.headers]
    return CRLF.join(head) + CRLF + CRLF + req.body


def load_http(data: bytes, kind: str = "corpus") -> tuple[Req, dict[str, str]]:
    """A stored request and its notes (dump_http's inverse)."""
    head, sep, body = data.partition(CRLF + CRLF)
    if not sep:
        raise ValueError("no empty line after the request head")
    lines = head.split(CRLF)
    notes = {}
    while lines and lines[0].startswith(b"#"):
        key, _, value = lines.pop(0)[1:].decode().partition(":")
        notes[key.strip()] = value.strip()
    method, _, target = lines[0].partition(b" ")
    headers = [(k, v.lstrip(b" ")) for k, _, v in (line.partition(b":") for line in lines[1:])]
    return Req(kind, method.decode(), target, headers, body), notes


# ---- corpus: valid inputs, and known-bad ones, built once --------------------------------------


def build_corpus(ply_bytes: bytes) -> dict[str, bytes]:
    import cv2

    png = png_bytes(32, 24, 0)
    huge_png = bytearray(png)
    huge_png[16:24] = (100_000).to_bytes(4, "big") * 2  # IHDR claims 100000 x 100000
    return {
        "ply": ply_bytes,
        "ply_ascii": b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n",
        "ply_huge_count": ply_bytes.replace(b"element vertex ", b"element vertex 99999999999", 1),
        "png": png,
        "png_huge": bytes(huge_png),
        "jpg": cv2.imencode(".jpg", np.full((24, 32, 3), 128, np.uint8))[1].tobytes(),
        "zip": zip_of({f"v{i}.png": png_bytes(32, 24, i) for i in range(3)}),
        "zip_traversal": zip_of({"../../evil.png": png, "ok.png": png}),
        "zip_bomb": zip_of({"zeros.png": png[:64] + bytes(20 << 20)}),
        "zip_text": zip_of({"a.txt": b"hello", "b.png": b"not a png"}),
        "zip_stored": zip_of({f"v{i}.png": png for i in range(3)}, zipfile.ZIP_STORED),
    }


# ---- strategies --------------------------------------------------------------------------------

JSON_LEAF = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
)
JSON_ANY = st.recursive(
    JSON_LEAF,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner, max_size=4),
    max_leaves=12,
)
OPTION_VALUES = st.one_of(
    JSON_LEAF,
    st.integers(-5, 10_000),
    st.floats(-1, 2),
    st.sampled_from(["auto", "coarse", "fine", "warp", "coarse,fine", "features", "colors", "l1", "cpu"]),
    st.lists(st.sampled_from(["coarse", "fine", "warp", "result", "aligned", "merged", "renders", "x"]), max_size=4),
)


def option_names() -> list[str]:
    from service.jobs.options import SERVICE_OPTIONS, align_option_names

    return sorted(align_option_names() | SERVICE_OPTIONS)


VALID_OPTIONS = st.sampled_from(
    [
        {},
        {"stages": ["coarse"], "outputs": ["result"]},
        {"coarse_iterations": 5, "seed": 1},
        {"outputs": ["result", "aligned"], "renders": False},
        {"stages": ["coarse", "fine"], "fine_iterations": 2, "fine_views": 1, "fine_image_size": 16},
    ]
)
OPTION_NAMES: list[str] = []  # filled by requests() from the library build's options


def options_strategy(names: list[str]):
    keys = st.sampled_from(names) | st.sampled_from(names) | st.text(max_size=12)
    return st.dictionaries(keys, OPTION_VALUES, max_size=5)


def mutate(blob: bytes):
    """Corrupted variants of a valid file: truncated, bytes flipped, bytes inserted, repeated."""
    n = max(len(blob), 1)

    def flip(args):
        b = bytearray(blob)
        for pos, val in args:
            if b:
                b[pos % len(b)] = val
        return bytes(b)

    return st.one_of(
        st.just(blob),
        st.integers(0, n).map(lambda k: blob[:k]),
        st.lists(st.tuples(st.integers(0, n), st.integers(0, 255)), min_size=1, max_size=8).map(flip),
        st.tuples(st.integers(0, n), st.binary(max_size=64)).map(lambda a: blob[: a[0]] + a[1] + blob[a[0] :]),
        st.just(blob * 2),
        st.binary(max_size=256),
    )


FILENAMES = st.one_of(
    st.sampled_from(["model.ply", "a.png", "b.jpg", "set.zip", "пример-模型.ply", "../../etc/passwd", "", "x" * 300]),
    st.text(max_size=40),
)
PRINTABLE = st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=40).map(str.encode)
HEADER_VALUE = st.one_of(
    PRINTABLE,
    PRINTABLE,
    PRINTABLE,
    st.sampled_from([b"", b" ", b"%00", b"\xff\xfe", b"a" * 9000, "пример".encode()]),
    # bytes HTTP does not allow in a header (the parser's 400), now and then
    st.binary(max_size=40).map(lambda b: b.replace(b"\r", b"").replace(b"\n", b"")),
)


def _disposition(name: str, filename: str | None, star: bool) -> bytes:
    d = b'form-data; name="' + name.encode("utf-8", "replace") + b'"'
    if filename is not None:
        if star:
            d += b"; filename*=UTF-8''" + quote(filename).encode()
        else:
            d += b'; filename="' + filename.encode("utf-8", "surrogatepass").replace(b'"', b"") + b'"'
    return d


@st.composite
def multipart_body(draw, corpus: dict[str, bytes], field_names: list[str], for_job: bool):
    boundary = draw(st.sampled_from([b"gsafuzzboundary", b"x", b"-" * 70, b"b\xc3\xa9"]))
    parts = []
    shape = draw(st.sampled_from(["well-formed", "well-formed", "images", "any"]))
    if shape == "well-formed":
        plan = [("source", True), ("target", True), ("options", False)] if for_job else [("file", True)]
    elif shape == "images" and for_job:
        plan = [(draw(st.sampled_from(["source_images", "target_images"])), True) for _ in range(3)]
        plan += [("target", True), ("options", False)]
    elif shape == "images":
        plan = [("file", True) for _ in range(3)]
    else:
        plan = [
            (draw(st.sampled_from(field_names) | st.text(max_size=8)), draw(st.booleans()))
            for _ in range(draw(st.integers(0, 5)))
        ]
    for name, is_file in plan:
        if is_file:
            good = "zip" if name.endswith("images") else "png" if shape == "images" else "ply"
            key = draw(st.sampled_from([good] * len(corpus) + sorted(corpus)))
            content = draw(mutate(corpus[key])) if one_in(draw, 3) else corpus[key]
            filename = draw(FILENAMES) if one_in(draw, 4) else f"upload.{key.split('_')[0]}"
            disp = _disposition(name, filename, draw(st.booleans()))
            ctype = draw(st.sampled_from([b"application/octet-stream", b"image/png", b"", b"text/plain"]))
            head = b"Content-Disposition: " + disp + (CRLF + b"Content-Type: " + ctype if ctype else b"")
        else:
            content = draw(
                st.one_of(
                    VALID_OPTIONS.map(lambda o: json.dumps(o).encode()),
                    options_strategy(OPTION_NAMES).map(lambda o: json.dumps(o).encode()),
                    st.binary(max_size=64),
                    st.sampled_from([b"http://127.0.0.1:1/hook", b"https://example.invalid/x", b"{"]),
                )
            )
            head = b"Content-Disposition: " + _disposition(name, None, False)
        parts.append(head + CRLF + CRLF + content)
    body = b"".join(b"--" + boundary + CRLF + p + CRLF for p in parts) + b"--" + boundary + b"--" + CRLF
    body = draw(st.one_of(st.just(body), mutate(body))) if one_in(draw, 10) else body
    ctype = draw(
        st.sampled_from(
            [b"multipart/form-data; boundary=" + boundary] * 6
            + [b'multipart/form-data; boundary="' + boundary + b'"', b"multipart/form-data", b"multipart/mixed"]
            + [b"multipart/form-data; boundary=other"]
        )
    )
    return ctype, body


def _range(ab) -> bytes:
    a, z = ("" if v is None else str(v) for v in ab)
    return f"bytes={a}-{z}".encode()


RANGE = st.one_of(
    st.tuples(st.integers(0, 4000), st.integers(0, 4000)).map(sorted).map(_range),  # well formed
    st.tuples(st.integers(0, 4000), st.none()).map(_range),  # open end
    st.tuples(st.none(), st.integers(0, 4000)).map(_range),  # suffix
    st.tuples(st.integers(-5, 10**12) | st.none(), st.integers(-5, 10**12) | st.none()).map(_range),
    st.sampled_from([b"bytes=0-0,5-9", b"bytes=99999999999999999999-", b"items=0-1", b"bytes=-0", b"bytes=5-2"]),
    HEADER_VALUE,
)


class Targets:
    """Ids and artifact names the fuzzer aims at: the baseline's (the caller's own,
    and another owner's, which must stay invisible and unchanged) plus garbage."""

    def __init__(self, own_job: str, own_asset: str, other_job: str, other_asset: str, artifacts: list[str]):
        self.own_job, self.own_asset = own_job, own_asset
        self.other_job, self.other_asset = other_job, other_asset
        self.artifacts = artifacts
        self.etags: dict[str, str] = {}  # artifact name -> its ETag (If-Range that matches)

    def ids(self, job: bool):
        real = [self.own_job, self.other_job] if job else [self.own_asset, self.other_asset]
        return st.one_of(
            st.sampled_from(real),
            st.sampled_from(real).map(lambda i: i[:-1]),
            st.text(max_size=60),
            st.sampled_from(["job_" + "0" * 32, "ast_x", "..", "%2e%2e", "a/b", "\x00", "x" * 5000]),
        )

    def deletable_ids(self):
        """DELETE never aims at the caller's own baseline job/asset (it would rightly go)."""
        return st.one_of(st.sampled_from([self.other_job, self.other_asset]), st.text(max_size=40))


def _path(draw, prefix: str, ident: str, suffix: str = "") -> bytes:
    if one_in(draw, 5):  # raw, unquoted bytes now and then
        return (prefix + ident + suffix).encode("utf-8", "surrogatepass")
    return (prefix + quote(ident, safe="") + suffix).encode()


AUTH = st.sampled_from(
    [b"Bearer key-alice"] * 40 + [b"Bearer key-bobx", b"bearer key-alice", b"Basic a2V5", b"Bearer "]
)


@st.composite
def requests(draw, corpus: dict[str, bytes], targets: Targets, names: list[str]) -> Req:
    OPTION_NAMES[:] = names
    kind = draw(
        st.sampled_from(
            ["json_job", "json_job", "multipart_job", "multipart_job", "asset", "asset"]
            + ["get_job", "get_asset", "list", "cancel", "delete", "artifact", "artifact", "misc", "big"]
        )
    )
    headers: list[tuple[bytes, bytes]] = []
    if not one_in(draw, 20):
        headers.append((b"Authorization", draw(HEADER_VALUE) if one_in(draw, 10) else draw(AUTH)))
    for name in draw(
        st.lists(st.sampled_from([b"X-Request-Id", b"Idempotency-Key", b"Origin", b"Accept"]), max_size=2)
    ):
        headers.append((name, draw(HEADER_VALUE)))
    if kind == "json_job":
        return _json_job_request(draw, headers, targets, names)
    if kind in ("multipart_job", "asset"):
        fields = ["source", "target", "source_images", "target_images", "options", "webhook_url", "file"]
        ctype, body = draw(multipart_body(corpus, fields + names[:5], kind == "multipart_job"))
        path = b"/v1/jobs" if kind == "multipart_job" else b"/v1/assets"
        return Req(kind, "POST", path, headers + [(b"Content-Type", ctype)], body)
    if kind == "get_job":
        return _get_job_request(draw, headers, targets)
    if kind == "get_asset":
        return Req(kind, "GET", _path(draw, "/v1/assets/", draw(targets.ids(False))), headers)
    if kind == "list":
        return _list_request(draw, headers)
    if kind == "cancel":
        return Req(kind, "POST", _path(draw, "/v1/jobs/", draw(targets.ids(True)), ":cancel"), headers)
    if kind == "delete":
        prefix = draw(st.sampled_from(["/v1/jobs/", "/v1/assets/"]))
        return Req(kind, "DELETE", _path(draw, prefix, draw(targets.deletable_ids())), headers)
    if kind == "artifact":
        return _artifact_request(draw, headers, targets)
    if kind == "misc":
        return _misc_request(draw, headers)
    return _big_request(draw, headers, corpus)


def _json_job_request(draw, headers: list[tuple[bytes, bytes]], targets: Targets, names: list[str]) -> Req:
    own = st.sampled_from([targets.own_asset]) | targets.ids(job=False)
    spec = draw(
        st.fixed_dictionaries(
            {"source": own, "target": own, "options": VALID_OPTIONS | options_strategy(names)},
            optional={"webhook": st.fixed_dictionaries({"url": st.text(max_size=30)})},
        )
        | st.fixed_dictionaries(
            {},
            optional={
                "source": targets.ids(job=False),
                "sources": st.lists(targets.ids(job=False), max_size=20),
                "target": targets.ids(job=False),
                "options": options_strategy(names) | JSON_ANY,
                "webhook": st.fixed_dictionaries({"url": st.text(max_size=30)}) | JSON_ANY,
            },
        )
        | JSON_ANY
    )
    text = json.dumps(spec).encode()
    body = draw(mutate(text)) if one_in(draw, 5) else text
    ctype = draw(st.sampled_from([b"application/json"] * 4 + [b"application/json; charset=latin-1", b"text/plain"]))
    return Req("json_job", "POST", b"/v1/jobs", headers + [(b"Content-Type", ctype)], body)


def _get_job_request(draw, headers: list[tuple[bytes, bytes]], targets: Targets) -> Req:
    if draw(st.booleans()):
        headers.append((b"If-None-Match", draw(HEADER_VALUE | st.just(b"*"))))
    return Req(
        "get_job", draw(st.sampled_from(["GET", "HEAD"])), _path(draw, "/v1/jobs/", draw(targets.ids(True))), headers
    )


def _list_request(draw, headers: list[tuple[bytes, bytes]]) -> Req:
    q = draw(
        st.dictionaries(
            st.sampled_from(["state", "limit", "cursor", "x"]),
            st.sampled_from(["succeeded", "queued", "0", "201", "-1", "abc", "eyJ4Ijp9"]) | st.text(max_size=12),
            max_size=3,
        )
    )
    qs = "&".join(f"{quote(k)}={quote(v)}" for k, v in q.items())
    return Req("list", "GET", ("/v1/jobs" + ("?" + qs if qs else "")).encode(), headers)


def _artifact_request(draw, headers: list[tuple[bytes, bytes]], targets: Targets) -> Req:
    own = not one_in(draw, 4)
    job = targets.own_job if own else draw(st.sampled_from([targets.other_job]) | targets.ids(True))
    real = draw(st.sampled_from(targets.artifacts))
    name = real if not one_in(draw, 4) else draw(st.sampled_from(["../x", "%2e%2e/x", "s0/result.json", ""]))
    if not one_in(draw, 3):
        headers.append((b"Range", draw(RANGE)))
    if one_in(draw, 2):
        etag = targets.etags.get(real, '"none"').encode()
        stale = st.sampled_from([b'"stale-1"', b"Wed, 21 Oct 2015 07:28:00 GMT", b"W/" + etag])
        headers.append((b"If-Range", etag if one_in(draw, 2) else draw(stale | HEADER_VALUE)))
    method = draw(st.sampled_from(["GET", "GET", "GET", "HEAD"]))
    return Req("artifact", method, _path(draw, "/v1/jobs/", job, "/artifacts/" + name), headers)


def _misc_request(draw, headers: list[tuple[bytes, bytes]]) -> Req:
    method = draw(st.sampled_from(["GET", "PUT", "PATCH", "OPTIONS", "TRACE", "DELETE", "POST", "FOO"]))
    path = draw(
        st.sampled_from(["/", "/readyz", "/healthz", "/metrics", "/openapi.json", "/docs", "/v1", "/v1/jobs/x/y/z"])
        | st.text(max_size=30).map(lambda s: "/" + quote(s))
    )
    if method == "OPTIONS":
        headers += [(b"Origin", b"https://evil.example"), (b"Access-Control-Request-Method", b"POST")]
    return Req("misc", method, path.encode(), headers, draw(st.binary(max_size=64)))


def _big_request(draw, headers: list[tuple[bytes, bytes]], corpus: dict[str, bytes]) -> Req:
    """Bodies past the limits (JSON cap 1 MiB; per-file upload cap set by the deployment)."""
    which = draw(st.sampled_from(["json", "upload", "chunked", "many_fields", "many_files", "part_header"]))
    if which in ("many_fields", "many_files", "part_header"):
        # Memory: parts under every per-part cap that add up (80 form fields or 100 files
        # of just under 1 MiB), or one part header of 40 MiB.
        if which != "part_header":
            filename = b'; filename="f.png"' if which == "many_files" else b""
            disp = b'--B\r\nContent-Disposition: form-data; name="source_images"' + filename + b"\r\n\r\n"
            body = (disp + b" " * ((1 << 20) - 100) + CRLF) * (100 if filename else 80) + b"--B--\r\n"
        else:
            body = (
                b"--B\r\nX-Junk: "
                + b"j" * (40 << 20)
                + b'\r\nContent-Disposition: form-data; name="file"\r\n\r\nx\r\n--B--\r\n'
            )
        path = draw(st.sampled_from([b"/v1/jobs", b"/v1/assets"]))
        return Req("big", "POST", path, headers + [(b"Content-Type", b"multipart/form-data; boundary=B")], body)
    if which == "json":
        body = b'{"target": "' + b"x" * (2 << 20) + b'"}'
        return Req("big", "POST", b"/v1/jobs", headers + [(b"Content-Type", b"application/json")], body)
    if which == "chunked":
        chunk = b"x" * 65536
        body = b"".join(b"%x\r\n" % len(chunk) + chunk + CRLF for _ in range(40)) + b"0\r\n\r\n"
        hdrs = headers + [(b"Content-Type", b"application/json"), (b"Transfer-Encoding", b"chunked")]
        return Req("big", "POST", b"/v1/jobs", hdrs, body)
    body = (
        b'--B\r\nContent-Disposition: form-data; name="file"; filename="big.ply"\r\n\r\n'
        + corpus["ply"]
        + bytes(10 << 20)
        + b"\r\n--B--\r\n"
    )
    return Req("big", "POST", b"/v1/assets", headers + [(b"Content-Type", b"multipart/form-data; boundary=B")], body)


# ---- checks ------------------------------------------------------------------------------------


def problems_with(req: Req, resp: Resp, bound_s: float, outage: bool) -> list[str]:
    """What is wrong with one answer; [] when it is fine."""
    out = []
    if resp.status == 0:
        return [f"no answer: {resp.error}"]
    if (
        resp.status == 400
        and "x-request-id" not in resp.headers
        and resp.body in (b"", b"Invalid HTTP request received.")
    ):
        # uvicorn's HTTP parser refused bytes that are not HTTP (a NUL in a header, a bad
        # request line) before any application code ran (which would have added an id):
        # a plain 400 is the right answer.
        return [f"took {resp.elapsed:.1f} s"] if resp.elapsed > bound_s else []
    if resp.elapsed > bound_s:
        out.append(f"took {resp.elapsed:.1f} s (bound {bound_s} s)")
    if resp.status >= 500 and not (outage and resp.status == 503):
        out.append(f"{resp.status}: {resp.body[:300]!r}")
    if resp.status >= 400 and req.method != "HEAD" and resp.body:
        if not resp.headers.get("content-type", "").startswith("application/problem+json"):
            out.append(f"{resp.status} is not problem+json: {resp.headers.get('content-type')}")
    if "x-request-id" not in resp.headers:
        out.append("no X-Request-Id")
    return out
