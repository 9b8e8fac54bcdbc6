"""Image sets through the service with the real reconstruction (pycolmap SfM +
3DGS training). About 1-2 minutes on 2 CPU cores."""

from __future__ import annotations

import json
import time
import zipfile

import pytest

from tests.exif import IPHONE, camera_jpeg

pytestmark = pytest.mark.slow  # starts servers and worker processes


def test_image_set_pair_job(tmp_path):
    """Two photo sets of one object from one camera (EXIF): each reconstructed (the source with
    the target's intrinsics held fixed), registered by their photos."""
    import cv2
    from fastapi.testclient import TestClient

    from gsa.recon.synthetic import render_image_set
    from service.api.app import create_app
    from service.settings import Settings

    zips = []
    for name, orbit in (("src", 1), ("tgt", 2)):
        render_image_set(tmp_path / name, orbit_seed=orbit, n_views=24, size=256)
        z = tmp_path / f"{name}.zip"
        with zipfile.ZipFile(z, "w") as zf:
            for p in sorted((tmp_path / name / "images").iterdir()):
                jpeg = camera_jpeg(tmp_path / f"{name}-{p.stem}.jpg", image=cv2.imread(str(p)))
                zf.write(jpeg, f"images/{p.stem}.jpg")
        zips.append(z)
    app = create_app(Settings(storage_root=tmp_path / "data", api_keys={"k": "me"}))
    headers = {"Authorization": "Bearer k"}
    with TestClient(app) as c, open(zips[0], "rb") as a, open(zips[1], "rb") as b:
        r = c.post(
            "/v1/jobs",
            headers=headers,
            files=[("source", ("src.zip", a)), ("target", ("tgt.zip", b))],
            data={"options": json.dumps({"recon_iterations": 60, "outputs": ["result", "aligned"]})},
        )
        assert r.status_code == 202, r.text
        deadline = time.monotonic() + 600
        while (job := c.get(r.headers["location"], headers=headers).json())["state"] not in (
            "succeeded",
            "failed",
            "cancelled",
        ):
            assert time.monotonic() < deadline
            time.sleep(0.5)
        assert job["state"] == "succeeded", job["error"]
        names = {a["name"] for a in job["artifacts"]}
        assert {
            "reconstructed/source0.ply",
            "reconstructed/target.ply",
            "aligned.ply",
            "result.json",
        } <= names
        rec = job["result"]["reconstructions"]
        assert rec["source0"]["registered"] >= 12 and rec["target"]["registered"] >= 12
        # one camera by EXIF: the source's SfM kept the target's lens (gsa.recon.calibration)
        assert rec["target"]["exif_camera"] == list(IPHONE) and not rec["target"]["intrinsics"]["fixed"]
        assert rec["source0"]["intrinsics"]["fixed"], rec["source0"]["intrinsics"]
        assert job["result"]["scale"] > 0
        # two photo sets of one object: their photos' shared texture gave the pose (gsa.align.photo)
        assert job["result"]["stages_run"] == ["photo"], job["result"]["metrics"].get("photo_match")
        assert job["result"]["metrics"]["photo_match"]["accepted"] and not job["result"]["metrics"]["doubtful"]
