#!/usr/bin/env python
"""Results page: time to first frame in headless Chromium (software WebGL), and the
screenshots in docs/img/.

    python -m benchmarks.service.bench_viewer [--gaussians 300000] [--runs 3] [--screenshots docs/img]

Time to first frame: two samplings of a generated car with N Gaussians each (the
preview cap is 300k, so N = 300000 is the largest preview a page ever loads), aligned,
their .splat previews written; `gsa view` serves the page; a fresh Chromium page is
opened `--runs` times and window.gsaViewer reports when the preview files were loaded
and decoded and when all three views first showed splats, both from navigation start.

--screenshots DIR: the page of `gsa view` for a 20k pair aligned with the fine stage
(loss curve, renders), and a real API's job page and jobs list for a two-model job.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[2]  # the repository
sys.path.insert(0, str(ROOT))
# Same numba threading layer as `gsa worker` uses (gsa.kernels), so "direct" and "service" run the same kernels.
from gsa.kernels import use_workqueue_layer  # noqa: E402

use_workqueue_layer()

from tests.browser import browser_page, wait_drawn, wait_ready  # noqa: E402


def make_pair(d: Path, n: int, seed: int = 2) -> tuple[Path, Path]:
    from gsa.io.ply import write_ply
    from gsa.synth import make_object, random_sim3

    target = make_object("car", seed=seed, n_gaussians=n, sample_seed=seed)
    truth = random_sim3(np.random.default_rng(5))
    source = make_object("car", seed=seed, n_gaussians=n, sample_seed=seed + 1000).transformed(truth.inverse())
    return write_ply(source, d / "source.ply"), write_ply(target, d / "target.ply")


def gsa(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "gsa.cli", *args], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)


def serve(path: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "gsa.cli", "view", str(path)], stdout=subprocess.PIPE, text=True)
    return proc, proc.stdout.readline().strip()


def first_frame(n: int, runs: int, work: Path) -> None:
    src, tgt = make_pair(work, n)
    t = time.perf_counter()
    gsa("align", str(src), str(tgt), "--out", str(work / "result.json"), "--preview", "--quiet")
    print(f"{n} Gaussians per model: gsa align --preview {time.perf_counter() - t:.1f} s")
    sizes = {p.name: p.stat().st_size for p in sorted((work / "preview").iterdir())}
    print("previews:", ", ".join(f"{k} {v / 1e6:.1f} MB" for k, v in sizes.items()))
    proc, url = serve(work / "result.json")
    try:
        loaded, first = [], []
        for _ in range(runs):
            with browser_page() as (page, messages):
                page.goto(url)
                state = wait_ready(page, timeout=300)
                if state["error"]:
                    raise SystemExit(f"viewer error: {state['error']}")
                loaded.append(state["loadedMs"] / 1000)
                first.append(state["firstFrameMs"] / 1000)
                print(f"  run: loaded + decoded {loaded[-1]:.2f} s, first frame {first[-1]:.2f} s")
        print(
            f"time to first frame (3 views, {n} + {n} + {n} splats): median {statistics.median(first):.2f} s, "
            f"min {min(first):.2f} s; previews loaded and decoded: median {statistics.median(loaded):.2f} s"
        )
    finally:
        proc.terminate()


def screenshots(out: Path, work: Path) -> None:
    from tests.service.conftest import ALICE, service_env, start_api, wait_job

    out.mkdir(parents=True, exist_ok=True)
    src, tgt = make_pair(work, 20000)
    res = work / "local"
    gsa("align", str(src), str(tgt), "--out", str(res / "result.json"), "--preview", "--renders", str(res / "renders"))
    gsa("align", str(src), str(tgt), "--out", str(work / "fine.json"), "--stages", "coarse,fine", "--quiet")
    data = json.loads((res / "result.json").read_text())  # the fine stage's loss curve on the page
    data["stages"]["fine"] = json.loads((work / "fine.json").read_text())["stages"]["fine"]
    (res / "result.json").write_text(json.dumps(data))
    proc, url = serve(res / "result.json")
    try:
        with browser_page(1280, 1000) as (page, _):
            page.goto(url)
            wait_ready(page)
            wait_drawn(page, "#view-overlay")
            time.sleep(1)
            page.screenshot(path=str(out / "gsa-view.jpg"), full_page=True, type="jpeg", quality=88)
    finally:
        proc.terminate()
    # The service: a real API (embedded worker), a two-model job, its page and the jobs list.
    from gsa.io.ply import write_ply
    from gsa.synth import make_object

    other = write_ply(make_object("car", seed=7, n_gaussians=20000), work / "other car.ply")
    api, base, _ = start_api(work, service_env(work, GSA_VIEW_SECRET="bench"))
    try:
        with httpx.Client(base_url=base, headers=ALICE, timeout=120) as c:
            ids = {}
            for name, path in (("source", src), ("other", other), ("target", tgt)):
                with open(path, "rb") as fh:
                    ids[name] = c.post("/v1/assets", files={"file": (path.name, fh)}).json()["id"]
            job = c.post("/v1/jobs", json={"sources": [ids["source"], ids["other"]], "target": ids["target"]}).json()
            wait_job(c, job["id"], timeout=600)
            link = c.post(f"/v1/jobs/{job['id']}/view-link").json()["url"]
            jobs_link = c.post("/v1/view-link").json()["url"]
        with browser_page(1280, 1000) as (page, _):
            page.goto(base + link)
            wait_ready(page)
            wait_drawn(page, "#view-overlay")
            time.sleep(1)
            page.screenshot(path=str(out / "service-job.jpg"), type="jpeg", quality=88)
            page.goto(base + jobs_link)
            page.set_viewport_size({"width": 1000, "height": 160})
            page.screenshot(path=str(out / "service-jobs.png"))
    finally:
        api.stop()
    print("screenshots:", ", ".join(sorted(p.name for p in out.iterdir())))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=300_000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--screenshots", type=Path, default=None, help="write the docs' screenshots into this folder")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="gsa-bench-viewer-") as tmp:
        if args.screenshots:
            screenshots(args.screenshots, Path(tmp))
        if args.runs:
            first_frame(args.gaussians, args.runs, Path(tmp))


if __name__ == "__main__":
    main()
