"""Real parts for service tests: a private redis-server on a free loopback port,
uvicorn API processes, RQ worker processes, gRPC on the API process.
Never touches the Redis on 6379."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
PY = sys.executable
KEYS = {"key-alice": "alice", "key-bob": "bob"}
ALICE = {"Authorization": "Bearer key-alice"}
BOB = {"Authorization": "Bearer key-bob"}
MAX_UPLOAD = 8 * 1024 * 1024


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(pred, timeout=30.0, interval=0.05, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(interval)
    raise TimeoutError(f"timed out waiting for {what}")


class Proc:
    """A child process in its own session, so SIGKILL can take its whole group
    (an RQ worker and its forked work horse), as when a machine dies."""

    def __init__(self, args, env, log: Path):
        self.log = log
        self.fh = open(log, "ab")
        self.p = subprocess.Popen(
            args,
            env=env,
            cwd=ROOT,
            stdout=self.fh,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    def kill(self, sig=signal.SIGKILL):
        if self.p.poll() is None:
            try:
                os.killpg(self.p.pid, sig)
            except ProcessLookupError:
                pass
        try:
            self.p.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(self.p.pid, signal.SIGKILL)
            self.p.wait(5)
        self.fh.close()

    def descendants(self) -> list[int]:
        """Child pids, recursively, from /proc (an RQ work horse runs in its own
        process group, so killpg alone would miss it)."""
        parents: dict[int, list[int]] = {}
        for d in Path("/proc").iterdir():
            if d.name.isdigit():
                try:
                    ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
                except (OSError, IndexError, ValueError):
                    continue
                parents.setdefault(ppid, []).append(int(d.name))
        out, todo = [], [self.p.pid]
        while todo:
            kids = parents.get(todo.pop(), [])
            out += kids
            todo += kids
        return out

    def kill_tree(self):
        """SIGKILL the process and all its descendants at once: a machine dying."""
        victims = self.descendants()
        for pid in [self.p.pid, *victims]:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.p.wait(10)
        self.fh.close()
        return victims

    def stop(self):
        self.kill(signal.SIGTERM)

    def tail(self, n=3000) -> str:
        return self.log.read_text(errors="replace")[-n:]


def service_env(tmp: Path, **extra) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("GSA_")}
    env.update(
        {
            "PYTHONPATH": str(ROOT),
            "GSA_STORAGE_ROOT": str(tmp / "data"),
            "GSA_API_KEYS": json.dumps(KEYS),
            "GSA_LEASE_S": "2",
            "GSA_REAPER_INTERVAL_S": "0.5",
            "GSA_WEBHOOK_ALLOW_PRIVATE": "true",
            "GSA_WEBHOOK_LOOPBACK_ONLY": "true",  # no webhook leaves this machine
            "GSA_METRICS_OWNERS": '["alice"]',  # /metrics is for operators
            "GSA_MAX_UPLOAD_BYTES": str(MAX_UPLOAD),
            "GSA_MAX_ATTEMPTS": "3",
            # the semantic tie-break's 10-20 s per doubtful job is off here (tests/conftest.py)
            "GSA_SEMANTIC": "off",
        }
    )
    env.update({k: str(v) for k, v in extra.items()})
    return env


def start_api(
    tmp: Path, env: dict, grpc: bool = False, name="api", log_level: str = "warning"
) -> tuple[Proc, str, int | None]:
    port = free_port()
    gport = free_port() if grpc else None
    args = [
        PY,
        "-m",
        "service.cli",
        "serve",
        "--port",
        str(port),
        "--log-level",
        log_level,
    ]
    if gport:
        args += ["--grpc-port", str(gport)]
    proc = Proc(args, env, tmp / f"{name}.log")
    url = f"http://127.0.0.1:{port}"

    wait_until(lambda: api_up(url, proc), 60, 0.1, "API to start")
    return proc, url, gport


def api_up(url: str, api: Proc) -> bool:
    """Whether the API answers /healthz; an API process that exited is an error, not a wait."""
    if api.p.poll() is not None:
        raise RuntimeError(f"API exited: {api.tail()}")
    try:
        return httpx.get(url + "/healthz", timeout=1).status_code == 200
    except httpx.HTTPError:
        return False


def start_worker(tmp: Path, env: dict, name="worker") -> Proc:
    return Proc(
        [PY, "-m", "service.cli", "worker", "--name", f"{name}-{time.time_ns()}"],
        env,
        tmp / f"{name}.log",
    )


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory):
    exe = shutil.which("redis-server")
    if exe is None:
        pytest.fail("redis-server not installed (./dev.sh test installs it)")
    d = tmp_path_factory.mktemp("redis")
    port = free_port()
    p = subprocess.Popen(
        [
            exe,
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--appendonly",
            "no",
            "--dir",
            str(d),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    import redis

    r = redis.Redis(port=port)
    wait_until(lambda: _ping(r), 10, 0.05, "redis-server")
    yield f"redis://127.0.0.1:{port}"
    p.terminate()
    p.wait(10)


def _ping(r):
    from redis.exceptions import RedisError

    try:
        return r.ping()
    except RedisError:  # not accepting connections (or still loading) yet
        return False


@pytest.fixture(scope="session")
def pair(tmp_path_factory):
    """A generated source/target PLY pair, the true Sim(3), and the files' bytes."""
    from scipy.spatial.transform import Rotation

    from gsa.io.ply import write_ply
    from gsa.sim3 import Sim3
    from gsa.synth import make_object

    d = tmp_path_factory.mktemp("pair")
    src = make_object("car", seed=3, n_gaussians=3000)
    gt = Sim3(
        1.4,
        Rotation.from_euler("xyz", [35, 80, -20], degrees=True).as_matrix(),
        np.array([0.4, -0.2, 0.7]),
    )
    write_ply(src, d / "source.ply")
    write_ply(src.transformed(gt), d / "target.ply")
    src2 = make_object("car", seed=4, n_gaussians=2500)
    write_ply(src2, d / "source2.ply")
    big = make_object("bus", seed=1, n_gaussians=50_000)
    write_ply(big, d / "big_source.ply")
    write_ply(big.transformed(gt), d / "big_target.ply")
    return {
        "dir": d,
        "source": d / "source.ply",
        "target": d / "target.ply",
        "source2": d / "source2.ply",
        "big_source": d / "big_source.ply",
        "big_target": d / "big_target.ply",
        "gt": gt,
    }


@pytest.fixture(scope="session")
def stack(tmp_path_factory, redis_url):
    """Distributed mode: API (HTTP + gRPC) and one worker process on a private Redis."""
    tmp = tmp_path_factory.mktemp("stack")
    env = service_env(tmp, GSA_REDIS_URL=redis_url + "/0")
    api, url, gport = start_api(tmp, env, grpc=True)
    worker = start_worker(tmp, env)
    yield {
        "url": url,
        "grpc": f"127.0.0.1:{gport}",
        "env": env,
        "tmp": tmp,
        "api": api,
        "worker": worker,
        "redis_url": redis_url + "/0",
    }
    worker.stop()
    api.stop()


@pytest.fixture
def http(stack):
    with httpx.Client(base_url=stack["url"], headers=ALICE, timeout=60) as c:
        yield c


def submit_pair(c: httpx.Client, pair, options=None, headers=None, **data) -> httpx.Response:
    with open(pair["source"], "rb") as s, open(pair["target"], "rb") as t:
        return c.post(
            "/v1/jobs",
            files=[("source", ("source.ply", s)), ("target", ("target.ply", t))],
            data={"options": json.dumps(options or {}), **data},
            headers=headers or {},
        )


def submit_slow_job(http: httpx.Client, pair: dict, copies: int) -> tuple[dict, list[str]]:
    """Upload the big pair as assets and submit one multi-model job aligning
    `copies` copies of the source: long enough to kill or restart things mid-run.
    Returns (job, [source asset id, target asset id])."""
    ids = []
    for k in ("big_source", "big_target"):
        with open(pair[k], "rb") as fh:
            ids.append(http.post("/v1/assets", files={"file": (k + ".ply", fh)}).json()["id"])
    job = http.post(
        "/v1/jobs",
        json={
            "sources": [ids[0]] * copies,
            "target": ids[1],
            "options": {"coarse_iterations": 100, "outputs": ["result"]},
        },
    ).json()
    return job, ids


def wait_job(
    c: httpx.Client,
    job_id: str,
    timeout=60.0,
    states=("succeeded", "failed", "cancelled"),
) -> dict:
    def done():
        j = c.get(f"/v1/jobs/{job_id}").json()
        return j if j.get("state") in states else None

    return wait_until(done, timeout, 0.05, f"job {job_id} to reach {states}")


def library_result(pair, options: dict):
    from gsa.align.pipeline import AlignOptions, align
    from gsa.io.ply import read_ply

    return align(read_ply(pair["source"]), read_ply(pair["target"]), AlignOptions(**options))


def assert_problem(r: httpx.Response, status: int, kind: str | None = None) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json"), r.headers
    body = r.json()
    assert body["status"] == status and body["title"] and body["type"].startswith("https://")
    if kind:
        assert body["type"].endswith("/" + kind), body
    return body
