"""Files we write open in a real web viewer: Spark (the results page's 3DGS library, web/)
decodes our PLY, compressed PLY, .splat, .ksplat, SPZ and SOG files in headless Chromium,
with every Gaussian and the positions as each format stores them. (Spark has no glTF
reader; GLB files are checked with pygltflib in test_formats.py.)"""

from __future__ import annotations

import functools
import http.server
import json
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gsa.io.formats import EXTENSIONS, write_model
from gsa.io.frames import RDF_TO_RUB
from gsa.synth import make_object
from tests.browser import browser_page

pytestmark = pytest.mark.slow  # bundles a page and starts a browser

WEB = Path(__file__).resolve().parents[1] / "web"
FORMATS = ("ply", "compressed-ply", "splat", "ksplat", "spz", "sog")
# Spark picks its decoder from the file name's extension
SPARK_NAMES = {fmt: f"model{EXTENSIONS[fmt]}" for fmt in FORMATS} | {"compressed-ply": "model.compressed.ply"}

ENTRY = """
import { PackedSplats } from "@sparkjsdev/spark";
const files = %s;
window.results = {};
(async () => {
  for (const [fmt, name] of files) {
    try {
      const bytes = new Uint8Array(await (await fetch(name)).arrayBuffer());
      const splats = new PackedSplats({ fileBytes: bytes, fileName: name });
      await splats.initialized;
      const centers = [];
      splats.forEachSplat((i, center) => { centers.push([center.x, center.y, center.z]); });
      window.results[fmt] = { numSplats: splats.numSplats, centers };
    } catch (e) {
      window.results[fmt] = { error: String(e) };
    }
  }
  window.done = true;
})();
"""


def _bundle(tmp: Path) -> None:
    esbuild = WEB / "node_modules" / ".bin" / "esbuild"
    if not esbuild.exists():
        raise RuntimeError("web/node_modules is missing: ./dev.sh test installs it (npm ci in web/)")
    files = [[fmt, SPARK_NAMES[fmt]] for fmt in FORMATS]
    entry = WEB / f".formats-check-{time.time_ns()}.js"  # inside web/ so node_modules resolves
    entry.write_text(ENTRY % json.dumps(files))
    try:
        subprocess.run(
            [str(esbuild), str(entry), "--bundle", "--format=esm", f"--outfile={tmp / 'check.js'}"],
            check=True,
            capture_output=True,
            timeout=120,
        )
    finally:
        entry.unlink(missing_ok=True)
    (tmp / "index.html").write_text('<!doctype html><script type="module" src="check.js"></script>')


def test_spark_reads_every_file_we_write(tmp_path):
    model = make_object("car", seed=3, n_gaussians=2000, sh_degree=3)
    for fmt in FORMATS:
        write_model(model, tmp_path / SPARK_NAMES[fmt], fmt)
    _bundle(tmp_path)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(tmp_path))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with browser_page() as (page, messages):
            page.goto(f"http://127.0.0.1:{server.server_address[1]}/index.html")
            deadline = time.monotonic() + 120
            while not page.evaluate("() => window.done === true"):
                assert time.monotonic() < deadline, messages
                time.sleep(0.2)
            results = page.evaluate("() => window.results")
    finally:
        server.shutdown()
    for fmt in FORMATS:
        got = results[fmt]
        assert "error" not in got, (fmt, got)
        assert got["numSplats"] == len(model), fmt
        stored = model.means @ RDF_TO_RUB.T if fmt == "spz" else model.means  # SPZ files are RUB
        centers = np.array(got["centers"])
        # Spark packs positions as float16 (SOG reorders: compare nearest neighbours)
        from scipy.spatial import cKDTree

        dist = cKDTree(stored).query(centers)[0]
        assert dist.max() < 5e-3 * np.ptp(stored, axis=0).max(), (fmt, dist.max())
