"""`gsa view RESULT_DIR_OR_JSON`: the results page for a local result, on 127.0.0.1.

A result is `gsa align`'s result.json (previews from `--preview`, or made here from the
input files it names) or a folder of a service job's artifacts (`gsa fetch JOB --out DIR`:
result.json or s0/, s1/, ... with preview/ and renders/ beside them), or many.json of
`gsa align-many` (previews made from the model files it names) or of a many job (its
preview/model{k}.splat beside it): all models in the reference frame. Every URL starts
with a random token, so other local users cannot read the result through the port.
"""

from __future__ import annotations

import json
import secrets
import shlex
import shutil
import tempfile
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from gsa.errors import GSAError
from gsa.viewer.page import (
    PAGE_HEADERS,
    STATIC_FILES,
    ResultView,
    is_many_result,
    render_many_page,
    render_page,
    static_file,
)
from gsa.viewer.preview import PREVIEW_NAMES

CONTENT_TYPES = {".splat": "application/octet-stream", ".png": "image/png", ".json": "application/json"}


class ResultError(GSAError, ValueError):
    """The path is not a result this command can show."""


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ResultError(f"{path}: not a readable result JSON ({exc})") from None
    if not isinstance(data, dict) or "transform" not in data and "results" not in data:
        raise ResultError(f"{path}: not an alignment result (no 'transform')")
    return data


def _made_previews(result: dict, work: Path) -> dict[str, Path]:
    """Previews from the input files a CLI result names (when it was written without them)."""
    from gsa.io.formats import read_model  # every 3DGS format gsa align reads, in the same frame
    from gsa.sim3 import Sim3
    from gsa.viewer.preview import write_previews

    inputs = result.get("inputs") or {}
    try:
        source, target = read_model(inputs["source"]), read_model(inputs["target"])
    except (KeyError, TypeError, OSError, ValueError):
        return {}
    # The readers give internal coordinates (gsa.io.frames): the pose in those is
    # `transform_internal` where the files' frames differ from it (SPZ, GLB), else `transform`.
    pose = result.get("transform_internal") or result["transform"]
    return write_previews(source, target, Sim3.from_matrix(pose), work)


def collect(path: str | Path, work: Path) -> tuple[str, list[ResultView], dict[str, Path], list[tuple[str, str]]]:
    """(title, result views, {url name: file}, extra renders) for a result file or folder."""
    p = Path(path)
    if p.is_dir():
        parts = sorted((d for d in p.glob("s[0-9]*") if (d / "result.json").is_file()), key=lambda d: int(d.name[1:]))
        if not parts and not (p / "result.json").is_file():
            raise ResultError(f"{p}: no result.json (nor s0/result.json) in this folder")
        folders = parts or [p]
    elif p.is_file():
        folders = [p.parent]
    else:
        raise ResultError(f"{p}: no such file or folder")
    files: dict[str, Path] = {}
    views = []
    for i, folder in enumerate(folders):
        result = _load_json(p if p.is_file() else folder / "result.json")
        found = {k: folder / name for k, name in PREVIEW_NAMES.items() if (folder / name).is_file()}
        for k, name in (result.get("preview") or {}).items() if isinstance(result.get("preview"), dict) else ():
            if k in PREVIEW_NAMES and Path(name).is_file():
                found[k] = Path(name)
        if len(found) < 3:
            made = _made_previews(result, work / f"made{i}")
            found = {k: made[n] for k, n in PREVIEW_NAMES.items() if n in made} or found
        preview = {}
        for k, f in found.items():
            files[f"s{i}/{k}.splat"] = f
            preview[k] = f"files/s{i}/{k}.splat"
        renders = []
        for png in sorted({*folder.glob("renders/*.png"), *folder.glob("renders/renders/*.png")}):
            files[f"s{i}/{png.name}"] = png
            renders.append((png.name, f"files/s{i}/{png.name}"))
        inputs = result.get("inputs") or {}
        label = Path(str(inputs.get("source", f"source {i + 1}"))).name if isinstance(inputs, dict) else "source"
        views.append(ResultView(label=label, result=result, preview=preview, renders=renders))
    extra = []
    for png in sorted(p.glob("synchronized/*.png")) if p.is_dir() else ():
        files[f"sync/{png.name}"] = png
        extra.append((png.name, f"files/sync/{png.name}"))
    return str(p), views, files, extra


def many_json(path: str | Path) -> dict | None:
    """many.json's content when the path is one (`gsa align-many --out DIR`'s, a many job's
    fetched artifacts) or a folder holding one, else None."""
    p = Path(path)
    f = p / "many.json" if p.is_dir() else p
    if not f.is_file() or f.suffix.lower() != ".json":
        return None
    try:
        data = json.loads(f.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return data if is_many_result(data) else None


def many_previews(path: str | Path, data: dict, work: Path) -> dict[str, Path]:
    """{url name: file} of each model's .splat preview in its own frame: preview/model{k}.splat
    beside many.json (a many job's artifacts), else made from the model files it names
    (`files`, gsa align-many); a model with neither has none."""
    from gsa.viewer.preview import DEFAULT_MAX_GAUSSIANS, downsample, write_splat

    p = Path(path)
    folder = p if p.is_dir() else p.parent
    names = data.get("files") if isinstance(data.get("files"), list) else []
    n = len(data["models"])
    out = {}
    for k in range(n):
        found = folder / f"preview/model{k}.splat"
        if found.is_file():
            out[f"m{k}.splat"] = found
            continue
        try:
            from gsa.io.formats import read_model

            model = read_model(names[k])
        except (IndexError, TypeError, OSError, ValueError):
            continue
        out[f"m{k}.splat"] = write_splat(
            downsample(model, max(DEFAULT_MAX_GAUSSIANS // n, 20_000)), work / f"m{k}.splat"
        )
    return out


def _many_page(path: str | Path, data: dict, work: Path) -> tuple[bytes, dict[str, Path]]:
    files = many_previews(path, data, work)
    previews = [f"files/m{k}.splat" if f"m{k}.splat" in files else None for k in range(len(data["models"]))]
    page = render_many_page(
        f"GSA many: {path}", data, previews, "static/", subtitle=f"{len(previews)} models into one frame"
    )
    return page.encode(), files


def cli_guide(path: str | Path, views: list[ResultView]) -> dict:
    """The page's guide shows `gsa align` commands (there is no job to refine locally): the
    input files result.json names (placeholders for a fetched service result) and the result
    itself for --init, shell-quoted."""
    p = Path(path)
    inputs = views[0].result.get("inputs") if views and isinstance(views[0].result.get("inputs"), dict) else {}
    source, target = inputs.get("source"), inputs.get("target")
    return {
        "mode": "cli",
        "source": shlex.quote(str(source)) if source else "SOURCE",
        "target": shlex.quote(str(target)) if target else "TARGET",
        "result": shlex.quote(str(p if p.is_file() else p / "result.json")),
    }


def _pair_page(path: str | Path, work: Path) -> tuple[bytes, dict[str, Path]]:
    title, views, files, extra = collect(path, work)
    target = (
        views[0].result.get("inputs", {}).get("target") if isinstance(views[0].result.get("inputs"), dict) else None
    )
    page = render_page(
        f"GSA result: {title}",
        views,
        "static/",
        subtitle=f"target: {Path(str(target)).name}" if target else "",
        extra_renders=extra,
        guide=cli_guide(path, views),
    )
    return page.encode(), files


def make_server(path: str | Path, host: str = "127.0.0.1", port: int = 0) -> tuple[ThreadingHTTPServer, str]:
    """A server for the result's page (not yet serving); returns it and the page URL."""
    work = Path(tempfile.mkdtemp(prefix="gsa-view-"))  # previews made here; removed with the server
    try:
        many = many_json(path)
        if many is not None:
            page, files = _many_page(path, many, work)
        else:
            page, files = _pair_page(path, work)
        static_file("viewer.js")  # fail now, with the build hint, rather than on the first request
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    token = secrets.token_urlsafe(16)

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - http.server's name
            prefix = f"/{token}/"
            if not self.path.startswith(prefix):
                return self._send(HTTPStatus.NOT_FOUND, b"not found", "text/plain")
            rest = self.path[len(prefix) :].split("?", 1)[0]
            if rest == "":
                return self._send(HTTPStatus.OK, page, "text/html; charset=utf-8", PAGE_HEADERS)
            if rest.startswith("static/") and rest[7:] in STATIC_FILES:
                return self._send(HTTPStatus.OK, static_file(rest[7:]), STATIC_FILES[rest[7:]])
            f = files.get(rest[6:]) if rest.startswith("files/") else None
            if f is None:
                return self._send(HTTPStatus.NOT_FOUND, b"not found", "text/plain")
            return self._send(HTTPStatus.OK, f.read_bytes(), CONTENT_TYPES.get(f.suffix, "application/octet-stream"))

        def _send(self, status, body: bytes, ctype: str, headers: dict | None = None):
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            for k, v in (headers or {}).items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, format, *args):  # quiet: the URL is the only output
            pass

    server = ThreadingHTTPServer((host, port), Handler)
    server.daemon_threads = True
    server.work_dir = work
    return server, f"http://{host}:{server.server_address[1]}/{token}/"
