"""Model artifacts in a requested 3DGS format (GET .../artifacts/aligned.ply?format=spz).

A conversion reads the whole model, so it never runs in the API process: a child process
(`python -m service.worker.convert_child`) reads the stored artifact and writes the requested
format through the library (gsa.io.formats); the API waits for it without holding a thread,
stores the result in storage next to the job's artifacts, and serves that file like any
other artifact (Range, If-Range, ETag, If-None-Match, HEAD). So:

- the API's memory stays flat whatever the model's size (5 concurrent conversions of a
  3M-Gaussian merged model took it from 181 MB to 2.8 GB when they ran inside it);
- at most `GSA_MAX_CONVERSIONS` children run per API process; a request finding every slot
  taken waits up to `GSA_CONVERSION_WAIT_S` for one, then gets 503 `conversions-busy` with
  Retry-After;
- a converted file is kept under `<the job's artifact folder>/conv/<digest>/<name>`, the
  digest naming (artifact key, size, format, converter version): artifact keys are written
  once per attempt and never rewritten, so the key and size identify the source bytes. A
  repeated request streams the stored file, and requests for one conversion that is
  running wait for it instead of starting another. Deleting the job deletes them too.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path, PurePosixPath

from starlette.concurrency import run_in_threadpool

from service.jobs.inputs import model_content_type
from service.models import Artifact
from service.problems import Problem, invalid_input
from service.worker.convert_child import BAD_INPUT_EXIT

log = logging.getLogger("gsa.api")

# Part of the cache key: bump it when the writers change what they write, so files
# converted by an older service are not served for the new one.
CONVERTER_VERSION = 1


def _formats():
    # lazy: the library's format tables (the readers and writers load in the child)
    from gsa.io.formats import EXTENSIONS, FORMATS, format_for_path

    return EXTENSIONS, FORMATS, format_for_path


def converted_name(name: str, fmt: str) -> str:
    """aligned.ply → aligned.spz; s0/merged.ply → merged.spz (the download's file name)."""
    extensions, _, _ = _formats()
    stem = PurePosixPath(name).name
    for ext in sorted(extensions.values(), key=len, reverse=True):
        if stem.lower().endswith(ext):
            stem = stem[: -len(ext)]
            break
    return f"{stem}{extensions[fmt]}"


def cache_key(art: Artifact, fmt: str) -> str:
    """Where the converted file is kept: beside the job's artifacts (jobs/<id>/<token>/...),
    so that it goes when the job goes."""
    digest = hashlib.sha256(f"{art.key}\0{art.size}\0{fmt}\0{CONVERTER_VERSION}".encode()).hexdigest()[:32]
    suffix = "/" + art.name
    folder = art.key[: -len(suffix)] if art.key.endswith(suffix) else art.key.rsplit("/", 1)[0]
    return f"{folder}/conv/{digest}/{converted_name(art.name, fmt)}"


def check_request(art: Artifact, fmt: str) -> None:
    """422 for an unknown format or an artifact that is not a model."""
    _, formats, format_for_path = _formats()
    if fmt not in formats:
        raise invalid_input(f"format {fmt!r} is not one of {', '.join(formats)}")
    if format_for_path(art.name) is None:
        raise invalid_input(f"{art.name} is not a 3DGS model artifact; only models convert")


class Conversions:
    """One API process's conversions: a limit on how many children run at once, and the
    conversions in progress (so that concurrent requests for one of them share it)."""

    def __init__(self, limit: int):
        self.limit = max(int(limit), 1)
        self.slots = asyncio.Semaphore(self.limit)
        self.running: dict[str, asyncio.Future] = {}

    async def converted(self, b, art: Artifact, fmt: str) -> Artifact:
        """The converted file as a stored artifact (converting it first if it is not stored yet)."""
        check_request(art, fmt)
        key = cache_key(art, fmt)
        stored = await run_in_threadpool(_stored, b.storage, key)
        if stored is not None:
            return _artifact(key, stored, art, fmt)
        pending = self.running.get(key)
        if pending is None:
            pending = asyncio.get_running_loop().create_future()
            self.running[key] = pending
            # A task of its own: the conversion completes and is stored even if the client
            # that asked for it goes away meanwhile (the next request then finds it).
            asyncio.ensure_future(self._convert(b, art, fmt, key, pending))
        size = await asyncio.shield(pending)
        return _artifact(key, size, art, fmt)

    async def _convert(self, b, art: Artifact, fmt: str, key: str, done: asyncio.Future) -> None:
        s = b.settings
        try:
            try:
                await asyncio.wait_for(self.slots.acquire(), timeout=max(s.conversion_wait_s, 0.001))
            except TimeoutError:
                p = Problem(
                    503,
                    "conversions-busy",
                    "Conversions busy",
                    f"{self.limit} conversion(s) are running on this server; none became free within "
                    f"{s.conversion_wait_s:g} s. Retry later (a finished conversion is kept and served at once)",
                )
                p.headers["Retry-After"] = str(s.unavailable_retry_after_s)
                raise p from None
            try:
                size = await _run_child(b, art, fmt, key)
            finally:
                self.slots.release()
            done.set_result(size)
        # forwarded, not swallowed: every outcome, a cancellation too, goes to the requests waiting on it
        except BaseException as exc:  # noqa: BLE001
            done.set_exception(exc)
            done.exception()  # retrieved: no "never retrieved" warning when nobody waits any more
        finally:
            self.running.pop(key, None)


def conversions(b) -> Conversions:
    """The backend's Conversions, made on first use (GSA_MAX_CONVERSIONS slots)."""
    c = getattr(b, "conversions", None)
    if c is None:
        c = Conversions(b.settings.max_conversions)
        b.conversions = c
    return c


def _stored(storage, key: str) -> int | None:
    return storage.size(key) if storage.exists(key) else None


def _artifact(key: str, size: int, art: Artifact, fmt: str) -> Artifact:
    return Artifact(name=converted_name(art.name, fmt), key=key, size=size, content_type=model_content_type(fmt))


async def _run_child(b, art: Artifact, fmt: str, key: str) -> int:
    """Convert in a child process and store the result under `key`; returns its size."""
    s = b.settings
    extensions, _, _ = _formats()
    tmp = Path(tempfile.mkdtemp(prefix="gsa-convert-"))
    try:
        # Local storage hard-links the blob; S3 streams it to the file (no copy in memory).
        src = await run_in_threadpool(b.storage.download, art.key, tmp / "model")
        out = tmp / f"out{extensions[fmt]}"
        # The service wrote this file: a merged model is a source plus the target, each
        # within max_gaussians, so it may hold up to twice that many.
        args = [sys.executable, "-m", "service.worker.convert_child", str(src), str(out), fmt]
        args += [str(2 * s.max_gaussians), str(os.getpid())]
        child = await asyncio.create_subprocess_exec(
            *args,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            start_new_session=True,  # its own group: a timeout kills it and whatever it started
        )
        try:
            stdout, stderr = await asyncio.wait_for(child.communicate(), timeout=s.conversion_timeout_s)
        except asyncio.CancelledError:  # the API is shutting down: no child outlives it
            _kill(child)
            raise
        except TimeoutError:
            _kill(child)
            await child.wait()
            raise Problem(
                504,
                "conversion-timeout",
                "Conversion timed out",
                f"converting {art.name} to {fmt} took longer than {s.conversion_timeout_s:g} s",
            ) from None
        if child.returncode == BAD_INPUT_EXIT:
            detail = json.loads(stdout.decode() or "{}").get("detail", "unreadable model")
            raise invalid_input(f"{art.name}: {detail}")
        if child.returncode != 0 or not out.is_file():
            log.error(
                "conversion of %s to %s failed (exit %s): %s",
                art.key,
                fmt,
                child.returncode,
                stderr.decode(errors="replace")[-2000:],
            )
            why = f"signal {-child.returncode}" if child.returncode < 0 else f"status {child.returncode}"
            raise Problem(500, "conversion-failed", "Conversion failed", f"the conversion process ended with {why}")

        def store() -> int:
            with open(out, "rb") as fh:
                return b.storage.put(key, fh)

        return await run_in_threadpool(store)
    finally:
        await run_in_threadpool(shutil.rmtree, tmp, True)


def _kill(child) -> None:
    try:
        os.killpg(child.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
