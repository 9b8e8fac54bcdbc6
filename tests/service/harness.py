"""A whole service deployment from real processes, for the fuzzing and chaos
runs (tests/service/test_fuzz_service.py, test_chaos_service.py and the
benchmarks/service/fuzz_service.py, benchmarks/service/chaos_service.py that print their numbers):
a private redis-server that can be stopped and started again on its port and
data folder, `gsa serve` processes and `gsa worker` processes.

Never touches the Redis on 6379."""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import httpx

from tests.service.conftest import PY, Proc, free_port, start_worker, wait_until


class RedisServer:
    """redis-server on a free loopback port with an fsync'ed append-only file in
    its own folder, so what was stored survives a restart, as in production."""

    def __init__(self, d: Path):
        self.exe = shutil.which("redis-server")
        if self.exe is None:
            raise RuntimeError("redis-server not installed (./dev.sh test installs it)")
        self.dir, self.port, self.p = d, free_port(), None
        d.mkdir(parents=True, exist_ok=True)

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        args = [self.exe, "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.dir)]
        args += ["--appendonly", "yes", "--appendfsync", "always", "--save", ""]
        self.p = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        import redis

        r = redis.Redis(port=self.port)

        def up():
            try:
                return r.ping()
            except redis.RedisError:  # not accepting connections (or still loading its AOF) yet
                return False

        wait_until(up, 30, 0.05, "redis-server")
        r.close()

    def stop(self, kill: bool = False) -> None:
        if self.p is not None and self.p.poll() is None:
            self.p.kill() if kill else self.p.terminate()
            self.p.wait(30)
        self.p = None


def rss_bytes(pid: int, field: str = "VmRSS") -> int:
    """Resident memory of a process from /proc/<pid>/status, 0 once it is gone:
    VmRSS now, or VmHWM, the highest it has been (catches a peak between samples)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


class Deployment:
    """Redis + API processes + worker processes sharing one storage folder."""

    def __init__(self, tmp: Path, env: dict, redis: RedisServer):
        self.tmp, self.env, self.redis = tmp, env, redis
        self.api: Proc | None = None
        self.url = ""
        self.workers: list[Proc] = []
        self.n_api = 0
        self.n_workers = 0

    def start_api(self) -> str:
        """(Re)start the API, on the same port each time (clients keep their URL)."""
        self.n_api += 1
        self.port = getattr(self, "port", None) or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        args = [PY, "-m", "service.cli", "serve", "--port", str(self.port), "--log-level", "warning"]
        self.api = Proc(args, self.env, self.tmp / f"api{self.n_api}.log")

        def up():
            if self.api.p.poll() is not None:
                raise RuntimeError(f"API exited: {self.api.tail()}")
            try:
                return httpx.get(self.url + "/healthz", timeout=1).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(up, 60, 0.1, "API to start")
        return self.url

    def stop_api(self, kill: bool = True) -> None:
        if self.api is not None:
            self.api.kill() if kill else self.api.stop()
            self.api = None

    def add_worker(self) -> Proc:
        self.n_workers += 1
        w = start_worker(self.tmp, self.env, name=f"worker{self.n_workers}")
        self.workers.append(w)
        return w

    def api_rss(self, field: str = "VmRSS") -> int:
        return rss_bytes(self.api.p.pid, field) if self.api is not None else 0

    def client(self, headers: dict, timeout: float = 30) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=headers, timeout=timeout)

    def close(self) -> None:
        for w in self.workers:
            w.kill()
        self.workers = []
        self.stop_api()
        self.redis.stop()

    def logs(self, n: int = 2000) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-n:]}" for p in sorted(self.tmp.glob("*.log")))


def wait_ready(url: str, timeout: float = 60) -> float:
    """Seconds until /readyz answers 200 (the API sees its store and storage)."""
    t = time.monotonic()

    def ready():
        try:
            return httpx.get(url + "/readyz", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    wait_until(ready, timeout, 0.1, "/readyz")
    return time.monotonic() - t
